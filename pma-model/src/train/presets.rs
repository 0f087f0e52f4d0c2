//! Training presets: the hyper-parameters of the loop for each named configuration, and the
//! run TOML that names a preset and overrides single fields (see [`crate::network::presets`]).

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::average::AverageConfig;
use super::error::TrainError;
use crate::network::config::Config;
use crate::network::occupancy::OccupancyConfig;
use crate::render::options::{Culling, PassOptions};
use pma_data::error_map::ErrorMapConfig;

/// Limit of the rays of a training step and of a render chunk (the paper's step: 3,072).
pub const MAX_RAYS: usize = crate::render::MAX_CHUNK_RAYS;

/// The most iterations a run may ask for (10¹²: years at any speed pma reaches).
pub const MAX_ITERS: u64 = 1_000_000_000_000;
/// The largest seed: the run's TOML keeps it, and TOML integers are signed 64-bit.
pub const MAX_SEED: u64 = i64::MAX as u64;

/// The largest run TOML read (1 MiB; a complete resolved config is ~2 KB).
pub const MAX_CONFIG_BYTES: u64 = 1 << 20;

/// Hyper-parameters of the training loop (docs/reference.md, "Training schedule and Adam").
/// Field names follow the reference's yaml where one exists (given in the doc comments).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainConfig {
    /// Seeds the model initialisation, the ray sampler and the density noise.
    pub seed: u64,
    /// Total iterations of a run (`iters`); a resumed run continues up to this count.
    pub iters: u64,
    /// Rays per step (`N_rays`); must be a multiple of `images_per_step`.
    pub rays_per_step: usize,
    /// Images per step (`N_sample_images`); each contributes `rays_per_step / images_per_step` rays.
    pub images_per_step: usize,
    /// Learning rate of the "other" group: NeRF MLPs and frame codes (`trainer.optim.lr`).
    pub lr: f64,
    /// Learning rate of the "freq" group: GNN, window, extractor, modulator, point encoders,
    /// axis scale (`model.lr_freq`).
    pub lr_freq: f64,
    /// Adam betas (torch defaults; the paper says beta2 = 0.99, the code uses 0.999).
    pub betas: [f64; 2],
    /// Adam epsilon.
    pub eps: f64,
    /// `lr(t) = max(lr0 * lr_decay^(t / lr_decay_steps), lr_floor)` (`lr_sched`).
    pub lr_decay: f64,
    pub lr_decay_steps: f64,
    pub lr_floor: f64,
    /// Global gradient L2-norm clip; `0` disables clipping.
    pub grad_clip: f64,
    /// Weight of the L1 loss on the fine render (`NeRFRGBLoss.fine`).
    pub loss_fine: f64,
    /// Weight of the L1 loss on the coarse render (`NeRFRGBLoss.coarse`).
    pub loss_coarse: f64,
    /// Weight of the sum of box volumes (`SigmaLoss.weight`).
    pub loss_scale: f64,
    /// Random-noise backgrounds for background pixels (`perturb_bg`).
    pub perturb_bg: bool,
    /// Iterations between progress rows in `log.csv` (`i_print`).
    pub log_every: u64,
    /// Iterations between checkpoints (`latest.th` cadence in the reference).
    pub ckpt_every: u64,
    /// Iterations between held-out evaluations (`i_testset`); `0` = only at the end.
    pub eval_every: u64,
    /// Held-out images rendered at each evaluation during training (evenly spread).
    pub eval_images: usize,
    /// Rays per render chunk at evaluation (`chunk`).
    pub render_chunk: usize,
    /// Abort after this many consecutive non-finite steps (each is skipped, not applied).
    pub max_consecutive_skips: u64,
    /// Rays per forward/backward chunk of a training step (gradients are accumulated over
    /// the chunks, so the step is the same as unchunked up to float summation order); `0` =
    /// automatic, sized from the device ([`crate::train::chunk_rays`]): its free memory on a
    /// GPU, [`crate::train::AUTO_CHUNK_POINT_JOINTS`] point-joint pairs on the CPU.
    pub chunk_rays: usize,
    /// Steps between read-backs of the loss, gradient norm and skip decisions (one
    /// device-to-host copy for all of them; the log and the progress display get the numbers
    /// then, and skipped steps are counted then). `0` = automatic: every step on the CPU,
    /// where a read-back costs nothing, every
    /// [`crate::train::AUTO_READ_EVERY_DEVICE`] steps on other devices. Never changes the
    /// training itself.
    pub read_every: u64,
    /// Culling in the training step (`[train.culling]`; docs/numerics.md, "Empty rays and
    /// culling"). Off by default (parity); omitted from the saved configuration while off.
    #[serde(skip_serializing_if = "Culling::is_off")]
    pub culling: Culling,
    /// An occupancy grid built and refreshed during training and used by its steps after the
    /// warm-up (`[train.occupancy]`, `pma train --occupancy`), saved with every checkpoint.
    /// Off (`None`) by default; omitted from the saved configuration while off.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub occupancy: Option<OccupancyConfig>,
    /// With the grid: each ray's coarse samples are placed in the intervals the grid marks
    /// occupied instead of over its whole box interval (`render::placement`). Off by default;
    /// omitted from the saved configuration while off.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub coarse_from_grid: bool,
    /// Stratified samples: each step moves every coarse sample to a random place in its
    /// stratum and draws the importance samples at random places of their CDF
    /// ([`crate::render::raycast::Jitter`], the `perturb` of the original NeRF; the
    /// reference trains on evenly spaced samples). Off by default; omitted from the saved
    /// configuration while off.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub jitter: bool,
    /// Part of each image's rays drawn where a running map of the training error is high
    /// (`[train.error_map]`, `pma_data::error_map`), saved with every checkpoint. Off
    /// (`None`) by default; omitted from the saved configuration while off.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error_map: Option<ErrorMapConfig>,
    /// The learning rates anneal over the run's own length (its wall-clock budget or its
    /// iterations) instead of following `lr_decay` over `lr_decay_steps` (`[train.anneal]`).
    /// Off (`None`) by default; omitted from the saved configuration while off.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub anneal: Option<Anneal>,
    /// The pose side's rate (the "freq" group, `lr_freq`) starts at a multiple and comes down
    /// to its own over the run's length (`[train.pose_boost]`). Off (`None`) by default;
    /// omitted from the saved configuration while off.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pose_boost: Option<PoseBoost>,
    /// The run's model is the moving average of its weights over the steps
    /// (`[train.average]`, [`crate::train::average`]): the model file of every checkpoint,
    /// and what the held-out evaluation scores. Off (`None`) by default; omitted from the
    /// saved configuration while off.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub average: Option<AverageConfig>,
}

