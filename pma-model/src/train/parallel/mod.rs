//! Data-parallel training: one avatar trained by a group of ranks (one per device), each
//! computing the gradients of its share of every step's batch.
//!
//! Every rank samples the global batch exactly as one device would (the same seeded
//! streams, the same density noise) and takes its slice of it: the same rows of each pose's
//! block of rays, rank r the r-th of `size` near-equal parts ([`Group::share`]). The per-pose
//! work and the ray casting are done for the whole batch on every rank (casting depends on
//! the batch as a whole through the fallback bounds of rays that miss the body), the
//! per-chunk work only for the rank's rows. Then, between the summed gradients and the
//! optimizer, one exchange of the flat gradient buffer sums it over the ranks, and a second,
//! small one the step's loss terms, the ranks' stop votes and their has-a-gradient flags.
//! Every rank then clips, skips and updates on the same numbers: the replicas stay equal.
//!
//! The sum is the engine's all-reduce (its summation order). With
//! [`crate::compute::numerics::Numerics::deterministic`] it is an all-gather followed by a
//! sum in rank order on every rank: N ranks then give, bit for bit, what one device gives
//! with chunks equal to the ranks' slices, and a run repeats and resumes bit for bit.
//!
//! Stopping is agreed, never unilateral: a rank never leaves a step halfway (interruption
//! checks are held, [`pma_data::interrupt::hold`]), and each step carries every rank's vote
//! (a signal it received, its time budget spent) in its exchanged numbers. When the numbers
//! are read back (at the same iterations on every rank) all ranks see the same votes and
//! stop after the same step ([`GroupStop`]).
//!
//! * `comm`: the [`Communicator`] trait and the exchange op;
//! * `cpu`: ranks as threads of one process (the test double of NCCL, `--device cpu,cpu`);
//! * `nccl` (feature `nccl`): NCCL, one rank per GPU;
//! * `launch`: a group of processes started by `srun`, `mpirun` or `torchrun`, and the file
//!   rendezvous that carries NCCL's id;
//! * `run`: a whole run on a group ([`train_group`], [`train_launched`]).

pub mod comm;
pub mod cpu;
pub mod launch;
#[cfg(feature = "nccl")]
pub mod nccl;
mod run;

pub use comm::{Communicator, GroupError, Kind};
pub(crate) use run::injected_failure;
#[cfg(feature = "nccl")]
pub use run::NcclEngine;
pub use run::{
    cpu_engine, train_group, train_launched, Engine, GroupOptions, DEFAULT_GROUP_TIMEOUT,
};

use candle_core::{DType, Tensor};

use crate::compute::account::Collective;

use crate::train::TrainError;

/// One rank's membership of a data-parallel group, as a trainer holds it.
pub struct Group {
    comm: Box<dyn Communicator>,
    /// Sum in rank order ([`Kind::Gather`], then adds) instead of the engine's all-reduce.
    ordered: bool,
}

impl Group {
    pub fn new(comm: Box<dyn Communicator>, ordered: bool) -> Self {
        Self { comm, ordered }
    }

    pub fn rank(&self) -> usize {
        self.comm.rank()
    }

    pub fn size(&self) -> usize {
        self.comm.size()
    }

    /// This rank's slice `lo..hi` of a pose's block of `k` rays.
    pub fn share(&self, k: usize) -> (usize, usize) {
        share(self.rank(), self.size(), k)
    }

    /// `t` (f32 or f64) summed over the ranks; every rank gets the same values.
    pub fn sum(&self, t: &Tensor) -> Result<Tensor, TrainError> {
        if self.size() == 1 {
            return Ok(t.clone());
        }
        if !self.ordered {
            return comm::Exchange::run(self.comm.as_ref(), Kind::Sum, t);
        }
        let all = comm::Exchange::run(self.comm.as_ref(), Kind::Gather, t)?;
        let mut acc = all.get(0)?;
        for r in 1..self.size() {
            acc = (acc + all.get(r)?)?;
        }
        Ok(acc)
    }

    /// Rank 0's `t` on every rank (its values exactly: the others add zeros).
    pub fn from_first(&self, t: &Tensor) -> Result<Tensor, TrainError> {
        let mine = match self.rank() {
            0 => t.clone(),
            _ => t.zeros_like()?,
        };
        self.sum(&mine)
    }

    /// `Ok` while the group is whole.
    pub fn health(&self) -> Result<(), TrainError> {
        Ok(self.comm.health()?)
    }
}

/// Rank `rank`'s slice of `k` items split over `size` ranks in near-equal parts.
pub fn share(rank: usize, size: usize, k: usize) -> (usize, usize) {
    (rank * k / size, (rank + 1) * k / size)
}

/// What one rank says, with a step, about stopping after it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Vote {
    /// The signal this rank's process received (0: none).
    pub signal: i32,
    /// This rank's time budget is spent.
    pub budget: bool,
}

