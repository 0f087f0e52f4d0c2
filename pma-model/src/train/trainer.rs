//! One training iteration of the reference (`Trainer.train_batch`; see `docs/reference.md`,
//! "Training schedule and Adam"):
//! forward, loss, backward, global-norm clip, Adam, then the learning rates for the next step.
//!
//! [`Optimization`] is the model-agnostic half (clip, skip, Adam, schedule, counters);
//! [`Trainer`] adds the avatar, a [`BatchSource`] (the pma-data ray sampler in real runs) and
//! the density-noise generator.
//!
//! Nothing is read back to the host inside a step: the loss, the gradient norm, the skip
//! decision (a non-finite loss or norm) and the clip factor stay on the device, the update is
//! masked there, and the numbers of the steps since the last read-back reach the host together
//! in one copy ([`Trainer::read_back`], every [`TrainConfig::read_every`] steps). Skipped
//! steps are counted, and a streak of them stops the run, when their numbers arrive.
//!
//! Everything random in training comes from seeded ChaCha generators whose positions are
//! saved in the train state, and candle's CPU kernels are deterministic, so a run resumed
//! from a checkpoint continues bit for bit like one that never stopped.

use std::path::Path;
use std::sync::Arc;

use candle_core::{DType, Device, Tensor, Var};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::adam::Adam;
use super::batch::{BatchSource, TrainBatch};
use super::source::DatasetSource;
use super::state::{Progress, RngState, TrainState};
use super::TrainError;
use crate::network::config::Config;
use crate::network::occupancy::OccupancyGrid;
use crate::render::avatar::{Avatar, GridObservation, Mode, PassOptions, PassStats, Rays};
use crate::render::occupancy::{CellChoice, RefreshOptions};
use crate::render::options::GridFeed;
use crate::render::raycast::CoarseSamples;
use crate::train::presets::{RunConfig, TrainConfig};
use pma_data::dataset::Dataset;
use pma_data::metrics::psnr_from_mse;

pub use crate::network::run_dir::{MODEL_FILE, STATE_FILE};

/// Loss terms of one step (the paper's loss, [`crate::train::loss`]), as plain numbers for logging.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LossParts {
    /// Weighted sum that was differentiated.
    pub total: f64,
    /// Mean |fine − target| over rays and channels.
    pub fine: f64,
    /// Mean |coarse − target|.
    pub coarse: f64,
    /// Σ_j s_x s_y s_z (unweighted).
    pub scale: f64,
    /// PSNR of the fine render against the target (−10 log10 MSE).
    pub psnr: f64,
}

/// Why a step was not applied.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SkipReason {
    NonFiniteLoss,
    NonFiniteGradNorm,
}

impl std::fmt::Display for SkipReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            SkipReason::NonFiniteLoss => "non-finite loss",
            SkipReason::NonFiniteGradNorm => "non-finite gradient norm",
        })
    }
}

/// What one iteration did (known on the host once its numbers are read back).
#[derive(Debug, Clone, PartialEq)]
pub struct StepStats {
    /// The iteration (1-based, = completed iterations after it).
    pub iter: u64,
    pub loss: LossParts,
    /// Global gradient norm before clipping (NaN when the loss was already non-finite).
    pub grad_norm: f64,
    /// Factor the gradients were scaled by (1 = not clipped).
    pub clip_coef: f64,
    /// Rates used by this step, per group (reference order: freq, other).
    pub lrs: Vec<f64>,
    /// `Some` when the update was not applied; the weights and optimizer are unchanged.
    pub skipped: Option<SkipReason>,
}

/// The loss terms of a step on the device, f64 scalars: the differentiated total, the L1
/// terms, the box-volume term and the mean squared error of the fine render.
#[derive(Debug, Clone)]
pub struct StepLoss {
    pub total: Tensor,
    pub fine: Tensor,
    pub coarse: Tensor,
    pub scale: Tensor,
    pub mse: Tensor,
}

impl StepLoss {
    /// Zeros on `device`, to add chunks to.
    fn zeros(device: &Device) -> candle_core::Result<Self> {
        let z = Tensor::zeros((), DType::F64, device)?;
        Ok(Self {
            total: z.clone(),
            fine: z.clone(),
            coarse: z.clone(),
            scale: z.clone(),
            mse: z,
        })
    }

    /// The five numbers as one [5] f64 tensor.
    fn stacked(&self) -> candle_core::Result<Tensor> {
        Tensor::stack(
            &[
                &self.total,
                &self.fine,
                &self.coarse,
                &self.scale,
                &self.mse,
            ],
            0,
        )
    }
}

/// A step whose numbers are still on the device: [total, fine, coarse, scale, mse, norm].
struct Pending {
    iter: u64,
    lrs: Vec<f64>,
    numbers: Tensor,
}

/// Clip, skip, Adam and schedule: everything of a step after the gradients exist.
pub struct Optimization {
    pub adam: Adam,
    pub cfg: TrainConfig,
    /// Completed iterations.
    pub iter: u64,
    /// Skip counters as of the last read-back.
    pub progress: Progress,
    pending: Vec<Pending>,
}

/// 1 (u8) where `x` is finite: `0·x` is 0 for finite values, NaN for ±inf and NaN.
fn finite(x: &Tensor) -> candle_core::Result<Tensor> {
    x.affine(0.0, 0.0)?.eq(&x.zeros_like()?)
}

