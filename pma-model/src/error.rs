//! Errors of the model crate.
//!
//! Every variant names what was wrong and where (file, tensor, expected vs found), so a
//! caller can print it as is.

use std::path::PathBuf;

use pma_data::FileError;

#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    /// Reading an input or writing an output failed.
    #[error(transparent)]
    File(#[from] FileError),

    /// A checkpoint is unusable; `problems` lists every issue found (missing, unexpected and
    /// mis-shaped tensors, bad metadata), not just the first. The message is one line: the
    /// first problem and how many more there are.
    #[error("checkpoint {path}: {}", summarize(problems))]
    Checkpoint {
        path: PathBuf,
        problems: Vec<String>,
    },

    /// The safetensors container itself could not be parsed or written.
    #[error("safetensors {path}: {source}")]
    Safetensors {
        path: PathBuf,
        #[source]
        source: safetensors::SafeTensorError,
    },

    /// An inconsistent or unsupported `Config`.
    #[error("invalid config: {0}")]
    Config(String),

    /// A tensor handed to the model has the wrong shape or dtype.
    #[error("{what}: expected {expected}, found {found}")]
    Shape {
        what: String,
        expected: String,
        found: String,
    },

    /// Bad caller input that is not a shape problem (e.g. rays not grouped by pose).
    #[error("invalid input: {0}")]
    Input(String),

    /// A motion file could not be read (see `tools::retarget::read_motion`).
    #[error("reading motion {}: {source}", path.display())]
    Motion {
        path: PathBuf,
        #[source]
        source: Box<pma_data::DataError>,
    },

    #[error(transparent)]
    Candle(#[from] candle_core::Error),

    #[error(transparent)]
    Data(#[from] pma_data::DataError),

    /// The process-wide interrupt flag was raised (see [`crate::interrupt`]).
    #[error("{0}")]
    Interrupted(#[from] pma_data::interrupt::Interrupted),
}

/// The first problem of a list, the count of the others, and a closing note (an entry in
/// parentheses) if the list ends with one: one line for a message.
pub fn summarize(problems: &[String]) -> String {
    let (note, list) = match problems.split_last() {
        Some((last, rest)) if last.starts_with('(') && !rest.is_empty() => (Some(last), rest),
        _ => (None, problems),
    };
    let mut out = match list {
        [] => "unusable".to_string(),
        [one] => one.clone(),
        [first, rest @ ..] => format!("{first} (and {} more problem(s))", rest.len()),
    };
    if let Some(n) = note {
        out.push(' ');
        out.push_str(n);
    }
    pma_data::error::one_line(&out)
}

impl pma_data::ExitKind for ModelError {
    fn kind(&self) -> pma_data::ErrorKind {
        use pma_data::ErrorKind;
        match self {
            ModelError::File(f) => f.kind(),
            ModelError::Candle(_) => ErrorKind::Failure,
            ModelError::Checkpoint { .. }
            | ModelError::Safetensors { .. }
            | ModelError::Config(_)
            | ModelError::Shape { .. }
            | ModelError::Input(_) => ErrorKind::Refused,
            ModelError::Data(d) => d.kind(),
            ModelError::Motion { source, .. } => source.kind(),
            ModelError::Interrupted(_) => ErrorKind::Interrupted,
        }
    }
}

impl ModelError {
    /// Whether the work stopped because an interruption was requested.
    pub fn is_interrupted(&self) -> bool {
        pma_data::interrupt::caused(self)
    }

    /// Shape error helper: `what` names the tensor (and its source, if any).
    pub fn shape(
        what: impl Into<String>,
        expected: impl std::fmt::Debug,
        found: impl std::fmt::Debug,
    ) -> Self {
        Self::Shape {
            what: what.into(),
            expected: format!("{expected:?}"),
            found: format!("{found:?}"),
        }
    }
}

pub type Result<T> = std::result::Result<T, ModelError>;

/// `From` each source error for an error type that keeps them boxed (so that its results
/// stay small): `boxed_from!(TrainError: Model(ModelError), Data(DataError))` wraps a
/// `ModelError` as `TrainError::Model(Box::new(e))`, and so on.
macro_rules! boxed_from {
    ($target:ty: $($variant:ident($t:ty)),* $(,)?) => {
        $(impl From<$t> for $target {
            fn from(e: $t) -> Self {
                Self::$variant(Box::new(e))
            }
        })*
    };
}
pub(crate) use boxed_from;

/// `From<Interrupted>` for an error type that wraps a [`ModelError`], which says what an
/// interruption is.
macro_rules! interrupted_as_model {
    ($target:ty) => {
        impl From<pma_data::interrupt::Interrupted> for $target {
            fn from(e: pma_data::interrupt::Interrupted) -> Self {
                crate::error::ModelError::from(e).into()
            }
        }
    };
}
pub(crate) use interrupted_as_model;
