//! The share of samples that run the network, per pass (coarse, fine), under each way of
//! leaving work out: `pma bench --shares`. These are counts ([`PassStats`]), not timings:
//! for one model, scene and set of rays they are the same on every run and machine.
//!
//! The model is `--model`, or the preset trained in-process for a fixed number of steps (a
//! step count, not a wall-clock budget, so the figures repeat). Its occupancy grid is the one
//! saved with it, or grids built as `pma occupancy build` builds them over the scene's
//! training poses, one per span as `pma bench` builds them: the grid alone over the whole
//! window, the culling row's over where its threshold lets a window through. Two sets of rays
//! are counted:
//!
//! * **render**: the rays a render of held-out views traces (the pixels inside the body's
//!   2-D box, at the dataset's resolution), as `pma render` / `pma eval` would;
//! * **training batches**: the rays of the first training batches the preset's sampler draws
//!   (its rays per step), through one forward pass without gradients. The coarse pass's
//!   decisions are those of a training step; the fine pass places its samples from coarse
//!   weights without density noise, so its share can differ a little from a noisy step's.
//!
//! A share is evaluated samples over all samples of the traced rays (rays × samples of the
//! pass); far-away constants are not counted as samples.

use std::path::PathBuf;

use candle_core::Device;
use pma_data::dataset::Dataset;
use pma_data::synth::SynthConfig;
use serde::{Deserialize, Serialize};

use super::measure::{grids_for, prepare_scene, Scene};
use super::{BenchError, BenchObserver, BenchOption, Result};
use crate::eval::dataset_pose;
use crate::network::occupancy::OccupancyConfig;
use crate::render::avatar::{Avatar, Mode};
use crate::render::image::ImageOptions;
use crate::render::{Culling, PassOptions, PassStats, SampleFill};
use crate::train::{BatchSource, DatasetSource, Preset, RunConfig, Trainer};

/// What to count.
#[derive(Debug, Clone)]
pub struct SharesRequest {
    pub preset: Preset,
    /// Count on this trained model instead of training one in-process.
    pub model: Option<PathBuf>,
    /// Where the scene and the model trained in-process (`shares-model.safetensors`) go.
    pub out: PathBuf,
    pub scene: SynthConfig,
    /// Training steps of the in-process model.
    pub train_steps: u64,
    /// Rays per step of the in-process training (`None`: the preset's). The counted training
    /// batches always have the preset's rays per step.
    pub train_rays: Option<usize>,
    /// The w^p culling threshold of the culling rows.
    pub threshold: f64,
    /// The grid built when the model has none.
    pub occupancy: OccupancyConfig,
    /// Training poses that grid is built over.
    pub occupancy_poses: usize,
    /// Held-out views rendered.
    pub eval_images: usize,
    /// Training batches counted.
    pub batches: usize,
    pub device: Device,
    pub numerics: crate::compute::numerics::Numerics,
}

/// The counts of one option on one set of rays.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PassShare {
    pub option: String,
    pub rays: u64,
    pub coarse_samples: u64,
    pub coarse_evaluated: u64,
    pub fine_samples: u64,
    pub fine_evaluated: u64,
    /// Samples left out because the grid marks their cells empty (both passes).
    pub skipped_empty: u64,
}

impl PassShare {
    pub fn coarse(&self) -> f64 {
        self.coarse_evaluated as f64 / self.coarse_samples.max(1) as f64
    }
    pub fn fine(&self) -> f64 {
        self.fine_evaluated as f64 / self.fine_samples.max(1) as f64
    }
    pub fn all(&self) -> f64 {
        (self.coarse_evaluated + self.fine_evaluated) as f64
            / (self.coarse_samples + self.fine_samples).max(1) as f64
    }
}

/// `shares.json`.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct SharesReport {
    pub preset: String,
    pub model: String,
    /// Training steps of the counted model (`None` for `--model`).
    pub train_steps: Option<u64>,
    pub train_rays_per_step: Option<usize>,
    pub threshold: f64,
    /// How the grids were made: the model's own for every row, or one per span (each with
    /// its span and occupied share).
    pub grid: String,
    /// Occupied share of the grid the `occupancy` row (the grid alone) uses.
    pub grid_occupied_fraction: f64,
    pub coarse_samples_per_ray: usize,
    pub fine_samples_per_ray: usize,
    /// Held-out views rendered (image indices of the novel-view split).
    pub render_images: Vec<usize>,
    pub render: Vec<PassShare>,
    pub batch_rays: usize,
    pub batches: usize,
    pub training_batches: Vec<PassShare>,
}