/// Learning rates that anneal over a run's own length: at the share f of its span done
/// every group's rate is `lr0 · final_factor^g` with g = max(0, f − hold) / (1 − hold)
/// (floored at `lr_floor`), so a run of a few minutes ends its schedule when it ends, as the
/// reference's 300,000 iterations end theirs (at 0.25 of the initial rates) and a short run
/// of the reference's schedule never does. With a `hold` the rates stay at their start for
/// that share of the span and fall only in the rest (a cool-down at the end of the budget).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Anneal {
    /// The rates at the end of the span, as a share of the initial rates.
    pub final_factor: f64,
    /// The share of the span at the initial rates before they start to fall, in [0, 1).
    pub hold: f64,
    /// The span in seconds of the run's wall clock (its budget, `--minutes`); 0: the run's
    /// iterations (`iters`). A wall-clock span makes the rates depend on the machine's
    /// speed, so such a run does not repeat bit for bit.
    pub seconds: f64,
}

impl Default for Anneal {
    fn default() -> Self {
        Self {
            final_factor: 0.1,
            hold: 0.0,
            seconds: 0.0,
        }
    }
}

/// The share of a span done after `iter` iterations of a run of `iters` at `wall_s`
/// seconds: of `seconds` of wall clock, or of the iterations when `seconds` is 0.
fn span_done(seconds: f64, iter: u64, iters: u64, wall_s: f64) -> f64 {
    let done = match seconds > 0.0 {
        true => wall_s / seconds,
        false => iter as f64 / iters.max(1) as f64,
    };
    done.clamp(0.0, 1.0)
}

/// What is wrong with a span's `seconds` (`key` names it in the configuration), if anything.
fn span_problem(key: &str, seconds: f64) -> Option<String> {
    (!(seconds.is_finite() && seconds >= 0.0)).then(|| {
        format!("{key} must be finite and >= 0 (0 = over the iterations), found {seconds}")
    })
}

impl Anneal {
    /// The factor of the initial rates after `iter` iterations of a run of `iters` at
    /// `wall_s` seconds.
    pub fn factor(&self, iter: u64, iters: u64, wall_s: f64) -> f64 {
        let done = span_done(self.seconds, iter, iters, wall_s);
        let falling = ((done - self.hold) / (1.0 - self.hold)).max(0.0);
        self.final_factor.powf(falling)
    }

    fn problems(&self) -> Vec<String> {
        let mut bad = Vec::new();
        if !(self.final_factor.is_finite() && self.final_factor > 0.0 && self.final_factor <= 1.0) {
            bad.push(format!(
                "anneal.final_factor must be in (0, 1], found {}",
                self.final_factor
            ));
        }
        if !(self.hold.is_finite() && (0.0..1.0).contains(&self.hold)) {
            bad.push(format!(
                "anneal.hold must be in [0, 1), found {}",
                self.hold
            ));
        }
        bad.extend(span_problem("anneal.seconds", self.seconds));
        bad
    }
}

