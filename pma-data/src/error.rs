//! The data layer's typed error. Every variant that comes from a file names
//! the file and the key, and says what was expected and what was found, so a
//! bad dataset can be fixed from the message alone.

use std::path::{Path, PathBuf};

/// Result alias for the data layer.
pub type Result<T, E = DataError> = std::result::Result<T, E>;

/// What an error means for the one who ran the command: the exit status of every pma
/// command follows from it (`pma` maps [`ErrorKind::Refused`] to 2,
/// [`ErrorKind::Interrupted`] to 128 + the signal, [`ErrorKind::Failure`] to 1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ErrorKind {
    /// The input or the command is wrong (a missing, corrupt or hostile file, a flag out of
    /// range, an output path that cannot be used): the user has to change it.
    Refused,
    /// The work was stopped on request (Ctrl-C, SIGTERM, SIGHUP).
    Interrupted,
    /// Everything else: the environment (a full disk, an I/O error) or the work itself.
    Failure,
}

/// An error type that says which [`ErrorKind`] it is. Every library error of pma
/// implements it; front ends map the kind to their own reporting.
pub trait ExitKind {
    fn kind(&self) -> ErrorKind;
}

impl ExitKind for crate::interrupt::Interrupted {
    fn kind(&self) -> ErrorKind {
        ErrorKind::Interrupted
    }
}

/// The kind of an I/O error met while reading an input: a path that does not lead to a
/// readable file (missing, a directory, no permission, a symlink loop, a name too long, not
/// a regular file) or content that is not what it claims (truncated, invalid) is refused
/// input; anything else (a device error, out of memory) is a failure.
pub fn input_io_kind(e: &std::io::Error) -> ErrorKind {
    use std::io::ErrorKind as K;
    let refused = matches!(
        e.kind(),
        K::NotFound
            | K::PermissionDenied
            | K::InvalidData
            | K::InvalidInput
            | K::UnexpectedEof
            | K::IsADirectory
            | K::NotADirectory
    );
    #[cfg(unix)]
    let refused = refused
        || matches!(
            e.raw_os_error(),
            Some(libc::ELOOP | libc::ENAMETOOLONG | libc::ENOTDIR | libc::EISDIR | libc::EACCES)
        );
    if refused {
        ErrorKind::Refused
    } else {
        ErrorKind::Failure
    }
}

/// `msg` on one line: line breaks (and the indentation after them) become "; ", list
/// bullets are dropped. Every message pma prints for a refused input is one line.
pub fn one_line(msg: &str) -> String {
    let mut out = String::with_capacity(msg.len());
    for line in msg.lines().map(str::trim).filter(|l| !l.is_empty()) {
        let item = line.strip_prefix("- ").unwrap_or(line);
        if !out.is_empty() {
            out.push_str(if out.ends_with(':') { " " } else { "; " });
        }
        out.push_str(item);
    }
    out
}

/// `x` as a message shows it: plain while that is short, in scientific notation for very
/// large or very small magnitudes (`1e300`, not three hundred digits).
pub fn short_number(x: f64) -> String {
    let a = x.abs();
    if x.is_finite() && a != 0.0 && !(1e-4..1e9).contains(&a) {
        format!("{x:e}")
    } else {
        format!("{x}")
    }
}

/// A file that could not be read or written: the one file error of every pma error type
/// (data, model, training, evaluation), which each wraps as it is.
#[derive(Debug, thiserror::Error)]
pub enum FileError {
    /// Reading an input failed: refused input or a failure (see [`input_io_kind`]).
    #[error("{path}: {source}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },

    /// Writing an output failed (a full disk, no permission): a failure, not bad input.
    #[error("writing {path}: {source}")]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

impl FileError {
    pub fn read(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Self::Read {
            path: path.into(),
            source,
        }
    }

    pub fn write(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Self::Write {
            path: path.into(),
            source,
        }
    }

    /// A `map_err` for reading `path`.
    pub fn reading(path: &Path) -> impl FnOnce(std::io::Error) -> Self + '_ {
        move |source| Self::read(path, source)
    }

    /// A `map_err` for writing `path`.
    pub fn writing(path: &Path) -> impl FnOnce(std::io::Error) -> Self + '_ {
        move |source| Self::write(path, source)
    }
}

impl ExitKind for FileError {
    fn kind(&self) -> ErrorKind {
        match self {
            FileError::Read { source, .. } => input_io_kind(source),
            FileError::Write { .. } => ErrorKind::Failure,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum DataError {
    #[error(transparent)]
    File(#[from] FileError),

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

    /// The process-wide interrupt flag was raised while a file was read or written.
    #[error("{0}")]
    Interrupted(#[from] crate::interrupt::Interrupted),

    /// Invalid arguments to a data-layer function (sizes that do not fit, ...).
    #[error("invalid argument `{name}`: expected {expected}, found {found}")]
    Argument {
        name: String,
        expected: String,
        found: String,
    },
}

impl ExitKind for DataError {
    fn kind(&self) -> ErrorKind {
        match self {
            DataError::File(f) => f.kind(),
            DataError::Interrupted(_) => ErrorKind::Interrupted,
            _ => ErrorKind::Refused,
        }
    }
}

impl DataError {
    pub(crate) fn write(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        FileError::write(path, source).into()
    }

    pub(crate) fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        FileError::read(path, source).into()
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

#[cfg(test)]
mod tests {
    use super::*;
    use std::error::Error as _;
    use std::io;

    /// The file error reads as the data layer's own read and write errors did ("PATH: ERROR",
    /// "writing PATH: ERROR"), keeps the I/O error as its source, and its kind follows the
    /// I/O error on a read and is a failure on a write, also wrapped in a [`DataError`].
    #[test]
    fn file_errors_name_the_file_and_keep_their_kind() {
        let missing = || io::Error::new(io::ErrorKind::NotFound, "No such file");
        let full = || io::Error::new(io::ErrorKind::StorageFull, "disk full");
        let read = DataError::io("/d/train.npz", missing());
        assert_eq!(read.to_string(), "/d/train.npz: No such file");
        assert_eq!(read.kind(), ErrorKind::Refused);
        let source = read.source().and_then(|s| s.downcast_ref::<io::Error>());
        assert_eq!(source.map(io::Error::kind), Some(io::ErrorKind::NotFound));
        let broken = FileError::read("/d/x", io::Error::other("device error"));
        assert_eq!(broken.kind(), ErrorKind::Failure);
        let write = DataError::write("/out/a.npz", full());
        assert_eq!(write.to_string(), "writing /out/a.npz: disk full");
        assert_eq!(write.kind(), ErrorKind::Failure);
        let writing = FileError::writing(Path::new("/out/b.npz"))(full());
        assert_eq!(writing.to_string(), "writing /out/b.npz: disk full");
    }
}