/// The options counted: parity, each way of leaving work out alone, and combined.
pub fn share_options(threshold: f64) -> Vec<BenchOption> {
    let culling = |rays: bool, t: Option<f64>| Culling {
        rays,
        sample_threshold: t,
        sample_fill: SampleFill::Network,
    };
    let t = Some(threshold);
    let row = |name: String, culling: Culling, occupancy: bool| BenchOption {
        name,
        culling,
        occupancy,
        ..BenchOption::default()
    };
    vec![
        BenchOption::parity(),
        row("rays".into(), culling(true, None), false),
        row(format!("samples<={threshold}"), culling(false, t), false),
        row(
            format!("rays+samples<={threshold}"),
            culling(true, t),
            false,
        ),
        row("occupancy".into(), Culling::default(), true),
        row(
            format!("rays+samples<={threshold}+occupancy"),
            culling(true, t),
            true,
        ),
    ]
}

/// Count every option of [`share_options`] (see the module docs).
pub fn shares(req: &SharesRequest, obs: &mut dyn BenchObserver) -> Result<SharesReport> {
    if !(req.threshold.is_finite() && (0.0..1.0).contains(&req.threshold)) {
        return Err(BenchError::Setting(format!(
            "--shares-threshold must be in [0, 1), found {}",
            req.threshold
        )));
    }
    if req.batches == 0 && req.eval_images == 0 {
        return Err(BenchError::Setting(
            "nothing to count: no held-out views and no training batches".into(),
        ));
    }
    let scene = prepare_scene(&req.out, &req.scene, req.eval_images, obs)?;
    let (avatar, model, steps) = shares_model(req, &scene, obs)?;
    let options = share_options(req.threshold);
    let saved = avatar.occupancy().map(|g| {
        let how = format!(
            "saved with the model ({}^3 per joint, {} refreshes), for every row",
            g.config().resolution,
            g.refreshes()
        );
        (how, g.occupied_fraction())
    });
    let (mut avatar, grids) = grids_for(
        &req.occupancy,
        req.occupancy_poses,
        &options,
        avatar,
        &scene.train,
        obs,
    )?;
    let (grid, occupied) = match saved {
        Some(s) => s,
        None => {
            // One grid per span, as the timing bench builds them: the grid alone over the
            // whole window, the culling row's over where its threshold lets a window through.
            let mut spans = Vec::new();
            let mut whole = 1.0;
            for o in options.iter().filter(|o| o.occupancy) {
                grids.select(&mut avatar, o);
                if let Some(g) = avatar.occupancy() {
                    if o.culling.sample_threshold.is_none() {
                        whole = g.occupied_fraction();
                    }
                    spans.push(format!(
                        "{}: |x̄| < {:.3}, {:.1} % occupied",
                        o.name,
                        g.config().extent,
                        100.0 * g.occupied_fraction()
                    ));
                }
            }
            let how = format!(
                "built over {} training poses as `pma occupancy build` does ({}^3 per joint), \
                 one per span ({})",
                req.occupancy_poses.max(1),
                req.occupancy.resolution,
                spans.join("; ")
            );
            (how, whole)
        }
    };
    let cfg = avatar.config().clone();
    for o in &options {
        o.pass()
            .validate(&cfg)
            .map_err(|e| BenchError::Setting(e.to_string()))?;
    }

    let images: Vec<usize> = match req.eval_images {
        0 => Vec::new(),
        _ => scene.eval_set.clone(),
    };
    obs.phase(
        "counting held-out renders (option x view)",
        (options.len() * images.len()) as u64,
    );
    let mut render = Vec::new();
    for (k, o) in options.iter().enumerate() {
        grids.select(&mut avatar, o);
        let mut stats = PassStats::default();
        for (i, &n) in images.iter().enumerate() {
            obs.progress((k * images.len() + i) as u64, &o.name);
            stats.add(&render_counts(&avatar, &scene.held, n, &o.pass(), req)?);
        }
        render.push(share(&o.name, &stats, &cfg));
    }
    obs.phase_end();

    let run = RunConfig::from_preset(req.preset);
    let batch_rays = run.train.rays_per_step;
    let mut source = DatasetSource::new(
        scene.train.clone(),
        batch_rays,
        run.train.images_per_step,
        run.train.perturb_bg,
        run.train.seed,
        &req.device,
    )?;
    let batches: Vec<_> = (0..req.batches)
        .map(|_| source.next_batch())
        .collect::<std::result::Result<_, _>>()?;
    obs.phase(
        "counting training batches (option x batch)",
        (options.len() * batches.len()) as u64,
    );
    let mut training_batches = Vec::new();
    if !batches.is_empty() {
        for (k, o) in options.iter().enumerate() {
            grids.select(&mut avatar, o);
            let mut stats = PassStats::default();
            for (i, b) in batches.iter().enumerate() {
                obs.progress((k * batches.len() + i) as u64, &o.name);
                crate::interrupt::check()?;
                let out = avatar.forward(&b.rays, &b.poses, &mut Mode::Infer, &o.pass(), None)?;
                stats.add(&out.stats);
            }
            training_batches.push(share(&o.name, &stats, &cfg));
        }
    }
    obs.phase_end();
    Ok(SharesReport {
        preset: req.preset.name().to_string(),
        model,
        train_steps: steps,
        train_rays_per_step: steps.map(|_| {
            req.train_rays
                .unwrap_or(RunConfig::from_preset(req.preset).train.rays_per_step)
        }),
        threshold: req.threshold,
        grid,
        grid_occupied_fraction: occupied,
        coarse_samples_per_ray: cfg.n_samples,
        fine_samples_per_ray: cfg.n_importance,
        render_images: images,
        render,
        batch_rays,
        batches: req.batches,
        training_batches,
    })
}