/// A pose side that learns faster early: its rate is `factor^(1 − f)` times what the
/// schedule gives it at the share f of the span done, so it starts at `factor` times and ends
/// at the schedule's own: the reference's pose-side rate, a fifth of the trunk's, is made for
/// 300,000 steps, and in a run of minutes that side lags. Over the recipe it learned faster
/// for two minutes and was 0.11 dB behind at five (docs/performance.md "Time to quality").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PoseBoost {
    /// The pose side's rate at the start, as a multiple of its scheduled rate.
    pub factor: f64,
    /// The span in seconds of the run's wall clock (its budget, `--minutes`); 0: the run's
    /// iterations (`iters`). A wall-clock span makes the rates depend on the machine's
    /// speed, so such a run does not repeat bit for bit.
    pub seconds: f64,
}

impl Default for PoseBoost {
    fn default() -> Self {
        Self {
            factor: 4.0,
            seconds: 0.0,
        }
    }
}

impl PoseBoost {
    /// The pose side's multiple after `iter` iterations of a run of `iters` at `wall_s`
    /// seconds.
    pub fn multiple(&self, iter: u64, iters: u64, wall_s: f64) -> f64 {
        self.factor
            .powf(1.0 - span_done(self.seconds, iter, iters, wall_s))
    }

    fn problems(&self) -> Vec<String> {
        let mut bad = Vec::new();
        if !(self.factor.is_finite() && (1.0..=100.0).contains(&self.factor)) {
            bad.push(format!(
                "pose_boost.factor must be in [1, 100], found {}",
                self.factor
            ));
        }
        bad.extend(span_problem("pose_boost.seconds", self.seconds));
        bad
    }
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self::paper()
    }
}

impl TrainConfig {
    /// Switch on the annealed rates (keeping any settings given) over a budget of `budget_s`
    /// seconds of wall clock (`--minutes`), or over the run's iterations with `None`.
    pub fn anneal_over(&mut self, budget_s: Option<f64>) {
        self.anneal.get_or_insert_with(Anneal::default).seconds = budget_s.unwrap_or(0.0);
    }

    /// Switch on the pose side's boost (keeping any settings given) over a budget of
    /// `budget_s` seconds of wall clock, or over the run's iterations with `None`.
    pub fn boost_pose_over(&mut self, budget_s: Option<f64>) {
        self.pose_boost
            .get_or_insert_with(PoseBoost::default)
            .seconds = budget_s.unwrap_or(0.0);
    }

    /// The reference's training setup (`configs/basic.yaml`, `pm_avatar.yaml`).
    pub fn paper() -> Self {
        Self {
            seed: 0,
            iters: 300_000,
            rays_per_step: 3072,
            images_per_step: 16,
            lr: 5e-4,
            lr_freq: 1e-4,
            betas: [0.9, 0.999],
            eps: 1e-8,
            lr_decay: 0.1,
            lr_decay_steps: 500_000.0,
            lr_floor: 1e-5,
            grad_clip: 1.0,
            loss_fine: 1.0,
            loss_coarse: 1.0,
            loss_scale: 0.001,
            perturb_bg: true,
            log_every: 400,
            ckpt_every: 400,
            eval_every: 10_000,
            eval_images: 4,
            render_chunk: 5120,
            max_consecutive_skips: 100,
            chunk_rays: 0,
            read_every: 0,
            culling: Culling::default(),
            occupancy: None,
            coarse_from_grid: false,
            jitter: false,
            error_map: None,
            anneal: None,
            pose_boost: None,
            average: None,
        }
    }

    /// The pass options of a training step at iteration `iter` (completed iterations): the
    /// culling, and the occupancy grid once its warm-up is over.
    pub fn pass_options(&self, iter: u64) -> PassOptions {
        PassOptions {
            culling: self.culling.clone(),
            occupancy: self.grid_active(iter),
            coarse_from_grid: self.coarse_from_grid && self.grid_active(iter),
            // Training places its fine samples from the coarse render (its coarse loss
            // needs that render anyway).
            occupancy_fine: false,
            // Every sample of a training step takes part in its gradients.
            early_stop: None,
            cull_joints: false,
            // The trainer gives each chunk its own feed (probes and observations).
            grid_feed: None,
            // Each step its own places, from the seed and the step.
            jitter: self.jitter.then(|| crate::render::raycast::Jitter {
                seed: self.seed ^ (iter + 1).wrapping_mul(0xa076_1d64_78bd_642f),
            }),
        }
    }

    /// Whether the steps after `iter` completed iterations use the occupancy grid (its
    /// warm-up is over).
    fn grid_active(&self, iter: u64) -> bool {
        self.occupancy
            .as_ref()
            .is_some_and(|o| iter >= o.warmup_steps)
    }

    /// The loss weights (fine, coarse, box volume).
    pub fn loss_weights(&self) -> crate::train::loss::LossWeights {
        crate::train::loss::LossWeights {
            fine: self.loss_fine,
            coarse: self.loss_coarse,
            scale: self.loss_scale,
        }
    }

