//! Errors of the model crate.
//!
//! Every variant names what was wrong and where (file, tensor, expected vs found), so a
//! caller can print it as is.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },

    /// A checkpoint is unusable; `problems` lists every issue found (missing, unexpected and
    /// mis-shaped tensors, bad metadata), not just the first.
    #[error("checkpoint {path}: {} problem(s):\n  - {}", problems.len(), problems.join("\n  - "))]
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

    #[error(transparent)]
    Candle(#[from] candle_core::Error),

    #[error(transparent)]
    Data(#[from] pma_data::DataError),

    /// The process-wide interrupt flag was raised (see [`crate::interrupt`]).
    #[error("{0}")]
    Interrupted(#[from] pma_data::interrupt::Interrupted),
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
