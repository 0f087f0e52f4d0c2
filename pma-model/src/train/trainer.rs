//! One training iteration of the reference (`Trainer.train_batch`; see `docs/reference.md`,
//! "Training schedule and Adam"):
//! forward, loss, backward, global-norm clip, Adam, then the learning rates for the next step.
//!
//! [`Optimization`] is the model-agnostic half (clip, skip, Adam, schedule, counters);
//! [`Trainer`] adds the avatar, a [`BatchSource`] (the pma-data ray sampler in real runs) and
//! the density-noise generator.
//!
//! Everything random in training comes from seeded ChaCha generators whose positions are
//! saved in the train state, and candle's CPU kernels are deterministic, so a run resumed
//! from a checkpoint continues bit for bit like one that never stopped.

use std::path::Path;
use std::sync::Arc;

use candle_core::{Device, Tensor, Var};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::adam::{clip_grad_norm, global_norm, Adam};
use super::batch::{BatchSource, TrainBatch};
use super::source::DatasetSource;
use super::state::{Progress, RngState, TrainState};
use super::TrainError;
use crate::network::config::Config;
use crate::render::avatar::{Avatar, Mode, Outputs, PoseFeatures, Rays};
use crate::train::loss::LossWeights;
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

/// What one iteration did.
#[derive(Debug, Clone, PartialEq)]
pub struct StepStats {
    /// The iteration just completed (1-based, = completed iterations afterwards).
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

/// Clip, skip, Adam and schedule: everything of a step after the gradients exist.
pub struct Optimization {
    pub adam: Adam,
    pub cfg: TrainConfig,
    /// Completed iterations.
    pub iter: u64,
    pub progress: Progress,
}

impl Optimization {
    pub fn new(adam: Adam, cfg: TrainConfig) -> Self {
        Self {
            adam,
            cfg,
            iter: 0,
            progress: Progress::default(),
        }
    }

    /// Rates of the next step, per group.
    pub fn lrs(&self) -> Vec<f64> {
        self.adam.groups().iter().map(|g| g.lr).collect()
    }

