//! A whole training run on a data-parallel group: the same session as on one device
//! ([`crate::train::run`]), once per rank. Rank 0 is the run's one writer: it holds the run
//! directory's lock, prepares the run (clears an interrupted checkpoint's leftovers, writes
//! the configuration), logs, evaluates on held-out data and checkpoints; the other ranks
//! train along and write nothing. Every rank starts from the same checkpoint.
//!
//! * [`train_group`]: one process, one thread per device (`--device cpu,cpu`,
//!   `--device cuda:0,1,2,3`); the lock covers the group because it is one process.
//! * [`train_launched`]: one process per device, started by a launcher
//!   ([`super::launch::Launch`]); rank 0 takes the lock, prepares, then posts the group's id
//!   in the rendezvous file (or why it refused), and the others wait for it.
//!
//! A rank that fails ends its session with its error; its communicator drops, so the other
//! ranks fail at their next exchange ([`super::GroupError::Left`], or a timeout where a
//! process died without a word). [`train_group`] reports the first rank's own error.

use std::path::{Path, PathBuf};
use std::time::Duration;

use candle_core::Device;

use super::comm::Communicator;
use super::cpu;
use super::error::GroupError;
use super::group::Group;
use super::launch::{self, Launch, Posted};
use crate::train::lock::RunLock;
use crate::train::run::{prepare, Prepared, Role};
use crate::train::{Silent, TrainError, TrainObserver, TrainOutcome, TrainRequest};

/// How long a rank waits for the others at an exchange (and at setup) before it gives up:
/// longer than rank 0's longest held-out evaluation, while the others wait at the next step.
pub const DEFAULT_GROUP_TIMEOUT: Duration = Duration::from_secs(1800);

/// Settings of a group run.
#[derive(Debug, Clone)]
pub struct GroupOptions {
    /// See [`DEFAULT_GROUP_TIMEOUT`].
    pub timeout: Duration,
}

impl Default for GroupOptions {
    fn default() -> Self {
        Self {
            timeout: DEFAULT_GROUP_TIMEOUT,
        }
    }
}

/// How the ranks of a group connect: rank 0 makes the group's id, every rank joins with it.
pub trait Engine: Sync {
    fn id(&self) -> Result<Vec<u8>, TrainError>;
    /// Rank `rank`'s communicator on `device`. Every rank calls it at once (NCCL's setup
    /// waits for all).
    fn join(
        &self,
        rank: usize,
        size: usize,
        device: &Device,
        id: &[u8],
    ) -> Result<Box<dyn Communicator>, TrainError>;
}

/// A CPU group's handles, each taken once by its rank's thread.
struct CpuEngine(std::sync::Mutex<Vec<Option<cpu::CpuComm>>>);

impl Engine for CpuEngine {
    fn id(&self) -> Result<Vec<u8>, TrainError> {
        Ok(Vec::new())
    }

    fn join(
        &self,
        rank: usize,
        _: usize,
        _: &Device,
        _: &[u8],
    ) -> Result<Box<dyn Communicator>, TrainError> {
        let mut handles = self.0.lock().unwrap_or_else(|e| e.into_inner());
        let comm = handles
            .get_mut(rank)
            .and_then(Option::take)
            .ok_or_else(|| TrainError::Config(format!("rank {rank} joined twice")))?;
        Ok(Box::new(comm))
    }
}

/// NCCL: rank 0's unique id, carried to every rank.
#[cfg(feature = "nccl")]
pub struct NcclEngine {
    pub timeout: Duration,
}

#[cfg(feature = "nccl")]
impl Engine for NcclEngine {
    fn id(&self) -> Result<Vec<u8>, TrainError> {
        Ok(super::nccl::NcclId::new()?.0.to_vec())
    }

    fn join(
        &self,
        rank: usize,
        size: usize,
        device: &Device,
        id: &[u8],
    ) -> Result<Box<dyn Communicator>, TrainError> {
        let id: [u8; 128] = id.try_into().map_err(|_| {
            TrainError::Config(format!("NCCL's id has 128 bytes, not {}", id.len()))
        })?;
        Ok(Box::new(super::nccl::NcclComm::join(
            device,
            rank,
            size,
            super::nccl::NcclId(id),
            self.timeout,
        )?))
    }
}

