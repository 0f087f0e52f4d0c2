//! Parity against each [`BenchOption`], side by side in one process: network points/s and
//! rays/s of inference, ms per rendered W×H image, ms per training step, peak RSS of each
//! phase, the render's difference from parity's, held-out PSNR and LPIPS against ground
//! truth, the same after a wall-clock training budget per option, and the achieved GFLOP/s
//! against an estimate of the machine's fp32 peak.
//!
//! Render timings go round-robin over the options (every option's first repeat, then every
//! option's second, ...), so a machine whose speed drifts during the run shifts all options
//! alike. Training is timed the same way: every option's trainer trains in turns of a few
//! seconds until each has spent its wall-clock budget.
//!
//! FLOPs and the peak they are set against are [`crate::compute::flops`]'s: matmul FLOPs per
//! network point (3× for a training step: forward, input and weight gradients) over
//! cores × GHz × FLOP/cycle from /proc/cpuinfo.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use candle_core::{Device, Tensor};
use pma_data::camera::Camera;
use pma_data::dataset::{Dataset, Profile};
use pma_data::metrics::psnr;
use pma_data::skeleton::Joints;
use pma_data::synth::{generate, SynthConfig};
use serde::{Deserialize, Serialize};

use super::{peak_rss_mib, reset_peak_rss, BenchError, BenchObserver, BenchOption, Result};
use crate::compute::flops;
use crate::eval::{dataset_pose, evaluate, read_dataset, EvalOptions};
use crate::network::occupancy::{OccupancyConfig, OccupancyGrid};
use crate::render::avatar::{Avatar, Poses};
use crate::render::image::{body_box, ImageOptions, RenderedImage};
use crate::render::PassOptions;
use crate::train::{Preset, RunConfig, Trainer};

/// Rays per render chunk of every bench render and held-out score.
const CHUNK: usize = 4096;

/// What to measure.
#[derive(Debug, Clone)]
pub struct BenchRequest {
    pub preset: Preset,
    /// Render this trained model (its own preset) instead of training one in-process.
    pub model: Option<PathBuf>,
    /// Where the scene (`scene/`) and the model trained in-process (`model.safetensors`) go.
    pub out: PathBuf,
    /// The synthetic scene: training data and the held-out images.
    pub scene: SynthConfig,
    /// Seconds of in-process training of the rendered model (without `model`).
    pub train_seconds: f64,
    /// Training budget per option for the held-out columns (0: two steps only, the first a
    /// warm-up).
    pub budget_seconds: f64,
    /// Rendered image size (square).
    pub res: usize,
    /// Timed renders per option after one untimed one (medians are reported).
    pub repeats: usize,
    /// Held-out images scored.
    pub eval_images: usize,
    pub options: Vec<BenchOption>,
    /// The grid of the training rows with `occupancy` (its warm-up decides when the grid
    /// starts to skip samples).
    pub occupancy: OccupancyConfig,
    /// Training poses the rendered model's grid is built over when an option needs one and
    /// the model has none.
    pub occupancy_poses: usize,
    pub device: Device,
    /// How every avatar computes before an option changes it (`--tf32`).
    pub numerics: crate::compute::numerics::Numerics,
}

