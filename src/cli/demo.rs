//! `pma demo`: the main job on the embedded default. Makes the synthetic scene (`pma synth`
//! defaults), trains the `cpu-small` preset with the fast recipe
//! (`pma_model::train::recipe`; `--parity` trains without it) for a wall-clock budget,
//! evaluates the novel-view and novel-pose splits, and writes renders, `psnr_vs_time.png`
//! and `summary.json`:
//!
//! ```text
//! DIR/scene/{train,novel_view,novel_pose}.npz, scene.json, preview.png
//! DIR/run/{ckpt-<iteration>/, config.toml, model.safetensors, log.csv, psnr_vs_time.png}
//! DIR/renders/<split>_<image>.png       ground truth | render | error heat map
//! DIR/eval_<split>.json                 per-image scores
//! DIR/psnr_vs_time.png                  copy of the run's plot
//! DIR/summary.json
//! ```

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::Context as _;
use pma_data::dataset::Profile;
use pma_data::synth::{generate, SynthConfig};
use pma_model::eval::{mean_foreground_colour, EvalOptions};
use pma_model::render::avatar::Avatar;
use pma_model::train::{Preset, RunConfig, TrainOutcome, TrainRequest, LOG_FILE};

use super::eval::{lpips_cell, score_split};
use super::train::{train, PLOT_FILE};
use super::{progress, read_dataset, write_json};

#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Training budget in minutes (scene synthesis and the final evaluation come on top,
    /// about half a minute on 2 cores). The default fits `cargo run --release -- demo` on a
    /// fresh 2-core machine in 15 minutes, the release build with the crates' download
    /// (about 5 minutes) included, and the recipe reaches in it the held-out PSNR parity
    /// mode reaches in 10 minutes.
    #[arg(long, default_value_t = 7.0)]
    pub minutes: f64,
    /// Train the preset as the paper's code does (no fast recipe: every ray and sample
    /// through the network, uniform rays, the reference's learning-rate schedule).
    #[arg(long)]
    pub parity: bool,
    /// Output directory.
    #[arg(long, default_value = "runs/demo")]
    pub out: PathBuf,
    /// Stop after this many iterations even if budget is left.
    #[arg(long)]
    pub iters: Option<u64>,
    /// Training preset (`cpu-small` is the one sized for this demo; `tiny` is for tests).
    #[arg(long, default_value = "cpu-small")]
    pub preset: String,
    /// Scene image size in pixels (default: `pma synth`'s).
    #[arg(long)]
    pub res: Option<usize>,
    /// Training frames of the scene (default: `pma synth`'s).
    #[arg(long)]
    pub frames: Option<usize>,
    /// Score at most this many images per split, evenly spread over it (0 = all); rendering
    /// the full splits takes several times as long as the default.
    #[arg(long, default_value_t = 32)]
    pub max_eval_images: usize,
    /// Side-by-side PNGs per split.
    #[arg(long, default_value_t = 4)]
    pub pngs: usize,
    /// Random seed of the training run.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// No progress bars.
    #[arg(long)]
    pub quiet: bool,
    /// Compute device for training and evaluation: cpu, cuda, cuda:N, metal (cuda/metal
    /// need a binary built with that feature). Scene synthesis runs on the CPU.
    #[arg(long, default_value = "cpu")]
    pub device: String,
}

/// The part of `summary.json` other tools read.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct SplitSummary {
    pub psnr: f64,
    pub ssim: f64,
    /// `null` when the images are under LPIPS's 31×31 minimum.
    pub lpips: Option<f64>,
    pub baseline_psnr: f64,
    pub images: usize,
    /// The file the split was scored on.
    pub data: PathBuf,
}

#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Summary {
    pub iterations: u64,
    /// Wall-clock seconds of training (including the periodic held-out evaluations).
    pub wall_s: f64,
    /// Training iterations per second (periodic evaluations excluded).
    pub it_per_s: f64,
    pub model: PathBuf,
    /// The held-out file the run was scored on while it trained (novel view); each split
    /// names its own file in `splits`.
    pub data: PathBuf,
    /// The training images.
    pub train_data: PathBuf,
    pub preset: String,
    /// The fast recipe's options the run trained with (empty: parity).
    pub options: Vec<String>,
    /// Held-out images each point of the plot's curve scores (the periodic evaluation); the
    /// splits below score `images` each.
    pub curve_images: usize,
    pub skipped_steps: u64,
    pub splits: std::collections::BTreeMap<String, SplitSummary>,
    pub plot: PathBuf,
    pub log: PathBuf,
    pub renders: PathBuf,
}