/// The engine for a group on `devices`: CPU threads for CPUs, NCCL for CUDA devices.
fn engine_for(devices: &[Device], opts: &GroupOptions) -> Result<Box<dyn Engine>, TrainError> {
    if devices.iter().all(Device::is_cpu) {
        return Ok(Box::new(CpuEngine(std::sync::Mutex::new(
            cpu::group(devices.len(), opts.timeout)
                .into_iter()
                .map(Some)
                .collect(),
        ))));
    }
    if devices.iter().all(Device::is_cuda) {
        #[cfg(feature = "nccl")]
        return Ok(Box::new(NcclEngine {
            timeout: opts.timeout,
        }));
        #[cfg(not(feature = "nccl"))]
        return Err(TrainError::Config(
            "several CUDA devices need NCCL: a binary built with the `nccl` feature".into(),
        ));
    }
    Err(TrainError::Config(format!(
        "the devices of a group must all be CPUs or all CUDA devices, not {devices:?}"
    )))
}

/// The checks of [`crate::train::train_run`] on a request, before anything is written.
fn check_request(req: &TrainRequest, size: usize) -> Result<(), TrainError> {
    if size == 0 {
        return Err(TrainError::Config(
            "a group needs at least one device".into(),
        ));
    }
    // A new run's settings are known here: refused before anything is created (a resumed
    // run's come from its checkpoint and are checked when the ranks join).
    if let Some(run) = &req.run {
        crate::train::trainer::check_group(&run.train, size)?;
    }
    if let Some(m) = req.minutes {
        let max = crate::train::MAX_MINUTES;
        if !(m.is_finite() && m > 0.0 && m <= max) {
            return Err(TrainError::Config(format!(
                "minutes must be finite and in (0, {max}], found {}",
                pma_data::error::short_number(m)
            )));
        }
    }
    Ok(())
}

/// One rank's session: join the group, build the trainer, train.
fn rank_run(
    (rank, size): (usize, usize),
    device: &Device,
    (engine, id): (&dyn Engine, &[u8]),
    req: &TrainRequest,
    prepared: &mut Prepared,
    observer: &mut dyn TrainObserver,
) -> Result<TrainOutcome, TrainError> {
    let comm = engine.join(rank, size, device, id)?;
    let mut trainer = prepared.trainer(req, device)?;
    let ordered = prepared.run.numerics.deterministic;
    trainer.join_group(Group::new(comm, ordered))?;
    prepared.session(req, trainer, observer)?.run()
}

/// The run's result from every rank's: rank 0's outcome when all succeeded, otherwise the
/// first error that is a rank's own (not the group's report of another rank leaving),
/// named by its rank unless it is rank 0's.
fn combine(
    size: usize,
    results: Vec<Result<TrainOutcome, TrainError>>,
) -> Result<TrainOutcome, TrainError> {
    let own = |e: &TrainError| !matches!(e, TrainError::Group(GroupError::Left { .. }));
    let first = results
        .iter()
        .position(|r| r.as_ref().is_err_and(own))
        .or_else(|| results.iter().position(Result::is_err));
    let mut results = results;
    match first {
        None => results.swap_remove(0),
        Some(0) => results.swap_remove(0),
        Some(rank) => Err(TrainError::Rank {
            rank,
            size,
            source: Box::new(results.swap_remove(rank).expect_err("an error")),
        }),
    }
}

