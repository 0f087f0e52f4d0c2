//! `pma eval`: PSNR, SSIM and LPIPS of a trained avatar on a held-out split (the protocol is
//! `pma_model::eval`'s).
//!
//! Output: a table on stdout, `eval.json` (`{"split", "psnr", "ssim", "lpips", "per_image":
//! [...]}`; `lpips` is null for images under 31×31 pixels)
//! and side-by-side PNGs (ground truth | render | error heat map) for a few images.
//! `--freq-png` also plots the split's mean frequency histograms of render and ground truth
//! (`pma_model::eval::spectrum`).

use std::path::{Path, PathBuf};

use anyhow::Context as _;
use pma_data::dataset::Profile;
use pma_model::eval::{
    evaluate, mean_foreground_colour, resolve_split, split_images, spread, EvalOptions, EvalReport,
};
use pma_model::render::avatar::Avatar;
use pma_model::render::PassOptions;

use super::{read_dataset, write_json};

#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Trained model (`RUN/model.safetensors`, or the run directory: its newest complete model).
    #[arg(long)]
    pub model: PathBuf,
    /// Dataset: a pma-npz file, or a directory from `pma synth` holding `<split>.npz`.
    #[arg(long)]
    pub data: PathBuf,
    /// Which images to score: `novel_view`, `novel_pose`, `train` or `val`. In a file with
    /// `eval_tag`, the images with the split's tag; a file without one holds only the split
    /// its name gives (`novel_pose.npz`), any other split is refused.
    #[arg(long, default_value = "novel_view")]
    pub split: String,
    /// Output directory for eval.json and the PNGs (default: `eval_<split>` next to the model).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Region of the PSNR: `mask` (foreground pixels, the reference's committed code) or
    /// `bbox` (the tight box of the mask, as the paper's text says).
    #[arg(long, default_value = "mask")]
    pub psnr_region: String,
    /// SSIM data range (2.0 reproduces the reference's scikit-image; 1.0 is the textbook value).
    #[arg(long, default_value_t = 2.0)]
    pub ssim_data_range: f64,
    /// Score at most this many images, evenly spread over the split (default: all).
    #[arg(long)]
    pub max_images: Option<usize>,
    /// Side-by-side PNGs to write (evenly spread).
    #[arg(long, default_value_t = 4)]
    pub pngs: usize,
    /// Also write the split's mean frequency histograms (render against ground truth, log
    /// scale) as a PNG here.
    #[arg(long)]
    pub freq_png: Option<PathBuf>,
    /// Rays per render chunk.
    #[arg(long, default_value_t = 4096)]
    pub chunk: usize,
    /// Training data, for the trivial baseline (mean training foreground colour inside the
    /// mask). Default: `train.npz` beside a split file or in the `--data` directory.
    #[arg(long)]
    pub train_data: Option<PathBuf>,
    #[command(flatten)]
    pub pass: PassOptions,
    #[command(flatten)]
    pub device: super::DeviceArgs,
}

