//! Paths of the repository's fixtures, their checkpoint conversion and the raw-bytes reader
//! the tests share.

use std::path::{Path, PathBuf};

use pma_convert::checkpoint::{convert_checkpoint, CheckpointOptions, CheckpointReport};

/// The repository root.
pub fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

/// `fixtures/convert/<name>`.
pub fn fixture(name: &str) -> PathBuf {
    root().join("fixtures/convert").join(name)
}

/// `fixtures/<rel>`, a reference checkpoint, converted to `out` (with its Adam state when
/// `with_optimizer`).
pub fn convert_fixture(
    rel: &str,
    out: &Path,
    with_optimizer: bool,
) -> pma_convert::Result<CheckpointReport> {
    convert_checkpoint(
        &root().join("fixtures").join(rel),
        out,
        &CheckpointOptions { with_optimizer },
    )
}

/// Little-endian f32 values of raw tensor bytes.
pub fn f32s(b: &[u8]) -> Vec<f32> {
    b.chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect()
}