    /// CPU training on the synthetic scene: 256 rays from 4 images per step and twice the
    /// reference's learning rates. On the demo scene 2× reached a given held-out PSNR in
    /// about half the iterations of 1×; 4× was faster still there but made the `tiny` net
    /// collapse to empty space (zero density everywhere, from which relu gives no way
    /// back), so 2× is the margin kept. The run is short, so the schedule barely decays.
    pub fn cpu_small() -> Self {
        Self {
            iters: 1_000_000,
            rays_per_step: 256,
            images_per_step: 4,
            lr: 1e-3,
            lr_freq: 2e-4,
            log_every: 25,
            ckpt_every: 250,
            eval_every: 100,
            eval_images: 2,
            render_chunk: 4096,
            ..Self::paper()
        }
    }

    /// For tests: a handful of rays per step, frequent logging, no periodic evaluation.
    pub fn tiny() -> Self {
        Self {
            iters: 50,
            rays_per_step: 128,
            images_per_step: 2,
            log_every: 5,
            ckpt_every: 1_000_000,
            eval_every: 0,
            eval_images: 1,
            render_chunk: 2048,
            ..Self::paper()
        }
    }

    /// Reject settings the training loop cannot run with.
    pub fn validate(&self) -> Result<(), TrainError> {
        let mut bad = Vec::new();
        // Counts that size buffers are bounded (the paper's step has 3,072 rays).
        for (name, v, max) in [
            ("rays_per_step", self.rays_per_step, MAX_RAYS),
            ("images_per_step", self.images_per_step, MAX_RAYS),
            ("chunk_rays", self.chunk_rays, MAX_RAYS),
            ("render_chunk", self.render_chunk, MAX_RAYS),
            ("eval_images", self.eval_images, 100_000),
        ] {
            if v > max {
                bad.push(format!("{name} = {v} is over the limit of {max}"));
            }
        }
        for (name, v, max) in [
            ("iters", self.iters, MAX_ITERS),
            ("seed", self.seed, MAX_SEED),
        ] {
            if v > max {
                bad.push(format!("{name} = {v} is over the limit of {max}"));
            }
        }
        if self.images_per_step == 0 || self.rays_per_step == 0 {
            bad.push("rays_per_step and images_per_step must be > 0".to_string());
        } else if self.rays_per_step % self.images_per_step != 0 {
            bad.push(format!(
                "rays_per_step ({}) must be a multiple of images_per_step ({}): rays are grouped by image",
                self.rays_per_step, self.images_per_step
            ));
        }
        for (name, v) in [
            ("lr", self.lr),
            ("lr_freq", self.lr_freq),
            ("eps", self.eps),
        ] {
            if !(v.is_finite() && v > 0.0) {
                bad.push(format!("{name} must be finite and > 0, found {v}"));
            }
        }
        if !self.betas.iter().all(|b| (0.0..1.0).contains(b)) {
            bad.push(format!("betas must lie in [0, 1), found {:?}", self.betas));
        }
        if !(self.lr_decay.is_finite() && self.lr_decay > 0.0) {
            bad.push(format!(
                "lr_decay must be finite and > 0, found {}",
                self.lr_decay
            ));
        }
        if !(self.lr_decay_steps.is_finite() && self.lr_decay_steps > 0.0) {
            bad.push(format!(
                "lr_decay_steps must be finite and > 0, found {}",
                self.lr_decay_steps
            ));
        }
        if !(self.lr_floor.is_finite() && self.lr_floor >= 0.0) {
            bad.push(format!(
                "lr_floor must be finite and >= 0, found {}",
                self.lr_floor
            ));
        }
        if !(self.grad_clip.is_finite() && self.grad_clip >= 0.0) {
            bad.push(format!(
                "grad_clip must be finite and >= 0 (0 = off), found {}",
                self.grad_clip
            ));
        }
        for (name, v) in [
            ("loss_fine", self.loss_fine),
            ("loss_coarse", self.loss_coarse),
            ("loss_scale", self.loss_scale),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                bad.push(format!("{name} must be finite and >= 0, found {v}"));
            }
        }
        if self.log_every == 0 || self.ckpt_every == 0 {
            bad.push("log_every and ckpt_every must be > 0".to_string());
        }
        if self.render_chunk == 0 {
            bad.push("render_chunk must be > 0".to_string());
        }
        if self.max_consecutive_skips == 0 {
            bad.push("max_consecutive_skips must be > 0".to_string());
        }
        if let Some(t) = self.culling.sample_threshold {
            if !(t.is_finite() && (0.0..1.0).contains(&t)) {
                bad.push(format!(
                    "culling.sample_threshold must be in [0, 1), found {t}"
                ));
            }
        }
        if let Some(o) = &self.occupancy {
            bad.extend(o.problems().into_iter().map(|p| format!("occupancy.{p}")));
        }
        if self.coarse_from_grid && self.occupancy.is_none() {
            bad.push(
                "coarse_from_grid places the coarse samples from the occupancy grid: it needs \
                 [train.occupancy]"
                    .to_string(),
            );
        }
        if let Some(m) = &self.error_map {
            bad.extend(m.problems().into_iter().map(|p| format!("error_map.{p}")));
        }
        if let Some(a) = &self.anneal {
            bad.extend(a.problems());
        }
        if let Some(b) = &self.pose_boost {
            bad.extend(b.problems());
        }
        if let Some(a) = &self.average {
            bad.extend(a.problems());
        }
        if bad.is_empty() {
            Ok(())
        } else {
            Err(TrainError::Config(bad.join("; ")))
        }
    }
}

