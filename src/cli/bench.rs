//! `pma bench`: parity against each speed option (culling thresholds, the vectorised sine,
//! with `--occupancy` the occupancy grid alone and with the last culling option),
//! side by side in one process: render and training speed, memory, the render's difference
//! from parity's and held-out quality (`pma_model::bench::measure` measures; see its docs
//! for how). Writes `bench.json` and `error_vs_time.png`.
//!
//! `--shares` replaces all of this by counts (`pma_model::bench::shares`): the share of
//! samples that run the network per pass under each way of leaving work out.
//! `--forward-batch` adds the wall time of whole `pma forward` processes (`bench/forward.rs`).
//! `--account` replaces all of this by step accounting (`bench/account.rs`): counts of one
//! training step and one inference pass as a GPU would run them, with estimated GPU times.

use std::path::PathBuf;

use anyhow::Context as _;
use pma_model::bench::{measure, options, BenchReport, BenchRequest};
use pma_model::train::Preset;

use super::plot::plot_error_vs_time;
use super::progress::Phases;
use super::{refuse, write_json};

mod account;
mod forward;
mod quality;
mod shares;

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
    /// Wall-clock training budget per option for the held-out-PSNR comparison; the options
    /// train in turns of 2 s until each has spent it (0 = two steps each, no held-out score).
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
    /// The transmittance at which the early-stop rows stop a ray (`render --early-stop`).
    #[arg(long, value_name = "EPS", default_value_t = pma_model::bench::options::BENCH_EARLY_STOP)]
    pub early_stop: f64,
    /// Add the occupancy-grid rows: the grid alone and with the last threshold's culling.
    /// Rendering uses the model's grid (built from the scene's training poses when it has
    /// none); training builds and refreshes one during each run.
    /// With `--account`: the accounted step trains with a grid (built by one unaccounted
    /// step before it) and the report says what it left out.
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
    /// The free memory (GB) of the GPU the accounted inference pass is sized for: its
    /// network calls take as many points as that memory holds, as on a CUDA device
    /// (default: the CPU's 4,096 points per call).
    #[arg(long, requires = "account")]
    pub device_memory_gb: Option<f64>,
    /// The accounted step culls rays and the samples whose w^p ≤ T for every joint
    /// (`train --cull-rays --cull-samples T`); with `--occupancy` its grid too. The report
    /// says what the step left out.
    #[arg(long, value_name = "T", requires = "account")]
    pub account_cull: Option<f64>,
    /// Estimate data-parallel training on these numbers of GPUs (e.g. `1,2,4,8,16`): each
    /// rank's one-pass step of its share of `--rays` plus the gradient all-reduce over NVLink
    /// within 8-GPU nodes and InfiniBand between them (datasheet figures). Every figure is
    /// an estimate. Needs `--extrapolate-from`; the counts must include 1.
    #[arg(long, value_delimiter = ',', requires = "extrapolate_from")]
    pub gpus: Vec<usize>,
    /// Counts instead of timings: the share of samples that run the network in the coarse
    /// and the fine pass with ray culling, w^p culling, the occupancy grid and all combined,
    /// on held-out renders and training batches; writes `shares.json`. The model is
    /// `--model`, or `--preset` trained in-process for `--shares-steps` steps; its grid is
    /// built over `--occupancy-poses` training poses when it has none.
    #[arg(long, conflicts_with_all = ["account", "forward_only"])]
    pub shares: bool,
    /// Training steps of the in-process model of `--shares`.
    #[arg(long, default_value_t = 100, requires = "shares")]
    pub shares_steps: u64,
    /// Rays per step of that training (default: the preset's). The counted training
    /// batches keep the preset's rays per step.
    #[arg(long, requires = "shares")]
    pub shares_train_rays: Option<usize>,
    /// The w^p threshold of the culling rows of `--shares`.
    #[arg(long, default_value_t = 0.6, requires = "shares")]
    pub shares_threshold: f64,
    /// Training batches counted by `--shares` (0: held-out renders only).
    #[arg(long, default_value_t = 1, requires = "shares")]
    pub shares_batches: usize,
    /// Time to quality instead of all of this: parity and the options of `--ttq-options`
    /// (culling at 0.6 with the grid, each other option alone, the fast recipe, all
    /// together) train in turns on the synthetic scenes of `--ttq-seeds`; held-out PSNR
    /// (`--eval-images` novel views) against training time, and the minutes each needs to
    /// reach parity's PSNR at each of `--ttq-marks`. Writes quality.json, quality.md and
    /// time_to_quality.png. The full measurement (the defaults) trains 72 minutes per seed.
    #[arg(long, conflicts_with_all = ["account", "forward_only", "shares"])]
    pub time_to_quality: bool,
    /// Scene seeds of `--time-to-quality` (not the seeds the options were tuned on: 0 and 7).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "101,102,103",
        requires = "time_to_quality"
    )]
    pub ttq_seeds: Vec<u64>,
    /// Minutes of training at which parity's held-out PSNR is a target (ascending).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "1,2,5",
        requires = "time_to_quality"
    )]
    pub ttq_marks: Vec<f64>,
    /// Held-out scores along each curve over the last mark (the marks are scored too).
    #[arg(long, default_value_t = 20, requires = "time_to_quality")]
    pub ttq_points: usize,
    /// The options `--time-to-quality` compares (parity, the target, always runs):
    /// cull-grid, error-map, anneal, coarse-from-grid, jitter, average, lr-freq,
    /// pose-boost, recipe-no-boost, recipe, all.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "cull-grid,error-map,anneal,coarse-from-grid,jitter,average,lr-freq,pose-boost,recipe-no-boost,recipe,all",
        requires = "time_to_quality"
    )]
    pub ttq_options: Vec<String>,
}

