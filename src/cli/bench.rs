//! `pma bench`: parity mode against each culling option, side by side in one process.
//! For every option: network points/s and rays/s of inference, ms per rendered
//! W×H image, ms per training step, peak RSS of each phase, PSNR of the render against the
//! parity render, the change of held-out PSNR against ground truth, held-out PSNR (and LPIPS)
//! after the same wall-clock training budget, and the achieved GFLOP/s against an estimate of the
//! machine's fp32 peak. Writes `bench.json` and `error_vs_time.png`.
//!
//! Render timings go round-robin over the options (every option's first repeat, then every
//! option's second, ...), so a machine whose speed drifts during the run shifts all options
//! alike. Training is timed per option within its wall-clock budget, one option after the
//! other.
//!
//! FLOPs and the peak they are set against are [`pma_model::compute::flops`]'s: matmul FLOPs per
//! network point (3× for a training step: forward, input and weight gradients) over
//! cores × GHz × FLOP/cycle from /proc/cpuinfo.
//!
//! `--occupancy` adds the occupancy-grid rows (the grid alone and with the last culling
//! option); `--scene-seed` synthesises another scene (colours, glyphs, camera ring).
//!
//! `--account` replaces all of this by step accounting (`bench/account.rs`): counts of one
//! training step and one inference pass as a GPU would run them, with estimated GPU times.

// Without training support only the report types and flags are compiled, unused.
#![cfg_attr(not(feature = "train"), allow(dead_code))]

use std::path::PathBuf;

#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Output directory (scene, bench.json, error_vs_time.png).
    #[arg(long, default_value = "runs/bench")]
    pub out: PathBuf,
    /// Network preset (`cpu-small`, `default` = the paper's, `tiny`).
    #[arg(long, default_value = "cpu-small")]
    pub preset: String,
    /// Use this trained model (its preset) instead of training one briefly in-process.
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Seconds of in-process training of the model that is rendered (without --model).
    #[arg(long, default_value_t = 60.0)]
    pub train_seconds: f64,
    /// Wall-clock training budget per option for the held-out-PSNR comparison (0 = skip).
    #[arg(long, default_value_t = 20.0)]
    pub budget_seconds: f64,
    /// Rendered image size (square).
    #[arg(long, default_value_t = 256)]
    pub res: usize,
    /// Timed repeats after one warm-up (medians are reported).
    #[arg(long, default_value_t = 3)]
    pub repeats: usize,
    /// Held-out images for the PSNR columns.
    #[arg(long, default_value_t = 2)]
    pub eval_images: usize,
    /// Sample thresholds to compare (each with ray culling on).
    #[arg(long, value_delimiter = ',', default_value = "0,1e-6,1e-4,1e-2")]
    pub thresholds: Vec<f64>,
    /// Add the occupancy-grid rows: the grid alone and with the last threshold's culling.
    /// Rendering uses the model's grid (built from the scene's training poses when it has
    /// none); training builds and refreshes one during each run.
    #[arg(long)]
    pub occupancy: bool,
    /// Training poses the rendered model's grid is built over when it has none (each costs
    /// one network point per cell: 24 joints × ~28,000 cells).
    #[arg(long, default_value_t = 4)]
    pub occupancy_poses: usize,
    /// Training rows with the grid: steps without it before it is built and used.
    #[arg(long, default_value_t = 200)]
    pub occupancy_warmup: u64,
    /// Seed of the synthetic bench scene (colours, glyphs, camera ring): another seed is a
    /// scene the options were not tuned on.
    #[arg(long, default_value_t = 0)]
    pub scene_seed: u64,
    /// Smallest run that exercises everything (tests): tiny preset, 32×32, one repeat,
    /// 2 s budgets, a 32-pixel scene.
    #[arg(long)]
    pub quick: bool,
    /// No progress bars.
    #[arg(long)]
    pub quiet: bool,
    /// Compute device: cpu, cuda, cuda:N, metal (cuda/metal need a binary built with that
    /// feature). Ray casting and the scoring stay on the CPU.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// TF32 matrix products on CUDA (changes results; refused on other devices).
    #[arg(long)]
    pub tf32: bool,
    /// Also time the whole `pma forward` process on this ray batch (npz, as `pma forward
    /// --batch` reads it): one warm-up run, then `--repeats` runs; the median wall time is
    /// the `forward` row of bench.json.
    #[arg(long)]
    pub forward_batch: Option<PathBuf>,
    /// Model for the `forward` row (default: the bench's model; it must have been made for
    /// the batch's rest pose).
    #[arg(long, requires = "forward_batch")]
    pub forward_model: Option<PathBuf>,
    /// Only the `forward` row: no scene, no training, no option rows.
    #[arg(long, requires = "forward_batch")]
    pub forward_only: bool,
    /// Step accounting instead of timings: count what one training step and one inference
    /// pass would launch, upload and wait for on a GPU (on any device; the step runs for
    /// real), print it with estimated GPU times and write `account.json`.
    #[arg(long, conflicts_with = "forward_only")]
    pub account: bool,
    /// Rays of the accounted training step (and of the inference pass).
    #[arg(long, default_value_t = 3072, requires = "account")]
    pub rays: usize,
    /// The route an accounted CPU run takes: `cuda` (the kernels, one worker and the
    /// chunking a CUDA device would get) or `cpu` (pma's CPU route).
    #[arg(long, default_value = "cuda", requires = "account")]
    pub account_as: String,
    /// Rays per chunk of the accounted step (0 = automatic, as in training).
    #[arg(long, default_value_t = 0, requires = "account")]
    pub chunk_rays: usize,
    /// Account a one-pass step (`--chunk-rays` >= `--rays`) too large for this machine's
    /// memory by extrapolation from one-pass steps of N, 2N and 3N rays (refused unless
    /// every count is exactly affine in the rays across the three).
    #[arg(long, requires = "account")]
    pub extrapolate_from: Option<usize>,
    /// The official code's counts (`bench/official/count_official.py --json`), printed and
    /// estimated beside pma's.
    #[arg(long, requires = "account")]
    pub official_json: Option<PathBuf>,
}