/// One option's measurements (a row of `bench.json`).
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct OptionResult {
    #[serde(flatten)]
    pub option: BenchOption,
    /// Median ms per rendered image.
    pub ms_per_image: f64,
    /// Rays traced per image (pixels inside the body box) per second.
    pub rays_per_s: f64,
    /// Network points (far-away constants included) per second.
    pub network_points_per_s: f64,
    /// All samples the rendered rays stand for (rays × (Sc + Sf)) per second.
    pub samples_per_s: f64,
    pub network_points_per_image: u64,
    /// Joints a network point carried through the per-joint work, on average (24 unless
    /// the calls are grouped by joints).
    #[serde(default)]
    pub joints_per_point: f64,
    /// Achieved matmul GFLOP/s (network points × FLOPs per point / time).
    pub gflops: f64,
    /// Mean ms per training step over the budget (the option's culling and grid in training,
    /// the grid's refreshes included).
    pub ms_per_step: f64,
    /// Achieved matmul GFLOP/s of a training step (evaluated points × FLOPs per point ×
    /// `flops::TRAIN_FACTOR` / mean step time).
    #[serde(default)]
    pub train_gflops: f64,
    /// Parity's mean ms per step over this option's (training speed-up).
    #[serde(default)]
    pub step_speedup_vs_parity: f64,
    /// Share of a training step's samples that ran the network (far-away constants
    /// included), over the option's training steps.
    #[serde(default)]
    pub train_evaluated_fraction: f64,
    /// Peak RSS of this option's render phase (VmHWM after a reset; process-wide if no
    /// reset). The training phase holds every option's trainer at once: its peak is
    /// [`BenchReport::training_peak_rss_mib`].
    pub peak_rss_mib: f64,
    /// PSNR of this option's W×H render against the parity render (inf = identical).
    pub psnr_vs_parity_render: f64,
    /// Max |Δrgb| against the parity render.
    pub max_abs_diff_vs_parity: f64,
    /// Held-out PSNR of the rendered model (`pma eval`'s protocol) and its loss against
    /// parity.
    pub heldout_psnr: f64,
    pub psnr_loss_vs_parity_db: f64,
    /// Held-out LPIPS (`None` under LPIPS's 31×31 minimum).
    pub heldout_lpips: Option<f64>,
    /// Held-out PSNR after `budget_seconds` of training with this option from the same init.
    pub budget_heldout_psnr: Option<f64>,
    pub budget_heldout_lpips: Option<f64>,
    pub budget_iterations: Option<u64>,
    /// Speed-up of rays/s against parity.
    pub speedup_vs_parity: f64,
}

/// `bench.json`.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
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
    /// Peak RSS of the training phase, every option's trainer held at once (they train in
    /// turns); VmHWM after a reset, process-wide if no reset.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub training_peak_rss_mib: Option<f64>,
    /// Whole-process `pma forward` runs on a ray batch, if asked for.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub forward: Option<ForwardResult>,
}

/// Wall time of whole `pma forward` processes (start-up, loading, the pass, writing).
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct ForwardResult {
    pub batch: String,
    pub model: String,
    pub rays: usize,
    /// Seconds of each timed run (after one warm-up run), in run order.
    pub runs_s: Vec<f64>,
    pub median_s: f64,
    pub rays_per_s: f64,
}

/// The median of `v` (the upper one of an even count; NaN when empty).
pub fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Measure every option of `req` (see the module docs). The first option is the one the
/// others are compared with.
pub fn measure(req: &BenchRequest, obs: &mut dyn BenchObserver) -> Result<BenchReport> {
    if req.options.is_empty() || req.repeats == 0 {
        return Err(BenchError::Setting(
            "a bench needs at least one option and one repeat".into(),
        ));
    }
    let rss_reset = reset_peak_rss();
    let scene = prepare_scene(&req.out, &req.scene, req.eval_images, obs)?;
    // Loaded before the per-option peak-RSS resets, so no option's phase pays for it.
    crate::eval::lpips::Lpips::shared()?;
    let (avatar, model_desc) = bench_model(req, &scene, obs)?;
    let (mut avatar, grids) = grids_for(
        &req.occupancy,
        req.occupancy_poses,
        &req.options,
        avatar,
        &scene.train,
        obs,
    )?;
    let cfg = avatar.config().clone();
    let fpp = flops::per_point(&cfg);
    let (peak, peak_how) = flops::fp32_peak();
    let view = bench_view(req, &scene)?;
    let inactive = inactive_joint_fraction(&avatar, &view)?;

    let mut results =
        measure_inference(req, &mut avatar, &grids, &scene, &view, fpp, rss_reset, obs)?;
    let training_peak_rss_mib = measure_training(req, &cfg, &scene, &mut results, obs)?;
    let (parity_rays, parity_step) = (results[0].rays_per_s, results[0].ms_per_step);
    for r in &mut results {
        r.speedup_vs_parity = r.rays_per_s / parity_rays;
        r.step_speedup_vs_parity = parity_step / r.ms_per_step;
    }
    Ok(BenchReport {
        preset: req.preset.name().to_string(),
        res: req.res,
        repeats: req.repeats,
        model: model_desc,
        flops_per_point: fpp,
        peak_gflops: peak,
        peak_estimate: peak_how,
        rss_reset_supported: rss_reset,
        inactive_joint_fraction: inactive,
        options: results,
        training_peak_rss_mib,
        forward: None,
    })
}

