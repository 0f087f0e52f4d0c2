//! One training iteration of the reference (`Trainer.train_batch`, spec `model.md` §6):
//! forward, loss, backward, global-norm clip, Adam, then the learning rates for the next step.
//!
//! [`Optimization`] is the model-agnostic half (clip, skip, Adam, schedule, counters);
//! [`Trainer`] adds the avatar, the ray sampler and the noise generator.

use candle_core::Tensor;

use super::adam::{clip_grad_norm, global_norm, Adam};
use super::state::Progress;
use super::TrainError;
use crate::presets::TrainConfig;

/// Loss terms of one step (spec §5), as plain numbers for logging.
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
        Self { adam, cfg, iter: 0, progress: Progress::default() }
    }

    /// Rates of the next step, per group.
    pub fn lrs(&self) -> Vec<f64> {
        self.adam.groups().iter().map(|g| g.lr).collect()
    }

    /// Finish iteration `iter + 1`. `grads` is aligned with `adam.param_names()` (`None` = no
    /// gradient). A non-finite loss or gradient norm skips the update: nothing reaches the
    /// weights or the moments, the skip is counted, and after `max_consecutive_skips` in a row
    /// the run stops with [`TrainError::Diverged`].
    pub fn apply(&mut self, loss: LossParts, mut grads: Vec<Option<Tensor>>) -> Result<StepStats, TrainError> {
        let lrs = self.lrs();
        let iter = self.iter + 1;
        let mut stats = StepStats { iter, loss, grad_norm: f64::NAN, clip_coef: 1.0, lrs, skipped: None };
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
        self.adam.apply_schedule(iter, c.lr_decay, c.lr_decay_steps, c.lr_floor);
        if self.progress.consecutive_skipped >= self.cfg.max_consecutive_skips {
            return Err(TrainError::Diverged { count: self.progress.consecutive_skipped, iter });
        }
        Ok(stats)
    }
}

/// PSNR from a mean squared error (`-10 log10 mse`; +inf for a perfect match).
pub fn psnr_from_mse(mse: f64) -> f64 {
    -10.0 * mse.log10()
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};

    fn setup() -> (Var, Optimization) {
        let x = Var::from_tensor(&Tensor::new(&[1f32, -2.0], &Device::Cpu).unwrap()).unwrap();
        let adam = Adam::reference(&[("pts_linears.0.weight".into(), x.clone())], 1e-4, 5e-4, [0.9, 0.999], 1e-8).unwrap();
        let cfg = TrainConfig { max_consecutive_skips: 3, ..TrainConfig::tiny() };
        (x, Optimization::new(adam, cfg))
    }

    fn loss(total: f64) -> LossParts {
        LossParts { total, fine: total, coarse: 0.0, scale: 0.0, psnr: 10.0 }
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
        assert_eq!((opt.iter, opt.progress.skipped, opt.progress.consecutive_skipped), (3, 2, 2));

        // A good step resets the streak; three bad ones in a row stop the run.
        opt.apply(loss(0.5), g([1.0, 1.0])).unwrap();
        assert_eq!(opt.progress.consecutive_skipped, 0);
        opt.apply(loss(f64::NAN), g([1.0, 1.0])).unwrap();
        opt.apply(loss(f64::NAN), g([1.0, 1.0])).unwrap();
        let err = opt.apply(loss(f64::NAN), g([1.0, 1.0])).unwrap_err();
        assert!(matches!(err, TrainError::Diverged { count: 3, iter: 7 }), "{err}");
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