#[cfg(not(feature = "train"))]
pub fn run(_args: Args) -> anyhow::Result<()> {
    anyhow::bail!("this build of pma has no training support; rebuild with `--features train` (on by default)")
}

#[cfg(feature = "train")]
pub fn run(args: Args) -> anyhow::Result<()> {
    imp::run(args)
}

/// Peak resident set size of this process so far (VmHWM), MiB.
pub fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// Reset VmHWM to the current RSS (Linux `clear_refs` 5); false where unsupported.
pub fn reset_peak_rss() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

/// One option's measurements (a row of `bench.json`).
#[derive(Debug, Clone, Default, serde::Serialize, serde::Deserialize)]
pub struct OptionResult {
    pub name: String,
    pub culling: pma_model::render::Culling,
    /// The occupancy grid was used (rendering: the bench model's grid; training: a grid
    /// built and refreshed during the run).
    #[serde(default)]
    pub occupancy: bool,
    /// The vectorised sine (`--fast-sine`) was on for this option.
    #[serde(default)]
    pub fast_sine: bool,
    /// Median ms per rendered image.
    pub ms_per_image: f64,
    /// Rays traced per image (pixels inside the body box) per second.
    pub rays_per_s: f64,
    /// Network points (far-away constants included) per second.
    pub network_points_per_s: f64,
    /// All samples the rendered rays stand for (rays × (Sc + Sf)) per second.
    pub samples_per_s: f64,
    pub network_points_per_image: u64,
    /// Achieved matmul GFLOP/s (network points × FLOPs per point / time).
    pub gflops: f64,
    /// Median ms per training step (the option's culling in training).
    pub ms_per_step: f64,
    /// Achieved matmul GFLOP/s of a training step (evaluated points × FLOPs per point ×
    /// `flops::TRAIN_FACTOR` / median step time).
    #[serde(default)]
    pub train_gflops: f64,
    /// Parity's median ms per step over this option's (training speed-up).
    #[serde(default)]
    pub step_speedup_vs_parity: f64,
    /// Share of a training step's samples that ran the network (far-away constants
    /// included), over the option's training steps.
    #[serde(default)]
    pub train_evaluated_fraction: f64,
    /// Peak RSS of this option's phases (VmHWM after a reset; process-wide if no reset).
    pub peak_rss_mib: f64,
    /// PSNR of this option's W×H render against the parity render (inf = identical).
    pub psnr_vs_parity_render: f64,
    /// Max |Δrgb| against the parity render.
    pub max_abs_diff_vs_parity: f64,
    /// Held-out PSNR (rendered model vs ground truth) and its loss against parity.
    pub heldout_psnr: f64,
    pub psnr_loss_vs_parity_db: f64,
    /// Held-out LPIPS of the whole image (`None` under LPIPS's 31×31 minimum).
    pub heldout_lpips: Option<f64>,
    /// Held-out PSNR after `budget_seconds` of training with this option from the same init.
    pub budget_heldout_psnr: Option<f64>,
    pub budget_heldout_lpips: Option<f64>,
    pub budget_iterations: Option<u64>,
    /// Speed-up of rays/s against parity.
    pub speedup_vs_parity: f64,
}

#[derive(Debug, Clone, Default, serde::Serialize, serde::Deserialize)]
pub struct BenchReport {
    pub preset: String,
    pub res: usize,
    pub repeats: usize,
    pub model: String,
    pub flops_per_point: f64,
    pub peak_gflops: f64,
    pub peak_estimate: String,
    pub rss_reset_supported: bool,
    /// Fraction of (image chunk, joint) pairs whose window is 0 on every coarse sample of
    /// the chunk (what skipping optional joints could leave out).
    pub inactive_joint_fraction: f64,
    pub options: Vec<OptionResult>,
    /// Whole-process `pma forward` on `--forward-batch`, if asked for.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub forward: Option<ForwardResult>,
}