/// A named pair of model and training configurations.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Preset {
    /// The paper's sizes (spelled `default` on the command line and in TOML).
    #[serde(rename = "default")]
    Paper,
    CpuSmall,
    Tiny,
}

impl Preset {
    pub const ALL: [Preset; 3] = [Preset::Paper, Preset::CpuSmall, Preset::Tiny];

    /// The preset a run on `device` gets when none is named: the paper's network on a GPU,
    /// `cpu-small` on the CPU (where the paper's network makes about one step every few
    /// seconds).
    pub fn for_device(device: &candle_core::Device) -> Self {
        match device.is_cpu() {
            true => Preset::CpuSmall,
            false => Preset::Paper,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Preset::Paper => "default",
            Preset::CpuSmall => "cpu-small",
            Preset::Tiny => "tiny",
        }
    }

    pub fn model(self) -> Config {
        match self {
            Preset::Paper => Config::paper(),
            Preset::CpuSmall => Config::cpu_small(),
            Preset::Tiny => Config::tiny(),
        }
    }

    pub fn train(self) -> TrainConfig {
        match self {
            Preset::Paper => TrainConfig::paper(),
            Preset::CpuSmall => TrainConfig::cpu_small(),
            Preset::Tiny => TrainConfig::tiny(),
        }
    }
}

impl std::str::FromStr for Preset {
    type Err = TrainError;
    fn from_str(s: &str) -> Result<Self, TrainError> {
        Preset::ALL
            .into_iter()
            .find(|p| p.name() == s)
            .ok_or_else(|| {
                let names: Vec<_> = Preset::ALL.iter().map(|p| p.name()).collect();
                TrainError::Config(format!(
                    "unknown preset {s:?}; expected one of {}",
                    names.join(", ")
                ))
            })
    }
}

impl std::fmt::Display for Preset {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Model + training configuration of one run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunConfig {
    pub preset: Preset,
    pub model: Config,
    pub train: TrainConfig,
    /// How the network computes (kernels, sine, TF32): a choice of this process, not saved
    /// with the run, so a resumed run may change it.
    #[serde(skip)]
    pub numerics: crate::compute::numerics::Numerics,
}

impl RunConfig {
    pub fn from_preset(preset: Preset) -> Self {
        Self {
            preset,
            model: preset.model(),
            train: preset.train(),
            numerics: Default::default(),
        }
    }

    /// Parse a TOML run file: `preset` (default `default`) chooses the base, `[model]` and
    /// `[train]` override single fields of it. Unknown keys are errors, so a typo cannot
    /// silently fall back to a preset value.
    pub fn from_toml_str(text: &str) -> Result<Self, TrainError> {
        let bad = |msg: String| TrainError::Config(msg);
        let mut root: toml::Table = text
            .parse()
            .map_err(|e: toml::de::Error| bad(toml_error(text, &e)))?;
        let preset = match root.remove("preset") {
            None => Preset::Paper,
            Some(toml::Value::String(s)) => s.parse()?,
            Some(v) => return Err(bad(format!("`preset` must be a string, found {v}"))),
        };
        let mut model_over = take_table(&mut root, "model")?;
        let mut train_over = take_table(&mut root, "train")?;
        // Run directories written before culling became a training option keep it under
        // [model]; they still resume.
        if let Some(c) = model_over.remove("culling") {
            if train_over.contains_key("culling") {
                return Err(bad(
                    "`culling` is given under both [model] and [train]; keep [train.culling]"
                        .into(),
                ));
            }
            train_over.insert("culling".into(), c);
        }
        if let Some(k) = root.keys().next() {
            return Err(bad(format!(
                "unknown top-level key `{k}` (expected preset, [model], [train])"
            )));
        }
        let model: Config = merge("model", &preset.model(), model_over, &[])?;
        let train: TrainConfig = merge(
            "train",
            &preset.train(),
            train_over,
            &[
                "culling",
                "occupancy",
                "coarse_from_grid",
                "jitter",
                "error_map",
                "anneal",
                "pose_boost",
                "average",
            ],
        )?;
        let run = Self {
            preset,
            model,
            train,
            numerics: Default::default(),
        };
        run.validate()?;
        Ok(run)
    }

