//! Importers for foreign files: reference PyTorch checkpoints, A-NeRF/DANBO
//! `.h5`/`.npz` datasets, raw ZJU-MoCap captures and real motion.

pub mod capture;
pub mod checkpoint;
pub mod dataset;
pub mod error;
pub mod h5;
pub mod motion;
pub mod pickle;
pub mod raw;
pub mod smpl;
pub mod torch;
pub mod train_state;

pub use error::{ConvertError, Result};

/// The largest pickle, `.npy` or SMPL file a converter reads into memory (4 GiB); larger
/// inputs are refused before they are read.
pub const MAX_INPUT_BYTES: u64 = 4 << 30;
pub use raw::RawTensor;

/// A file's extension in lower case (empty when it has none), which picks its reader.
pub(crate) fn extension(path: &std::path::Path) -> String {
    path.extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase()
}