/// Wall time of whole `pma forward` processes (start-up, loading, the pass, writing).
#[derive(Debug, Clone, Default, serde::Serialize, serde::Deserialize)]
pub struct ForwardResult {
    pub batch: String,
    pub model: String,
    pub rays: usize,
    /// Seconds of each timed run (after one warm-up run), in run order.
    pub runs_s: Vec<f64>,
    pub median_s: f64,
    pub rays_per_s: f64,
}

/// Rays in a `pma forward` batch (the first dimension of its `rays_o`).
fn batch_rays(path: &std::path::Path) -> anyhow::Result<usize> {
    let mut r = pma_data::dataset::npz::NpzReader::open(path)?;
    let a = r.read("rays_o")?;
    match a.shape.as_slice() {
        [n, 3] => Ok(*n),
        s => anyhow::bail!(
            "{}: key `rays_o`: expected shape [*,3], found {s:?}",
            path.display()
        ),
    }
}

/// One warm-up and `repeats` timed runs of this executable's `pma forward`.
pub fn time_forward_process(
    batch: &std::path::Path,
    model: &std::path::Path,
    repeats: usize,
    scratch: &std::path::Path,
) -> anyhow::Result<ForwardResult> {
    use anyhow::Context as _;
    let rays = batch_rays(batch)?;
    let exe = std::env::current_exe().context("locating the pma executable")?;
    let out = scratch.join("forward_out.npz");
    let mut runs = Vec::with_capacity(repeats);
    for i in 0..=repeats {
        let mut cmd = std::process::Command::new(&exe);
        let workers = pma_model::compute::parallel::workers();
        if workers > 1 {
            // This process set these for its own workers (`configure_cpu`); a child that
            // inherited them would take them for the user's and run one worker.
            cmd.env_remove("RAYON_NUM_THREADS")
                .env_remove("CANDLE_NUM_THREADS");
        }
        // The same worker count as this process (`pma --workers N bench` included).
        cmd.args(["--workers", &workers.to_string()]);
        let t = std::time::Instant::now();
        let o = cmd
            .args(["forward", "--model"])
            .arg(model)
            .arg("--batch")
            .arg(batch)
            .arg("--out")
            .arg(&out)
            .output()
            .with_context(|| format!("running {} forward", exe.display()))?;
        let secs = t.elapsed().as_secs_f64();
        if !o.status.success() {
            anyhow::bail!(
                "pma forward on {} failed: {}",
                batch.display(),
                String::from_utf8_lossy(&o.stderr).trim()
            );
        }
        if i > 0 {
            runs.push(secs);
        }
    }
    // The output is only a by-product of the timing.
    let _ = std::fs::remove_file(&out);
    let mut sorted = runs.clone();
    sorted.sort_by(f64::total_cmp);
    let median = sorted[sorted.len() / 2];
    Ok(ForwardResult {
        batch: batch.display().to_string(),
        model: model.display().to_string(),
        rays,
        runs_s: runs,
        median_s: median,
        rays_per_s: rays as f64 / median,
    })
}

/// The `forward` line of the table.
pub fn print_forward(f: &ForwardResult) {
    println!(
        "pma forward (whole process) {} rays: median {:.3} s over {} runs ({:.0} rays/s; {})",
        f.rays,
        f.median_s,
        f.runs_s.len(),
        f.rays_per_s,
        f.batch
    );
}

#[cfg(feature = "train")]
mod account;

#[cfg(feature = "train")]
mod imp {
    use std::sync::Arc;
    use std::time::Instant;

    use anyhow::Context as _;
    use candle_core::{Device, Tensor};
    use pma_data::camera::Camera;
    use pma_data::dataset::{Dataset, Profile};
    use pma_data::metrics::psnr;
    use pma_data::skeleton::Joints;
    use pma_data::synth::{generate, SynthConfig};
    use pma_model::eval::{dataset_pose, ground_truth, render_dataset_image};
    use pma_model::network::occupancy::OccupancyConfig;
    use pma_model::render::avatar::{Avatar, Poses};
    use pma_model::render::image::{ImageOptions, RenderedImage};
    use pma_model::render::{Culling, PassOptions, SampleFill};
    use pma_model::train::{Preset, RunConfig, Trainer};

    use super::super::plot::plot_error_vs_time;
    use super::super::{progress, read_dataset, refuse, write_json};
    use super::*;