/// The held-out splits the demo scores.
const SPLITS: [&str; 2] = ["novel_view", "novel_pose"];

pub fn run(args: Args) -> anyhow::Result<()> {
    let preset: Preset = args.preset.parse()?;
    super::check_minutes("--minutes", Some(args.minutes))?;
    // Opened first: a device this build cannot use is refused before any work.
    let device = super::device(&args.device)?;
    super::check_paths(pma_data::fsio::PathCheck::new().output_dir(
        "--out",
        &args.out,
        ["summary.json", PLOT_FILE],
    ))?;
    let out = args.out.clone();
    pma_data::fsio::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let scene = make_scene(args.res, args.frames, args.quiet, &out.join("scene"))?;
    let (outcome, it_per_s, options) =
        train_scene(&args, preset, &scene, &out.join("run"), &device)?;
    println!("[3/4] evaluating");
    let renders = out.join("renders");
    let splits = evaluate_splits(&args, preset, &scene, &outcome.model, &out, &device)?;

    let plot = out.join(PLOT_FILE);
    let run_plot = out.join("run").join(PLOT_FILE);
    let bytes =
        std::fs::read(&run_plot).with_context(|| format!("reading {}", run_plot.display()))?;
    pma_data::fsio::write_atomic(&plot, &bytes)
        .with_context(|| format!("copying the plot to {}", plot.display()))?;
    let summary = Summary {
        iterations: outcome.iterations,
        wall_s: outcome.wall_s,
        it_per_s,
        model: outcome.model.clone(),
        data: scene.join(format!("{}.npz", SPLITS[0])),
        train_data: scene.join("train.npz"),
        preset: preset.name().to_string(),
        options,
        curve_images: RunConfig::from_preset(preset).train.eval_images,
        skipped_steps: outcome.skipped,
        splits,
        plot,
        log: out.join("run").join(LOG_FILE),
        renders,
    };
    let path = out.join("summary.json");
    write_json(&summary, &path)?;
    println!("[4/4] wrote {}", path.display());
    println!("{}", serde_json::to_string_pretty(&summary)?);
    Ok(())
}

/// Step 1: the scene (reused when an identical one is already there).
pub fn make_scene(
    res: Option<usize>,
    frames: Option<usize>,
    quiet: bool,
    scene: &Path,
) -> anyhow::Result<PathBuf> {
    let mut synth = SynthConfig::default();
    if let Some(r) = res {
        synth.res = r;
    }
    if let Some(f) = frames {
        synth.frames = f;
    }
    if scene_matches(scene, &synth) {
        println!("[1/4] reusing the synthetic scene in {}", scene.display());
        return Ok(scene.to_path_buf());
    }
    println!("[1/4] synthesising the scene into {}", scene.display());
    let bar = progress::bar(quiet, 0, "      images");
    let summary = generate(&synth, scene, &mut |done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })
    .context("synthesising the demo scene")?;
    bar.finish_and_clear();
    for s in &summary.splits {
        println!(
            "      {}: {} images, {} poses",
            s.path.display(),
            s.images,
            s.poses
        );
    }
    Ok(scene.to_path_buf())
}

