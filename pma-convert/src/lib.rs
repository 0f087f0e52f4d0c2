//! Importers for foreign files: reference PyTorch checkpoints, A-NeRF/DANBO
//! `.h5`/`.npz` datasets and real motion.

pub mod checkpoint;
pub mod dataset;
pub mod error;
pub mod h5;
pub mod motion;
pub mod pickle;
pub mod raw;
pub mod torch;
pub mod train_state;

pub use error::{ConvertError, Result};
pub use raw::RawTensor;

use std::path::Path;

/// Temporary files are created owner-only (0600); a converted file is an
/// ordinary output, so give it the usual 0644 once it is in place.
pub(crate) fn set_readable(path: &Path) -> Result<()> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o644))
            .map_err(|e| ConvertError::io(path, e))?;
    }
    Ok(())
}