    /// (name, pass options, fast sine): parity, each culling option, then the vectorised
    /// sine alone and with the last (most aggressive) culling option; with `occupancy` the
    /// grid alone and with that culling option.
    fn options(thresholds: &[f64], occupancy: bool) -> Vec<(String, PassOptions, bool)> {
        let culled = |c: Culling| PassOptions::culled(c);
        let mut v = vec![
            ("parity".to_string(), PassOptions::parity(), false),
            (
                "rays".to_string(),
                culled(Culling {
                    rays: true,
                    ..Default::default()
                }),
                false,
            ),
        ];
        for &t in thresholds {
            v.push((
                format!("rays+samples@{t:e}"),
                culled(Culling {
                    rays: true,
                    sample_threshold: Some(t),
                    sample_fill: SampleFill::Network,
                }),
                false,
            ));
        }
        let (last_name, last_pass, _) = v.last().cloned().expect("parity is always there");
        v.push(("fast-sine".to_string(), PassOptions::parity(), true));
        if last_name != "rays" {
            v.push((format!("{last_name}+fast-sine"), last_pass.clone(), true));
        }
        if occupancy {
            let grid = |culling: Culling| PassOptions {
                culling,
                occupancy: true,
            };
            v.push(("occupancy".to_string(), grid(Culling::default()), false));
            v.push((
                format!("{last_name}+occupancy"),
                grid(last_pass.culling),
                false,
            ));
        }
        v
    }

    fn median(v: &mut [f64]) -> f64 {
        if v.is_empty() {
            return f64::NAN;
        }
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    }

    /// Train `run` for `seconds` (at least 2 steps); returns the trainer, the step times
    /// and the share of the steps' samples that ran the network.
    fn train_for(
        run: RunConfig,
        data: Arc<Dataset>,
        seconds: f64,
        max_steps: u64,
        dev: &Device,
        bar: &indicatif::ProgressBar,
    ) -> anyhow::Result<(Trainer, Vec<f64>, f64)> {
        let samples_per_step =
            (run.train.rays_per_step * (run.model.n_samples + run.model.n_importance)) as f64;
        let mut trainer = Trainer::new(run, data, dev)?;
        let start = Instant::now();
        let mut times = Vec::new();
        while (times.len() < 2 || start.elapsed().as_secs_f64() < seconds)
            && (times.len() as u64) < max_steps
        {
            let t = Instant::now();
            trainer.step()?;
            times.push(t.elapsed().as_secs_f64() * 1e3);
            bar.set_position((start.elapsed().as_secs_f64().min(seconds)) as u64);
        }
        let points = trainer.pass_totals().points_evaluated as f64;
        let fraction = points / (samples_per_step * times.len().max(1) as f64);
        Ok((trainer, times, fraction))
    }

    /// Mean PSNR and LPIPS of the unquantised renders of `images` against their ground
    /// truth, over the whole image (LPIPS `None` for images under its minimum size).
    fn heldout_psnr(
        avatar: &Avatar,
        data: &Dataset,
        images: &[usize],
        pass: &PassOptions,
    ) -> anyhow::Result<(f64, Option<f64>)> {
        let lpips = pma_model::eval::lpips::Lpips::shared()?;
        let (h, w) = (data.height(), data.width());
        let big_enough = h.min(w) >= pma_model::eval::lpips::MIN_SIDE;
        let (mut scores, mut lp) = (Vec::new(), Vec::new());
        for &n in images {
            let img = render_dataset_image(avatar, data, n, 4096, pass)?;
            let (gt, _) = ground_truth(data, n)?;
            scores.push(psnr(&img.rgb, &gt)?);
            if big_enough {
                lp.push(lpips.distance(&img.rgb, &gt, h, w)?);
            }
        }
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
        Ok((mean(&scores), big_enough.then(|| mean(&lp))))
    }

    /// The scene's training split and the held-out images the PSNR columns use.
    struct Scene {
        train: Arc<Dataset>,
        held: Dataset,
        eval_set: Vec<usize>,
    }

    /// The W×H view every option renders: the first held-out image's pose and camera,
    /// intrinsics rescaled.
    struct View {
        poses: Poses,
        kp3d: Joints,
        cam: Camera,
        opts: ImageOptions,
        /// Pixels inside the body box (the rays traced).
        box_rays: f64,
    }

