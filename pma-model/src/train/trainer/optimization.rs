//! The numbers of a step and what happens to the gradients once they exist: global-norm
//! clip, the skip of a non-finite step, Adam and the schedule ([`Optimization`]), and the
//! deferred read-back that brings the numbers of several steps to the host in one copy.

use candle_core::{DType, Device, Tensor};

use crate::train::adam::{Adam, FREQ_GROUP};
use crate::train::parallel::error::GroupError;
use crate::train::parallel::group::{
    step_numbers, Group, GroupStop, Vote, CLOCK_SLOTS, LOSS_TERMS, VOTE_SLOTS,
};
use crate::train::presets::TrainConfig;
use crate::train::state::Progress;
use crate::train::TrainError;
use pma_data::metrics::psnr_from_mse;

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
    /// The step's per-ray errors, when it computed them for an error map (in the order the
    /// step gave them; empty otherwise).
    pub ray_errors: Vec<f32>,
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
    pub(super) fn zeros(device: &Device) -> candle_core::Result<Self> {
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

/// A step whose numbers are still on the device: [total, fine, coarse, scale, mse, norm],
/// in a data-parallel group the summed votes and has-a-gradient flags after them, then its
/// per-ray errors if it has them.
struct Pending {
    iter: u64,
    lrs: Vec<f64>,
    numbers: Tensor,
    /// The group's size and the length of its votes and flags, for a step of a
    /// data-parallel group.
    group: Option<(usize, usize)>,
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
    /// What a data-parallel group agreed on in the steps read back so far.
    group_stop: Option<GroupStop>,
    /// In a data-parallel group, the clock the schedules follow: rank 0's, as of the last
    /// step read back (every rank reads back at the same iterations, so every rank sets the
    /// same rates); `None` on one device, whose schedules follow `progress.wall_s`.
    group_clock: Option<f64>,
}

/// 1 (u8) where `x` is finite: `0·x` is 0 for finite values, NaN for ±inf and NaN.
fn finite(x: &Tensor) -> candle_core::Result<Tensor> {
    x.affine(0.0, 0.0)?.eq(&x.zeros_like()?)
}

impl Optimization {
    pub fn new(adam: Adam, cfg: TrainConfig) -> Self {
        let mut opt = Self {
            adam,
            cfg,
            iter: 0,
            progress: Progress::default(),
            pending: Vec::new(),
            group_stop: None,
            group_clock: None,
        };
        // The first step's rates (the initial ones, but for the pose side's boost).
        opt.schedule();
        opt
    }

    /// Join a data-parallel group: from now on the schedules follow rank 0's clock, which
    /// starts at the restored run's (the same on every rank).
    pub fn join_group(&mut self) {
        self.group_clock = Some(self.progress.wall_s);
        self.schedule();
    }

    /// Whether the steps read back so far carried a data-parallel group's vote to stop.
    pub fn group_stop(&self) -> Option<GroupStop> {
        self.group_stop
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
    /// Nothing is read back; the step's numbers (and `ray_errors`, [R] per-ray errors for an
    /// error map, when given) wait for [`Self::read_back`].
    pub fn apply(
        &mut self,
        loss: &StepLoss,
        grads: Vec<Option<Tensor>>,
        ray_errors: Option<&Tensor>,
    ) -> Result<(), TrainError> {
        self.apply_in(loss, grads, ray_errors, None)
    }

    /// [`Self::apply`] for a rank of a data-parallel group: the flat gradient and the loss
    /// terms (with the rank's `vote` and has-a-gradient flags) are summed over the group
    /// first, so the norm, the skip, the clip and the update are the same on every rank.
    pub fn apply_in(
        &mut self,
        loss: &StepLoss,
        grads: Vec<Option<Tensor>>,
        ray_errors: Option<&Tensor>,
        group: Option<(&Group, Vote)>,
    ) -> Result<(), TrainError> {
        let lrs = self.lrs();
        let iter = self.iter + 1;
        let (mut g, mut has) = self.adam.flatten(&grads)?;
        // When the step leaves work out a rank's graph follows its own rays: a parameter no
        // sample of its slice reached has no gradient there but may have one on another
        // rank. Every parameter then takes the group's sum (zeros from the ranks that did
        // not reach it), so all ranks update alike without a read-back; one device skips
        // a parameter that no sample of the whole step reached (Adam's moments of it then
        // stand still), which the group instead updates with a zero gradient.
        if group.is_some() && self.cfg.pass_options(self.iter).leaves_out_work() {
            has.fill(true);
        }
        let mut numbers = loss.stacked()?;
        let mut tail = None;
        if let Some((group, vote)) = group {
            g = group.sum(&g)?;
            let clock = match group.rank() {
                0 => self.progress.wall_s,
                _ => 0.0,
            };
            let all = group.sum(&step_numbers(&numbers, vote, clock, &has)?)?;
            numbers = all.narrow(0, 0, LOSS_TERMS)?;
            tail = Some(all.narrow(0, LOSS_TERMS, all.dim(0)? - LOSS_TERMS)?);
        }
        let total = match tail {
            Some(_) => numbers.get(0)?,
            None => loss.total.clone(),
        };
        let norm = g.to_dtype(DType::F64)?.sqr()?.sum_all()?.sqrt()?;
        let ok = (finite(&total)? * finite(&norm)?)?;
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
        let tail_len = tail.as_ref().map(|t| t.dim(0)).transpose()?.unwrap_or(0);
        let mut row = vec![numbers, norm.unsqueeze(0)?];
        row.extend(tail);
        if let Some(e) = ray_errors {
            row.push(e.to_dtype(DType::F64)?);
        }
        let numbers = Tensor::cat(&row, 0)?;
        self.pending.push(Pending {
            iter,
            lrs,
            numbers,
            group: group.map(|(g, _)| (g.size(), tail_len)),
        });
        self.iter = iter;
        self.schedule();
        Ok(())
    }

    /// Set the rates of the next step: the reference's decay by the iteration count, skipped
    /// steps included (it sets the rates from global_iter after every step), or with
    /// `anneal` the share of the run's span done (iterations, or the wall clock: rank 0's in
    /// a group, else `progress.wall_s`); with `pose_boost` the pose side's rate a multiple of
    /// that.
    pub fn schedule(&mut self) {
        let c = &self.cfg;
        let wall_s = self.group_clock.unwrap_or(self.progress.wall_s);
        match &c.anneal {
            None => self
                .adam
                .apply_schedule(self.iter, c.lr_decay, c.lr_decay_steps, c.lr_floor),
            Some(a) => {
                let factor = a.factor(self.iter, c.iters, wall_s);
                self.adam.apply_factor(factor, c.lr_floor);
            }
        }
        if let Some(b) = &c.pose_boost {
            let by = b.multiple(self.iter, c.iters, wall_s);
            self.adam.scale_group(FREQ_GROUP, by);
        }
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
            let [total, fine, coarse, scale, mse, norm] = v[..LOSS_TERMS + 1] else {
                unreachable!("six numbers per step")
            };
            let mut rest = &v[LOSS_TERMS + 1..];
            if let Some((size, tail_len)) = p.group {
                let (tail, after) = rest.split_at(tail_len);
                rest = after;
                let (votes, rest) = tail.split_at(VOTE_SLOTS);
                let (clock, has) = rest.split_at(CLOCK_SLOTS);
                self.group_clock = Some(clock[0]);
                // Which parameters have a gradient is decided by the graph, the same on every
                // rank; a rank that disagrees would apply another update than the others.
                if let Some(i) = has.iter().position(|&c| c != 0.0 && c != size as f64) {
                    return Err(GroupError::Disagree(format!(
                        "at iteration {}, {} of {size} ranks have a gradient for parameter {i}",
                        p.iter, has[i]
                    ))
                    .into());
                }
                if let Some(stop) = GroupStop::from_counts(votes) {
                    self.group_stop = Some(match self.group_stop {
                        Some(first) => first.or(Some(stop)),
                        None => stop,
                    });
                }
            }
            let ray_errors = rest.iter().map(|&e| e as f32).collect();
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
                ray_errors,
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
        opt.apply(&l, g, None)?;
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

    /// In a data-parallel group with culling a parameter can have a gradient on one rank
    /// and none on another (no sample of the other's slice reached it): both ranks apply
    /// the group's sum, the same update. Without culling the graph is the same on every
    /// rank, so ranks that disagree are an error, read back on both.
    #[test]
    fn a_culled_group_updates_a_parameter_one_rank_reached_on_every_rank() {
        use crate::train::parallel::{cpu, Communicator, Group, Vote};
        let (x1, mut one) = setup();
        let g = || Tensor::new(&[1f32, -1.0], &Device::Cpu).unwrap();
        apply(&mut one, loss(0.5), vec![Some(g())]).unwrap();
        let alone = x1.to_vec1::<f32>().unwrap();
        for culling in [true, false] {
            let comms = cpu::group(2, std::time::Duration::from_secs(60));
            let ranks: Vec<(bool, Vec<f32>)> = std::thread::scope(|s| {
                let handles: Vec<_> = comms
                    .into_iter()
                    .map(|comm| {
                        s.spawn(move || {
                            let (x, mut opt) = setup();
                            opt.cfg.culling.rays = culling;
                            opt.join_group();
                            let rank = comm.rank();
                            let group = Group::new(Box::new(comm), true);
                            let grads = vec![(rank == 0).then(g)];
                            opt.apply_in(&loss(0.5), grads, None, Some((&group, Vote::default())))
                                .unwrap();
                            let read = opt.read_back();
                            (read.is_ok(), x.to_vec1::<f32>().unwrap())
                        })
                    })
                    .collect();
                handles.into_iter().map(|h| h.join().unwrap()).collect()
            });
            match culling {
                true => {
                    assert!(ranks.iter().all(|(ok, _)| *ok), "a rank failed");
                    assert_eq!(ranks[0].1, alone, "rank 0 is not the one device");
                    assert_eq!(ranks[1].1, alone, "rank 1 is not the one device");
                }
                false => assert!(
                    ranks.iter().all(|(ok, _)| !*ok),
                    "ranks that disagree on a gradient were accepted"
                ),
            }
        }
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
            deferred.apply(&loss(l), g(v), None).unwrap();
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
            opt.apply(&loss(f64::NAN), g([1.0, 1.0]), None).unwrap();
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
