//! What can stop a training run, and the one atomic write every run file goes through.

use std::path::{Path, PathBuf};

/// A [`super::TrainObserver`]'s own failure (e.g. the plot it writes at a checkpoint).
pub type ObserverError = Box<dyn std::error::Error + Send + Sync>;

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
    Observer(ObserverError),

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
