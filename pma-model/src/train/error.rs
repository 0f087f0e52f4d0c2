//! What can stop a training run, and the one atomic write every run file goes through.

use std::path::{Path, PathBuf};

use pma_data::FileError;

/// A [`super::TrainObserver`]'s own failure (e.g. the plot it writes at a checkpoint).
pub type ObserverError = Box<dyn std::error::Error + Send + Sync>;

#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// Reading an input (dataset, config, checkpoint, log) or writing the run directory
    /// failed; after a failed write the last complete checkpoint is intact.
    #[error(transparent)]
    File(#[from] FileError),

    /// Another process holds the run directory's lock.
    #[error("{} is in use by another pma train ({}); one writer per run directory", dir.display(), holder(*pid))]
    Locked { dir: PathBuf, pid: Option<u32> },

    /// Bad training settings (TOML file, preset, flags).
    #[error("invalid training config: {0}")]
    Config(String),

    /// Optimizer state that does not fit the model (every problem listed; the message is
    /// the first and how many more).
    #[error("train state: {}", crate::error::summarize(.0))]
    State(Vec<String>),

    /// A train-state file that cannot be used (every problem listed).
    #[error("train state {path}: {}", crate::error::summarize(problems))]
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

    /// A data-parallel group cannot go on (a rank left, hangs or disagrees).
    #[error(transparent)]
    Group(#[from] super::parallel::error::GroupError),

    /// One rank of a data-parallel group failed; the others stopped with it.
    #[error("rank {rank} of {size}: {source}")]
    Rank {
        rank: usize,
        size: usize,
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

fn holder(pid: Option<u32>) -> String {
    match pid {
        Some(p) => format!("PID {p}"),
        None => "PID unknown".to_string(),
    }
}

impl pma_data::ExitKind for TrainError {
    fn kind(&self) -> pma_data::ErrorKind {
        use pma_data::ErrorKind;
        match self {
            TrainError::File(f) => f.kind(),
            TrainError::Config(_)
            | TrainError::State(_)
            | TrainError::StateFile { .. }
            | TrainError::Resume { .. }
            | TrainError::RunExists(_)
            | TrainError::Locked { .. } => ErrorKind::Refused,
            TrainError::Diverged { .. }
            | TrainError::Observer(_)
            | TrainError::Candle(_)
            | TrainError::Group(_) => ErrorKind::Failure,
            TrainError::Stopped { source, .. } | TrainError::Rank { source, .. } => source.kind(),
            TrainError::Model(m) => m.kind(),
            TrainError::Data(d) => d.kind(),
            TrainError::Eval(e) => e.kind(),
        }
    }
}

impl TrainError {
    /// Whether the work stopped because an interruption was requested.
    pub fn is_interrupted(&self) -> bool {
        pma_data::interrupt::caused(self)
    }
}

crate::error::interrupted_as_model!(TrainError);

crate::error::boxed_from!(
    TrainError:
    Eval(crate::eval::EvalError),
    Model(crate::error::ModelError),
    Data(pma_data::DataError),
    Candle(candle_core::Error),
);

/// Write `bytes` to `path` atomically (see `pma_data::fsio`).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), TrainError> {
    pma_data::fsio::write_atomic(path, bytes).map_err(write_err(path))
}

/// A `map_err` for writing `path`.
pub(crate) fn write_err(path: &Path) -> impl FnOnce(std::io::Error) -> TrainError + '_ {
    move |source| FileError::write(path, source).into()
}

/// A `map_err` for reading `path`.
pub(crate) fn read_err(path: &Path) -> impl FnOnce(std::io::Error) -> TrainError + '_ {
    move |source| FileError::read(path, source).into()
}
