//! Training (feature `train`): the reference's optimisation (see `docs/reference.md`,
//! "Training schedule and Adam") and the files a run writes.
//!
//! * [`adam`]: Adam with parameter groups, the lr schedule, global-norm clipping.
//! * [`batch`]: what a step consumes ([`TrainBatch`]) and where it comes from ([`BatchSource`]).
//! * [`state`]: the train-state file (optimizer moments, RNG, sampler, iteration).
//! * `log`: `log.csv`.
//! * [`source`]: training batches from a dataset (see `docs/conventions.md`, "Ray sampler").
//! * [`trainer`]: one training step (forward, loss, backward, clip, Adam, schedule), run in
//!   chunks of rays with gradient accumulation when the batch is large, non-finite step
//!   skipping, checkpoint and resume.
//! * [`run`]: a whole training run (run directory, loop, held-out evaluation schedule,
//!   checkpoints, interruption), reporting to a [`TrainObserver`].
//!
//! The inference path of the crate does not depend on anything here.

pub mod adam;
pub mod batch;
pub mod log;
pub mod run;
pub mod source;
pub mod state;
pub mod trainer;

use std::path::{Path, PathBuf};

pub use adam::{clip_grad_norm, decayed_lr, global_norm, Adam, ParamGroup, ParamState};
pub use batch::{BatchSource, FixedBatch, TrainBatch};
pub use log::{LogRow, TrainLog};
pub use pma_data::metrics::psnr_from_mse;
pub use run::{
    train_run, ObserverError, Silent, StepReport, TrainObserver, TrainOutcome, TrainRequest,
    CONFIG_FILE, LOG_FILE,
};
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

    /// The output directory holds a run and neither resuming nor overwriting was asked for.
    #[error("{} already holds a run (pass --resume to continue it, or choose another --out)", .0.display())]
    RunExists(PathBuf),

    /// Training stopped early; the checkpoint of `iter` is in `dir`.
    #[error("training stopped; checkpoint of iteration {iter} written to {}", dir.display())]
    Stopped {
        iter: u64,
        dir: PathBuf,
        #[source]
        source: Box<TrainError>,
    },

    /// A [`TrainObserver`]'s own work failed (e.g. the plot it writes at a checkpoint).
    #[error(transparent)]
    Observer(run::ObserverError),

    // The wrapped errors are boxed so `Result<_, TrainError>` stays small on the hot path.
    #[error(transparent)]
    Model(Box<crate::error::ModelError>),

    #[error(transparent)]
    Data(Box<pma_data::DataError>),

    #[error(transparent)]
    Candle(Box<candle_core::Error>),

    #[error(transparent)]
    Eval(Box<crate::eval::EvalError>),
}

impl TrainError {
    /// Whether the work stopped because an interruption was requested.
    pub fn is_interrupted(&self) -> bool {
        pma_data::interrupt::caused(self)
    }
}

impl From<pma_data::interrupt::Interrupted> for TrainError {
    fn from(e: pma_data::interrupt::Interrupted) -> Self {
        TrainError::Model(Box::new(e.into()))
    }
}

impl From<crate::eval::EvalError> for TrainError {
    fn from(e: crate::eval::EvalError) -> Self {
        TrainError::Eval(Box::new(e))
    }
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

/// Write `bytes` to `path` atomically (see `pma_data::fsio`).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), TrainError> {
    pma_data::fsio::write_atomic(path, bytes).map_err(|source| TrainError::Io {
        path: path.to_path_buf(),
        source,
    })
}