impl Optimization {
    pub fn new(adam: Adam, cfg: TrainConfig) -> Self {
        Self {
            adam,
            cfg,
            iter: 0,
            progress: Progress::default(),
            pending: Vec::new(),
        }
    }

    /// Rates of the next step, per group.
    pub fn lrs(&self) -> Vec<f64> {
        self.adam.groups().iter().map(|g| g.lr).collect()
    }

    /// Steps whose numbers have not been read back yet.
    pub fn pending(&self) -> usize {
        self.pending.len()
    }

    /// Finish iteration `iter + 1` on the device. `grads` is aligned with
    /// `adam.param_names()` (`None` = no gradient). A non-finite loss or gradient norm skips
    /// the update: the update is masked, so nothing reaches the weights or the moments.
    /// Nothing is read back; the step's numbers wait for [`Self::read_back`].
    pub fn apply(&mut self, loss: &StepLoss, grads: Vec<Option<Tensor>>) -> Result<(), TrainError> {
        let lrs = self.lrs();
        let iter = self.iter + 1;
        let (g, has) = self.adam.flatten(&grads)?;
        let norm = g.to_dtype(DType::F64)?.sqr()?.sum_all()?.sqrt()?;
        let ok = (finite(&loss.total)? * finite(&norm)?)?;
        let coef = if self.cfg.grad_clip > 0.0 {
            // torch's clip_grad_norm_: max_norm / (norm + 1e-6), applied below 1.
            let max = Tensor::full(self.cfg.grad_clip, (), norm.device())?;
            let coef = max.div(&norm.affine(1.0, 1e-6)?)?;
            let one = coef.ones_like()?;
            Some(
                coef.lt(&one)?
                    .where_cond(&coef, &one)?
                    .to_dtype(DType::F32)?,
            )
        } else {
            None
        };
        self.adam.step_clipped(&g, &has, Some(&ok), coef.as_ref())?;
        let numbers = Tensor::cat(&[&loss.stacked()?, &norm.unsqueeze(0)?], 0)?;
        self.pending.push(Pending { iter, lrs, numbers });
        self.iter = iter;
        // The schedule follows the iteration count, skipped or not (the reference sets the
        // rates from global_iter after every step).
        let c = &self.cfg;
        self.adam
            .apply_schedule(iter, c.lr_decay, c.lr_decay_steps, c.lr_floor);
        Ok(())
    }

    /// The numbers of every step since the last read-back (one device-to-host copy), in
    /// iteration order. Skipped steps are counted here; after `max_consecutive_skips` in a
    /// row the run stops with [`TrainError::Diverged`].
    pub fn read_back(&mut self) -> Result<Vec<StepStats>, TrainError> {
        if self.pending.is_empty() {
            return Ok(Vec::new());
        }
        let numbers: Vec<&Tensor> = self.pending.iter().map(|p| &p.numbers).collect();
        let host = Tensor::stack(&numbers, 0)?
            .to_device(&Device::Cpu)?
            .to_vec2::<f64>()?;
        let mut out = Vec::with_capacity(host.len());
        for (p, v) in std::mem::take(&mut self.pending).into_iter().zip(host) {
            let [total, fine, coarse, scale, mse, norm] = v[..] else {
                unreachable!("six numbers per step")
            };
            let skipped = if !total.is_finite() {
                Some(SkipReason::NonFiniteLoss)
            } else if !norm.is_finite() {
                Some(SkipReason::NonFiniteGradNorm)
            } else {
                None
            };
            let coef = self.cfg.grad_clip / (norm + 1e-6);
            let clip_coef = match skipped {
                None if self.cfg.grad_clip > 0.0 && coef < 1.0 => coef,
                _ => 1.0,
            };
            if skipped.is_some() {
                self.progress.skipped += 1;
                self.progress.consecutive_skipped += 1;
            } else {
                self.progress.consecutive_skipped = 0;
            }
            out.push(StepStats {
                iter: p.iter,
                loss: LossParts {
                    total,
                    fine,
                    coarse,
                    scale,
                    psnr: psnr_from_mse(mse),
                },
                grad_norm: if total.is_finite() { norm } else { f64::NAN },
                clip_coef,
                lrs: p.lrs,
                skipped,
            });
            if self.progress.consecutive_skipped >= self.cfg.max_consecutive_skips {
                return Err(TrainError::Diverged {
                    count: self.progress.consecutive_skipped,
                    iter: p.iter,
                });
            }
        }
        Ok(out)
    }
}

/// Automatic chunking of a training step (`chunk_rays = 0`) on the CPU: at most this many
/// point × joint × feature elements per chunk (samples per ray × joints × the widest per-joint
/// feature). Forward and backward keep some 50 tensors of that size alive: a 512-ray chunk
/// of the paper config peaked near 8 GiB, so the budget is 128 rays of it (about 2 GiB).
pub const AUTO_CHUNK_POINT_JOINTS: usize = 128 * 72 * 24 * 128;

/// The loss, the gradients (in parameter order), what the passes did, and what their
/// evaluated samples saw of the occupancy grid, of a step or one of its chunks.
type Gradients = (
    StepLoss,
    Vec<Option<Tensor>>,
    PassStats,
    Vec<GridObservation>,
);