    pub fn run(mut args: Args) -> anyhow::Result<()> {
        check_args(&mut args)?;
        let dev = super::super::device_tf32(&args.device, args.tf32)?;
        std::fs::create_dir_all(&args.out)
            .with_context(|| format!("creating {}", args.out.display()))?;
        if args.forward_only {
            return forward_only(&args);
        }
        if args.account {
            return super::account::run(&args, &dev);
        }
        let rss_reset = reset_peak_rss();
        let scene = prepare_scene(&args)?;
        // Loaded before the per-option peak-RSS resets, so no option's phase pays for it.
        pma_model::eval::lpips::Lpips::shared()?;
        let preset: Preset = args.preset.parse()?;
        let (avatar, model_desc) = bench_model(&args, preset, &scene, &dev)?;
        let avatar = match args.occupancy && avatar.occupancy().is_none() {
            true => grid_for(&args, avatar, &scene)?,
            false => avatar,
        };
        let cfg = avatar.config().clone();
        let fpp = pma_model::compute::flops::per_point(&cfg);
        let (peak, peak_how) = pma_model::compute::flops::fp32_peak();
        let view = bench_view(&args, &scene, &dev)?;
        let inactive =
            inactive_joint_fraction(&avatar, &view.poses, &view.cam, &view.kp3d, &view.opts)?;

        let opts = options(&args.thresholds, args.occupancy);
        let mut results = measure_inference(&args, &avatar, &scene, &view, &opts, fpp, rss_reset)?;
        measure_training(&args, preset, &cfg, &scene, &opts, &mut results, rss_reset)?;
        let (parity_rays, parity_step) = (results[0].rays_per_s, results[0].ms_per_step);
        for r in &mut results {
            r.speedup_vs_parity = r.rays_per_s / parity_rays;
            r.step_speedup_vs_parity = parity_step / r.ms_per_step;
        }
        let mut report = BenchReport {
            preset: args.preset.clone(),
            res: args.res,
            repeats: args.repeats,
            model: model_desc,
            flops_per_point: fpp,
            peak_gflops: peak,
            peak_estimate: peak_how,
            rss_reset_supported: rss_reset,
            inactive_joint_fraction: inactive,
            options: results,
            forward: None,
        };
        if let Some(batch) = &args.forward_batch {
            let model = match &args.forward_model {
                Some(m) => m.clone(),
                None => bench_model_path(&args),
            };
            report.forward = Some(time_forward_process(
                batch,
                &model,
                args.repeats,
                &args.out,
            )?);
        }
        print_table(&report);
        write_json(&report, &args.out.join("bench.json"))?;
        let pts: Vec<(f64, f64, &str)> = report
            .options
            .iter()
            .map(|o| {
                let loss = o.psnr_loss_vs_parity_db;
                let loss = if loss.is_finite() { loss } else { 0.0 };
                (o.ms_per_image / 1e3, loss, o.name.as_str())
            })
            .collect();
        let title = format!(
            "pma bench ({}, {}x{})",
            report.preset, report.res, report.res
        );
        plot_error_vs_time(&title, &pts, &args.out.join("error_vs_time.png"))?;
        println!(
            "wrote {} and {}",
            args.out.join("bench.json").display(),
            args.out.join("error_vs_time.png").display()
        );
        Ok(())
    }

    /// `avatar` with an occupancy grid built from the scene's training poses (for the
    /// rendering rows of `--occupancy`).
    fn grid_for(args: &Args, avatar: Avatar, scene: &Scene) -> anyhow::Result<Avatar> {
        use pma_model::tools::occupancy::{build, BuildOptions};
        let b = progress::bar(args.quiet, 0, "building the occupancy grid (poses)");
        let t = Instant::now();
        let (avatar, s) = build(
            avatar,
            &scene.train,
            &BuildOptions {
                poses: args.occupancy_poses.max(1),
                ..Default::default()
            },
            &mut |d, n| {
                b.set_length(n as u64);
                b.set_position(d as u64);
            },
        )?;
        b.finish_and_clear();
        println!(
            "built the occupancy grid of the rendered model in {:.1} s ({} poses, {} network \
             points, {:.1} % of cells occupied)",
            t.elapsed().as_secs_f64(),
            s.poses,
            s.points,
            100.0 * s.occupied_fraction
        );
        Ok(avatar)
    }

    /// Where the rendered model lives: `--model`, or the one trained in-process.
    fn bench_model_path(args: &Args) -> PathBuf {
        args.model
            .clone()
            .unwrap_or_else(|| args.out.join("model.safetensors"))
    }

    /// `--forward-only`: the whole-process `pma forward` row alone.
    fn forward_only(args: &Args) -> anyhow::Result<()> {
        let Some(batch) = &args.forward_batch else {
            refuse!("--forward-only needs --forward-batch");
        };
        let Some(model) = args.forward_model.clone().or_else(|| args.model.clone()) else {
            refuse!("--forward-only needs --forward-model (or --model)");
        };
        let f = time_forward_process(batch, &model, args.repeats, &args.out)?;
        print_forward(&f);
        let report = BenchReport {
            repeats: args.repeats,
            model: model.display().to_string(),
            forward: Some(f),
            ..Default::default()
        };
        write_json(&report, &args.out.join("bench.json"))?;
        println!("wrote {}", args.out.join("bench.json").display());
        Ok(())
    }

    /// `--quick` settings, then the checks of the flags.
    fn check_args(args: &mut Args) -> anyhow::Result<()> {
        if args.quick {
            args.preset = "tiny".into();
            args.res = 32;
            args.repeats = 1;
            args.train_seconds = args.train_seconds.min(2.0);
            args.budget_seconds = args.budget_seconds.min(2.0);
            args.eval_images = 1;
        }
        if args.repeats < 1 {
            refuse!("--repeats must be >= 1");
        }
        if !(8..=4096).contains(&args.res) {
            refuse!("--res must be in 8..=4096, found {}", args.res);
        }
        if args.repeats > 1000 {
            refuse!("--repeats must be <= 1000, found {}", args.repeats);
        }
        for (flag, v) in [
            ("--train-seconds", args.train_seconds),
            ("--budget-seconds", args.budget_seconds),
        ] {
            if !(v.is_finite() && (0.0..=1e6).contains(&v)) {
                refuse!("{flag} {v}: expected a finite number of seconds in [0, 1e6]");
            }
        }
        super::super::check_paths(
            pma_data::fsio::PathCheck::new()
                .input_opt("--model", args.model.as_deref())
                .input_opt("--forward-batch", args.forward_batch.as_deref())
                .input_opt("--forward-model", args.forward_model.as_deref())
                .output_dir("--out", &args.out, ["bench.json"]),
        )?;
        for &t in &args.thresholds {
            if !(t.is_finite() && (0.0..1.0).contains(&t)) {
                refuse!("--thresholds: {t} is not in [0, 1)");
            }
        }
        Ok(())
    }