    /// Finish iteration `iter + 1`. `grads` is aligned with `adam.param_names()` (`None` = no
    /// gradient). A non-finite loss or gradient norm skips the update: nothing reaches the
    /// weights or the moments, the skip is counted, and after `max_consecutive_skips` in a row
    /// the run stops with [`TrainError::Diverged`].
    pub fn apply(
        &mut self,
        loss: LossParts,
        mut grads: Vec<Option<Tensor>>,
    ) -> Result<StepStats, TrainError> {
        let lrs = self.lrs();
        let iter = self.iter + 1;
        let mut stats = StepStats {
            iter,
            loss,
            grad_norm: f64::NAN,
            clip_coef: 1.0,
            lrs,
            skipped: None,
        };
        if !loss.total.is_finite() {
            stats.skipped = Some(SkipReason::NonFiniteLoss);
        } else {
            stats.grad_norm = global_norm(&grads)?;
            if !stats.grad_norm.is_finite() {
                stats.skipped = Some(SkipReason::NonFiniteGradNorm);
            }
        }
        if stats.skipped.is_none() {
            if self.cfg.grad_clip > 0.0 {
                stats.clip_coef = clip_grad_norm(&mut grads, self.cfg.grad_clip, stats.grad_norm)?;
            }
            self.adam.step(&grads)?;
            self.progress.consecutive_skipped = 0;
        } else {
            self.progress.skipped += 1;
            self.progress.consecutive_skipped += 1;
        }
        self.iter = iter;
        // The schedule follows the iteration count, skipped or not (the reference sets the
        // rates from global_iter after every step).
        let c = &self.cfg;
        self.adam
            .apply_schedule(iter, c.lr_decay, c.lr_decay_steps, c.lr_floor);
        if self.progress.consecutive_skipped >= self.cfg.max_consecutive_skips {
            return Err(TrainError::Diverged {
                count: self.progress.consecutive_skipped,
                iter,
            });
        }
        Ok(stats)
    }
}

/// The differentiated loss ([`crate::train::loss`]) and its parts as numbers.
pub fn training_loss(
    out: &Outputs,
    target: &Tensor,
    cfg: &TrainConfig,
) -> Result<(Tensor, LossParts), TrainError> {
    let weights = LossWeights {
        fine: cfg.loss_fine,
        coarse: cfg.loss_coarse,
        scale: cfg.loss_scale,
    };
    let loss = crate::train::loss::training_loss(out, target, &weights)?;
    let mse = (&out.fine.rgb.detach() - target)?.sqr()?.mean_all()?;
    // One read-back for the five numbers (one device sync on a GPU).
    let parts = [&loss.total, &loss.fine, &loss.coarse, &loss.scale, &mse]
        .map(|t| t.to_dtype(candle_core::DType::F32));
    let v = Tensor::stack(
        &parts.into_iter().collect::<candle_core::Result<Vec<_>>>()?,
        0,
    )?
    .to_device(&Device::Cpu)?
    .to_vec1::<f32>()?;
    let parts = LossParts {
        total: v[0] as f64,
        fine: v[1] as f64,
        coarse: v[2] as f64,
        scale: v[3] as f64,
        psnr: psnr_from_mse(v[4] as f64),
    };
    Ok((loss.total, parts))
}

/// Automatic chunking of a training step (`chunk_rays = 0`): at most this many
/// point × joint × feature elements per chunk (samples per ray × joints × the widest per-joint
/// feature). Forward and backward keep some 50 tensors of that size alive: a 512-ray chunk
/// of the paper config peaked near 8 GiB, so the budget is 128 rays of it (about 2 GiB).
pub const AUTO_CHUNK_POINT_JOINTS: usize = 128 * 72 * 24 * 128;

/// Rays per chunk of a training step (see [`TrainConfig::chunk_rays`]).
pub fn chunk_rays(train: &TrainConfig, model: &Config) -> usize {
    if train.chunk_rays > 0 {
        return train.chunk_rays;
    }
    let width = model.win_hidden.max(model.point_enc_dim).max(1);
    let per_ray = (model.n_samples + model.n_importance) * model.n_joints * width;
    (AUTO_CHUNK_POINT_JOINTS / per_ray.max(1)).max(1)
}

/// The density noise of one step, drawn a whole block (all rays of the batch) at a time in
/// the order the unchunked forward draws it; each chunk reads its own rays' rows. Chunks may
/// run on different workers: every chunk makes its calls in the same order (coarse, fine),
/// so block `c` is always drawn before block `c + 1`, whichever chunk asks first.
struct NoiseTape<'a> {
    rng: &'a mut ChaCha8Rng,
    /// One block per noise call of a forward pass (coarse, fine): [R·S] each.
    blocks: Vec<Vec<f32>>,
}

impl NoiseTape<'_> {
    /// Call number `call` of a chunk: `n` noise values for the samples of rays `rows`
    /// (S = n / rows per ray) of a batch of `r` rays.
    fn rows(
        &mut self,
        call: usize,
        n: usize,
        rows: &[usize],
        r: usize,
        device: &Device,
    ) -> crate::error::Result<Tensor> {
        use rand_distr::Distribution;
        if rows.is_empty() || n % rows.len() != 0 {
            return Err(crate::error::ModelError::Input(format!(
                "density noise: {n} samples requested for {} rays (not a whole number per ray)",
                rows.len()
            )));
        }
        let s = n / rows.len();
        if self.blocks.len() == call {
            let rng = &mut *self.rng;
            self.blocks.push(
                (0..r * s)
                    .map(|_| rand_distr::StandardNormal.sample(rng))
                    .collect(),
            );
        }
        let block = self.blocks.get(call).ok_or_else(|| {
            crate::error::ModelError::Input(format!(
                "density noise call {call} before call {}",
                self.blocks.len()
            ))
        })?;
        if block.len() != r * s {
            return Err(crate::error::ModelError::Input(format!(
                "density noise call {call}: {s} samples per ray, but the first chunk drew {} per ray",
                block.len() / r
            )));
        }
        let mut v = Vec::with_capacity(n);
        for &row in rows {
            v.extend_from_slice(&block[row * s..(row + 1) * s]);
        }
        Ok(Tensor::from_vec(v, n, device)?)
    }
}