/// Train `req` on a group of `devices` in this process, one thread per device, rank r on
/// `devices[r]` (`req.device` is not used). Reports to `observer` as [`crate::train::train_run`]
/// does (rank 0's view). Interruption checks are held for the run (see [`super`]): a signal
/// stops every rank after the same step, with one checkpoint.
pub fn train_group(
    req: &TrainRequest,
    devices: &[Device],
    opts: &GroupOptions,
    observer: &mut dyn TrainObserver,
) -> Result<TrainOutcome, TrainError> {
    let size = devices.len();
    check_request(req, size)?;
    let engine = engine_for(devices, opts)?;
    pma_data::fsio::create_dir_all(&req.out)
        .map_err(|e| pma_data::FileError::write(&req.out, e))?;
    let lock = RunLock::acquire(&req.out)?;
    let _hold = crate::interrupt::hold();
    let mut prepared = match prepare(req, observer, Role::Writer) {
        Ok(p) => p,
        Err(e) => {
            lock.remove();
            return Err(e);
        }
    };
    let id = engine.id()?;
    let results = std::thread::scope(|s| {
        let followers: Vec<_> = (1..size)
            .map(|rank| {
                let mut mine = prepared.follower();
                let (engine, id, device) = (engine.as_ref(), &id, &devices[rank]);
                std::thread::Builder::new()
                    .name(format!("rank-{rank}"))
                    .spawn_scoped(s, move || {
                        rank_run(
                            (rank, size),
                            device,
                            (engine, id),
                            req,
                            &mut mine,
                            &mut Silent,
                        )
                    })
            })
            .collect();
        let mut results = vec![rank_run(
            (0, size),
            &devices[0],
            (engine.as_ref(), &id),
            req,
            &mut prepared,
            observer,
        )];
        for (i, f) in followers.into_iter().enumerate() {
            results.push(match f {
                Ok(handle) => handle.join().unwrap_or_else(|_| {
                    Err(GroupError::Left {
                        rank: i + 1,
                        size,
                        why: "it panicked".into(),
                    }
                    .into())
                }),
                Err(e) => {
                    Err(GroupError::Engine(format!("cannot start rank {}: {e}", i + 1)).into())
                }
            });
        }
        results
    });
    drop(lock);
    combine(size, results)
}

/// Train `req` as one rank of a group of processes started by a launcher, on `device`.
/// Rank 0 holds the lock, prepares the run and posts the group's id (from `engine`) in
/// `rendezvous`, which it removes at the end; the other ranks wait for it (at most the
/// group's timeout) and prepare after it, reading only. A refusal of rank 0 (the run
/// directory locked, a run already there) is posted too, and every rank ends with it.
pub fn train_launched(
    req: &TrainRequest,
    launch: &Launch,
    rendezvous: &Path,
    engine: &dyn Engine,
    opts: &GroupOptions,
    observer: &mut dyn TrainObserver,
) -> Result<TrainOutcome, TrainError> {
    let (rank, size) = (launch.rank, launch.size);
    check_request(req, size)?;
    let _hold = crate::interrupt::hold();
    if rank != 0 {
        let id = match launch::wait(rendezvous, opts.timeout)? {
            Posted::Ready { size: s, payload } if s == size => payload,
            Posted::Ready { size: s, .. } => {
                return Err(TrainError::Config(format!(
                    "{}: rank 0 started a group of {s}, this rank's launcher says {size}",
                    rendezvous.display()
                )))
            }
            Posted::Refused(why) => {
                return Err(TrainError::Config(format!("rank 0 refused the run: {why}")))
            }
        };
        let mut prepared = prepare(req, &mut Silent, Role::Follower)?;
        return rank_run(
            (rank, size),
            &req.device,
            (engine, &id),
            req,
            &mut prepared,
            observer,
        );
    }
    let refuse = |e: TrainError| {
        let _ = launch::publish(rendezvous, &Posted::Refused(e.to_string()));
        e
    };
    pma_data::fsio::create_dir_all(&req.out)
        .map_err(|e| refuse(pma_data::FileError::write(&req.out, e).into()))?;
    let lock = RunLock::acquire(&req.out).map_err(refuse)?;
    let started = prepare(req, observer, Role::Writer).and_then(|p| Ok((p, engine.id()?)));
    let (mut prepared, id) = match started {
        Ok(x) => x,
        Err(e) => {
            lock.remove();
            return Err(refuse(e));
        }
    };
    launch::publish(
        rendezvous,
        &Posted::Ready {
            size,
            payload: id.clone(),
        },
    )?;
    let _posted = RemoveOnDrop(rendezvous.to_path_buf());
    rank_run(
        (0, size),
        &req.device,
        (engine, &id),
        req,
        &mut prepared,
        observer,
    )
}

/// Removes the rendezvous file when rank 0's run ends (every rank has read it by then: the
/// group's first exchange needs them all).
struct RemoveOnDrop(PathBuf);

impl Drop for RemoveOnDrop {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

/// The CPU engine of a group of `size` threads standing for processes (tests of
/// [`train_launched`]).
pub fn cpu_engine(size: usize, opts: &GroupOptions) -> impl Engine {
    CpuEngine(std::sync::Mutex::new(
        cpu::group(size, opts.timeout)
            .into_iter()
            .map(Some)
            .collect(),
    ))
}