    /// The synthetic scene (small: it only serves training and the held-out PSNR).
    fn prepare_scene(args: &Args) -> anyhow::Result<Scene> {
        let mut synth = SynthConfig {
            seed: args.scene_seed,
            ..Default::default()
        };
        if args.quick {
            synth.res = 32;
            synth.frames = 8;
            synth.novel_pose_walk = 2;
            synth.novel_pose_dance = 2;
        }
        let scene = match args.scene_seed {
            0 => args.out.join("scene"),
            n => args.out.join(format!("scene-seed{n}")),
        };
        if !scene.join("novel_view.npz").is_file() {
            println!("synthesising the scene into {}", scene.display());
            generate(&synth, &scene, &mut |_, _| {}).context("synthesising the bench scene")?;
        }
        let train = Arc::new(read_dataset(&scene.join("train.npz"), Profile::Train)?);
        let held = read_dataset(&scene.join("novel_view.npz"), Profile::Eval)?;
        let k = args.eval_images.clamp(1, held.n_images());
        let eval_set: Vec<usize> = (0..k).map(|i| i * held.n_images() / k).collect();
        Ok(Scene {
            train,
            held,
            eval_set,
        })
    }

    /// The model that is rendered: `--model`, or one trained in-process for
    /// `--train-seconds`. Returns it with a description for the report.
    fn bench_model(
        args: &Args,
        preset: Preset,
        scene: &Scene,
        dev: &Device,
    ) -> anyhow::Result<(Avatar, String)> {
        if let Some(p) = &args.model {
            return Ok((
                Avatar::load(p, dev).with_context(|| format!("loading {}", p.display()))?,
                p.display().to_string(),
            ));
        }
        let b = progress::bar(
            args.quiet,
            args.train_seconds as u64,
            "training the bench model (s)",
        );
        let (trainer, _, _) = train_for(
            RunConfig::from_preset(preset),
            scene.train.clone(),
            args.train_seconds,
            u64::MAX,
            dev,
            &b,
        )?;
        b.finish_and_clear();
        let path = args.out.join("model.safetensors");
        trainer.avatar().save(&path)?;
        println!(
            "trained {} iterations of {} in-process ({:.0} s)",
            trainer.iteration(),
            args.preset,
            args.train_seconds
        );
        Ok((
            Avatar::load(&path, dev)?,
            format!("{} (trained in-process)", path.display()),
        ))
    }

    fn bench_view(args: &Args, scene: &Scene, dev: &Device) -> anyhow::Result<View> {
        let held = &scene.held;
        let n0 = scene.eval_set[0];
        let (poses, kp3d) = dataset_pose(held, held.pose_row(n0)?, dev)?;
        let cam0 = held.image_camera(n0)?;
        let sx = args.res as f32 / cam0.width as f32;
        let sy = args.res as f32 / cam0.height as f32;
        let cam = Camera::new(
            args.res,
            args.res,
            cam0.fx * sx,
            cam0.fy * sy,
            cam0.cx * sx,
            cam0.cy * sy,
            cam0.c2w,
        )?;
        let opts = ImageOptions {
            chunk: 4096,
            head: held.head()?,
            device: dev.clone(),
            pass: PassOptions::parity(),
        };
        let box_rays = {
            let b = pma_model::render::image::body_box(&cam, &kp3d, opts.head);
            ((b.x1.min(args.res as i64) - b.x0.max(0)).max(0)
                * (b.y1.min(args.res as i64) - b.y0.max(0)).max(0)) as f64
        };
        Ok(View {
            poses,
            kp3d,
            cam,
            opts,
            box_rays,
        })
    }