/// Rays per chunk of a training step (see [`TrainConfig::chunk_rays`]). Automatic chunks are
/// sized from the device ([`crate::compute::device::element_budget`]: a share of its free
/// memory) on a GPU, [`AUTO_CHUNK_POINT_JOINTS`] on the CPU.
pub fn chunk_rays(train: &TrainConfig, model: &Config, device: &Device) -> usize {
    if train.chunk_rays > 0 {
        return train.chunk_rays;
    }
    let width = model.win_hidden.max(model.point_enc_dim).max(1);
    let per_ray = (model.n_samples + model.n_importance) * model.n_joints * width;
    let budget = crate::compute::device::element_budget(device).unwrap_or(AUTO_CHUNK_POINT_JOINTS);
    (budget / per_ray.max(1)).max(1)
}

/// The density noise of one step: a standard normal for every coarse and every fine sample
/// of the batch, [R,Sc] and [R,Sf], drawn in the order a forward pass over the whole batch
/// asks for them (coarse, then fine). A chunk takes its rays' rows, so chunking never
/// changes the noise a sample gets.
struct StepNoise {
    coarse: Tensor,
    fine: Tensor,
}

impl StepNoise {
    fn draw(
        rng: &mut ChaCha8Rng,
        rays: usize,
        (sc, sf): (usize, usize),
        device: &Device,
    ) -> Result<Self, TrainError> {
        use rand_distr::Distribution;
        let mut block = |s: usize| -> candle_core::Result<Tensor> {
            let v: Vec<f32> = (0..rays * s)
                .map(|_| rand_distr::StandardNormal.sample(&mut *rng))
                .collect();
            Tensor::from_vec(v, (rays, s), device)
        };
        let coarse = block(sc)?;
        Ok(Self {
            coarse,
            fine: block(sf)?,
        })
    }
}

/// The rays `rows` of a batch: their rows of every per-ray tensor (`None` = all rays).
struct Rows<'a> {
    ids: Option<(Vec<usize>, Tensor)>,
    batch: &'a TrainBatch,
}

impl Rows<'_> {
    fn take(&self, t: &Tensor) -> candle_core::Result<Tensor> {
        match &self.ids {
            None => Ok(t.clone()),
            Some((_, idx)) => t.index_select(idx, 0),
        }
    }

    fn rays(&self) -> candle_core::Result<Rays> {
        let r = &self.batch.rays;
        Ok(Rays {
            origins: self.take(&r.origins)?,
            dirs: self.take(&r.dirs)?,
            bgs: r.bgs.as_ref().map(|b| self.take(b)).transpose()?,
            framecodes: match &self.ids {
                None => r.framecodes.clone(),
                Some((rows, _)) => rows.iter().map(|&i| r.framecodes[i]).collect(),
            },
        })
    }

    fn samples(&self, c: &CoarseSamples) -> candle_core::Result<CoarseSamples> {
        Ok(CoarseSamples {
            bounds: match (&c.bounds, &self.ids) {
                (Some(b), Some((rows, _))) => Some(b.select(rows)),
                (b, _) => b.clone(),
            },
            z: self.take(&c.z)?,
            pts: self.take(&c.pts)?,
        })
    }
}

/// Gradient hook: sees (and may change) the gradients of a step before clipping, aligned
/// with [`Trainer::param_names`].
pub type GradHook<'a> = &'a mut dyn FnMut(&mut [Option<Tensor>]);

/// The training loop's state: avatar, optimizer, batch source, noise generator.
pub struct Trainer {
    run: RunConfig,
    avatar: Avatar,
    /// Parameters aligned with `opt.adam.param_names()`.
    params: Vec<Var>,
    names: Vec<String>,
    opt: Optimization,
    source: Box<dyn BatchSource>,
    noise_rng: ChaCha8Rng,
    /// Rays per chunk, fixed at the first step (free device memory changes once the
    /// allocator holds a step's tensors, and the chunking sets the summation order).
    chunk: Option<usize>,
    /// What the passes of the steps so far evaluated and left out (host counts).
    pass_totals: PassStats,
    /// Network points spent refreshing the occupancy grid so far.
    refresh_points: u64,
}

/// The density-noise stream is seeded from the run seed on its own ChaCha stream, so it
/// never overlaps the sampler's or the initialisation's draws.
const NOISE_STREAM: u64 = 0x6e_6f69_7365;

/// The occupancy refreshes draw their cells and points from the run seed on this stream,
/// re-seeded from the iteration, so a resumed run refreshes exactly like an uninterrupted
/// one without saving a generator.
const OCCUPANCY_STREAM: u64 = 0x6f_6363_7570;

/// Read-back interval of `read_every = 0` on devices other than the CPU (an estimate: a
/// read-back drains the device's queue once, tens of microseconds, against steps of tens of
/// milliseconds or more; on the CPU nothing is queued and every step is read).
pub const AUTO_READ_EVERY_DEVICE: u64 = 10;