pub fn run(mut args: Args) -> anyhow::Result<()> {
    if !(1..=pma_model::render::MAX_CHUNK_RAYS).contains(&args.chunk) {
        super::refuse!(
            "--chunk {} must be in 1..={}",
            args.chunk,
            pma_model::render::MAX_CHUNK_RAYS
        );
    }
    if args.pngs > 10_000 {
        super::refuse!("--pngs {}: at most 10000", args.pngs);
    }
    // Opened first: a device this build cannot use is refused before any work.
    let device = args.device.open()?;
    // A run directory: the PNGs go beside its published model.
    let run_dir = args.model.is_dir().then(|| args.model.clone());
    args.model = super::model_path(&args.model)?;
    super::check_paths(pma_data::fsio::PathCheck::new().input("--model", &args.model))?;
    let (data_path, split) = resolve_split(&args.data, &args.split)?;
    let out = args.out.clone().unwrap_or_else(|| {
        run_dir
            .as_deref()
            .unwrap_or(args.model.parent().unwrap_or(Path::new(".")))
            .join(format!("eval_{}", split.name))
    });
    let baseline_path = baseline_source(&args, &data_path);
    super::check_paths(
        pma_data::fsio::PathCheck::new()
            .input("--model", &args.model)
            .input("--data", &data_path)
            .input_opt("--train-data", baseline_path.as_deref())
            .output_dir("--out", &out, ["eval.json"])
            .output_opt("--freq-png", args.freq_png.as_deref()),
    )?;
    let avatar = Avatar::load(&args.model, &device)
        .with_context(|| format!("loading model {}", args.model.display()))?
        .with_numerics(super::numerics());
    let data = read_dataset(&data_path, Profile::Eval)?;
    let images = split_images(&data, &data_path, &split)?;
    let images = spread(&images, args.max_images.unwrap_or(usize::MAX));
    // The side-by-side PNGs must not replace an input either.
    let pngs: Vec<String> = spread(&images, args.pngs)
        .iter()
        .map(|n| format!("{}_{n:04}.png", split.name))
        .collect();
    super::check_paths(
        pma_data::fsio::PathCheck::new()
            .input("--model", &args.model)
            .input("--data", &data_path)
            .input_opt("--train-data", baseline_path.as_deref())
            .output_dir("--out", &out, pngs),
    )?;
    pma_data::fsio::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let baseline = match baseline_path {
        Some(p) => Some(mean_foreground_colour(&read_dataset(&p, Profile::Eval)?)?),
        None => None,
    };
    let opts = EvalOptions {
        region: args.psnr_region.parse()?,
        ssim_data_range: args.ssim_data_range,
        chunk: args.chunk,
        png_dir: Some(out.clone()),
        pngs: args.pngs,
        baseline_colour: baseline,
        pass: args.pass.clone(),
    };
    let report = evaluate(&avatar, &data, &split.name, &images, &opts, &mut |_, _| {})?;
    warn_empty_masks(&report, &data.source);
    print_table(&report);
    let json = out.join("eval.json");
    write_json(&report, &json)?;
    println!(
        "wrote {} and {} side-by-side PNG(s) to {}",
        json.display(),
        report.pngs.len(),
        out.display()
    );
    if let Some(path) = &args.freq_png {
        let title = format!(
            "frequency histograms, {} ({} images)",
            report.split, report.images
        );
        super::plot::plot_freq_hist(&report.freq, &title, path)?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

fn baseline_source(args: &Args, data_path: &Path) -> Option<PathBuf> {
    if let Some(p) = &args.train_data {
        return Some(p.clone());
    }
    let beside = data_path.parent()?.join("train.npz");
    beside.is_file().then_some(beside)
}

/// Score the whole-file split `split` of `path` (`pma_model::eval::score_split_file`) with
/// a progress bar, showing the file's warnings and the images left out for an empty mask.
#[cfg(feature = "train")]
pub fn score_split(
    avatar: &Avatar,
    path: &Path,
    split: &str,
    max_images: usize,
    opts: &EvalOptions,
    quiet: bool,
) -> anyhow::Result<EvalReport> {
    let bar = super::progress::bar(quiet, 0, "      images");
    let scored =
        pma_model::eval::score_split_file(avatar, path, split, max_images, opts, &mut |d, t| {
            bar.set_length(t as u64);
            bar.set_position(d as u64);
        })?;
    bar.finish_and_clear();
    for w in &scored.warnings {
        eprintln!("warning: {}: {w}", path.display());
    }
    warn_empty_masks(&scored.report, &scored.source);
    Ok(scored.report)
}

/// The images `evaluate` left out for an empty mask.
pub fn warn_empty_masks(report: &EvalReport, source: &str) {
    for n in &report.empty_masks {
        eprintln!("warning: {source}: image {n} has an empty mask; skipped");
    }
}

fn print_table(report: &EvalReport) {
    println!("split {} ({} images)", report.split, report.images);
    println!(
        "{:>6}  {:>8}  {:>7}  {:>7}",
        "image", "PSNR", "SSIM", "LPIPS"
    );
    for s in &report.per_image {
        println!(
            "{:>6}  {:>8.3}  {:>7.4}  {:>7}",
            s.index,
            s.psnr,
            s.ssim,
            lpips_cell(s.lpips)
        );
    }
    println!(
        "{:>6}  {:>8.3}  {:>7.4}  {:>7}",
        "mean",
        report.psnr,
        report.ssim,
        lpips_cell(report.lpips)
    );
    println!(
        "frequency-histogram distance (mean |log10 ratio| over {} bins): {:.4}",
        report.freq.hist_gt.len(),
        report.freq.distance
    );
    if let Some(b) = report.baseline_psnr {
        println!("baseline (mean training colour inside the mask): PSNR {b:.3}");
    }
    if report.lpips.is_nan() {
        println!(
            "LPIPS: n/a for images under {0}x{0} pixels (AlexNet's minimum)",
            pma_model::eval::lpips::MIN_SIDE
        );
    }
}

/// LPIPS to 4 decimals, `n/a` where it could not be computed.
pub fn lpips_cell(v: f64) -> String {
    if v.is_nan() {
        "n/a".to_string()
    } else {
        format!("{v:.4}")
    }
}