    pub fn from_toml_file(path: &Path) -> Result<Self, TrainError> {
        let text = pma_data::fsio::read_input_to_string(path, MAX_CONFIG_BYTES)
            .map_err(super::error::read_err(path))?;
        Self::from_toml_str(&text).map_err(|e| match e {
            TrainError::Config(msg) => TrainError::Config(format!("{}: {msg}", path.display())),
            other => other,
        })
    }

    pub fn validate(&self) -> Result<(), TrainError> {
        self.model.validate()?;
        self.train.validate()?;
        let mut all = self.train.pass_options(0);
        all.occupancy = self.train.occupancy.is_some();
        match all.problem(&self.model) {
            Some(p) => Err(TrainError::Config(p)),
            None => Ok(()),
        }
    }

    /// The one rule for what may change when a run is resumed, used wherever a run is
    /// continued (`train::run` against the configuration given on the command line, the
    /// trainer against the one its train state was saved with): `given` must equal `self`
    /// (the run's configuration) except for
    ///
    /// * `train.iters`: the length of the run;
    /// * `train.chunk_rays`: rays per forward/backward chunk, which bounds memory and leaves
    ///   the step unchanged.
    ///
    /// `model.n_framecodes` is the training set's image count, not a setting: it must match
    /// (the same data). Everything else (the model, the seed, rates, schedule, culling,
    /// variant) is the run. The error names the first difference and how many more.
    pub fn check_resume(&self, given: &RunConfig) -> Result<(), String> {
        let norm = |r: &RunConfig| {
            let mut r = r.clone();
            r.train.iters = 0;
            r.train.chunk_rays = 0;
            r.train.read_every = 0;
            serde_json::to_value(&r).unwrap_or(serde_json::Value::Null)
        };
        let mut diffs = Vec::new();
        json_diffs("", &norm(self), &norm(given), &mut diffs);
        let Some((key, ours, theirs)) = diffs.first() else {
            return Ok(());
        };
        let what = if key == "model.n_framecodes" {
            format!(
                "the run was trained on {ours} images, the data has {theirs} (n_framecodes = the training set's image count)"
            )
        } else {
            format!("{key} is {ours} in the run, {theirs} given")
        };
        let more = match diffs.len() {
            1 => String::new(),
            n => format!(" (and {} more difference(s))", n - 1),
        };
        Err(format!(
            "{what}{more}; a resumed run keeps its configuration (only train.iters, train.chunk_rays and train.read_every may change)"
        ))
    }

