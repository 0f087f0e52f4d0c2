//! Paths of the repository's fixtures and the raw-bytes reader the tests share.

use std::path::{Path, PathBuf};

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

/// Little-endian f32 values of raw tensor bytes.
pub fn f32s(b: &[u8]) -> Vec<f32> {
    b.chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect()
}