    /// Inference per option: render time, points, peak RSS, and the PSNR columns.
    fn measure_inference(
        args: &Args,
        avatar: &Avatar,
        scene: &Scene,
        view: &View,
        opts: &[(String, PassOptions, bool)],
        flops_per_point: f64,
        rss_reset: bool,
    ) -> anyhow::Result<Vec<OptionResult>> {
        let samples_per_ray = {
            let c = avatar.config();
            (c.n_samples + c.n_importance) as f64
        };
        let mut results: Vec<OptionResult> = Vec::new();
        let mut parity: Option<(RenderedImage, f64)> = None;
        let render = |a: &Avatar, pass: &PassOptions| -> anyhow::Result<RenderedImage> {
            let opts = ImageOptions {
                pass: pass.clone(),
                ..view.opts.clone()
            };
            Ok(a.render_image(&view.poses, &view.kp3d, &view.cam, None, &opts)?)
        };
        let set = |(_, _, fast_sine): &(String, PassOptions, bool)| {
            pma_model::compute::fast_sine::set_enabled(*fast_sine);
        };
        let b = progress::bar(
            args.quiet,
            (opts.len() * (1 + args.repeats)) as u64,
            "inference per option",
        );
        // First each option's untimed render (the warm-up), its quality and memory.
        for opt in opts {
            let (name, pass, fast_sine) = opt;
            b.set_message(format!("render {name}"));
            set(opt);
            if rss_reset {
                reset_peak_rss();
            }
            let img = render(avatar, pass)?;
            let (held_psnr, held_lpips) = heldout_psnr(avatar, &scene.held, &scene.eval_set, pass)?;
            let peak_rss = peak_rss_mib().unwrap_or(f64::NAN);
            let (vs_parity, max_diff) = match &parity {
                None => (f64::INFINITY, 0.0),
                Some((p, _)) => (
                    psnr(&img.rgb, &p.rgb)?,
                    img.rgb
                        .iter()
                        .zip(&p.rgb)
                        .map(|(a, b)| (a - b).abs() as f64)
                        .fold(0.0, f64::max),
                ),
            };
            let parity_psnr = parity.as_ref().map_or(held_psnr, |p| p.1);
            if parity.is_none() {
                parity = Some((img, held_psnr));
            }
            results.push(OptionResult {
                name: name.clone(),
                culling: pass.culling.clone(),
                occupancy: pass.occupancy,
                fast_sine: *fast_sine,
                peak_rss_mib: peak_rss,
                psnr_vs_parity_render: vs_parity,
                max_abs_diff_vs_parity: max_diff,
                heldout_psnr: held_psnr,
                psnr_loss_vs_parity_db: parity_psnr - held_psnr,
                heldout_lpips: held_lpips,
                ..Default::default()
            });
            b.inc(1);
        }
        // Then the timed renders, round-robin over the options: a VM whose speed drifts
        // during the run slows every option alike instead of the ones timed last.
        let mut times = vec![Vec::new(); opts.len()];
        for _ in 0..args.repeats {
            for ((opt, t_opt), res) in opts.iter().zip(times.iter_mut()).zip(results.iter_mut()) {
                b.set_message(format!("time {}", opt.0));
                set(opt);
                let t = Instant::now();
                let img = render(avatar, &opt.1)?;
                t_opt.push(t.elapsed().as_secs_f64());
                res.network_points_per_image = img.stats.points_evaluated;
                b.inc(1);
            }
        }
        for (res, t_opt) in results.iter_mut().zip(times.iter_mut()) {
            let sec = median(t_opt);
            let points = res.network_points_per_image as f64;
            res.ms_per_image = sec * 1e3;
            res.rays_per_s = view.box_rays / sec;
            res.network_points_per_s = points / sec;
            res.samples_per_s = view.box_rays * samples_per_ray / sec;
            res.gflops = points * flops_per_point / sec / 1e9;
        }
        b.finish_and_clear();
        pma_model::compute::fast_sine::set_enabled(false);
        Ok(results)
    }

    /// Training per option: ms per step and held-out PSNR after the same wall-clock budget.
    fn measure_training(
        args: &Args,
        preset: Preset,
        cfg: &pma_model::Config,
        scene: &Scene,
        opts: &[(String, PassOptions, bool)],
        results: &mut [OptionResult],
        rss_reset: bool,
    ) -> anyhow::Result<()> {
        let dev = super::super::device(&args.device)?;
        let budget = args.budget_seconds.max(0.0);
        let b = progress::bar(args.quiet, opts.len() as u64, "training per option");
        for (res, (name, pass, fast_sine)) in results.iter_mut().zip(opts) {
            b.set_message(format!("train {name}"));
            pma_model::compute::fast_sine::set_enabled(*fast_sine);
            let mut run = RunConfig::from_preset(preset);
            run.model = cfg.clone();
            run.train.culling = pass.culling.clone();
            run.train.occupancy = pass.occupancy.then(|| OccupancyConfig {
                warmup_steps: args.occupancy_warmup,
                ..Default::default()
            });
            let samples_per_step =
                (run.train.rays_per_step * (cfg.n_samples + cfg.n_importance)) as f64;
            if rss_reset {
                reset_peak_rss();
            }
            let hidden = indicatif::ProgressBar::hidden();
            let (trainer, mut times, fraction) = if budget > 0.0 {
                train_for(run, scene.train.clone(), budget, u64::MAX, &dev, &hidden)?
            } else {
                train_for(run, scene.train.clone(), 0.0, 3, &dev, &hidden)?
            };
            if times.len() > 1 {
                times.remove(0); // warm-up
            }
            res.ms_per_step = median(&mut times);
            res.train_evaluated_fraction = fraction;
            res.train_gflops = samples_per_step
                * fraction
                * pma_model::compute::flops::per_point(cfg)
                * pma_model::compute::flops::TRAIN_FACTOR
                / (res.ms_per_step * 1e6);
            res.peak_rss_mib = res.peak_rss_mib.max(peak_rss_mib().unwrap_or(f64::NAN));
            if budget > 0.0 {
                let (p, l) = heldout_psnr(trainer.avatar(), &scene.held, &scene.eval_set, pass)?;
                res.budget_heldout_psnr = Some(p);
                res.budget_heldout_lpips = l;
                res.budget_iterations = Some(trainer.iteration());
            }
            b.inc(1);
        }
        b.finish_and_clear();
        pma_model::compute::fast_sine::set_enabled(false);
        Ok(())
    }