impl Trainer {
    /// Train `avatar` on batches from `source`. `run.model` must be the avatar's config.
    pub fn with_source(
        run: RunConfig,
        avatar: Avatar,
        source: Box<dyn BatchSource>,
    ) -> Result<Self, TrainError> {
        run.train.validate()?;
        if avatar.config() != &run.model {
            return Err(TrainError::Config(
                "the avatar's config differs from the run's model config".to_string(),
            ));
        }
        // A run with the grid starts one (or continues the one saved with its model).
        let avatar = match (&run.train.occupancy, avatar.occupancy()) {
            (Some(cfg), None) => {
                let cfg = cfg
                    .clone()
                    .covering(run.train.culling.sample_threshold, &run.model);
                avatar.with_occupancy(Some(OccupancyGrid::new(cfg)?))
            }
            _ => avatar,
        };
        let vars = avatar.trainable();
        let t = &run.train;
        let adam = Adam::reference(&vars, t.lr_freq, t.lr, t.betas, t.eps)?;
        let names: Vec<String> = adam.param_names().map(str::to_string).collect();
        let by_name: std::collections::HashMap<&str, &Var> =
            vars.iter().map(|(n, v)| (n.as_str(), v)).collect();
        let params = names.iter().map(|n| by_name[n.as_str()].clone()).collect();
        let mut noise_rng = ChaCha8Rng::seed_from_u64(t.seed);
        noise_rng.set_stream(NOISE_STREAM);
        let opt = Optimization::new(adam, run.train.clone());
        Ok(Self {
            run,
            avatar,
            params,
            names,
            opt,
            source,
            noise_rng,
            chunk: None,
            pass_totals: PassStats::default(),
            refresh_points: 0,
        })
    }

    /// A fresh run on `data` (train profile): the avatar is initialised from the dataset's
    /// rest pose with one frame code per training image, and batches come from
    /// [`DatasetSource`]. `run.model.n_framecodes` is set to the number of images.
    pub fn new(
        mut run: RunConfig,
        data: Arc<Dataset>,
        device: &Device,
    ) -> Result<Self, TrainError> {
        run.model.n_framecodes = data.n_images();
        run.validate()?;
        let rest = data.rest_pose.ok_or_else(|| {
            TrainError::Config(format!(
                "{}: no rest_pose (required for training)",
                data.source
            ))
        })?;
        let source = Self::dataset_source(&run, data, device)?;
        let avatar = Avatar::new(run.model.clone(), &rest, run.train.seed, device)?
            .with_numerics(run.numerics);
        Self::with_source(run, avatar, source)
    }

    /// Continue the run in `dir` on the same `data` (see [`Self::resume_with_source`]).
    pub fn resume(
        dir: &Path,
        mut run: RunConfig,
        data: Arc<Dataset>,
        device: &Device,
    ) -> Result<Self, TrainError> {
        run.model.n_framecodes = data.n_images();
        let source = Self::dataset_source(&run, data, device)?;
        Self::resume_with_source(dir, run, source, device)
    }

    pub(super) fn dataset_source(
        run: &RunConfig,
        data: Arc<Dataset>,
        device: &Device,
    ) -> Result<Box<dyn BatchSource>, TrainError> {
        let t = &run.train;
        Ok(Box::new(DatasetSource::new(
            data,
            t.rays_per_step,
            t.images_per_step,
            t.perturb_bg,
            t.seed,
            device,
        )?))
    }

    pub fn run_config(&self) -> &RunConfig {
        &self.run
    }

    pub fn avatar(&self) -> &Avatar {
        &self.avatar
    }

    /// Completed iterations.
    pub fn iteration(&self) -> u64 {
        self.opt.iter
    }

    /// Skip counters as of the last read-back.
    pub fn progress(&self) -> &Progress {
        &self.opt.progress
    }

    /// Record the run's wall-clock time (saved with the next checkpoint).
    pub fn set_wall_s(&mut self, wall_s: f64) {
        self.opt.progress.wall_s = wall_s;
    }

    /// Rates of the next step per group (freq, other).
    pub fn lrs(&self) -> Vec<f64> {
        self.opt.lrs()
    }

    pub fn optimizer(&self) -> &Adam {
        &self.opt.adam
    }

    /// Trainable parameter names in optimizer order (the order of gradients in a [`GradHook`]).
    pub fn param_names(&self) -> &[String] {
        &self.names
    }

    /// Steps between read-backs ([`TrainConfig::read_every`], `0` resolved for the device).
    pub fn read_every(&self) -> u64 {
        match self.run.train.read_every {
            0 if crate::compute::account::cpu_route(self.avatar.device()) => 1,
            0 => AUTO_READ_EVERY_DEVICE,
            k => k,
        }
    }

    /// Steps done whose numbers have not been read back.
    pub fn pending(&self) -> usize {
        self.opt.pending()
    }

    /// What the passes of this trainer's steps evaluated and left out, summed (host counts,
    /// known at once).
    pub fn pass_totals(&self) -> PassStats {
        self.pass_totals
    }

    /// Network points this trainer spent refreshing its occupancy grid.
    pub fn refresh_points(&self) -> u64 {
        self.refresh_points
    }

    /// One iteration on the next batch of the source. Every [`Self::read_every`] iterations
    /// the numbers of the steps since the last read-back come back (oldest first); otherwise
    /// the result is empty. Errors of those steps (a streak of skipped steps:
    /// [`TrainError::Diverged`]) surface here too.
    ///
    /// A step cut short by an interruption (see [`crate::interrupt`]) is undone: it stops
    /// before the optimizer, so only the batch source and the noise generator have moved, and
    /// both are put back. The trainer is then exactly as after the last complete step, and a
    /// checkpoint of it resumes bit for bit.
    pub fn step(&mut self) -> Result<Vec<StepStats>, TrainError> {
        self.step_undoable(None)?;
        if self.opt.iter % self.read_every() == 0 {
            self.read_back()
        } else {
            Ok(Vec::new())
        }
    }

