//! Training (feature `train`): the reference's optimisation (spec `model.md` §5–§6) and the
//! files a run writes.
//!
//! * [`adam`]: Adam with parameter groups, the lr schedule, global-norm clipping.
//! * [`state`]: the train-state file (optimizer moments, RNG, sampler, iteration).
//! * `log`: `log.csv`.
//! * [`source`]: training batches from a dataset (spec data.md §7).
//! * [`trainer`]: one training step (forward, loss, backward, clip, Adam, schedule), run in
//!   chunks of rays with gradient accumulation when the batch is large, non-finite step
//!   skipping, checkpoint and resume.
//!
//! The inference path of the crate does not depend on anything here.

pub mod adam;
pub mod log;
pub mod source;
pub mod state;
pub mod trainer;

use std::io::Write as _;
use std::path::{Path, PathBuf};

pub use adam::{clip_grad_norm, decayed_lr, global_norm, Adam, ParamGroup, ParamState};
pub use log::{LogRow, TrainLog};
pub use source::DatasetSource;
pub use state::{Progress, RngState, TrainState};
pub use trainer::*;

pub use crate::presets::{Preset, RunConfig, TrainConfig};

#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },

    /// Bad training settings (TOML file, preset, flags).
    #[error("invalid training config: {0}")]
    Config(String),

    /// Optimizer state that does not fit the model (every problem listed).
    #[error("train state: {} problem(s):\n  - {}", .0.len(), .0.join("\n  - "))]
    State(Vec<String>),

    /// A train-state file that cannot be used (every problem listed).
    #[error("train state {path}: {} problem(s):\n  - {}", problems.len(), problems.join("\n  - "))]
    StateFile {
        path: PathBuf,
        problems: Vec<String>,
    },

    /// The run directory cannot be resumed (missing files, mismatched config or model).
    #[error("cannot resume from {dir}: {reason}")]
    Resume { dir: PathBuf, reason: String },

    /// Too many non-finite steps in a row: the weights are still finite (no bad step was
    /// applied), but training is not making progress.
    #[error("{count} consecutive non-finite steps up to iteration {iter}; stopping (the last checkpoint is intact)")]
    Diverged { count: u64, iter: u64 },

    // The wrapped errors are boxed so `Result<_, TrainError>` stays small on the hot path.
    #[error(transparent)]
    Model(Box<crate::error::ModelError>),

    #[error(transparent)]
    Data(Box<pma_data::DataError>),

    #[error(transparent)]
    Candle(Box<candle_core::Error>),
}

impl From<crate::error::ModelError> for TrainError {
    fn from(e: crate::error::ModelError) -> Self {
        TrainError::Model(Box::new(e))
    }
}

impl From<pma_data::DataError> for TrainError {
    fn from(e: pma_data::DataError) -> Self {
        TrainError::Data(Box::new(e))
    }
}

impl From<candle_core::Error> for TrainError {
    fn from(e: candle_core::Error) -> Self {
        TrainError::Candle(Box::new(e))
    }
}

/// Write `bytes` to `path` through a temporary file in the same directory, then rename, so
/// readers see either the old or the new file, never a partial one.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), TrainError> {
    let io = |source| TrainError::Io {
        path: path.to_path_buf(),
        source,
    };
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let mut tmp = tempfile::NamedTempFile::new_in(dir).map_err(io)?;
    tmp.write_all(bytes).map_err(io)?;
    tmp.as_file().sync_all().map_err(io)?;
    // Temporary files are created 0600; a run's outputs are ordinary files.
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        tmp.as_file()
            .set_permissions(std::fs::Permissions::from_mode(0o644))
            .map_err(io)?;
    }
    tmp.persist(path).map_err(|e| io(e.error))?;
    Ok(())
}