/// The scene's training split and the held-out images the quality columns use.
pub(crate) struct Scene {
    pub train: Arc<Dataset>,
    pub held: Dataset,
    pub eval_set: Vec<usize>,
}

/// The synthetic scene in `out/scene` (made once): training data and `eval_images`
/// held-out images spread over the novel-view split.
pub(crate) fn prepare_scene(
    out: &std::path::Path,
    scene: &SynthConfig,
    eval_images: usize,
    obs: &mut dyn BenchObserver,
) -> Result<Scene> {
    let dir = match scene.seed {
        0 => out.join("scene"),
        n => out.join(format!("scene-seed{n}")),
    };
    if !dir.join("novel_view.npz").is_file() {
        obs.note(&format!("synthesising the scene into {}", dir.display()));
        generate(scene, &dir, &mut |_, _| {}).map_err(|source| BenchError::Scene {
            what: "bench",
            source: Box::new(source),
        })?;
    }
    let train = Arc::new(read_dataset(&dir.join("train.npz"), Profile::Train)?);
    let held = read_dataset(&dir.join("novel_view.npz"), Profile::Eval)?;
    for (file, data) in [("train.npz", &*train), ("novel_view.npz", &held)] {
        for w in &data.warnings {
            obs.warning(&format!("{}: {w}", dir.join(file).display()));
        }
    }
    let eval_set = held_out_set(held.n_images(), eval_images);
    Ok(Scene {
        train,
        held,
        eval_set,
    })
}

/// The `k` held-out images the bench scores: the ones `pma eval --max-images k` scores, so
/// the bench's PSNR is eval's. The synthetic split interleaves its cameras, and a stride
/// that divides their count would see one camera only.
fn held_out_set(n_images: usize, k: usize) -> Vec<usize> {
    let all: Vec<usize> = (0..n_images).collect();
    crate::eval::spread(&all, k.max(1))
}

/// Train `run` for `seconds` (at least 2 steps); `elapsed` hears the seconds spent after
/// every step.
fn train_for(
    run: RunConfig,
    data: Arc<Dataset>,
    seconds: f64,
    dev: &Device,
    elapsed: &mut dyn FnMut(f64),
) -> Result<Trainer> {
    let mut trainer = Trainer::new(run, data, dev)?;
    let start = Instant::now();
    let mut steps = 0;
    while steps < 2 || start.elapsed().as_secs_f64() < seconds {
        trainer.step()?;
        steps += 1;
        elapsed(start.elapsed().as_secs_f64());
    }
    Ok(trainer)
}

/// Mean held-out PSNR and LPIPS of `avatar` on the scene's held-out images, by
/// [`crate::eval::evaluate`] (LPIPS `None` for images under its minimum size).
fn heldout_scores(
    avatar: &Avatar,
    scene: &Scene,
    pass: &PassOptions,
) -> Result<(f64, Option<f64>)> {
    let opts = EvalOptions {
        pass: pass.clone(),
        ..EvalOptions::quick(CHUNK)
    };
    let r = evaluate(
        avatar,
        &scene.held,
        "novel_view",
        &scene.eval_set,
        &opts,
        &mut |_, _| {},
    )?;
    Ok((r.psnr, (!r.lpips.is_nan()).then_some(r.lpips)))
}

