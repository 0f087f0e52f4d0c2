//! `pma eval`: PSNR and SSIM of a trained avatar on a held-out split (placeholder body while
//! the rendering API lands).

use std::io::Write as _;
use std::path::{Path, PathBuf};

use anyhow::Context as _;

#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Trained model (`RUN/model.safetensors`).
    #[arg(long)]
    pub model: PathBuf,
    /// Dataset: a pma-npz file, or a directory from `pma synth` holding `<split>.npz`.
    #[arg(long)]
    pub data: PathBuf,
    /// Which images to score.
    #[arg(long, default_value = "novel_view")]
    pub split: String,
    /// Output directory for eval.json and the side-by-side PNGs (default: next to the model).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

pub fn run(_args: Args) -> anyhow::Result<()> {
    anyhow::bail!("`pma eval` is being written")
}

/// Encode `img` as PNG and replace `path` atomically.
pub fn write_png_atomic(img: &image::RgbImage, path: &Path) -> anyhow::Result<()> {
    let mut bytes = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png)
        .with_context(|| format!("encoding {}", path.display()))?;
    write_atomic(path, &bytes)
}

/// Serialise `value` as pretty JSON and replace `path` atomically.
pub fn write_json_atomic<T: serde::Serialize>(value: &T, path: &Path) -> anyhow::Result<()> {
    let mut text = serde_json::to_string_pretty(value)?;
    text.push('\n');
    write_atomic(path, text.as_bytes())
}

/// Temporary file in the target directory, then rename: readers never see a partial file.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let mut tmp = tempfile::NamedTempFile::new_in(dir).with_context(|| format!("creating a file in {}", dir.display()))?;
    tmp.write_all(bytes).with_context(|| format!("writing {}", path.display()))?;
    tmp.as_file().sync_all().with_context(|| format!("writing {}", path.display()))?;
    tmp.persist(path).with_context(|| format!("replacing {}", path.display()))?;
    Ok(())
}