pub fn run(mut args: Args) -> anyhow::Result<()> {
    check_args(&mut args)?;
    let dev = super::device_tf32(&args.device, args.tf32)?;
    pma_data::fsio::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    if args.forward_only {
        return forward_only(&args);
    }
    if args.account {
        return account::run(&args, &dev);
    }
    if args.shares {
        return shares::run(&args, &dev);
    }
    if args.time_to_quality {
        return quality::run(&args, &dev);
    }
    let preset: Preset = args.preset.parse()?;
    let scene = scene(&args);
    let req = BenchRequest {
        preset,
        model: args.model.clone(),
        out: args.out.clone(),
        scene,
        train_seconds: args.train_seconds,
        budget_seconds: args.budget_seconds,
        res: args.res,
        repeats: args.repeats,
        eval_images: args.eval_images,
        options: options(&args.thresholds, args.occupancy, args.early_stop),
        occupancy: pma_model::network::occupancy::OccupancyConfig {
            warmup_steps: args.occupancy_warmup,
            ..Default::default()
        },
        occupancy_poses: args.occupancy_poses,
        device: dev,
        numerics: super::numerics(),
    };
    let mut report = measure(&req, &mut Phases::new(args.quiet))?;
    if let Some(batch) = &args.forward_batch {
        let model = match (&args.forward_model, &args.model) {
            (Some(m), _) | (None, Some(m)) => m.clone(),
            (None, None) => args.out.join("model.safetensors"),
        };
        report.forward = Some(forward::time(batch, &model, args.repeats, &args.out)?);
    }
    print_table(&report);
    write_json(&report, &args.out.join("bench.json"))?;
    let pts: Vec<(f64, f64, &str)> = report
        .options
        .iter()
        .map(|o| {
            let loss = o.psnr_loss_vs_parity_db;
            let loss = if loss.is_finite() { loss } else { 0.0 };
            (o.ms_per_image / 1e3, loss, o.option.name.as_str())
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

/// The synthetic scene of `--scene-seed`, a small one under `--quick`.
fn scene(args: &Args) -> pma_data::synth::SynthConfig {
    let mut scene = pma_data::synth::SynthConfig {
        seed: args.scene_seed,
        ..Default::default()
    };
    if args.quick {
        scene.res = 32;
        scene.frames = 8;
        scene.novel_pose_walk = 2;
        scene.novel_pose_dance = 2;
    }
    scene
}

/// `--forward-only`: the whole-process `pma forward` row alone.
fn forward_only(args: &Args) -> anyhow::Result<()> {
    let Some(batch) = &args.forward_batch else {
        refuse!("--forward-only needs --forward-batch");
    };
    let Some(model) = args.forward_model.clone().or_else(|| args.model.clone()) else {
        refuse!("--forward-only needs --forward-model (or --model)");
    };
    let f = forward::time(batch, &model, args.repeats, &args.out)?;
    forward::print(&f);
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
    super::check_paths(
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
    let e = args.early_stop;
    if !(e.is_finite() && e > 0.0 && e < 1.0) {
        refuse!("--early-stop: expected a transmittance in (0, 1), found {e}");
    }
    let t = args.shares_threshold;
    if !(t.is_finite() && (0.0..1.0).contains(&t)) {
        refuse!("--shares-threshold: expected a number in [0, 1), found {t}");
    }
    if args.shares && args.quick {
        args.shares_steps = args.shares_steps.min(2);
        args.occupancy_poses = args.occupancy_poses.min(2);
    }
    Ok(())
}

fn print_table(r: &BenchReport) {
    if let Some(f) = &r.forward {
        forward::print(f);
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
            "rdr MiB",
            "PSNR/par",
            "ΔPSNR dB",
            "held dB",
            "LPIPS",
            "budget dB"
        );
    for o in &r.options {
        println!(
                "{:<22} {:>9.1} {:>9.0} {:>7.2} {:>11.0} {:>11.0} {:>8.2} {:>8.1} {:>7.2} {:>8.2} {:>6.1}% {:>9.0} {:>9.2} {:>8.3} {:>9.2} {:>7} {:>9}",
                o.option.name,
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
    if let Some(mib) = r.training_peak_rss_mib {
        println!("training (every option's trainer held, in turns): peak RSS {mib:.0} MiB");
    }
}
