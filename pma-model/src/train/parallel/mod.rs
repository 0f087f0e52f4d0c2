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
//! With the occupancy grid two more exchanges follow (the ranks' counts of grid
//! observations, then the observations), so every rank's grid takes in what all ranks'
//! samples saw ([`Group::union_observations`]) and the grids stay equal too.
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
//! * `group`: a rank's membership ([`Group`]), its slice, the votes ([`Vote`], [`GroupStop`]);
//! * `comm`: the [`Communicator`] trait and the exchange op; `error`: [`GroupError`];
//! * `cpu`: ranks as threads of one process (the test double of NCCL, `--device cpu,cpu`);
//! * `nccl` (feature `nccl`): NCCL, one rank per GPU;
//! * `launch`: a group of processes started by `srun`, `mpirun` or `torchrun`, and the file
//!   rendezvous that carries NCCL's id;
//! * `run`: a whole run on a group ([`train_group`], [`train_launched`]).

pub mod comm;
pub mod cpu;
pub mod error;
pub mod group;
pub mod launch;
#[cfg(feature = "nccl")]
pub mod nccl;
mod run;

pub use comm::{Communicator, Kind};
pub use error::GroupError;
pub use group::{share, step_collectives, Group, GroupStop, Vote, CLOCK_SLOTS, VOTE_SLOTS};
#[cfg(feature = "nccl")]
pub use run::NcclEngine;
pub use run::{
    cpu_engine, train_group, train_launched, Engine, GroupOptions, DEFAULT_GROUP_TIMEOUT,
};