    /// One iteration, then a read-back: this step's numbers (tests, tools that inspect every
    /// step; on a GPU each call waits for the device).
    pub fn step_read(&mut self) -> Result<StepStats, TrainError> {
        self.step_undoable(None)?;
        self.last_read()
    }

    /// [`Self::step_read`] with a gradient hook (e.g. to inject a fault in tests).
    pub fn step_hooked(&mut self, hook: GradHook) -> Result<StepStats, TrainError> {
        self.step_undoable(Some(hook))?;
        self.last_read()
    }

    /// The numbers of every step done since the last read-back, oldest first (one copy).
    pub fn read_back(&mut self) -> Result<Vec<StepStats>, TrainError> {
        self.opt.read_back()
    }

    /// Read back and return the last step's numbers.
    fn last_read(&mut self) -> Result<StepStats, TrainError> {
        self.read_back()?
            .pop()
            .ok_or_else(|| TrainError::Config("no step to read back".into()))
    }

    fn step_undoable(&mut self, hook: Option<GradHook>) -> Result<(), TrainError> {
        let noise = self.noise_rng.clone();
        let source = self.source.state();
        let result = self
            .source
            .next_batch()
            .and_then(|batch| self.advance_hooked(&batch, hook));
        match result {
            Err(e) if e.is_interrupted() => {
                self.noise_rng = noise;
                self.source.restore(&source)?;
                Err(e)
            }
            r => r,
        }
    }

    /// One iteration on `batch`, then a read-back: this step's numbers.
    pub fn step_on(
        &mut self,
        batch: &TrainBatch,
        hook: Option<GradHook>,
    ) -> Result<StepStats, TrainError> {
        self.advance_hooked(batch, hook)?;
        self.last_read()
    }

    /// One iteration on `batch` without a read-back (its numbers wait for
    /// [`Self::read_back`]).
    pub fn advance(&mut self, batch: &TrainBatch) -> Result<(), TrainError> {
        self.advance_hooked(batch, None)
    }

    /// One iteration on `batch`: forward (training mode, density noise), loss, backward,
    /// `hook`, clip, Adam, schedule, without reading anything back.
    fn advance_hooked(
        &mut self,
        batch: &TrainBatch,
        hook: Option<GradHook>,
    ) -> Result<(), TrainError> {
        let device = self.avatar.device().clone();
        crate::compute::profile::start(&device);
        let chunk = self.chunk_size(batch.rays.origins.dim(0)?);
        let opts = self.run.train.pass_options(self.opt.iter);
        let (loss, mut grads, stats, seen) = self.gradients(batch, chunk, &opts)?;
        if let Some(h) = hook {
            h(&mut grads);
        }
        self.opt.apply(&loss, grads)?;
        crate::compute::profile::mark("grad norm + Adam", &device);
        self.pass_totals.add(&stats);
        // The densities the step saw are the model's before this update: recent enough for a
        // grid that decays what no sample finds again.
        self.avatar.observe_occupancy(&seen)?;
        self.refresh_occupancy(batch)?;
        Ok(())
    }

    /// After step `iter` (completed iterations): refresh the occupancy grid on the batch's
    /// poses with the updated weights when it is due. The refresh that ends the warm-up (and
    /// any before the grid's first) evaluates every cell; later ones every `refresh_every`
    /// steps a share of them. It makes no interruption check: the step is already applied.
    fn refresh_occupancy(&mut self, batch: &TrainBatch) -> Result<(), TrainError> {
        let Some(cfg) = self.run.train.occupancy.clone() else {
            return Ok(());
        };
        let iter = self.opt.iter;
        let built = self.avatar.occupancy().is_some_and(|g| g.is_built());
        let cells = match (iter >= cfg.warmup_steps, built) {
            (false, _) => return Ok(()),
            (true, false) => CellChoice::All,
            (true, true) if (iter - cfg.warmup_steps) % cfg.refresh_every == 0 => {
                CellChoice::Share(cfg.refresh_share)
            }
            (true, true) => return Ok(()),
        };
        let mut rng = ChaCha8Rng::seed_from_u64(
            self.run.train.seed ^ iter.wrapping_mul(0x9e37_79b9_7f4a_7c15),
        );
        rng.set_stream(OCCUPANCY_STREAM);
        let pose = self.avatar.pose_features(&batch.poses, None)?;
        let opts = RefreshOptions { cells, decay: true };
        let stats = self
            .avatar
            .refresh_occupancy(&batch.poses, &pose, opts, &mut rng)?;
        self.refresh_points += stats.cells as u64;
        crate::compute::profile::mark("occupancy refresh", self.avatar.device());
        Ok(())
    }

    /// Rays per chunk for a batch of `rays`: [`chunk_rays`], fixed at the first step, and on
    /// the CPU at most a worker's share, so every worker has a chunk.
    fn chunk_size(&mut self, rays: usize) -> usize {
        let device = self.avatar.device().clone();
        let chunk = *self
            .chunk
            .get_or_insert_with(|| chunk_rays(&self.run.train, self.avatar.config(), &device));
        let workers = crate::compute::parallel::workers_on(&device);
        if workers > 1 {
            chunk.min(rays.div_ceil(workers))
        } else {
            chunk
        }
    }

