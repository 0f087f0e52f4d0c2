//! `pma demo`: the main job on the embedded default. Makes the synthetic scene (`pma synth`
//! defaults), trains the `cpu-small` preset for a wall-clock budget, evaluates the novel-view
//! and novel-pose splits, and writes renders, `psnr_vs_time.png` and `summary.json`:
//!
//! ```text
//! DIR/scene/{train,novel_view,novel_pose}.npz, scene.json, preview.png
//! DIR/run/{config.toml, model.safetensors, train_state.safetensors, log.csv, psnr_vs_time.png}
//! DIR/renders/<split>_<image>.png       ground truth | render | error heat map
//! DIR/eval_<split>.json                 per-image scores
//! DIR/psnr_vs_time.png                  copy of the run's plot
//! DIR/summary.json
//! ```

use std::path::PathBuf;

#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Training budget in minutes (scene synthesis and the final evaluation come on top).
    #[arg(long, default_value_t = 10.0)]
    pub minutes: f64,
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
    /// Score at most this many images per split, evenly spread over it (0 = all). Rendering
    /// one 96×96 image takes ~3 s with `cpu-small` on 2 cores; the full splits (64 + 128
    /// images) would add ~10 minutes.
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
}

#[cfg(not(feature = "train"))]
pub fn run(_args: Args) -> anyhow::Result<()> {
    anyhow::bail!("this build of pma has no training support; rebuild with `--features train` (on by default)")
}

#[cfg(feature = "train")]
pub fn run(args: Args) -> anyhow::Result<()> {
    imp::run(args)
}

/// The part of `summary.json` other tools read.
#[cfg(feature = "train")]
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct SplitSummary {
    pub psnr: f64,
    pub ssim: f64,
    pub baseline_psnr: f64,
    pub images: usize,
}

#[cfg(feature = "train")]
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Summary {
    pub iterations: u64,
    /// Wall-clock seconds of training (including the periodic held-out evaluations).
    pub wall_s: f64,
    /// Training iterations per second (periodic evaluations excluded).
    pub it_per_s: f64,
    pub model: PathBuf,
    pub data: PathBuf,
    pub preset: String,
    pub skipped_steps: u64,
    pub splits: std::collections::BTreeMap<String, SplitSummary>,
    pub plot: PathBuf,
    pub log: PathBuf,
    pub renders: PathBuf,
    pub lpips: Option<f64>,
    pub lpips_note: String,
}

#[cfg(feature = "train")]
mod imp {
    use std::collections::BTreeMap;

    use anyhow::Context as _;
    use pma_data::dataset::Profile;
    use pma_data::synth::{generate, SynthConfig};
    use pma_model::avatar::Avatar;
    use pma_model::train::{Preset, RunConfig};

    use super::super::eval::{
        evaluate, mean_foreground_colour, read_dataset, split_images, spread, write_json_atomic,
        EvalOptions, PsnrRegion, Split, LPIPS_NOTE,
    };
    use super::super::train::{train_run, TrainRequest};
    use super::*;
    use std::path::Path;