/// Slots of the votes in a step's exchanged numbers: how many ranks voted SIGINT (or a
/// signal other than these three), SIGTERM, SIGHUP, an exhausted budget.
pub const VOTE_SLOTS: usize = 4;

impl Vote {
    /// This vote as counts, one slot per reason.
    pub fn counts(&self) -> [f64; VOTE_SLOTS] {
        let mut c = [0.0; VOTE_SLOTS];
        match self.signal {
            0 => {}
            15 => c[1] = 1.0,
            1 => c[2] = 1.0,
            _ => c[0] = 1.0,
        }
        if self.budget {
            c[3] = 1.0;
        }
        c
    }
}

/// What the group agreed on after a step: stop, because of a signal one of its ranks got
/// (SIGINT before SIGTERM before SIGHUP when several did) or a spent budget.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GroupStop {
    pub signal: Option<i32>,
    pub budget: bool,
}

impl GroupStop {
    /// From the summed vote counts of a step; `None` when nobody voted to stop.
    pub fn from_counts(c: &[f64]) -> Option<Self> {
        let at = |i: usize| c.get(i).copied().unwrap_or(0.0) > 0.0;
        let signal = [(0, 2), (1, 15), (2, 1)]
            .into_iter()
            .find(|&(i, _)| at(i))
            .map(|(_, s)| s);
        (signal.is_some() || at(3)).then_some(Self {
            signal,
            budget: at(3),
        })
    }

    /// The first reason of two (a signal wins over a budget).
    pub fn or(self, later: Option<Self>) -> Self {
        match later {
            Some(l) if self.signal.is_none() && l.signal.is_some() => l,
            _ => self,
        }
    }
}

/// The exchanges of one rank's step in a group of `size` (none for one rank), for a model
/// of `params` trainable tensors of `elems` elements in all: the flat f32 gradient, then the
/// f64 step numbers ([`step_numbers`]: the loss terms, the votes, a flag per tensor).
/// Summed by the engine's all-reduce, or with `ordered` gathered and summed in rank order.
/// What an accounted group step counts, and what the scaling estimate prices.
pub fn step_collectives(
    size: usize,
    elems: usize,
    params: usize,
    ordered: bool,
) -> Vec<Collective> {
    if size < 2 {
        return Vec::new();
    }
    let numbers = crate::train::trainer::LOSS_TERMS + VOTE_SLOTS + params;
    [elems as u64 * 4, numbers as u64 * 8]
        .into_iter()
        .map(|bytes| match ordered {
            false => Collective::AllReduce { bytes },
            true => Collective::AllGather { bytes },
        })
        .collect()
}

/// The per-step numbers a group exchanges besides the gradient: the loss terms (f64), the
/// votes and the has-a-gradient flags, one buffer.
pub(crate) fn step_numbers(loss: &Tensor, vote: Vote, has: &[bool]) -> Result<Tensor, TrainError> {
    let mut host: Vec<f64> = vote.counts().to_vec();
    host.extend(has.iter().map(|&h| f64::from(u8::from(h))));
    let n = host.len();
    let tail = Tensor::from_vec(host, n, loss.device())?;
    Ok(Tensor::cat(&[&loss.to_dtype(DType::F64)?, &tail], 0)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shares_cover_a_block_in_order() {
        for size in 1..6 {
            for k in size..20 {
                let mut next = 0;
                for r in 0..size {
                    let (lo, hi) = share(r, size, k);
                    assert_eq!(lo, next);
                    assert!(hi > lo, "rank {r} of {size} has no ray of {k}");
                    next = hi;
                }
                assert_eq!(next, k);
            }
        }
    }

    #[test]
    fn votes_sum_to_one_decision() {
        let sum = |votes: &[Vote]| {
            let mut c = [0.0; VOTE_SLOTS];
            for v in votes {
                for (a, b) in c.iter_mut().zip(v.counts()) {
                    *a += b;
                }
            }
            GroupStop::from_counts(&c)
        };
        let none = Vote::default();
        assert_eq!(sum(&[none, none]), None);
        let term = Vote {
            signal: 15,
            budget: false,
        };
        let int = Vote {
            signal: 2,
            budget: false,
        };
        let spent = Vote {
            signal: 0,
            budget: true,
        };
        assert_eq!(
            sum(&[none, term, none]),
            Some(GroupStop {
                signal: Some(15),
                budget: false
            })
        );
        assert_eq!(sum(&[term, int, int]).unwrap().signal, Some(2));
        assert_eq!(
            sum(&[spent, none]),
            Some(GroupStop {
                signal: None,
                budget: true
            })
        );
        let first = sum(&[spent]).unwrap();
        assert_eq!(first.or(sum(&[term])).signal, Some(15));
        assert_eq!(sum(&[term]).unwrap().or(sum(&[int])).signal, Some(15));
    }
}