    /// The loss and the gradients of one step on `batch`, computed `chunk` rays at a time
    /// (at least one ray per pose); one chunk is the whole batch in one pass.
    ///
    /// The per-pose work (GNN, `layer_pose`, box scales), the ray casting and the density
    /// noise are done once for the batch. Every chunk takes the same slice of each pose's
    /// block of rays, so it is itself a batch of all P poses: it takes its rows of the
    /// samples and the noise, renders, and differentiates its share of the loss (the L1 terms
    /// are sums scaled by `1/(3R)` of the whole batch, the same two multiplications as the
    /// mean; the box-volume term goes with the first chunk). Shares and gradients are summed
    /// in chunk order on the device. What chunking changes is only the order of float
    /// summation.
    fn gradients(
        &mut self,
        batch: &TrainBatch,
        chunk: usize,
        opts: &PassOptions,
    ) -> Result<Gradients, TrainError> {
        let r = batch.rays.origins.dim(0)?;
        let n_poses = batch.poses.bones.len();
        if n_poses == 0 || r % n_poses != 0 {
            return Err(TrainError::Config(format!(
                "{r} rays cannot be split into {n_poses} equal per-pose blocks"
            )));
        }
        let k = r / n_poses;
        let per_pose = (chunk / n_poses).clamp(1, k);
        let device = self.avatar.device().clone();
        let avatar = &self.avatar;
        let pose = avatar.pose_features(&batch.poses, None)?;
        crate::compute::profile::mark("pose features", &device);
        let coarse = avatar.cast(&batch.rays, &batch.poses, &pose, opts)?;
        crate::compute::profile::mark("cast", &device);
        let cfg = avatar.config();
        let noise = match cfg.density_noise_std > 0.0 {
            true => Some(StepNoise::draw(
                &mut self.noise_rng,
                r,
                (cfg.n_samples, cfg.n_importance),
                &device,
            )?),
            false => None,
        };
        let weights = self.run.train.loss_weights();
        let params = &self.params;
        let feed = self.run.train.occupancy.as_ref().filter(|_| opts.occupancy);
        let feed_seed = self.run.train.seed ^ self.opt.iter.wrapping_mul(0x9e37_79b9_7f4a_7c15);
        let run_chunk = |start: usize| -> Result<Gradients, TrainError> {
            // Each chunk feeds the grid with probes of its own.
            let opts = &PassOptions {
                grid_feed: feed.map(|o| GridFeed {
                    probe_share: o.probe_share,
                    seed: feed_seed ^ (start as u64).wrapping_mul(0xd6e8_feb8_6659_fd93),
                }),
                ..opts.clone()
            };
            let len = per_pose.min(k - start);
            let ids = (len < k)
                .then(|| -> candle_core::Result<_> {
                    let rows: Vec<usize> = (0..n_poses)
                        .flat_map(|p| p * k + start..p * k + start + len)
                        .collect();
                    let idx: Vec<u32> = rows.iter().map(|&i| i as u32).collect();
                    let n = idx.len();
                    Ok((rows, Tensor::from_vec(idx, n, &device)?))
                })
                .transpose()?;
            let rows = Rows { ids, batch };
            let rays = rows.rays()?;
            let target = rows.take(&batch.target)?;
            let samples = rows.samples(&coarse)?;
            crate::compute::profile::mark("chunk rows", &device);
            let mut blocks = match &noise {
                Some(n) => vec![rows.take(&n.coarse)?, rows.take(&n.fine)?],
                None => Vec::new(),
            }
            .into_iter();
            let mut noise_fn = |n: usize| -> crate::error::Result<Tensor> {
                let block = blocks.next().ok_or_else(|| {
                    crate::error::ModelError::Input("density noise: a third call in a pass".into())
                })?;
                if block.elem_count() != n {
                    return Err(crate::error::ModelError::Input(format!(
                        "density noise: {n} samples requested, the step drew {}",
                        block.elem_count()
                    )));
                }
                Ok(block.flatten_all()?)
            };
            let mut mode = match noise {
                Some(_) => Mode::Train(Some(&mut noise_fn)),
                None => Mode::Train(None),
            };
            let out = avatar.forward_cast(&rays, &batch.poses, &pose, samples, &mut mode, opts)?;
            let share = crate::train::loss::loss_share(&out, &target, &weights, r, start == 0)?;
            let f64_of = |t: &Tensor| t.detach().to_dtype(DType::F64);
            let mse = (&out.fine.rgb.detach() - &target)?.sqr()?.sum_all()?;
            let numbers = StepLoss {
                total: f64_of(&share.total)?,
                fine: f64_of(&share.fine)?,
                coarse: f64_of(&share.coarse)?,
                scale: f64_of(&share.scale)?,
                mse: (f64_of(&mse)? / (3 * r) as f64)?,
            };
            crate::compute::profile::mark("loss", &device);
            let store = share.total.backward()?;
            crate::compute::profile::mark("backward", &device);
            let grads = params
                .iter()
                .map(|v| store.get(v.as_tensor()).map(|d| d.detach()))
                .collect();
            Ok((numbers, grads, out.stats, out.observed))
        };
        let mut loss = StepLoss::zeros(&device)?;
        let mut grads: Vec<Option<Tensor>> = vec![None; params.len()];
        let mut stats = PassStats::default();
        let mut seen = Vec::new();
        let starts: Vec<usize> = (0..k).step_by(per_pose).collect();
        // One wave of chunks per round of workers; sums are taken in chunk order, so the
        // result is the sequential loop's, bit for bit, whatever the worker count.
        let workers = crate::compute::parallel::workers_on(&device);
        for wave in starts.chunks(workers) {
            crate::interrupt::check()?;
            let outs =
                crate::compute::parallel::map_ordered(workers, wave.len(), |i| run_chunk(wave[i]))?;
            for (part, chunk_grads, chunk_stats, chunk_seen) in outs {
                stats.add(&chunk_stats);
                seen.extend(chunk_seen);
                loss = StepLoss {
                    total: (loss.total + part.total)?,
                    fine: (loss.fine + part.fine)?,
                    coarse: (loss.coarse + part.coarse)?,
                    scale: (loss.scale + part.scale)?,
                    mse: (loss.mse + part.mse)?,
                };
                for (g, d) in grads.iter_mut().zip(chunk_grads) {
                    if let Some(d) = d {
                        *g = Some(match g.take() {
                            Some(sum) => (sum + d)?,
                            None => d,
                        });
                    }
                }
            }
        }
        // With several workers this thread waits here for the others' chunks: that wait and
        // the sums are this stage's, not the optimizer's.
        crate::compute::profile::mark("chunk sums", &device);
        Ok((loss, grads, stats, seen))
    }

