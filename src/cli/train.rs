//! `pma train`: train an avatar on a pma-npz dataset (spec model.md §5–§6).
//!
//! The run directory holds everything a run writes:
//!
//! | file | content |
//! | --- | --- |
//! | `config.toml` | the resolved run configuration (preset + overrides) |
//! | `model.safetensors` | the latest model (pma checkpoint) |
//! | `train_state.safetensors` | optimizer moments, RNG and sampler state, iteration |
//! | `log.csv` | one row per log interval (see `pma_model::train::log`) |
//! | `psnr_vs_time.png` | held-out PSNR against wall-clock time |
//!
//! Checkpoints are written every `ckpt_every` iterations, at the end, and on Ctrl-C; every
//! file is replaced atomically.

use std::path::{Path, PathBuf};

use anyhow::Context as _;

/// Arguments of `pma train`.
#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Training dataset (pma-npz, train profile), e.g. `DIR/train.npz` from `pma synth`.
    #[arg(long)]
    pub data: PathBuf,
    /// Run directory (created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// TOML run configuration: `preset = "..."` plus `[model]` / `[train]` overrides.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Preset when no `--config` is given: `default` (the paper's sizes, for GPUs),
    /// `cpu-small` (a 2-core CPU learns in minutes) or `tiny` (tests).
    #[arg(long, default_value = "default")]
    pub preset: String,
    /// Total iterations of the run (a resumed run continues up to this count).
    #[arg(long)]
    pub iters: Option<u64>,
    /// Wall-clock budget of this invocation in minutes; stops with a checkpoint when spent.
    #[arg(long)]
    pub minutes: Option<f64>,
    /// Continue the run in `--out` from its last checkpoint.
    #[arg(long)]
    pub resume: bool,
    /// Held-out data for the periodic evaluation (default: `novel_view.npz` next to `--data`,
    /// if it exists; otherwise no held-out evaluation).
    #[arg(long)]
    pub eval_data: Option<PathBuf>,
    /// Random seed (model initialisation, ray sampling, density noise); overrides the config.
    #[arg(long)]
    pub seed: Option<u64>,
    /// No progress bar (log lines only).
    #[arg(long)]
    pub quiet: bool,
}

#[cfg(not(feature = "train"))]
pub fn run(_args: Args) -> anyhow::Result<()> {
    anyhow::bail!("this build of pma has no training support; rebuild with `--features train` (on by default)")
}

#[cfg(feature = "train")]
pub fn run(args: Args) -> anyhow::Result<()> {
    imp::run(args).map(|_| ())
}

#[cfg(feature = "train")]
pub use imp::{train_run, TrainOutcome, TrainRequest};

/// Bundled font for plot text: plotters has no fonts of its own without system libraries.
static FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");

/// Plot held-out PSNR (and, lighter, training PSNR) against wall-clock time and write it
/// atomically as a PNG.
pub fn plot_psnr_vs_time(
    eval: &[(f64, f64)],
    train: &[(f64, f64)],
    title: &str,
    path: &Path,
) -> anyhow::Result<()> {
    use plotters::prelude::*;

    static REGISTER: std::sync::Once = std::sync::Once::new();
    REGISTER.call_once(|| {
        // A font that fails to parse leaves text unrendered; the curves are still drawn.
        let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, FONT);
    });

    let (w, h) = (900u32, 540u32);
    let mut buf = vec![0u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        let finite = |v: &&(f64, f64)| v.0.is_finite() && v.1.is_finite();
        let all: Vec<(f64, f64)> = eval.iter().chain(train).filter(finite).copied().collect();
        let minutes = |s: f64| s / 60.0;
        let x_max = all.iter().map(|p| minutes(p.0)).fold(0.0f64, f64::max).max(1e-3) * 1.02;
        let (mut y_min, mut y_max) = all
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| (lo.min(p.1), hi.max(p.1)));
        if !y_min.is_finite() {
            (y_min, y_max) = (0.0, 30.0);
        }
        let pad = ((y_max - y_min) * 0.08).max(0.5);
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 22))
            .margin(16)
            .x_label_area_size(44)
            .y_label_area_size(56)
            .build_cartesian_2d(0.0..x_max, (y_min - pad)..(y_max + pad))
            .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        chart
            .configure_mesh()
            .x_desc("wall-clock time [min]")
            .y_desc("PSNR [dB]")
            .label_style(("sans-serif", 15))
            .draw()
            .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        let train_colour = RGBColor(150, 150, 150);
        if !train.is_empty() {
            chart
                .draw_series(LineSeries::new(
                    train.iter().filter(finite).map(|p| (minutes(p.0), p.1)),
                    train_colour.stroke_width(1),
                ))
                .map_err(|e| anyhow::anyhow!("plot: {e}"))?
                .label("training batch PSNR")
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], train_colour));
        }
        if !eval.is_empty() {
            let blue = RGBColor(31, 90, 180);
            chart
                .draw_series(LineSeries::new(
                    eval.iter().filter(finite).map(|p| (minutes(p.0), p.1)),
                    blue.stroke_width(2),
                ))
                .map_err(|e| anyhow::anyhow!("plot: {e}"))?
                .label("held-out PSNR")
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], blue.stroke_width(2)));
            chart
                .draw_series(eval.iter().filter(finite).map(|p| Circle::new((minutes(p.0), p.1), 3, blue.filled())))
                .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::LowerRight)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 15))
            .draw()
            .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        root.present().map_err(|e| anyhow::anyhow!("plot: {e}"))?;
    }
    let img = image::RgbImage::from_raw(w, h, buf).context("plot buffer has the wrong size")?;
    super::eval::write_png_atomic(&img, path)
}

#[cfg(feature = "train")]
mod imp {
    use super::*;

    pub struct TrainRequest;
    pub struct TrainOutcome;

    pub fn run(_args: Args) -> anyhow::Result<TrainOutcome> {
        anyhow::bail!("`pma train` is being written")
    }

    pub fn train_run(_req: TrainRequest) -> anyhow::Result<TrainOutcome> {
        anyhow::bail!("`pma train` is being written")
    }
}