    pub fn run(args: Args) -> anyhow::Result<()> {
        let preset: Preset = args.preset.parse()?;
        let out = args.out.clone();
        std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;

        // 1. The scene (reused when an identical one is already there).
        let mut synth = SynthConfig::default();
        if let Some(r) = args.res {
            synth.res = r;
        }
        if let Some(f) = args.frames {
            synth.frames = f;
        }
        let scene = out.join("scene");
        if scene_matches(&scene, &synth) {
            println!("[1/4] reusing the synthetic scene in {}", scene.display());
        } else {
            println!("[1/4] synthesising the scene into {}", scene.display());
            let bar = bar(args.quiet);
            let summary = generate(&synth, &scene, &mut |done, total| {
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
        }
        let train_npz = scene.join("train.npz");

        // 2. Training for the budget.
        println!("[2/4] training preset `{preset}` for {} min", args.minutes);
        let mut run = RunConfig::from_preset(preset);
        run.train.seed = args.seed;
        run.train.iters = args.iters.unwrap_or(u64::MAX / 2);
        let run_dir = out.join("run");
        let outcome = train_run(TrainRequest {
            data: train_npz.clone(),
            out: run_dir.clone(),
            run: Some(run),
            resume: false,
            overwrite: true,
            iters: None,
            minutes: Some(args.minutes),
            eval_data: Some(scene.join("novel_view.npz")),
            quiet: args.quiet,
            chunk_rays: None,
            title: "pma demo: held-out (novel view) PSNR vs wall-clock time".into(),
            device: candle_core::Device::Cpu,
        })?;
        let train_s = (outcome.session_s - outcome.eval_s).max(1e-9);
        let it_per_s = outcome.session_iterations as f64 / train_s;
        println!(
            "      {} iterations in {:.0} s ({it_per_s:.2} it/s), {} skipped",
            outcome.iterations, outcome.wall_s, outcome.skipped
        );

        // 3. Evaluation of both held-out splits.
        println!("[3/4] evaluating");
        let device = candle_core::Device::Cpu;
        let avatar = Avatar::load(&outcome.model, &device)?;
        let baseline = mean_foreground_colour(&read_dataset(&train_npz, Profile::Eval)?)?;
        let renders = out.join("renders");
        std::fs::create_dir_all(&renders)
            .with_context(|| format!("creating {}", renders.display()))?;
        let chunk = RunConfig::from_preset(preset).train.render_chunk;
        let mut splits = BTreeMap::new();
        for name in ["novel_view", "novel_pose"] {
            let path = scene.join(format!("{name}.npz"));
            let data = read_dataset(&path, Profile::Eval)?;
            let images = split_images(
                &data,
                &Split {
                    name: name.into(),
                    tag: None,
                },
            )?;
            let images = spread(
                &images,
                if args.max_eval_images == 0 {
                    usize::MAX
                } else {
                    args.max_eval_images
                },
            );
            let opts = EvalOptions {
                region: PsnrRegion::Mask,
                ssim_data_range: 2.0,
                chunk,
                png_dir: Some(renders.clone()),
                pngs: args.pngs,
                baseline_colour: Some(baseline),
            };
            let bar = bar(args.quiet);
            let report = evaluate(&avatar, &data, name, &images, &opts, &mut |d, t| {
                bar.set_length(t as u64);
                bar.set_position(d as u64);
            })?;
            bar.finish_and_clear();
            write_json_atomic(&report, &out.join(format!("eval_{name}.json")))?;
            let baseline_psnr = report.baseline_psnr.unwrap_or(f64::NAN);
            println!(
                "      {name}: PSNR {:.2} dB, SSIM {:.4} over {} images (baseline PSNR {baseline_psnr:.2} dB)",
                report.psnr, report.ssim, report.images
            );
            splits.insert(
                name.to_string(),
                SplitSummary {
                    psnr: report.psnr,
                    ssim: report.ssim,
                    baseline_psnr,
                    images: report.images,
                },
            );
        }

        // 4. Summary.
        let plot = out.join("psnr_vs_time.png");
        std::fs::copy(&outcome.plot, &plot)
            .with_context(|| format!("copying the plot to {}", plot.display()))?;
        let summary = Summary {
            iterations: outcome.iterations,
            wall_s: outcome.wall_s,
            it_per_s,
            model: outcome.model.clone(),
            data: train_npz,
            preset: preset.name().to_string(),
            skipped_steps: outcome.skipped,
            splits,
            plot,
            log: run_dir.join("log.csv"),
            renders,
            lpips: None,
            lpips_note: LPIPS_NOTE.to_string(),
        };
        let path = out.join("summary.json");
        write_json_atomic(&summary, &path)?;
        println!("[4/4] wrote {}", path.display());
        println!("{}", serde_json::to_string_pretty(&summary)?);
        Ok(())
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

    fn bar(quiet: bool) -> indicatif::ProgressBar {
        if quiet {
            indicatif::ProgressBar::hidden()
        } else {
            let b = indicatif::ProgressBar::new(0);
            b.set_style(
                indicatif::ProgressStyle::with_template(
                    "      [{elapsed_precise}] {bar:30} {pos}/{len} {eta}",
                )
                .expect("static template"),
            );
            b
        }
    }
}