    /// What a checkpoint holds besides the model (see [`super::checkpoint`], which writes
    /// and reads run directories): optimizer moments, iteration, random streams, sampler
    /// position, counters and the run configuration. `model_fingerprint` ties it to the
    /// model file written with it.
    pub(crate) fn train_state(&self, model_fingerprint: String) -> Result<TrainState, TrainError> {
        if self.opt.pending() > 0 {
            return Err(TrainError::Config(format!(
                "checkpoint: {} step(s) not read back yet (call read_back first)",
                self.opt.pending()
            )));
        }
        Ok(TrainState {
            global_iter: self.opt.iter,
            groups: self.opt.adam.groups().to_vec(),
            params: self
                .opt
                .adam
                .states()?
                .into_iter()
                .map(|(n, s)| (n.to_string(), s))
                .collect(),
            rng: Some(RngState::capture(&self.noise_rng)),
            sampler: Some(self.source.state()),
            progress: Some(self.opt.progress.clone()),
            run_config: Some(
                serde_json::to_value(&self.run)
                    .map_err(|e| TrainError::Config(format!("run config: {e}")))?,
            ),
            model_fingerprint: Some(model_fingerprint),
        })
    }

    /// Continue from `state` (read from the checkpoint whose model this trainer's avatar
    /// was loaded from): optimizer moments and steps, iteration, rates, counters, the noise
    /// generator and the batch source's position.
    pub(crate) fn restore(&mut self, state: TrainState) -> Result<(), TrainError> {
        let lrs: Vec<f64> = state.groups.iter().map(|g| g.lr).collect();
        let saved_names: Vec<&String> = state.groups.iter().flat_map(|g| &g.params).collect();
        if saved_names.len() != self.names.len()
            || saved_names.iter().zip(&self.names).any(|(a, b)| *a != b)
        {
            return Err(TrainError::State(vec![
                "the optimizer's parameter groups differ from the model's".into(),
            ]));
        }
        self.opt.adam.load_states(state.params, &lrs)?;
        self.opt.iter = state.global_iter;
        // Rates follow from the iteration; recomputing avoids trusting JSON float parsing.
        let c = &self.run.train;
        self.opt
            .adam
            .apply_schedule(state.global_iter, c.lr_decay, c.lr_decay_steps, c.lr_floor);
        self.opt.progress = state.progress.unwrap_or_default();
        if let Some(r) = &state.rng {
            self.noise_rng = r.restore()?;
        }
        self.source
            .restore(state.sampler.as_ref().unwrap_or(&serde_json::Value::Null))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};

    fn setup() -> (Var, Optimization) {
        let x = Var::from_tensor(&Tensor::new(&[1f32, -2.0], &Device::Cpu).unwrap()).unwrap();
        let adam = Adam::reference(
            &[("pts_linears.0.weight".into(), x.clone())],
            1e-4,
            5e-4,
            [0.9, 0.999],
            1e-8,
        )
        .unwrap();
        let cfg = TrainConfig {
            max_consecutive_skips: 3,
            ..TrainConfig::tiny()
        };
        (x, Optimization::new(adam, cfg))
    }

    fn loss(total: f64) -> StepLoss {
        let t = |v: f64| Tensor::new(v, &Device::Cpu).unwrap();
        StepLoss {
            total: t(total),
            fine: t(total),
            coarse: t(0.0),
            scale: t(0.0),
            mse: t(0.1),
        }
    }

    /// One step, read back at once.
    fn apply(
        opt: &mut Optimization,
        l: StepLoss,
        g: Vec<Option<Tensor>>,
    ) -> Result<StepStats, TrainError> {
        opt.apply(&l, g)?;
        Ok(opt.read_back()?.pop().unwrap())
    }

