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
//! in one copy ([`Trainer::read_back`], every [`crate::train::TrainConfig::read_every`]
//! steps). Skipped steps are counted, and a streak of them stops the run, when their numbers
//! arrive.
//!
//! Everything random in training comes from seeded ChaCha generators whose positions are
//! saved in the train state, and candle's CPU kernels are deterministic, so a run resumed
//! from a checkpoint continues bit for bit like one that never stopped.
//!
//! * this file: the [`Trainer`] (construction, the step, the occupancy refresh, the state a
//!   checkpoint saves and restores);
//! * `chunks`: a step's rays in chunks (chunk size, rows, density noise, gradient sums);
//! * `optimization`: the numbers of a step, clip, skip, Adam, schedule and read-back.

mod chunks;
mod optimization;

pub use chunks::{chunk_rays, AUTO_CHUNK_POINT_JOINTS};
pub use optimization::{LossParts, Optimization, SkipReason, StepLoss, StepStats};

use std::sync::Arc;

use candle_core::{Device, Tensor, Var};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::adam::Adam;
use super::average::Average;
use super::batch::{BatchSource, TrainBatch};
use super::parallel::group::{injected_failure, Group, GroupStop, Vote};
use super::source::DatasetSource;
use super::state::{Progress, RngState, TrainState};
use super::TrainError;
use crate::network::occupancy::OccupancyGrid;
use crate::render::avatar::{Avatar, PassStats};
use crate::render::occupancy::{CellChoice, RefreshOptions};
use crate::train::presets::RunConfig;
use pma_data::dataset::Dataset;

pub use crate::network::run_dir::{MODEL_FILE, STATE_FILE};

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
    /// Lines for the user ([`Self::take_notes`]).
    notes: Vec<String>,
    /// This trainer's data-parallel group, if it is a rank of one ([`Self::join_group`]).
    group: Option<Group>,
    /// What this rank says about stopping, sent with its next step.
    vote: Vote,
    /// For each step whose per-ray errors are still on the device, oldest first: the image
    /// and pixel of each of its rays, in the order of its errors (the error map's input).
    drawn: std::collections::VecDeque<(Vec<usize>, Vec<usize>)>,
    /// The moving average of `params` (`[train.average]`).
    average: Option<Average>,
}