/// What one chunk of a training step contributes.
struct ChunkOut {
    fine: f64,
    coarse: f64,
    sq: f64,
    /// The box-volume term (first chunk only).
    scale: Option<f64>,
    finite: bool,
    /// Gradients aligned with the trainer's parameters (empty when not finite).
    grads: Vec<Option<Tensor>>,
}

/// The rows `rows` of `batch` (rays and targets), on `device`.
fn select_rays(
    batch: &TrainBatch,
    rows: &[usize],
    device: &Device,
) -> Result<(Rays, Tensor), TrainError> {
    let idx = Tensor::from_vec(
        rows.iter().map(|&i| i as u32).collect::<Vec<_>>(),
        rows.len(),
        device,
    )?;
    let rays = Rays {
        origins: batch.rays.origins.index_select(&idx, 0)?,
        dirs: batch.rays.dirs.index_select(&idx, 0)?,
        bgs: match &batch.rays.bgs {
            Some(b) => Some(b.index_select(&idx, 0)?),
            None => None,
        },
        framecodes: rows.iter().map(|&i| batch.rays.framecodes[i]).collect(),
    };
    Ok((rays, batch.target.index_select(&idx, 0)?))
}

/// Loss parts and gradients summed over a step's chunks, in chunk order.
struct ChunkSums {
    grads: Vec<Option<Tensor>>,
    fine: f64,
    coarse: f64,
    sq: f64,
    scale: f64,
    finite: bool,
}

impl ChunkSums {
    fn new(n_params: usize) -> Self {
        Self {
            grads: vec![None; n_params],
            fine: 0.0,
            coarse: 0.0,
            sq: 0.0,
            scale: 0.0,
            finite: true,
        }
    }

    fn add(&mut self, out: ChunkOut) -> Result<(), TrainError> {
        self.fine += out.fine;
        self.coarse += out.coarse;
        self.sq += out.sq;
        if let Some(v) = out.scale {
            self.scale = v;
        }
        self.finite &= out.finite;
        if !self.finite {
            return Ok(());
        }
        for (g, d) in self.grads.iter_mut().zip(out.grads) {
            if let Some(d) = d {
                *g = Some(match g.take() {
                    Some(sum) => (sum + d)?,
                    None => d,
                });
            }
        }
        Ok(())
    }

    /// The step's loss parts, and its gradients (none when a chunk was not finite).
    fn finish(mut self, cfg: &TrainConfig) -> (LossParts, Vec<Option<Tensor>>) {
        let total =
            self.fine * cfg.loss_fine + self.coarse * cfg.loss_coarse + self.scale * cfg.loss_scale;
        let parts = LossParts {
            total: if self.finite { total } else { f64::NAN },
            fine: self.fine,
            coarse: self.coarse,
            scale: self.scale,
            psnr: psnr_from_mse(self.sq),
        };
        if !self.finite {
            self.grads = vec![None; self.grads.len()];
        }
        (parts, self.grads)
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
}

/// The density-noise stream is seeded from the run seed on its own ChaCha stream, so it
/// never overlaps the sampler's or the initialisation's draws.
const NOISE_STREAM: u64 = 0x6e_6f69_7365;

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
        let avatar = Avatar::new(run.model.clone(), &rest, run.train.seed, device)?;
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

