//! Errors of the importers. Every variant names the file it was reading, and,
//! where there is one, the key inside it, so a user can find the bad input.

use std::path::PathBuf;

/// Causes are part of each message (one complete line), so they are plain
/// fields rather than `#[source]` chains that a reporter would print twice.
#[derive(Debug, thiserror::Error)]
pub enum ConvertError {
    /// Reading an input failed.
    #[error("{path}: {cause}")]
    Io {
        path: PathBuf,
        cause: std::io::Error,
    },

    /// Writing the output failed (a full disk, no permission); nothing was written.
    #[error("writing {path}: {cause}")]
    Write {
        path: PathBuf,
        cause: std::io::Error,
    },

    #[error("{path}: not a readable zip archive ({cause}); the file may be truncated or corrupt (torch checkpoints must use torch.save's zip format, torch >= 1.6)")]
    Zip {
        path: PathBuf,
        cause: zip::result::ZipError,
    },

    #[error("{path}: {msg}")]
    Format { path: PathBuf, msg: String },

    #[error("{path}: pickle {entry}, byte {offset}: forbidden opcode 0x{opcode:02x} ({name}); only the opcodes torch.save emits for tensors and plain containers are accepted")]
    ForbiddenOpcode {
        path: PathBuf,
        entry: String,
        offset: usize,
        opcode: u8,
        name: &'static str,
    },

    #[error("{path}: pickle {entry}, byte {offset}: forbidden global `{module}.{name}`; only {accepted} are accepted")]
    ForbiddenGlobal {
        path: PathBuf,
        entry: String,
        offset: usize,
        module: String,
        name: String,
        /// What the reader's policy accepts (a thin reference keeps the error small).
        accepted: &'static Accepted,
    },

    #[error("{path}: pickle {entry}, byte {offset}: {msg}")]
    Pickle {
        path: PathBuf,
        entry: String,
        offset: usize,
        msg: String,
    },

    #[error("{path}: key `{key}` is missing{context}")]
    MissingKey {
        path: PathBuf,
        key: String,
        context: String,
    },

    #[error("{path}: key `{key}`: expected {expected}, found {found}")]
    Mismatch {
        path: PathBuf,
        key: String,
        expected: String,
        found: String,
    },

    #[error("{path}: key `{key}`: {msg}")]
    Invalid {
        path: PathBuf,
        key: String,
        msg: String,
    },

    #[error("{path}: HDF5 key `{key}`: {cause}{}", hdf5_hint(cause))]
    Hdf5 {
        path: PathBuf,
        key: String,
        cause: hdf5_reader::error::Error,
    },

    #[error("{path}: {cause}")]
    Safetensors {
        path: PathBuf,
        cause: safetensors::SafeTensorError,
    },

    /// The data layer's errors already name the file and key.
    #[error(transparent)]
    Data(Box<pma_data::DataError>),

    /// Motion readers name the file and frame.
    #[error(transparent)]
    Motion(Box<pma_data::motion::MotionError>),

    /// The trainer's train-state file errors.
    #[error(transparent)]
    Train(Box<pma_model::train::TrainError>),

    /// The model crate's checkpoint errors already name the file and tensor.
    #[error(transparent)]
    Model(Box<pma_model::error::ModelError>),

    #[error("{0}")]
    Usage(String),

    /// The process-wide interrupt flag was raised (see `pma_data::interrupt`); the output
    /// was not written.
    #[error("{0}")]
    Interrupted(#[from] pma_data::interrupt::Interrupted),
}

pub type Result<T> = std::result::Result<T, ConvertError>;

// The wrapped errors are boxed: they are large, and every `Result` here would
// carry their size.
impl From<pma_data::DataError> for ConvertError {
    fn from(e: pma_data::DataError) -> Self {
        Self::Data(Box::new(e))
    }
}

impl From<pma_data::motion::MotionError> for ConvertError {
    fn from(e: pma_data::motion::MotionError) -> Self {
        Self::Motion(Box::new(e))
    }
}

impl From<pma_model::train::TrainError> for ConvertError {
    fn from(e: pma_model::train::TrainError) -> Self {
        Self::Train(Box::new(e))
    }
}

impl From<pma_model::error::ModelError> for ConvertError {
    fn from(e: pma_model::error::ModelError) -> Self {
        Self::Model(Box::new(e))
    }
}

impl pma_data::ExitKind for ConvertError {
    fn kind(&self) -> pma_data::ErrorKind {
        use pma_data::ErrorKind;
        match self {
            Self::Io { cause, .. } => pma_data::error::input_io_kind(cause),
            Self::Zip {
                cause: zip::result::ZipError::Io(io),
                ..
            } => pma_data::error::input_io_kind(io),
            Self::Write { .. } => ErrorKind::Failure,
            Self::Data(e) => e.kind(),
            Self::Motion(e) => e.kind(),
            Self::Train(e) => e.kind(),
            Self::Model(e) => e.kind(),
            Self::Interrupted(_) => ErrorKind::Interrupted,
            Self::Zip { .. }
            | Self::Format { .. }
            | Self::ForbiddenOpcode { .. }
            | Self::ForbiddenGlobal { .. }
            | Self::Pickle { .. }
            | Self::MissingKey { .. }
            | Self::Mismatch { .. }
            | Self::Invalid { .. }
            | Self::Hdf5 { .. }
            | Self::Safetensors { .. }
            | Self::Usage(_) => ErrorKind::Refused,
        }
    }
}

impl ConvertError {
    pub(crate) fn write(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Self::Write {
            path: path.into(),
            cause: source,
        }
    }

    pub(crate) fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Self::Io {
            path: path.into(),
            cause: source,
        }
    }

    pub(crate) fn format(path: impl Into<PathBuf>, msg: impl Into<String>) -> Self {
        Self::Format {
            path: path.into(),
            msg: msg.into(),
        }
    }

    pub(crate) fn missing(
        path: impl Into<PathBuf>,
        key: impl Into<String>,
        context: impl Into<String>,
    ) -> Self {
        Self::MissingKey {
            path: path.into(),
            key: key.into(),
            context: context.into(),
        }
    }

    pub(crate) fn mismatch(
        path: impl Into<PathBuf>,
        key: impl Into<String>,
        expected: impl Into<String>,
        found: impl Into<String>,
    ) -> Self {
        Self::Mismatch {
            path: path.into(),
            key: key.into(),
            expected: expected.into(),
            found: found.into(),
        }
    }

    pub(crate) fn invalid(
        path: impl Into<PathBuf>,
        key: impl Into<String>,
        msg: impl Into<String>,
    ) -> Self {
        Self::Invalid {
            path: path.into(),
            key: key.into(),
            msg: msg.into(),
        }
    }
}

fn hdf5_hint(e: &hdf5_reader::error::Error) -> &'static str {
    use hdf5_reader::error::Error as E;
    match e {
        E::UnexpectedEof { .. } | E::OffsetOutOfBounds(_) => " (the file is truncated or corrupt)",
        E::Context { source, .. } => hdf5_hint(source),
        _ => "",
    }
}

/// A policy's description of the globals it accepts, e.g. "collections.OrderedDict".
#[derive(Debug, PartialEq, Eq)]
pub struct Accepted(pub &'static str);

impl std::fmt::Display for Accepted {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.0)
    }
}
