//! The data layer's typed error. Every variant that comes from a file names
//! the file and the key, and says what was expected and what was found, so a
//! bad dataset can be fixed from the message alone.

use std::path::PathBuf;

/// Result alias for the data layer.
pub type Result<T, E = DataError> = std::result::Result<T, E>;

#[derive(Debug, thiserror::Error)]
pub enum DataError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },

    /// The container itself is unreadable (not a zip, truncated member, bad npy header).
    #[error("{file}: {key}: {msg}")]
    Format {
        file: String,
        key: String,
        msg: String,
    },

    #[error("{file}: key `{key}` is required for the {profile} profile but is missing{hint}")]
    MissingKey {
        file: String,
        key: String,
        profile: String,
        /// Extra advice, starting with "; " when present.
        hint: String,
    },

    #[error("{file}: key `{key}` has shape {found:?}, expected {expected}")]
    Shape {
        file: String,
        key: String,
        expected: String,
        found: Vec<usize>,
    },

    #[error("{file}: key `{key}` has dtype {found}, expected {expected}")]
    Dtype {
        file: String,
        key: String,
        expected: String,
        found: String,
    },

    /// Two keys disagree about a count (P, C, N, B or H·W).
    #[error("{file}: inconsistent {count}: `{key}` has {found}, but `{other_key}` has {expected}")]
    Count {
        file: String,
        count: String,
        key: String,
        found: usize,
        other_key: String,
        expected: usize,
    },

    #[error("{file}: key `{key}`[{position}] = {value} is out of range, expected an integer in [0, {bound})")]
    Index {
        file: String,
        key: String,
        position: usize,
        value: String,
        bound: usize,
    },

    #[error("{file}: key `{key}` holds a non-finite value ({value}) at flat index {position}")]
    NonFinite {
        file: String,
        key: String,
        position: usize,
        value: f64,
    },

    /// A value that has the right type and shape but is wrong (focal <= 0,
    /// non-orthonormal rotation, kp3d not matching FK, ...).
    #[error("{file}: key `{key}`: {problem}: expected {expected}, found {found}")]
    Value {
        file: String,
        key: String,
        problem: String,
        expected: String,
        found: String,
    },

    #[error("{file}: empty split: {what}")]
    Empty { file: String, what: String },

    /// A rest pose that the bone-align construction or the volume
    /// initialisation cannot use (coincident joints, zero-length bone).
    #[error("degenerate rest pose at joint {joint} ({name}): {reason}")]
    DegenerateRestPose {
        joint: usize,
        name: &'static str,
        reason: String,
    },

    /// A 6D rotation whose columns cannot be orthonormalised.
    #[error("degenerate 6D rotation: {reason}")]
    DegenerateRotation { reason: String },

    /// An in-memory camera that fails validation (not tied to a file).
    #[error("invalid camera: {problem}: expected {expected}, found {found}")]
    Camera {
        problem: String,
        expected: String,
        found: String,
    },

    /// Invalid arguments to a data-layer function (sizes that do not fit, ...).
    #[error("invalid argument `{name}`: expected {expected}, found {found}")]
    Argument {
        name: String,
        expected: String,
        found: String,
    },
}

impl DataError {
    pub(crate) fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        DataError::Io {
            path: path.into(),
            source,
        }
    }

    pub(crate) fn arg(
        name: impl Into<String>,
        expected: impl Into<String>,
        found: impl std::fmt::Display,
    ) -> Self {
        DataError::Argument {
            name: name.into(),
            expected: expected.into(),
            found: found.to_string(),
        }
    }
}