fn share(name: &str, s: &PassStats, cfg: &crate::Config) -> PassShare {
    let per_ray = (cfg.n_samples + cfg.n_importance) as u64;
    let rays = s.samples / per_ray.max(1);
    PassShare {
        option: name.to_string(),
        rays,
        coarse_samples: rays * cfg.n_samples as u64,
        coarse_evaluated: s.coarse_evaluated,
        fine_samples: rays * cfg.n_importance as u64,
        fine_evaluated: s.fine_evaluated,
        skipped_empty: s.skipped_empty,
    }
}

/// What the render of held-out image `n` (its pose and camera, the dataset's resolution)
/// evaluated under `pass`.
fn render_counts(
    avatar: &Avatar,
    held: &Dataset,
    n: usize,
    pass: &PassOptions,
    req: &SharesRequest,
) -> Result<PassStats> {
    let (poses, kp3d) = dataset_pose(held, held.pose_row(n)?, &req.device)?;
    let cam = held.image_camera(n)?;
    let opts = ImageOptions {
        chunk: 4096,
        head: held.head()?,
        device: req.device.clone(),
        pass: pass.clone(),
    };
    Ok(avatar.render_image(&poses, &kp3d, &cam, None, &opts)?.stats)
}

/// `req.model`, or the preset trained in-process for `req.train_steps` steps (saved as
/// `shares-model.safetensors` so that a later run can pass it as `--model`).
fn shares_model(
    req: &SharesRequest,
    scene: &Scene,
    obs: &mut dyn BenchObserver,
) -> Result<(Avatar, String, Option<u64>)> {
    if let Some(p) = &req.model {
        let a = Avatar::load(p, &req.device).map_err(|source| BenchError::Load {
            path: p.clone(),
            source: Box::new(source),
        })?;
        return Ok((a.with_numerics(req.numerics), p.display().to_string(), None));
    }
    let mut run = RunConfig::from_preset(req.preset);
    run.numerics = req.numerics;
    if let Some(r) = req.train_rays {
        run.train.rays_per_step = r;
        run.train
            .validate()
            .map_err(|e| BenchError::Setting(format!("--shares-train-rays {r}: {e}")))?;
    }
    obs.phase("training the counted model (steps)", req.train_steps);
    let mut trainer = Trainer::new(run, scene.train.clone(), &req.device)?;
    for k in 0..req.train_steps {
        crate::interrupt::check()?;
        trainer.step()?;
        obs.progress(k + 1, "");
    }
    obs.phase_end();
    let path = req.out.join("shares-model.safetensors");
    trainer.avatar().save(&path)?;
    let avatar = Avatar::load(&path, &req.device).map_err(|source| BenchError::Load {
        path: path.clone(),
        source: Box::new(source),
    })?;
    Ok((
        avatar.with_numerics(req.numerics),
        format!(
            "{} ({} trained in-process for {} steps)",
            path.display(),
            req.preset.name(),
            req.train_steps
        ),
        Some(req.train_steps),
    ))
}