/// The model that is rendered: `req.model`, or one trained in-process for
/// `req.train_seconds`. Returns it with a description for the report.
fn bench_model(
    req: &BenchRequest,
    scene: &Scene,
    obs: &mut dyn BenchObserver,
) -> Result<(Avatar, String)> {
    let load = |path: &std::path::Path| {
        Avatar::load(path, &req.device)
            .map(|a| a.with_numerics(req.numerics))
            .map_err(|source| BenchError::Load {
                path: path.to_path_buf(),
                source: Box::new(source),
            })
    };
    if let Some(p) = &req.model {
        return Ok((load(p)?, p.display().to_string()));
    }
    obs.phase("training the bench model (s)", req.train_seconds as u64);
    let mut run = RunConfig::from_preset(req.preset);
    run.numerics = req.numerics;
    let trainer = train_for(
        run,
        scene.train.clone(),
        req.train_seconds,
        &req.device,
        &mut |s| obs.progress(s.min(req.train_seconds) as u64, ""),
    )?;
    obs.phase_end();
    let path = req.out.join("model.safetensors");
    trainer.with_model(|a| a.save(&path).map_err(crate::train::TrainError::from))?;
    obs.note(&format!(
        "trained {} iterations of {} in-process ({:.0} s)",
        trainer.iteration(),
        req.preset.name(),
        req.train_seconds
    ));
    Ok((
        load(&path)?,
        format!("{} (trained in-process)", path.display()),
    ))
}

/// The occupancy grids of the rendering rows: empty when no option uses one or the model
/// brought its own (every row then uses that); otherwise one grid per span, built from the
/// scene's training poses, spanning where the option's culling threshold lets the window
/// through ([`OccupancyConfig::covering`]): the grid alone spans the whole window.
pub(super) struct Grids {
    grids: Vec<(u64, Arc<OccupancyGrid>)>,
    config: OccupancyConfig,
}

impl Grids {
    fn extent(config: &OccupancyConfig, avatar: &Avatar, opt: &BenchOption) -> f64 {
        config
            .clone()
            .covering(opt.culling.sample_threshold, avatar.config())
            .extent
    }

    /// Give `avatar` the grid `opt` renders with.
    pub(super) fn select(&self, avatar: &mut Avatar, opt: &BenchOption) {
        if self.grids.is_empty() || !opt.occupancy {
            return;
        }
        let key = Self::extent(&self.config, avatar, opt).to_bits();
        let grid = self
            .grids
            .iter()
            .find(|(k, _)| *k == key)
            .map(|(_, g)| g.clone());
        avatar.set_occupancy(grid);
    }
}