    /// The full configuration as TOML; [`Self::from_toml_str`] reads it back unchanged.
    pub fn to_toml_string(&self) -> Result<String, TrainError> {
        toml::to_string(self)
            .map_err(|e| TrainError::Config(format!("cannot write the run config as TOML: {e}")))
    }
}

/// The leaves where `a` and `b` differ, as (dotted key, value in a, value in b).
fn json_diffs(
    prefix: &str,
    a: &serde_json::Value,
    b: &serde_json::Value,
    out: &mut Vec<(String, String, String)>,
) {
    use serde_json::Value;
    match (a, b) {
        (Value::Object(x), Value::Object(y)) => {
            let mut keys: Vec<&String> = x.keys().chain(y.keys()).collect();
            keys.sort();
            keys.dedup();
            for k in keys {
                let key = if prefix.is_empty() {
                    k.clone()
                } else {
                    format!("{prefix}.{k}")
                };
                let null = Value::Null;
                json_diffs(
                    &key,
                    x.get(k).unwrap_or(&null),
                    y.get(k).unwrap_or(&null),
                    out,
                );
            }
        }
        _ if a != b => out.push((prefix.to_string(), a.to_string(), b.to_string())),
        _ => {}
    }
}

/// A TOML parse error on one line: where (line and column) and what.
fn toml_error(text: &str, e: &toml::de::Error) -> String {
    let at = e.span().map(|s| {
        let before = &text[..s.start.min(text.len())];
        let line = before.matches('\n').count() + 1;
        let col = before.len() - before.rfind('\n').map_or(0, |i| i + 1) + 1;
        format!(" at line {line}, column {col}")
    });
    format!(
        "not valid TOML{}: {}",
        at.unwrap_or_default(),
        pma_data::error::one_line(e.message())
    )
}

fn take_table(root: &mut toml::Table, key: &str) -> Result<toml::Table, TrainError> {
    match root.remove(key) {
        None => Ok(toml::Table::new()),
        Some(toml::Value::Table(t)) => Ok(t),
        Some(v) => Err(TrainError::Config(format!(
            "`{key}` must be a table, found {v}"
        ))),
    }
}

/// Overlay `over` on the serialised `base` (one level deep: nested tables such as
/// `model.quirks` are merged too) and deserialise the result. `optional` names the tables of
/// the section that the serialised base leaves out while they are off (their own types
/// refuse unknown keys, so they are taken as given: tables and switches).
fn merge<T: Serialize + serde::de::DeserializeOwned>(
    section: &str,
    base: &T,
    over: toml::Table,
    optional: &[&str],
) -> Result<T, TrainError> {
    let bad = |msg: String| TrainError::Config(msg);
    let mut merged = toml::Table::try_from(base).map_err(|e| {
        bad(format!(
            "[{section}]: {}",
            pma_data::error::one_line(&e.to_string())
        ))
    })?;
    for (k, v) in over {
        let optional = optional.contains(&k.as_str());
        match (merged.get_mut(&k), v) {
            (None, v) if optional => {
                merged.insert(k, v);
            }
            (Some(toml::Value::Table(dst)), toml::Value::Table(src)) if optional => {
                dst.extend(src);
            }
            (None, _) => return Err(bad(format!("unknown key `{section}.{k}`"))),
            (Some(toml::Value::Table(dst)), toml::Value::Table(src)) => {
                for (k2, v2) in src {
                    if !dst.contains_key(&k2) {
                        return Err(bad(format!("unknown key `{section}.{k}.{k2}`")));
                    }
                    dst.insert(k2, v2);
                }
            }
            (Some(dst), v) => *dst = v,
        }
    }
    toml::Value::Table(merged)
        .try_into()
        .map_err(|e: toml::de::Error| {
            bad(format!(
                "[{section}]: {}",
                pma_data::error::one_line(&e.to_string())
            ))
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_validate() {
        for p in Preset::ALL {
            let run = RunConfig::from_preset(p);
            run.validate().unwrap_or_else(|e| panic!("preset {p}: {e}"));
            assert_eq!(p.name().parse::<Preset>().unwrap(), p);
        }
    }

    #[test]
    fn the_pose_boost_comes_down_to_one_over_its_span_and_refuses_bad_values() {
        let over_iters = PoseBoost::default();
        assert_eq!(over_iters.multiple(0, 100, 99.0), 4.0);
        assert_eq!(over_iters.multiple(50, 100, 0.0), 2.0);
        assert_eq!(over_iters.multiple(100, 100, 0.0), 1.0);
        assert_eq!(over_iters.multiple(500, 100, 0.0), 1.0);
        let over_clock = PoseBoost {
            factor: 9.0,
            seconds: 60.0,
        };
        assert_eq!(over_clock.multiple(7, 100, 30.0), 3.0);
        assert_eq!(over_clock.multiple(7, 100, 61.0), 1.0);
        let run = RunConfig::from_toml_str(
            "preset = \"tiny\"\n[train.pose_boost]\nfactor = 2.0\nseconds = 300.0\n",
        )
        .unwrap();
        assert_eq!(
            run.train.pose_boost,
            Some(PoseBoost {
                factor: 2.0,
                seconds: 300.0
            })
        );
        let back = RunConfig::from_toml_str(&run.to_toml_string().unwrap()).unwrap();
        assert_eq!(back, run);
        for (bad, key) in [
            ("factor = 0.5", "pose_boost.factor"),
            ("factor = nan", "pose_boost.factor"),
            ("seconds = -1.0", "pose_boost.seconds"),
        ] {
            let text = format!("preset = \"tiny\"\n[train.pose_boost]\n{bad}\n");
            let e = RunConfig::from_toml_str(&text).unwrap_err().to_string();
            assert!(e.contains(key), "{bad}: {e}");
        }
        // Off by default, and then absent from the saved configuration.
        let plain = RunConfig::from_preset(Preset::Tiny);
        assert!(!plain.to_toml_string().unwrap().contains("pose_boost"));
    }

    #[test]
    fn annealed_rates_hold_then_fall_to_the_final_factor_and_refuse_bad_values() {
        let from_start = Anneal::default();
        assert_eq!(from_start.factor(0, 100, 0.0), 1.0);
        assert!((from_start.factor(50, 100, 0.0) - 0.1f64.sqrt()).abs() < 1e-12);
        assert!((from_start.factor(100, 100, 0.0) - 0.1).abs() < 1e-12);
        let cool_down = Anneal {
            final_factor: 0.01,
            hold: 0.6,
            seconds: 100.0,
        };
        assert_eq!(cool_down.factor(9, 10, 0.0), 1.0);
        assert_eq!(cool_down.factor(9, 10, 60.0), 1.0);
        assert!((cool_down.factor(9, 10, 80.0) - 0.1).abs() < 1e-12);
        assert!((cool_down.factor(0, 10, 500.0) - 0.01).abs() < 1e-12);
        for bad in ["hold = 1.0", "hold = -0.1", "hold = nan"] {
            let text = format!("preset = \"tiny\"\n[train.anneal]\n{bad}\n");
            let e = RunConfig::from_toml_str(&text).unwrap_err().to_string();
            assert!(e.contains("anneal.hold"), "{bad}: {e}");
        }
        // A budget spans a schedule switched on with it and keeps the settings given.
        let mut run = RunConfig::from_toml_str(
            "preset = \"tiny\"\n[train.anneal]\nhold = 0.5\n[train.pose_boost]\nfactor = 8.0\n",
        )
        .unwrap();
        run.train.anneal_over(Some(120.0));
        run.train.boost_pose_over(None);
        let a = run.train.anneal.unwrap();
        assert_eq!((a.hold, a.seconds), (0.5, 120.0));
        let b = run.train.pose_boost.unwrap();
        assert_eq!((b.factor, b.seconds), (8.0, 0.0));
    }

    #[test]
    fn toml_overrides_single_fields() {
        let run = RunConfig::from_toml_str(
            "preset = \"cpu-small\"\n[model]\ntrunk_width = 48\n[model.quirks]\nnormalize_view_dirs = true\n[train]\nrays_per_step = 256\n",
        )
        .unwrap();
        assert_eq!(run.preset, Preset::CpuSmall);
        assert_eq!(run.model.trunk_width, 48);
        assert!(run.model.quirks.normalize_view_dirs);
        assert_eq!(run.model.view_width, Config::cpu_small().view_width);
        assert_eq!(run.train.rays_per_step, 256);
        assert_eq!(
            run.train.images_per_step,
            TrainConfig::cpu_small().images_per_step
        );
    }

    #[test]
    fn culling_under_model_is_read_as_the_training_culling() {
        let old = "preset = \"tiny\"\n[model.culling]\nrays = true\nsample_threshold = 0.2\n";
        let run = RunConfig::from_toml_str(old).unwrap();
        assert!(run.train.culling.rays);
        assert_eq!(run.train.culling.sample_threshold, Some(0.2));
        let both = format!("{old}[train.culling]\nrays = true\n");
        let e = RunConfig::from_toml_str(&both).unwrap_err().to_string();
        assert!(e.contains("both [model] and [train]"), "{e}");
    }

    #[test]
    fn toml_roundtrip_is_exact() {
        for p in Preset::ALL {
            let run = RunConfig::from_preset(p);
            let back = RunConfig::from_toml_str(&run.to_toml_string().unwrap()).unwrap();
            assert_eq!(back, run, "{p}");
        }
    }

    #[test]
    fn resume_may_change_only_the_length_and_the_chunking() {
        let run = RunConfig::from_preset(Preset::Tiny);
        let mut same = run.clone();
        same.train.iters *= 3;
        same.train.chunk_rays = 16;
        run.check_resume(&same).unwrap();
        let mut other = run.clone();
        other.train.lr *= 2.0;
        other.model.trunk_width += 1;
        let err = run.check_resume(&other).unwrap_err();
        assert!(err.contains("model.trunk_width is"), "{err}");
        assert!(err.contains("and 1 more difference"), "{err}");
        let mut data = run.clone();
        data.model.n_framecodes += 5;
        let err = run.check_resume(&data).unwrap_err();
        assert!(err.contains("images"), "{err}");
    }

    #[test]
    fn sizes_from_a_toml_are_bounded_and_parse_errors_are_one_line() {
        for text in [
            "preset = \"tiny\"\n[model]\ntrunk_width = 1000000\n",
            "preset = \"tiny\"\n[model]\nn_samples = 1000000000\n",
            "preset = \"tiny\"\n[model]\ntrunk_depth = 1000000000\n",
            "preset = \"tiny\"\n[train]\nrays_per_step = 100000000\n",
        ] {
            let err = RunConfig::from_toml_str(text).unwrap_err().to_string();
            assert!(err.contains("over the limit"), "{text:?}: {err}");
        }
        let err = RunConfig::from_toml_str("[train\nlr = 1\n")
            .unwrap_err()
            .to_string();
        assert!(err.contains("line 1"), "{err}");
        assert_eq!(err.lines().count(), 1, "{err}");
    }

    #[test]
    fn toml_rejects_typos_and_bad_values() {
        for (text, needle) in [
            ("[train]\nrays_per_stp = 3\n", "train.rays_per_stp"),
            ("[model]\ntrunk_widht = 3\n", "model.trunk_widht"),
            ("preset = \"huge\"\n", "unknown preset"),
            (
                "[train]\nrays_per_step = 100\nimages_per_step = 3\n",
                "multiple of images_per_step",
            ),
            ("[train]\nlr = -1.0\n", "lr must be"),
            ("foo = 1\n", "unknown top-level key"),
            ("[train]\nlr = \"fast\"\n", "[train]"),
        ] {
            let err = RunConfig::from_toml_str(text).unwrap_err().to_string();
            assert!(err.contains(needle), "{text:?}: {err}");
        }
    }
}