/// Step 2: training for the budget; returns the outcome, the training it/s and the options
/// of the fast recipe it trained with.
fn train_scene(
    args: &Args,
    preset: Preset,
    scene: &Path,
    run_dir: &Path,
    device: &candle_core::Device,
) -> anyhow::Result<(TrainOutcome, f64, Vec<String>)> {
    let mut run = RunConfig::from_preset(preset);
    run.train.seed = args.seed;
    run.train.iters = args.iters.unwrap_or(pma_model::train::presets::MAX_ITERS);
    let mut options = Vec::new();
    if args.parity {
        println!(
            "[2/4] training preset `{preset}` for {} min in parity with the paper's code (--parity)",
            args.minutes
        );
    } else {
        println!(
            "[2/4] training preset `{preset}` for {} min with the fast recipe (`pma train --fast`; \
             --parity trains without it):",
            args.minutes
        );
        for c in pma_model::train::recipe::fast(&mut run, Some(args.minutes * 60.0)) {
            println!("      {}: {}", c.option, c.why);
            options.push(c.option.to_string());
        }
    }
    let req = TrainRequest {
        data: scene.join("train.npz"),
        out: run_dir.to_path_buf(),
        run: Some(run),
        resume: false,
        overwrite: true,
        iters: None,
        minutes: Some(args.minutes),
        eval_data: Some(scene.join("novel_view.npz")),
        chunk_rays: None,
        device: device.clone(),
        numerics: super::numerics(),
    };
    let outcome = train(
        &req,
        &super::train::Ranks::One,
        args.quiet,
        "pma demo: held-out (novel view) PSNR vs wall-clock time",
    )?;
    let train_s = (outcome.session_s - outcome.eval_s).max(1e-9);
    let it_per_s = outcome.session_iterations as f64 / train_s;
    println!(
        "      {} iterations in {:.0} s ({it_per_s:.2} it/s), {} skipped; the plot's held-out \
         curve scores {} novel-view images at each point, the evaluation below every split's \
         images up to --max-eval-images",
        outcome.iterations,
        outcome.wall_s,
        outcome.skipped,
        RunConfig::from_preset(preset).train.eval_images
    );
    Ok((outcome, it_per_s, options))
}

/// Step 3: both held-out splits, each from its own file of the scene.
fn evaluate_splits(
    args: &Args,
    preset: Preset,
    scene: &Path,
    model: &Path,
    out: &Path,
    device: &candle_core::Device,
) -> anyhow::Result<BTreeMap<String, SplitSummary>> {
    let renders = out.join("renders");
    let avatar = Avatar::load(model, device)?.with_numerics(super::numerics());
    let baseline = mean_foreground_colour(&read_dataset(&scene.join("train.npz"), Profile::Eval)?)?;
    pma_data::fsio::create_dir_all(&renders)
        .with_context(|| format!("creating {}", renders.display()))?;
    let opts = EvalOptions {
        png_dir: Some(renders.clone()),
        pngs: args.pngs,
        baseline_colour: Some(baseline),
        ..EvalOptions::quick(RunConfig::from_preset(preset).train.render_chunk)
    };
    let mut splits = BTreeMap::new();
    for name in SPLITS {
        let path = scene.join(format!("{name}.npz"));
        let report = score_split(
            &avatar,
            &path,
            name,
            args.max_eval_images,
            &opts,
            args.quiet,
        )?;
        write_json(&report, &out.join(format!("eval_{name}.json")))?;
        let baseline_psnr = report.baseline_psnr.unwrap_or(f64::NAN);
        println!(
            "      {name}: PSNR {:.2} dB, SSIM {:.4}, LPIPS {} over {} images (baseline PSNR {baseline_psnr:.2} dB)",
            report.psnr,
            report.ssim,
            lpips_cell(report.lpips),
            report.images
        );
        splits.insert(
            name.to_string(),
            SplitSummary {
                psnr: report.psnr,
                ssim: report.ssim,
                lpips: (!report.lpips.is_nan()).then_some(report.lpips),
                baseline_psnr,
                images: report.images,
                data: path,
            },
        );
    }
    Ok(splits)
}

/// The scene directory holds all three splits made with exactly `cfg`.
fn scene_matches(dir: &Path, cfg: &SynthConfig) -> bool {
    let files_there = ["train.npz", "novel_view.npz", "novel_pose.npz"]
        .iter()
        .all(|f| dir.join(f).is_file());
    let Ok(text) = std::fs::read_to_string(dir.join("scene.json")) else {
        return false;
    };
    let Ok(json) = serde_json::from_str::<serde_json::Value>(&text) else {
        return false;
    };
    files_there && serde_json::to_value(cfg).ok().as_ref() == json.get("config")
}
