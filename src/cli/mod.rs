//! One module per subcommand: clap `Args` plus `run`. The pipelines live in the libraries;
//! these modules parse, call and print.

pub mod bench;
pub mod check_stability;
pub mod convert;
pub mod demo;
pub mod eval;
pub mod forward;
pub mod inspect;
pub mod mesh;
pub mod metrics;
#[cfg(feature = "train")]
pub mod plot;
pub mod progress;
pub mod render;
pub mod synth;
pub mod train;

use std::path::Path;

use anyhow::Context as _;
use pma_data::dataset::{Dataset, Profile};

/// Exit status of a command refused because of its input (a split the file does not hold,
/// a corrupt file), as for clap's usage errors: the user has to change the command or its
/// input. Every other failure exits 1.
pub const EXIT_REFUSED: u8 = 2;
pub const EXIT_FAILURE: u8 = 1;

/// An error the user has to fix in the command or its input (see [`EXIT_REFUSED`]).
#[derive(Debug)]
pub struct Refused(Box<dyn std::error::Error + Send + Sync>);

impl Refused {
    pub fn new(e: impl Into<Box<dyn std::error::Error + Send + Sync>>) -> Self {
        Self(e.into())
    }
}

impl std::fmt::Display for Refused {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        self.0.fmt(f)
    }
}

impl std::error::Error for Refused {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        self.0.source()
    }
}

/// The exit status for `e`: [`EXIT_REFUSED`] if a [`Refused`] is anywhere in its chain.
pub fn exit_code(e: &anyhow::Error) -> u8 {
    if e.chain().any(|c| c.is::<Refused>()) {
        EXIT_REFUSED
    } else {
        EXIT_FAILURE
    }
}

/// `e` and its causes on one line, each cause left out when the message already holds it
/// (many errors print their source themselves).
pub fn report(e: &anyhow::Error) -> String {
    let mut out = String::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if out.contains(&text) {
            continue;
        }
        if !out.is_empty() {
            out.push_str(": ");
        }
        out.push_str(&text);
    }
    out
}

/// An evaluation error, as [`Refused`] when it is about the input.
pub fn eval_error(e: pma_model::eval::EvalError) -> anyhow::Error {
    if e.is_bad_input() {
        Refused::new(e).into()
    } else {
        e.into()
    }
}

/// Open the compute device named by a `--device` flag: cpu, cuda, cuda:N, metal or metal:N.
/// A backend missing from this build is reported with the cargo feature that brings it.
pub fn device(spec: &str) -> anyhow::Result<candle_core::Device> {
    Ok(pma_model::device::parse_device(spec)?)
}

/// Read a dataset for `profile`, printing its warnings.
pub fn read_dataset(path: &Path, profile: Profile) -> anyhow::Result<Dataset> {
    let data = pma_model::eval::read_dataset(path, profile)?;
    for w in &data.warnings {
        eprintln!("warning: {}: {w}", path.display());
    }
    Ok(data)
}

/// Serialise `value` as pretty JSON and replace `path` atomically.
pub fn write_json<T: serde::Serialize>(value: &T, path: &Path) -> anyhow::Result<()> {
    let mut text = serde_json::to_string_pretty(value)?;
    text.push('\n');
    pma_data::fsio::write_atomic(path, text.as_bytes())
        .with_context(|| format!("writing {}", path.display()))
}

/// Encode `img` as PNG and replace `path` atomically.
pub fn write_png(img: &image::RgbImage, path: &Path) -> anyhow::Result<()> {
    Ok(pma_model::eval::write_png(img, path)?)
}