/// An error's message and its causes, on one line.
fn chain(e: &dyn std::error::Error) -> String {
    let mut line = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        line.push_str(": ");
        line.push_str(&s.to_string());
        source = s.source();
    }
    line
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
        let params: Vec<Var> = names.iter().map(|n| by_name[n.as_str()].clone()).collect();
        let average = t
            .average
            .clone()
            .map(|cfg| Average::new(cfg, &params))
            .transpose()?;
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
            notes: Vec::new(),
            group: None,
            vote: Vote::default(),
            drawn: Default::default(),
            average,
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

    pub(in crate::train) fn dataset_source(
        run: &RunConfig,
        data: Arc<Dataset>,
        device: &Device,
    ) -> Result<Box<dyn BatchSource>, TrainError> {
        let t = &run.train;
        let source = DatasetSource::new(
            data,
            t.rays_per_step,
            t.images_per_step,
            t.perturb_bg,
            t.seed,
            device,
        )?;
        Ok(Box::new(match &t.error_map {
            Some(cfg) => source.with_error_map(cfg.clone())?,
            None => source,
        }))
    }

    pub fn run_config(&self) -> &RunConfig {
        &self.run
    }

    /// Whether the network gives every sample of the next batch zero density (no noise, the
    /// full pass). The density is ReLU(raw) as in the reference; where every raw value is
    /// ≤ 0 no gradient reaches the density, and only the density noise can open it. The
    /// source is put back, so the run's batches are as if this was never asked.
    pub fn density_closed(&mut self) -> Result<bool, TrainError> {
        let state = self.source.state();
        let batch = self.source.next_batch();
        self.source.restore(&state)?;
        let batch = batch?;
        let opts = crate::render::avatar::PassOptions::default();
        let out = self.avatar.forward(
            &batch.rays,
            &batch.poses,
            &mut crate::render::batch::Mode::Infer,
            &opts,
            None,
        )?;
        let largest = |t: &Tensor| -> Result<f32, TrainError> {
            Ok(t.flatten_all()?
                .max(0)?
                .to_dtype(candle_core::DType::F32)?
                .to_scalar::<f32>()?)
        };
        Ok(largest(&out.coarse.alpha)? <= 0.0 && largest(&out.fine.alpha)? <= 0.0)
    }

    pub fn avatar(&self) -> &Avatar {
        &self.avatar
    }

    /// Run `f` on the run's model: the avatar with the averaged weights where the run
    /// averages them (`[train.average]`), the avatar as trained otherwise.
    pub fn with_model<R, E: From<TrainError>>(
        &self,
        f: impl FnOnce(&Avatar) -> Result<R, E>,
    ) -> Result<R, E> {
        match &self.average {
            Some(a) => a.with_averaged(&self.params, || f(&self.avatar)),
            None => f(&self.avatar),
        }
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

    /// Steps between read-backs ([`crate::train::TrainConfig::read_every`], `0` resolved for
    /// the device).
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

    /// The error map its batch source draws rays from, if it has one.
    pub fn error_map(&self) -> Option<&pma_data::error_map::ErrorMap> {
        self.source.error_map()
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
    /// Per-ray errors among them go to the batch source's error map.
    pub fn read_back(&mut self) -> Result<Vec<StepStats>, TrainError> {
        let stats = self.opt.read_back()?;
        // Numbers exchanged by a group that broke meanwhile mean nothing.
        if let Some(g) = &self.group {
            g.health()?;
        }
        for s in stats.iter().filter(|s| !s.ray_errors.is_empty()) {
            let Some((images, pixels)) = self.drawn.pop_front() else {
                return Err(TrainError::Config(format!(
                    "step {}: per-ray errors without the rays they belong to",
                    s.iter
                )));
            };
            if let Some(map) = self.source.error_map_mut() {
                map.observe(&images, &pixels, &s.ray_errors)
                    .map_err(|e| TrainError::Config(format!("error map: {e}")))?;
            }
        }
        Ok(stats)
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
        if let Some(g) = &self.group {
            injected_failure(g.rank(), self.opt.iter + 1)?;
        }
        let device = self.avatar.device().clone();
        crate::compute::profile::start(&device);
        let opts = self.run.train.pass_options(self.opt.iter);
        // A source that keeps an error map learns from the per-ray errors of its batches.
        let errors_wanted = self.source.error_map().is_some() && batch.pixels.is_some();
        let (loss, mut grads, stats, seen, errors) =
            self.gradients_retried(batch, &opts, errors_wanted)?;
        if let Some(h) = hook {
            h(&mut grads);
        }
        let vote = self.vote;
        self.opt.apply_in(
            &loss,
            grads,
            errors.as_ref().map(|e| &e.errors),
            self.group.as_ref().map(|g| (g, vote)),
        )?;
        if let (Some(e), Some(pixels)) = (&errors, &batch.pixels) {
            let fc = &batch.rays.framecodes;
            self.drawn.push_back((
                e.rays.iter().map(|&r| fc[r] as usize).collect(),
                e.rays.iter().map(|&r| pixels[r] as usize).collect(),
            ));
        }
        if let Some(a) = &mut self.average {
            a.update(&self.params, self.opt.iter)?;
        }
        crate::compute::profile::mark("grad norm + Adam", &device);
        self.pass_totals.add(&stats);
        // The densities the step saw are the model's before this update: recent enough for a
        // grid that decays what no sample finds again. Every rank of a group takes in all
        // ranks' (the grids stay equal).
        let seen = match &self.group {
            Some(g) if opts.occupancy => g.union_observations(seen, &device)?,
            _ => seen,
        };
        self.avatar.observe_occupancy(&seen)?;
        self.refresh_occupancy(batch)?;
        Ok(())
    }

    /// The step's gradients, the same step again where it failed for a reason a retry
    /// fixes: a kernel that failed while it ran (switched off now: the step runs on the
    /// generic ops), or a device out of memory (the chunk is halved, for this step and the
    /// rest of the run; one note says so). The retry draws the same density noise, so it is
    /// the same step; a smaller chunk changes only the order of float summation.
    fn gradients_retried(
        &mut self,
        batch: &TrainBatch,
        opts: &crate::render::avatar::PassOptions,
        ray_errors: bool,
    ) -> Result<chunks::Gradients, TrainError> {
        let noise = self.noise_rng.clone();
        let rays = self.rank_rays(batch)?;
        let mut chunk = self.chunk_size(rays).min(rays);
        let first = chunk;
        loop {
            let off = crate::compute::kernel::health::switched_off();
            let e = match self.gradients(batch, chunk, opts, ray_errors) {
                Ok(g) => {
                    if chunk < first {
                        self.notes.push(format!(
                            "out of device memory at {first} rays per chunk: step {} retried at {chunk} rays per chunk, which the run keeps",
                            self.opt.iter + 1
                        ));
                    }
                    return Ok(g);
                }
                Err(e) if e.is_interrupted() => return Err(e),
                Err(e) => e,
            };
            if crate::compute::kernel::health::switched_off() > off {
                // The kernel's own warning named it; the step runs again without it.
            } else if chunk > 1 && crate::compute::device::is_out_of_memory(&chain(&e)) {
                chunk /= 2;
                self.chunk = Some(chunk);
            } else {
                return Err(e);
            }
            self.noise_rng = noise.clone();
        }
    }

    /// Make this trainer rank `group.rank()` of a data-parallel group (see
    /// [`super::parallel`]): from now on each step computes the gradients of the rank's
    /// slice of the batch and sums them with the others'. Every rank must join before its
    /// first step, with the same run; the parameters are made rank 0's (one exchange).
    /// Refused for a run with an error map (it draws the rays from the errors one device
    /// saw) or whose batches have fewer rays per image than ranks. Culling and the occupancy
    /// grid train in a group: the ranks' grid observations are exchanged with each step, and
    /// every parameter takes the group's gradient (see [`Optimization::apply_in`]).
    pub fn join_group(&mut self, group: Group) -> Result<(), TrainError> {
        check_group(&self.run.train, group.size())?;
        let flat: Vec<Tensor> = self
            .params
            .iter()
            .map(|v| v.as_tensor().flatten_all())
            .collect::<candle_core::Result<_>>()?;
        if !flat.is_empty() {
            let first = group.from_first(&Tensor::cat(&flat, 0)?)?;
            let mut at = 0;
            for v in &self.params {
                let n = v.elem_count();
                v.set(&first.narrow(0, at, n)?.reshape(v.shape())?)?;
                at += n;
            }
        }
        self.group = Some(group);
        self.opt.join_group();
        Ok(())
    }

    /// This trainer's data-parallel group, if any.
    pub fn group(&self) -> Option<&Group> {
        self.group.as_ref()
    }

    /// What this rank says about stopping; the group hears it with the next step.
    pub fn set_vote(&mut self, vote: Vote) {
        self.vote = vote;
    }

    /// What the group agreed on in the steps read back so far: stop after the last of them.
    pub fn group_stop(&self) -> Option<GroupStop> {
        self.opt.group_stop()
    }

    /// The rays of `batch` this trainer computes: its rank's slice, or all of them.
    fn rank_rays(&self, batch: &TrainBatch) -> Result<usize, TrainError> {
        let r = batch.rays.origins.dim(0)?;
        let poses = batch.poses.bones.len().max(1);
        Ok(match &self.group {
            Some(g) => {
                let (lo, hi) = g.share(r / poses);
                (hi - lo) * poses
            }
            None => r,
        })
    }

    /// Rays per chunk of this run's steps (fixed at the first step; 0 before it).
    pub fn chunk_rays(&self) -> usize {
        self.chunk.unwrap_or(0)
    }

    /// Lines for the user from the steps so far (a chunk halved after an out-of-memory
    /// error), oldest first; each is returned once.
    pub fn take_notes(&mut self) -> Vec<String> {
        std::mem::take(&mut self.notes)
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
            error_map: self
                .source
                .error_map()
                .map(|m| Tensor::from_vec(m.values().to_vec(), m.shape().to_vec(), &Device::Cpu))
                .transpose()?,
            occupied: self
                .avatar
                .occupancy()
                .map(|g| {
                    let cells: Vec<u8> = g.occupied_cells().iter().map(|&o| o as u8).collect();
                    Tensor::from_vec(cells, g.shape().to_vec(), &Device::Cpu)
                })
                .transpose()?,
            // An averaged run's model file holds the average; the trained weights go here.
            weights: match self.average {
                Some(_) => self
                    .names
                    .iter()
                    .zip(&self.params)
                    .map(|(n, p)| Ok((n.clone(), p.as_tensor().detach().copy()?)))
                    .collect::<Result<_, TrainError>>()?,
                None => Default::default(),
            },
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
        self.restore_weights(state.weights)?;
        // The grid loaded with the model marks its cells from its values, which hold what
        // the steps since its last refresh saw; the run marked them at that refresh. (A
        // state without them, from before they were saved, keeps the values' marks.)
        if let (Some(o), Some(_)) = (state.occupied, self.avatar.occupancy()) {
            let cells = o.flatten_all()?.to_vec1::<u8>()?;
            self.avatar
                .set_occupied_cells(cells.into_iter().map(|c| c != 0).collect())
                .map_err(|e| TrainError::State(vec![e.to_string()]))?;
        }
        self.opt.iter = state.global_iter;
        self.opt.progress = state.progress.unwrap_or_default();
        // Rates follow from the iteration (and the run's clock); recomputing avoids trusting
        // JSON float parsing.
        self.opt.schedule();
        if let Some(r) = &state.rng {
            self.noise_rng = r.restore()?;
        }
        // A run without a map, or a state without one (a converted reference checkpoint):
        // the map starts afresh.
        if let (Some(saved), Some(map)) = (state.error_map, self.source.error_map_mut()) {
            let values = saved.flatten_all()?.to_vec1::<f32>()?;
            map.set_values(values)
                .map_err(|e| TrainError::State(vec![format!("sampler.error_map: {e}")]))?;
        }
        self.source
            .restore(state.sampler.as_ref().unwrap_or(&serde_json::Value::Null))
    }

    /// An averaged run was loaded from its model file, the average: that becomes the
    /// average again, and the trained weights come from the train state.
    fn restore_weights(
        &mut self,
        mut weights: std::collections::HashMap<String, Tensor>,
    ) -> Result<(), TrainError> {
        let Some(cfg) = self.run.train.average.clone() else {
            return match weights.is_empty() {
                true => Ok(()),
                false => Err(TrainError::State(vec![
                    "the train state holds trained weights (`weights.*`) but the run does not \
                     average them ([train.average])"
                        .into(),
                ])),
            };
        };
        self.average = Some(Average::new(cfg, &self.params)?);
        let mut problems = Vec::new();
        for (name, p) in self.names.iter().zip(&self.params) {
            match weights.remove(name) {
                Some(w) if w.dims() == p.dims() => p.set(&w.to_device(p.device())?)?,
                Some(w) => problems.push(format!(
                    "`weights.{name}` is {:?}, the model's parameter {:?}",
                    w.dims(),
                    p.dims()
                )),
                None => problems.push(format!(
                    "`weights.{name}` is missing (a run with [train.average] keeps its trained \
                     weights in the train state)"
                )),
            }
        }
        let mut left: Vec<String> = weights.into_keys().collect();
        left.sort();
        problems.extend(
            left.into_iter()
                .map(|n| format!("`weights.{n}` names no parameter of the model")),
        );
        match problems.is_empty() {
            true => Ok(()),
            false => Err(TrainError::State(problems)),
        }
    }
}

/// Whether a run of `train` can train on a data-parallel group of `size` devices: an error
/// map is refused (each rank would draw its rays from the errors of its own slice), and so
/// is a batch with fewer rays per image than ranks.
pub fn check_group(train: &crate::train::TrainConfig, size: usize) -> Result<(), TrainError> {
    if train.error_map.is_some() {
        return Err(TrainError::Config(
            "the error map ([train.error_map], --error-map) is not supported with several \
             devices (each rank would see only its own rays)"
                .into(),
        ));
    }
    let per_image = train.rays_per_step / train.images_per_step.max(1);
    if per_image < size {
        return Err(TrainError::Config(format!(
            "{per_image} rays per image cannot be split over {size} devices (each takes a \
             slice of every image's rays)"
        )));
    }
    Ok(())
}