/// The grids of `options` (see [`Grids`]) built with `config` over `poses` training poses of
/// `train`; each is announced through `obs` with its span and occupied share.
pub(super) fn grids_for(
    config: &OccupancyConfig,
    poses: usize,
    options: &[BenchOption],
    mut avatar: Avatar,
    train: &Arc<Dataset>,
    obs: &mut dyn BenchObserver,
) -> Result<(Avatar, Grids)> {
    use crate::tools::occupancy::{build, BuildOptions};
    let mut grids: Vec<(u64, Arc<OccupancyGrid>)> = Vec::new();
    let config = config.clone();
    if avatar.occupancy().is_some() {
        return Ok((avatar, Grids { grids, config }));
    }
    for opt in options.iter().filter(|o| o.occupancy) {
        let extent = Grids::extent(&config, &avatar, opt);
        if grids.iter().any(|(k, _)| *k == extent.to_bits()) {
            continue;
        }
        let opts = BuildOptions {
            config: OccupancyConfig {
                extent,
                ..config.clone()
            },
            poses: poses.max(1),
            ..Default::default()
        };
        obs.phase("building the occupancy grid (poses)", opts.poses as u64);
        let t = Instant::now();
        let (built, s) = build(avatar, train, &opts, &mut |d, _| obs.progress(d as u64, ""))?;
        avatar = built;
        obs.phase_end();
        obs.note(&format!(
            "built an occupancy grid over |x̄| < {extent:.3} of the rendered model in {:.1} s \
             ({} poses, {} network points, {:.1} % of cells occupied)",
            t.elapsed().as_secs_f64(),
            s.poses,
            s.points,
            100.0 * s.occupied_fraction
        ));
        let grid = avatar
            .occupancy_shared()
            .ok_or_else(|| BenchError::Setting("the grid build returned no grid".into()))?;
        avatar.set_occupancy(None);
        grids.push((extent.to_bits(), grid));
    }
    Ok((avatar, Grids { grids, config }))
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

fn bench_view(req: &BenchRequest, scene: &Scene) -> Result<View> {
    let held = &scene.held;
    let n0 = scene.eval_set[0];
    let (poses, kp3d) = dataset_pose(held, held.pose_row(n0)?, &req.device)?;
    let cam0 = held.image_camera(n0)?;
    let sx = req.res as f32 / cam0.width as f32;
    let sy = req.res as f32 / cam0.height as f32;
    let cam = Camera::new(
        req.res,
        req.res,
        cam0.fx * sx,
        cam0.fy * sy,
        cam0.cx * sx,
        cam0.cy * sy,
        cam0.c2w,
    )?;
    let opts = ImageOptions {
        chunk: CHUNK,
        head: held.head()?,
        device: req.device.clone(),
        pass: PassOptions::parity(),
    };
    let box_rays = {
        let b = body_box(&cam, &kp3d, opts.head);
        let res = req.res as i64;
        ((b.x1.min(res) - b.x0.max(0)).max(0) * (b.y1.min(res) - b.y0.max(0)).max(0)) as f64
    };
    Ok(View {
        poses,
        kp3d,
        cam,
        opts,
        box_rays,
    })
}

/// Inference per option: render time, points, peak RSS, and the quality columns.
#[allow(clippy::too_many_arguments)]
fn measure_inference(
    req: &BenchRequest,
    avatar: &mut Avatar,
    grids: &Grids,
    scene: &Scene,
    view: &View,
    flops_per_point: f64,
    rss_reset: bool,
    obs: &mut dyn BenchObserver,
) -> Result<Vec<OptionResult>> {
    let opts = &req.options;
    let samples_per_ray = {
        let c = avatar.config();
        (c.n_samples + c.n_importance) as f64
    };
    let render = |a: &Avatar, pass: PassOptions| -> Result<RenderedImage> {
        let opts = ImageOptions {
            pass,
            ..view.opts.clone()
        };
        Ok(a.render_image(&view.poses, &view.kp3d, &view.cam, None, &opts)?)
    };
    let mut results: Vec<OptionResult> = Vec::new();
    let mut parity: Option<(RenderedImage, f64)> = None;
    obs.phase(
        "inference per option",
        (opts.len() * (1 + req.repeats)) as u64,
    );
    let mut done = 0;
    // First each option's untimed render (the warm-up), its quality and memory.
    for opt in opts {
        obs.progress(done, &format!("render {}", opt.name));
        let pass = opt.apply(avatar);
        grids.select(avatar, opt);
        if rss_reset {
            reset_peak_rss();
        }
        let img = render(avatar, pass.clone())?;
        let (held_psnr, held_lpips) = heldout_scores(avatar, scene, &pass)?;
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
            option: opt.clone(),
            peak_rss_mib: peak_rss,
            psnr_vs_parity_render: vs_parity,
            max_abs_diff_vs_parity: max_diff,
            heldout_psnr: held_psnr,
            psnr_loss_vs_parity_db: parity_psnr - held_psnr,
            heldout_lpips: held_lpips,
            ..Default::default()
        });
        done += 1;
    }
    // Then the timed renders, round-robin over the options: a VM whose speed drifts
    // during the run slows every option alike instead of the ones timed last.
    let mut times = vec![Vec::new(); opts.len()];
    for _ in 0..req.repeats {
        for ((opt, t_opt), res) in opts.iter().zip(times.iter_mut()).zip(results.iter_mut()) {
            obs.progress(done, &format!("time {}", opt.name));
            let pass = opt.apply(avatar);
            grids.select(avatar, opt);
            let t = Instant::now();
            let img = render(avatar, pass)?;
            t_opt.push(t.elapsed().as_secs_f64());
            res.network_points_per_image = img.stats.points_evaluated;
            res.joints_per_point =
                img.stats.joint_rows as f64 / img.stats.points_evaluated.max(1) as f64;
            done += 1;
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
    obs.phase_end();
    BenchOption::parity().apply(avatar);
    Ok(results)
}

/// Seconds each trainer runs before the next takes its turn (see [`measure_training`]).
const TRAINING_TURN_SECONDS: f64 = 2.0;

/// One training setting's run in [`measure_training`].
struct TrainingRun {
    trainer: Trainer,
    /// Wall time of each step, ms.
    times: Vec<f64>,
    /// Seconds trained so far (the budget is spent on these).
    trained: f64,
}

impl TrainingRun {
    /// Whether the run has trained for `budget` seconds (at least two steps: the first is
    /// a warm-up), or `max_steps` steps.
    fn done(&self, budget: f64, max_steps: u64) -> bool {
        (self.times.len() >= 2 && self.trained >= budget) || self.times.len() as u64 >= max_steps
    }
}

/// Training per option: ms per step and held-out quality after the same wall-clock budget.
///
/// Every distinct training setting gets its own trainer from the same initialisation
/// (options that differ only in how a render places, stops or groups its samples train
/// alike and share one), and the trainers take turns of [`TRAINING_TURN_SECONDS`] until
/// each has trained for the budget: a machine whose speed drifts during the bench slows
/// every option alike, as the renders' round-robin does. The peak RSS of this phase is that
/// of all trainers together, so the options' RSS figures are their renders'.
fn measure_training(
    req: &BenchRequest,
    cfg: &crate::Config,
    scene: &Scene,
    results: &mut [OptionResult],
    obs: &mut dyn BenchObserver,
) -> Result<Option<f64>> {
    let dev = &req.device;
    let budget = req.budget_seconds.max(0.0);
    let same_training = |o: &BenchOption| BenchOption {
        name: String::new(),
        occupancy_fine: false,
        early_stop: None,
        cull_joints: false,
        ..o.clone()
    };
    // The run of each option; per run its training setting and the first option with it.
    let mut settings: Vec<(BenchOption, &BenchOption)> = Vec::new();
    let run_of: Vec<usize> = req
        .options
        .iter()
        .map(|opt| {
            let key = same_training(opt);
            settings
                .iter()
                .position(|(s, _)| *s == key)
                .unwrap_or_else(|| {
                    settings.push((key, opt));
                    settings.len() - 1
                })
        })
        .collect();
    let mut runs = Vec::with_capacity(settings.len());
    for (_, opt) in &settings {
        let mut run = RunConfig::from_preset(req.preset);
        run.model = cfg.clone();
        run.numerics = req.numerics;
        opt.configure(&mut run, &req.occupancy);
        runs.push(TrainingRun {
            trainer: Trainer::new(run, scene.train.clone(), dev)?,
            times: Vec::new(),
            trained: 0.0,
        });
    }
    let max_steps = if budget > 0.0 { u64::MAX } else { 2 };
    reset_peak_rss();
    obs.phase(
        "training, options in turns (s)",
        (budget * runs.len() as f64).ceil() as u64,
    );
    let mut spent = 0.0;
    while runs.iter().any(|r| !r.done(budget, max_steps)) {
        for (k, run) in runs.iter_mut().enumerate() {
            let (before, turn) = (run.trained.min(budget), Instant::now());
            while !run.done(budget, max_steps)
                && turn.elapsed().as_secs_f64() < TRAINING_TURN_SECONDS
            {
                let t = Instant::now();
                run.trainer.step()?;
                let dt = t.elapsed().as_secs_f64();
                run.times.push(dt * 1e3);
                run.trained += dt;
            }
            spent += run.trained.min(budget) - before;
            obs.progress(spent as u64, &format!("train {}", settings[k].1.name));
        }
    }
    obs.phase_end();
    let phase_peak = peak_rss_mib();
    let samples_per_step = |t: &Trainer| {
        (t.run_config().train.rays_per_step * (cfg.n_samples + cfg.n_importance)) as f64
    };
    for ((res, opt), &k) in results.iter_mut().zip(&req.options).zip(&run_of) {
        let run = &runs[k];
        let steps = run.times.len();
        // The mean, not the median: steps/s over the budget, the grid's refreshes (one
        // step in `refresh_every`) included; the first step is a warm-up.
        let timed = &run.times[steps.min(1)..];
        res.ms_per_step = timed.iter().sum::<f64>() / timed.len().max(1) as f64;
        let points = run.trainer.pass_totals().points_evaluated as f64;
        res.train_evaluated_fraction =
            points / (samples_per_step(&run.trainer) * steps.max(1) as f64);
        res.train_gflops = results_gflops(
            cfg,
            &run.trainer,
            res.train_evaluated_fraction,
            res.ms_per_step,
        );
        if budget > 0.0 {
            let (p, l) = run
                .trainer
                .with_model(|a| heldout_scores(a, scene, &opt.pass()))?;
            res.budget_heldout_psnr = Some(p);
            res.budget_heldout_lpips = l;
            res.budget_iterations = Some(run.trainer.iteration());
        }
    }
    Ok(phase_peak)
}

/// Training GFLOP/s of a step at `ms` ms that ran the network on `fraction` of its samples.
fn results_gflops(cfg: &crate::Config, trainer: &Trainer, fraction: f64, ms: f64) -> f64 {
    let rays = trainer.run_config().train.rays_per_step;
    let samples_per_step = (rays * (cfg.n_samples + cfg.n_importance)) as f64;
    samples_per_step * fraction * flops::per_point(cfg) * flops::TRAIN_FACTOR / (ms * 1e6)
}

/// Fraction of (render chunk, joint) pairs with a zero window on every coarse sample.
fn inactive_joint_fraction(avatar: &Avatar, view: &View) -> Result<f64> {
    let (cam, kp3d, poses, opts) = (&view.cam, &view.kp3d, &view.poses, &view.opts);
    let pbox = body_box(cam, kp3d, opts.head);
    let (w, h) = (cam.width as i64, cam.height as i64);
    let pixels: Vec<(usize, usize)> = (pbox.y0.max(0)..pbox.y1.min(h))
        .flat_map(|y| (pbox.x0.max(0)..pbox.x1.min(w)).map(move |x| (x as usize, y as usize)))
        .collect();
    let scales = avatar.axis_scale()?.detach();
    let align: Vec<f32> = avatar.tensors()["pts_embedder.transforms"]
        .flatten_all()?
        .to_vec1()?;
    let skts: Vec<f32> = poses.skts.flatten_all()?.to_vec1()?;
    let test = crate::render::cull::WindowTest::new(
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_held_out_set_is_evals_and_sees_both_interleaved_cameras() {
        // `pma synth`'s novel-view split: 2 cameras interleaved over 32 poses.
        let set = held_out_set(64, 16);
        let all: Vec<usize> = (0..64).collect();
        assert_eq!(set, crate::eval::spread(&all, 16));
        assert_eq!(set.len(), 16);
        let odd = set.iter().filter(|&&i| i % 2 == 1).count();
        assert!((4..=12).contains(&odd), "{set:?}");
        assert_eq!(held_out_set(5, 16), vec![0, 1, 2, 3, 4]);
        assert_eq!(held_out_set(64, 0), vec![0]);
    }
}