    #[test]
    fn non_finite_steps_are_skipped_counted_and_never_applied() {
        let (x, mut opt) = setup();
        let g = |v: [f32; 2]| vec![Some(Tensor::new(&v, &Device::Cpu).unwrap())];
        let step = |opt: &Optimization| {
            opt.adam
                .state("pts_linears.0.weight")
                .unwrap()
                .unwrap()
                .step
        };
        let s = apply(&mut opt, loss(0.5), g([1.0, 1.0])).unwrap();
        assert_eq!(s.skipped, None);
        let after_good = x.to_vec1::<f32>().unwrap();
        assert_ne!(after_good, vec![1.0, -2.0]);

        let s = apply(&mut opt, loss(0.5), g([f32::NAN, 1.0])).unwrap();
        assert_eq!(s.skipped, Some(SkipReason::NonFiniteGradNorm));
        let s = apply(&mut opt, loss(f64::INFINITY), g([1.0, 1.0])).unwrap();
        assert_eq!(s.skipped, Some(SkipReason::NonFiniteLoss));
        assert!(s.grad_norm.is_nan());
        assert_eq!(x.to_vec1::<f32>().unwrap(), after_good);
        assert_eq!(step(&opt), 1);
        assert_eq!(
            (
                opt.iter,
                opt.progress.skipped,
                opt.progress.consecutive_skipped
            ),
            (3, 2, 2)
        );

        // A good step resets the streak; three bad ones in a row stop the run.
        apply(&mut opt, loss(0.5), g([1.0, 1.0])).unwrap();
        assert_eq!(opt.progress.consecutive_skipped, 0);
        apply(&mut opt, loss(f64::NAN), g([1.0, 1.0])).unwrap();
        apply(&mut opt, loss(f64::NAN), g([1.0, 1.0])).unwrap();
        let err = apply(&mut opt, loss(f64::NAN), g([1.0, 1.0])).unwrap_err();
        assert!(
            matches!(err, TrainError::Diverged { count: 3, iter: 7 }),
            "{err}"
        );
        assert_eq!(step(&opt), 2);
    }

    /// Steps read back together count their skips and stop the run like steps read one
    /// by one; the weights do not depend on when the numbers are read.
    #[test]
    fn deferred_read_back_gives_the_same_steps_and_counts() {
        let g = |v: [f32; 2]| vec![Some(Tensor::new(&v, &Device::Cpu).unwrap())];
        let plan = [
            (0.5, [1.0, 1.0]),
            (0.5, [f32::INFINITY, 1.0]),
            (0.5, [0.5, -3.0]),
            (f64::NAN, [1.0, 1.0]),
            (0.5, [2.0, 1.0]),
        ];
        let (x1, mut one_by_one) = setup();
        let mut singles = Vec::new();
        for (l, v) in plan {
            singles.push(apply(&mut one_by_one, loss(l), g(v)).unwrap());
        }
        let (x2, mut deferred) = setup();
        for (l, v) in plan {
            deferred.apply(&loss(l), g(v)).unwrap();
        }
        assert_eq!(deferred.pending(), 5);
        assert_eq!(
            deferred.progress.skipped, 0,
            "nothing is known before the read-back"
        );
        let together = deferred.read_back().unwrap();
        assert_eq!(deferred.pending(), 0);
        assert_eq!(together.len(), singles.len());
        for (a, b) in together.iter().zip(&singles) {
            assert_eq!((a.iter, a.skipped), (b.iter, b.skipped));
            assert_eq!(a.grad_norm.to_bits(), b.grad_norm.to_bits());
        }
        assert_eq!(deferred.progress, one_by_one.progress);
        assert_eq!(deferred.progress.skipped, 2);
        assert_eq!(x1.to_vec1::<f32>().unwrap(), x2.to_vec1::<f32>().unwrap());

        // A streak that ends the run is reported when its numbers arrive.
        let (_x, mut opt) = setup();
        for _ in 0..4 {
            opt.apply(&loss(f64::NAN), g([1.0, 1.0])).unwrap();
        }
        let err = opt.read_back().unwrap_err();
        assert!(
            matches!(err, TrainError::Diverged { count: 3, iter: 3 }),
            "{err}"
        );
    }

    #[test]
    fn clipping_applies_above_the_threshold_and_schedule_advances() {
        let (x, mut opt) = setup();
        let g = vec![Some(Tensor::new(&[30f32, 40.0], &Device::Cpu).unwrap())];
        let s = apply(&mut opt, loss(1.0), g).unwrap();
        assert!((s.grad_norm - 50.0).abs() < 1e-9);
        assert!((s.clip_coef - 1.0 / (50.0 + 1e-6)).abs() < 1e-12);
        assert_eq!(s.lrs, vec![1e-4, 5e-4]);
        assert!((opt.lrs()[1] - 0.0004999976974202089).abs() < 1e-15);
        // The clipped gradient reached Adam: its first moment is 0.1 · g · coef.
        let st = opt.adam.state("pts_linears.0.weight").unwrap().unwrap();
        let m = st.exp_avg.to_vec1::<f32>().unwrap();
        let coef = 1.0 / (50.0 + 1e-6);
        assert!((m[0] as f64 - 0.1 * 30.0 * coef).abs() < 1e-6, "{m:?}");
        assert!((m[1] as f64 - 0.1 * 40.0 * coef).abs() < 1e-6, "{m:?}");
        assert_ne!(x.to_vec1::<f32>().unwrap(), vec![1.0, -2.0]);
        // Below the threshold nothing is scaled.
        let (_x, mut opt) = setup();
        let g = vec![Some(Tensor::new(&[0.3f32, 0.4], &Device::Cpu).unwrap())];
        let s = apply(&mut opt, loss(1.0), g).unwrap();
        assert_eq!(s.clip_coef, 1.0);
        let st = opt.adam.state("pts_linears.0.weight").unwrap().unwrap();
        let m = st.exp_avg.to_vec1::<f32>().unwrap();
        assert_eq!(m, vec![0.3f32 * 0.1, 0.4f32 * 0.1]);
    }
}