    fn dataset_source(
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

    /// One iteration on the next batch of the source.
    ///
    /// A step cut short by an interruption (see [`crate::interrupt`]) is undone: it stops
    /// before the optimizer, so only the batch source and the noise generator have moved, and
    /// both are put back. The trainer is then exactly as after the last complete step, and a
    /// checkpoint of it resumes bit for bit.
    pub fn step(&mut self) -> Result<StepStats, TrainError> {
        self.step_undoable(None)
    }

    /// [`Self::step`] with a gradient hook (e.g. to inject a fault in tests).
    pub fn step_hooked(&mut self, hook: GradHook) -> Result<StepStats, TrainError> {
        self.step_undoable(Some(hook))
    }

    fn step_undoable(&mut self, hook: Option<GradHook>) -> Result<StepStats, TrainError> {
        let noise = self.noise_rng.clone();
        let source = self.source.state();
        let result = self
            .source
            .next_batch()
            .and_then(|batch| self.step_on(&batch, hook));
        match result {
            Err(e) if e.is_interrupted() => {
                self.noise_rng = noise;
                self.source.restore(&source)?;
                Err(e)
            }
            r => r,
        }
    }

    /// One iteration on `batch`: forward (training mode, density noise), loss, backward,
    /// `hook`, clip, Adam, schedule. A non-finite loss skips the backward pass too.
    ///
    /// A batch of more than [`chunk_rays`] rays runs in chunks (see [`Self::chunked_grads`]);
    /// clipping and Adam then see the accumulated gradient, as if it had been one pass.
    pub fn step_on(
        &mut self,
        batch: &TrainBatch,
        hook: Option<GradHook>,
    ) -> Result<StepStats, TrainError> {
        let rays = batch.rays.origins.dim(0)?;
        crate::compute::profile::start(self.avatar.device());
        let mut chunk = chunk_rays(&self.run.train, self.avatar.config());
        let workers = crate::compute::parallel::workers_on(self.avatar.device());
        if workers > 1 {
            // Enough chunks to keep every worker busy (chunks stay at least one ray per pose).
            chunk = chunk.min(rays.div_ceil(workers));
        }
        let (parts, mut grads) = if rays > chunk {
            self.chunked_grads(batch, chunk)?
        } else {
            let (loss, parts) = self.loss_on(batch)?;
            crate::compute::profile::mark("loss", self.avatar.device());
            let grads = if parts.total.is_finite() {
                let store = loss.backward()?;
                crate::compute::profile::mark("backward", self.avatar.device());
                self.params
                    .iter()
                    .map(|v| store.get(v.as_tensor()).cloned())
                    .collect()
            } else {
                vec![None; self.params.len()]
            };
            (parts, grads)
        };
        if let Some(h) = hook {
            h(&mut grads);
        }
        let stats = self.opt.apply(parts, grads);
        crate::compute::profile::mark("grad norm + Adam", self.avatar.device());
        stats
    }

    /// Loss parts and gradients of one step on `batch`, computed `chunk` rays at a time
    /// (at least one ray per pose), so memory is bounded by the chunk, not the batch.
    ///
    /// Every chunk takes the same slice of each pose's block of rays, so it is itself a valid
    /// batch of all P poses and the per-pose work (GNN, `layer_pose`, box scales) is done once
    /// and shared: each chunk's backward pass adds its share to the GNN's gradient. The L1
    /// terms are sums scaled by `1/(3R)` of the whole batch (the same two multiplications
    /// as the mean), so the chunk losses add up to the unchunked loss; the box-volume term
    /// goes with the first chunk. The density noise of the whole step is drawn once, in the
    /// unchunked order, and each chunk takes its rays' rows; rays that miss the bounding
    /// cylinder get the whole batch's fallback bounds. What differs from one pass is only
    /// the order of float summation.
    pub fn chunked_grads(
        &mut self,
        batch: &TrainBatch,
        chunk: usize,
    ) -> Result<(LossParts, Vec<Option<Tensor>>), TrainError> {
        let host = |t: &Tensor| -> Result<Vec<f32>, TrainError> {
            Ok(t.flatten_all()?.to_device(&Device::Cpu)?.to_vec1::<f32>()?)
        };
        let pose = self.avatar.pose_features(&batch.poses, None)?;
        crate::compute::profile::mark("pose features", self.avatar.device());
        let bounds = self.avatar.ray_caster().near_far(
            &host(&batch.rays.origins)?,
            &host(&batch.rays.dirs)?,
            &host(&batch.poses.cyls)?,
            &host(&batch.poses.skts)?,
            &host(&pose.scales.detach())?,
        )?;
        self.avatar.pin_miss_fill(Some(bounds.miss_fill));
        let result = self.chunk_loop(batch, &pose, chunk);
        self.avatar.pin_miss_fill(None);
        result
    }

    fn chunk_loop(
        &mut self,
        batch: &TrainBatch,
        pose: &PoseFeatures,
        chunk: usize,
    ) -> Result<(LossParts, Vec<Option<Tensor>>), TrainError> {
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
        let cfg = self.run.train.clone();
        let inv_n = 1.0 / (3 * r) as f64;
        let (avatar, params) = (&self.avatar, &self.params);
        let tape = std::sync::Mutex::new(NoiseTape {
            rng: &mut self.noise_rng,
            blocks: Vec::new(),
        });
        let run_chunk = |start: usize| -> Result<ChunkOut, TrainError> {
            let len = per_pose.min(k - start);
            let rows: Vec<usize> = (0..n_poses)
                .flat_map(|p| p * k + start..p * k + start + len)
                .collect();
            let (rays, target) = select_rays(batch, &rows, &device)?;
            crate::compute::profile::mark("chunk select + batch near/far", &device);
            let mut call = 0;
            let mut noise = |n: usize| {
                let mut t = tape.lock().unwrap_or_else(|e| e.into_inner());
                call += 1;
                t.rows(call - 1, n, &rows, r, &device)
            };
            let mut opts = Mode::Train(Some(&mut noise));
            let out = avatar.forward_with_pose(&rays, &batch.poses, pose, &mut opts)?;
            // sum · (1/n) · w: the multiplications the unchunked mean and weight make.
            let l1 = |pred: &Tensor, w: f64| -> Result<Tensor, TrainError> {
                Ok((((pred - &target)?.abs()?.sum_all()? * inv_n)? * w)?)
            };
            let mut loss =
                (l1(&out.fine.rgb, cfg.loss_fine)? + l1(&out.coarse.rgb, cfg.loss_coarse)?)?;
            let f64_of = |t: &Tensor| t.to_dtype(candle_core::DType::F64);
            let mut numbers = vec![
                f64_of(&(&out.fine.rgb.detach() - &target)?.abs()?.sum_all()?)?,
                f64_of(&(&out.coarse.rgb.detach() - &target)?.abs()?.sum_all()?)?,
                f64_of(&(&out.fine.rgb.detach() - &target)?.sqr()?.sum_all()?)?,
            ];
            if start == 0 {
                let volume = crate::train::loss::box_volume(&out.vol_scale)?;
                numbers.push(f64_of(&volume)?);
                loss = (loss + (volume * cfg.loss_scale)?)?;
            }
            numbers.push(f64_of(&loss)?);
            // One read-back for the chunk's numbers (one device sync on a GPU).
            let v = Tensor::stack(&numbers, 0)?
                .to_device(&Device::Cpu)?
                .to_vec1::<f64>()?;
            let (fine, coarse, sq) = (v[0] * inv_n, v[1] * inv_n, v[2] * inv_n);
            let scale = (start == 0).then(|| v[3]);
            // A non-finite chunk is not differentiated; the step is then skipped.
            let finite = v[v.len() - 1].is_finite();
            crate::compute::profile::mark("loss", &device);
            let grads = if finite {
                let store = loss.backward()?;
                crate::compute::profile::mark("backward", &device);
                params
                    .iter()
                    .map(|v| store.get(v.as_tensor()).map(|d| d.detach()))
                    .collect()
            } else {
                Vec::new()
            };
            Ok(ChunkOut {
                fine,
                coarse,
                sq,
                scale,
                finite,
                grads,
            })
        };
        let mut sums = ChunkSums::new(self.params.len());
        let starts: Vec<usize> = (0..k).step_by(per_pose).collect();
        // One wave of chunks per round of workers; sums are taken in chunk order, so the
        // result is the sequential loop's, bit for bit, whatever the worker count.
        let workers = crate::compute::parallel::workers_on(&device);
        for wave in starts.chunks(workers) {
            crate::interrupt::check()?;
            let outs =
                crate::compute::parallel::map_ordered(workers, wave.len(), |i| run_chunk(wave[i]))?;
            for out in outs {
                sums.add(out)?;
            }
        }
        Ok(sums.finish(&cfg))
    }

    /// Forward pass and loss on `batch` in training mode (consumes density noise).
    pub fn loss_on(&mut self, batch: &TrainBatch) -> Result<(Tensor, LossParts), TrainError> {
        let device = self.avatar.device().clone();
        let rng = &mut self.noise_rng;
        let mut noise = |n: usize| -> crate::error::Result<Tensor> {
            use rand_distr::Distribution;
            let v: Vec<f32> = (0..n)
                .map(|_| rand_distr::StandardNormal.sample(&mut *rng))
                .collect();
            Ok(Tensor::from_vec(v, n, &device)?)
        };
        let mut opts = Mode::Train(Some(&mut noise));
        let out = self
            .avatar
            .forward(&batch.rays, &batch.poses, &mut opts, None)?;
        training_loss(&out, &batch.target, &self.run.train)
    }

    /// What a checkpoint holds besides the model (see [`super::checkpoint`], which writes
    /// and reads run directories): optimizer moments, iteration, random streams, sampler
    /// position, counters and the run configuration. `model_fingerprint` ties it to the
    /// model file written with it.
    pub(crate) fn train_state(&self, model_fingerprint: String) -> Result<TrainState, TrainError> {
        Ok(TrainState {
            global_iter: self.opt.iter,
            groups: self.opt.adam.groups().to_vec(),
            params: self
                .opt
                .adam
                .states()
                .map(|(n, s)| (n.to_string(), s.clone()))
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

    fn loss(total: f64) -> LossParts {
        LossParts {
            total,
            fine: total,
            coarse: 0.0,
            scale: 0.0,
            psnr: 10.0,
        }
    }

    #[test]
    fn non_finite_steps_are_skipped_counted_and_never_applied() {
        let (x, mut opt) = setup();
        let g = |v: [f32; 2]| vec![Some(Tensor::new(&v, &Device::Cpu).unwrap())];
        let s = opt.apply(loss(0.5), g([1.0, 1.0])).unwrap();
        assert_eq!(s.skipped, None);
        let after_good = x.to_vec1::<f32>().unwrap();
        assert_ne!(after_good, vec![1.0, -2.0]);

        let s = opt.apply(loss(0.5), g([f32::NAN, 1.0])).unwrap();
        assert_eq!(s.skipped, Some(SkipReason::NonFiniteGradNorm));
        let s = opt.apply(loss(f64::INFINITY), g([1.0, 1.0])).unwrap();
        assert_eq!(s.skipped, Some(SkipReason::NonFiniteLoss));
        assert_eq!(x.to_vec1::<f32>().unwrap(), after_good);
        assert_eq!(opt.adam.state("pts_linears.0.weight").unwrap().step, 1);
        assert_eq!(
            (
                opt.iter,
                opt.progress.skipped,
                opt.progress.consecutive_skipped
            ),
            (3, 2, 2)
        );

        // A good step resets the streak; three bad ones in a row stop the run.
        opt.apply(loss(0.5), g([1.0, 1.0])).unwrap();
        assert_eq!(opt.progress.consecutive_skipped, 0);
        opt.apply(loss(f64::NAN), g([1.0, 1.0])).unwrap();
        opt.apply(loss(f64::NAN), g([1.0, 1.0])).unwrap();
        let err = opt.apply(loss(f64::NAN), g([1.0, 1.0])).unwrap_err();
        assert!(
            matches!(err, TrainError::Diverged { count: 3, iter: 7 }),
            "{err}"
        );
        assert_eq!(opt.adam.state("pts_linears.0.weight").unwrap().step, 2);
    }

    #[test]
    fn clipping_applies_above_the_threshold_and_schedule_advances() {
        let (_x, mut opt) = setup();
        let g = vec![Some(Tensor::new(&[30f32, 40.0], &Device::Cpu).unwrap())];
        let s = opt.apply(loss(1.0), g).unwrap();
        assert!((s.grad_norm - 50.0).abs() < 1e-9);
        assert!((s.clip_coef - 1.0 / (50.0 + 1e-6)).abs() < 1e-12);
        assert_eq!(s.lrs, vec![1e-4, 5e-4]);
        assert!((opt.lrs()[1] - 0.0004999976974202089).abs() < 1e-15);
    }
}