    /// Fraction of (render chunk, joint) pairs with a zero window on every coarse sample.
    fn inactive_joint_fraction(
        avatar: &Avatar,
        poses: &Poses,
        cam: &Camera,
        kp3d: &[[f32; 3]; 24],
        opts: &ImageOptions,
    ) -> anyhow::Result<f64> {
        let pbox = pma_model::render::image::body_box(cam, kp3d, opts.head);
        let (w, h) = (cam.width as i64, cam.height as i64);
        let pixels: Vec<(usize, usize)> = (pbox.y0.max(0)..pbox.y1.min(h))
            .flat_map(|y| (pbox.x0.max(0)..pbox.x1.min(w)).map(move |x| (x as usize, y as usize)))
            .collect();
        let scales = avatar.axis_scale()?.detach();
        let align: Vec<f32> = avatar.tensors()["pts_embedder.transforms"]
            .flatten_all()?
            .to_vec1()?;
        let skts: Vec<f32> = poses.skts.flatten_all()?.to_vec1()?;
        let test = pma_model::render::cull::WindowTest::new(
            &align,
            &skts,
            &scales.flatten_all()?.to_vec1::<f32>()?,
            avatar.config().window_alpha,
            avatar.config().window_beta,
            0.0,
        )?;
        let (mut inactive, mut total) = (0usize, 0usize);
        let origin = cam.origin();
        for chunk in pixels.chunks(opts.chunk) {
            let c = chunk.len();
            let o: Vec<f32> = chunk.iter().flat_map(|_| origin).collect();
            let d: Vec<f32> = chunk
                .iter()
                .flat_map(|&(x, y)| cam.ray_dir(x, y, false))
                .collect();
            let samples = avatar.ray_caster().cast(
                &Tensor::from_vec(o, (c, 3), &opts.device)?,
                &Tensor::from_vec(d, (c, 3), &opts.device)?,
                &poses.cyls,
                &poses.skts,
                &scales,
            )?;
            let pts: Vec<f32> = samples.pts.flatten_all()?.to_vec1()?;
            let active = test.active_joints(&pts, c, avatar.ray_caster().n_samples())?;
            inactive += active[0].iter().filter(|a| !**a).count();
            total += 24;
        }
        Ok(inactive as f64 / total.max(1) as f64)
    }

    fn print_table(r: &BenchReport) {
        if let Some(f) = &r.forward {
            print_forward(f);
        }
        println!(
            "\npreset {} | {}x{} | {:.3} MFLOP/point | peak ≈ {:.0} GFLOP/s ({}) | inactive joints per chunk {:.0}%",
            r.preset,
            r.res,
            r.res,
            r.flops_per_point / 1e6,
            r.peak_gflops,
            r.peak_estimate,
            100.0 * r.inactive_joint_fraction
        );
        println!(
            "{:<22} {:>9} {:>9} {:>7} {:>11} {:>11} {:>8} {:>8} {:>7} {:>8} {:>7} {:>9} {:>9} {:>8} {:>9} {:>7} {:>9}",
            "option",
            "ms/img",
            "rays/s",
            "x par",
            "net pts/s",
            "samples/s",
            "GFLOP/s",
            "ms/step",
            "x step",
            "tr GFLOP",
            "tr pts",
            "RSS MiB",
            "PSNR/par",
            "ΔPSNR dB",
            "held dB",
            "LPIPS",
            "budget dB"
        );
        for o in &r.options {
            println!(
                "{:<22} {:>9.1} {:>9.0} {:>7.2} {:>11.0} {:>11.0} {:>8.2} {:>8.1} {:>7.2} {:>8.2} {:>6.1}% {:>9.0} {:>9.2} {:>8.3} {:>9.2} {:>7} {:>9}",
                o.name,
                o.ms_per_image,
                o.rays_per_s,
                o.speedup_vs_parity,
                o.network_points_per_s,
                o.samples_per_s,
                o.gflops,
                o.ms_per_step,
                o.step_speedup_vs_parity,
                o.train_gflops,
                100.0 * o.train_evaluated_fraction,
                o.peak_rss_mib,
                o.psnr_vs_parity_render,
                o.psnr_loss_vs_parity_db,
                o.heldout_psnr,
                o.heldout_lpips.map_or("-".to_string(), |v| format!("{v:.4}")),
                o.budget_heldout_psnr
                    .map_or("-".to_string(), |v| format!("{v:.2}")),
            );
        }
    }
}
