//! One rank's membership of a data-parallel group ([`Group`]): its slice of the batch, the
//! sums of its step's gradient and numbers over the group, and the votes that stop the group
//! at one step.

use candle_core::{DType, Device, Tensor};

use super::comm::{self, Communicator, Kind};
use super::error::GroupError;
use crate::compute::account::Collective;
use crate::render::options::GridObservation;

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

    /// What every rank's evaluated samples saw of the occupancy grid in a step
    /// ([`GridObservation`]s), in rank order, on every rank. A grid keeps the largest density
    /// seen per cell, so each rank taking in the union keeps the grids equal, and equal to
    /// one device's on the whole batch. Two exchanges on `device`: the ranks' counts, then
    /// the observations (three f64 each, exact for their u16, u32 and f32 fields) padded to
    /// the longest list.
    pub fn union_observations(
        &self,
        mine: Vec<GridObservation>,
        device: &Device,
    ) -> Result<Vec<GridObservation>, TrainError> {
        if self.size() == 1 {
            return Ok(mine);
        }
        let mut counts = vec![0f64; self.size()];
        counts[self.rank()] = mine.len() as f64;
        let counts = self
            .sum(&Tensor::from_vec(counts, self.size(), device)?)?
            .to_vec1::<f64>()?;
        let longest = counts.iter().fold(0f64, |a, &b| a.max(b)) as usize;
        if longest == 0 {
            return Ok(Vec::new());
        }
        let mut buf = vec![0f64; 3 * longest];
        for (slot, o) in buf.chunks_exact_mut(3).zip(&mine) {
            slot.copy_from_slice(&[f64::from(o.joint), f64::from(o.cell), f64::from(o.sigma)]);
        }
        let buf = Tensor::from_vec(buf, 3 * longest, device)?;
        let all = comm::Exchange::run(self.comm.as_ref(), Kind::Gather, &buf)?.to_vec2::<f64>()?;
        let mut out = Vec::with_capacity(counts.iter().sum::<f64>() as usize);
        for (row, &n) in all.iter().zip(&counts) {
            out.extend(
                row.chunks_exact(3)
                    .take(n as usize)
                    .map(|o| GridObservation {
                        joint: o[0] as u16,
                        cell: o[1] as u32,
                        sigma: o[2] as f32,
                    }),
            );
        }
        Ok(out)
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

/// The loss terms of a step (`StepLoss::stacked`), first of the numbers a
/// group exchanges with each step.
pub const LOSS_TERMS: usize = 5;

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

/// Slots after the votes: rank 0's training clock in seconds (the other ranks add 0), which
/// every rank's wall-clock schedules follow (annealing, the pose side's boost), so all
/// ranks set the same rates.
pub const CLOCK_SLOTS: usize = 1;

/// The exchanges of one rank's step in a group of `size` (none for one rank), for a model
/// of `params` trainable tensors of `elems` elements in all: the flat f32 gradient, then the
/// f64 step numbers ([`step_numbers`]: the loss terms, the votes, rank 0's clock, a flag per
/// tensor).
/// Summed by the engine's all-reduce, or with `ordered` gathered and summed in rank order.
/// What an accounted group step counts, and what the scaling estimate prices. A step with
/// the occupancy grid adds two ([`Group::union_observations`]: the counts, then the
/// observations, whose size follows the step), which neither counts here.
pub fn step_collectives(
    size: usize,
    elems: usize,
    params: usize,
    ordered: bool,
) -> Vec<Collective> {
    if size < 2 {
        return Vec::new();
    }
    let numbers = LOSS_TERMS + VOTE_SLOTS + CLOCK_SLOTS + params;
    [elems as u64 * 4, numbers as u64 * 8]
        .into_iter()
        .map(|bytes| match ordered {
            false => Collective::AllReduce { bytes },
            true => Collective::AllGather { bytes },
        })
        .collect()
}

/// The per-step numbers a group exchanges besides the gradient: the loss terms (f64), the
/// votes, `clock` (rank 0's seconds, 0 on the others) and the has-a-gradient flags, one
/// buffer.
pub(crate) fn step_numbers(
    loss: &Tensor,
    vote: Vote,
    clock: f64,
    has: &[bool],
) -> Result<Tensor, TrainError> {
    let mut host: Vec<f64> = vote.counts().to_vec();
    host.push(clock);
    host.extend(has.iter().map(|&h| f64::from(u8::from(h))));
    let n = host.len();
    let tail = Tensor::from_vec(host, n, loss.device())?;
    Ok(Tensor::cat(&[&loss.to_dtype(DType::F64)?, &tail], 0)?)
}

/// The fault `PMA_FAULT_RANK_FAILS=R@I` (tests and drills): rank R fails before iteration I,
/// as a rank whose device or process broke would.
pub(crate) fn injected_failure(rank: usize, iter: u64) -> Result<(), TrainError> {
    static FAULT: std::sync::OnceLock<Option<(usize, u64)>> = std::sync::OnceLock::new();
    let fault = FAULT.get_or_init(|| {
        let v = std::env::var("PMA_FAULT_RANK_FAILS").ok()?;
        let (r, i) = v.trim().split_once('@')?;
        Some((r.parse().ok()?, i.parse().ok()?))
    });
    match *fault {
        Some((r, i)) if r == rank && i == iter => Err(GroupError::Engine(format!(
            "rank {rank} failed before iteration {iter} (injected by PMA_FAULT_RANK_FAILS={r}@{i})"
        ))
        .into()),
        _ => Ok(()),
    }
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
