//! The CPU group: the ranks are threads of one process and exchange host buffers. It is the
//! test double of NCCL (`pma train --device cpu,cpu`, the data-parallel tests), not a way to
//! train faster: the ranks share the machine's cores.
//!
//! An exchange is a round: each rank leaves its buffer and waits; the last to arrive combines
//! the buffers and wakes the others. A sum adds each segment of the buffer in ring order
//! (segment s starts at rank s + 1 and ends at rank s, the order a ring all-reduce takes),
//! not in rank order: like NCCL's, it is fixed for a given group size but is not the order a
//! single device sums chunks in. A rank whose handle drops (its thread ended, by an error or a
//! panic) leaves the group: every rank waiting for it, or arriving later, fails with
//! [`GroupError::Left`]. A round that does not complete within the timeout fails with
//! [`GroupError::Timeout`].

use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use super::comm::{Communicator, HostBuf, Kind};
use super::error::GroupError;

/// One rank's handle of a CPU group (see the module docs).
pub struct CpuComm {
    rank: usize,
    shared: Arc<Shared>,
}

struct Shared {
    size: usize,
    timeout: Duration,
    state: Mutex<State>,
    woken: Condvar,
}

#[derive(Default)]
struct State {
    /// Completed rounds.
    round: u64,
    /// This round's buffers by rank.
    bufs: Vec<Option<HostBuf>>,
    kind: Option<Kind>,
    /// The last completed round's result, for the ranks that have not read it yet.
    result: Option<Result<HostBuf, GroupError>>,
    /// The first failure; every later exchange fails with it.
    broken: Option<GroupError>,
    /// Why each rank left, once its handle dropped.
    left: Vec<Option<&'static str>>,
}

/// `size` handles of one new CPU group, rank order; an exchange waits at most `timeout` for
/// the others.
pub fn group(size: usize, timeout: Duration) -> Vec<CpuComm> {
    let shared = Arc::new(Shared {
        size,
        timeout,
        state: Mutex::new(State {
            bufs: vec![None; size],
            left: vec![None; size],
            ..Default::default()
        }),
        woken: Condvar::new(),
    });
    (0..size)
        .map(|rank| CpuComm {
            rank,
            shared: shared.clone(),
        })
        .collect()
}

impl CpuComm {
    fn lock(&self) -> MutexGuard<'_, State> {
        self.shared.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Mark the group broken by `e` (the first failure wins) and wake every waiting rank.
    fn fail(&self, state: &mut State, e: GroupError) -> GroupError {
        let e = state.broken.get_or_insert(e).clone();
        self.shared.woken.notify_all();
        e
    }
}

impl Communicator for CpuComm {
    fn rank(&self) -> usize {
        self.rank
    }

    fn size(&self) -> usize {
        self.shared.size
    }

    fn engine(&self) -> &'static str {
        "CPU threads"
    }

    fn host(&self, kind: Kind, buf: HostBuf) -> Result<HostBuf, GroupError> {
        let size = self.shared.size;
        let mut state = self.lock();
        if let Some(e) = &state.broken {
            return Err(e.clone());
        }
        if state.kind.is_some_and(|k| k != kind) {
            let e = GroupError::Disagree(format!(
                "rank {} asked for a {kind:?} while others asked for a {:?}",
                self.rank,
                state.kind.expect("checked")
            ));
            return Err(self.fail(&mut state, e));
        }
        state.kind = Some(kind);
        state.bufs[self.rank] = Some(buf);
        let round = state.round;
        if state.bufs.iter().all(Option::is_some) {
            let bufs: Vec<HostBuf> = state
                .bufs
                .iter_mut()
                .map(|b| b.take().expect("all in"))
                .collect();
            let result = combine(kind, bufs);
            if let Err(e) = &result {
                self.fail(&mut state, e.clone());
            }
            state.result = Some(result);
            state.kind = None;
            state.round += 1;
            self.shared.woken.notify_all();
        }
        let deadline = Instant::now() + self.shared.timeout;
        while state.round == round {
            if let Some(e) = &state.broken {
                return Err(e.clone());
            }
            // A rank that left cannot bring its buffer: this round never completes.
            let gone = (0..size).find(|&r| state.bufs[r].is_none() && state.left[r].is_some());
            if let Some(r) = gone {
                let e = GroupError::Left {
                    rank: r,
                    size,
                    why: state.left[r].unwrap_or("it stopped").to_string(),
                };
                return Err(self.fail(&mut state, e));
            }
            let now = Instant::now();
            if now >= deadline {
                let e = GroupError::Timeout {
                    rank: self.rank,
                    size,
                    secs: self.shared.timeout.as_secs(),
                };
                return Err(self.fail(&mut state, e));
            }
            state = self
                .shared
                .woken
                .wait_timeout(state, deadline - now)
                .unwrap_or_else(|e| e.into_inner())
                .0;
        }
        // The next round cannot complete before this rank arrives again, so the result is
        // still this round's.
        state
            .result
            .clone()
            .expect("a completed round has a result")
    }

    fn health(&self) -> Result<(), GroupError> {
        match &self.lock().broken {
            Some(e) => Err(e.clone()),
            None => Ok(()),
        }
    }
}

impl Drop for CpuComm {
    fn drop(&mut self) {
        let why = if std::thread::panicking() {
            "it panicked"
        } else {
            "it stopped"
        };
        let mut state = self.lock();
        // Leaving only matters to a round this rank would have to join: a rank that leaves
        // at the end of a run, when no one waits for it, breaks nothing (the others may
        // still read back what the group exchanged).
        state.left[self.rank] = Some(why);
        self.shared.woken.notify_all();
    }
}

/// The result of a round: the sum in ring order, or the buffers in rank order.
fn combine(kind: Kind, bufs: Vec<HostBuf>) -> Result<HostBuf, GroupError> {
    let n = bufs[0].len();
    let same = bufs
        .iter()
        .all(|b| b.len() == n && std::mem::discriminant(b) == std::mem::discriminant(&bufs[0]));
    if !same {
        let lens: Vec<usize> = bufs.iter().map(HostBuf::len).collect();
        return Err(GroupError::Disagree(format!(
            "buffers of different lengths or dtypes in one exchange: {lens:?}"
        )));
    }
    Ok(match (kind, &bufs[0]) {
        (Kind::Sum, HostBuf::F32(_)) => HostBuf::F32(ring_sum(&bufs, |b| match b {
            HostBuf::F32(v) => v.as_slice(),
            HostBuf::F64(_) => unreachable!("dtypes checked"),
        })),
        (Kind::Sum, HostBuf::F64(_)) => HostBuf::F64(ring_sum(&bufs, |b| match b {
            HostBuf::F64(v) => v.as_slice(),
            HostBuf::F32(_) => unreachable!("dtypes checked"),
        })),
        (Kind::Gather, HostBuf::F32(_)) => HostBuf::F32(
            bufs.into_iter()
                .flat_map(|b| match b {
                    HostBuf::F32(v) => v,
                    HostBuf::F64(_) => unreachable!("dtypes checked"),
                })
                .collect(),
        ),
        (Kind::Gather, HostBuf::F64(_)) => HostBuf::F64(
            bufs.into_iter()
                .flat_map(|b| match b {
                    HostBuf::F64(v) => v,
                    HostBuf::F32(_) => unreachable!("dtypes checked"),
                })
                .collect(),
        ),
    })
}

/// Element-wise sum of the ranks' buffers, segment s (of `size` near-equal segments) summed
/// from rank s + 1 round to rank s.
fn ring_sum<T: Copy + std::ops::Add<Output = T>>(
    bufs: &[HostBuf],
    view: impl Fn(&HostBuf) -> &[T],
) -> Vec<T> {
    let size = bufs.len();
    let n = view(&bufs[0]).len();
    let mut out = Vec::with_capacity(n);
    for s in 0..size {
        let (lo, hi) = (s * n / size, (s + 1) * n / size);
        for i in lo..hi {
            let first = (s + 1) % size;
            let mut acc = view(&bufs[first])[i];
            for k in 2..=size {
                acc = acc + view(&bufs[(s + k) % size])[i];
            }
            out.push(acc);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run<T: Send>(comms: Vec<CpuComm>, f: impl Fn(&CpuComm) -> T + Sync) -> Vec<T> {
        std::thread::scope(|s| {
            let handles: Vec<_> = comms
                .into_iter()
                .map(|c| {
                    let f = &f;
                    s.spawn(move || f(&c))
                })
                .collect();
            handles.into_iter().map(|h| h.join().unwrap()).collect()
        })
    }

    #[test]
    fn sums_in_ring_order_and_gathers_in_rank_order() {
        // Values whose f32 sum depends on the order: 1e8 + 1 − 1e8 + 1.
        let vals = [1e8f32, 1.0, -1e8, 1.0];
        let out = run(group(4, Duration::from_secs(10)), |c| {
            let mine = vec![vals[c.rank()]; 8];
            let sum = c.host(Kind::Sum, HostBuf::F32(mine.clone())).unwrap();
            let gathered = c.host(Kind::Gather, HostBuf::F32(mine)).unwrap();
            (sum, gathered)
        });
        let ring = |s: usize| {
            let mut acc = vals[(s + 1) % 4];
            for k in 2..=4 {
                acc += vals[(s + k) % 4];
            }
            acc
        };
        // Two elements per segment; every rank gets the same bits.
        let want: Vec<f32> = (0..8).map(|i| ring(i / 2)).collect();
        let rank_order = ((vals[0] + vals[1]) + vals[2]) + vals[3];
        assert!(want.iter().any(|&v| v != rank_order), "{want:?}");
        for (sum, gathered) in &out {
            assert_eq!(sum, &HostBuf::F32(want.clone()));
            let g: Vec<f32> = vals.iter().flat_map(|&v| [v; 8]).collect();
            assert_eq!(gathered, &HostBuf::F32(g));
        }
    }

    #[test]
    fn a_rank_that_leaves_stops_the_others_and_a_silent_one_times_out() {
        let out = run(group(3, Duration::from_secs(30)), |c| {
            if c.rank() == 2 {
                return Ok(HostBuf::F64(vec![]));
            }
            c.host(Kind::Sum, HostBuf::F64(vec![1.0]))
        });
        // Rank 2's handle dropped when its thread ended without exchanging.
        for r in &out[..2] {
            match r {
                Err(GroupError::Left {
                    rank: 2, size: 3, ..
                }) => {}
                other => panic!("{other:?}"),
            }
        }

        let start = Instant::now();
        let mut comms = group(2, Duration::from_millis(200));
        let silent = comms.pop().unwrap();
        let e = comms[0]
            .host(Kind::Sum, HostBuf::F32(vec![1.0]))
            .unwrap_err();
        assert!(
            matches!(
                e,
                GroupError::Timeout {
                    rank: 0,
                    size: 2,
                    ..
                }
            ),
            "{e}"
        );
        assert!(start.elapsed() < Duration::from_secs(5));
        assert_eq!(silent.health(), Err(e));

        // A rank that leaves after the last exchange breaks nothing for the others.
        let out: Vec<Result<HostBuf, GroupError>> = run(group(2, Duration::from_secs(30)), |c| {
            let sum = c.host(Kind::Sum, HostBuf::F32(vec![1.0]))?;
            if c.rank() == 0 {
                std::thread::sleep(Duration::from_millis(200));
                c.health()?;
            }
            Ok(sum)
        });
        assert_eq!(out, vec![Ok(HostBuf::F32(vec![2.0])); 2]);
    }

    #[test]
    fn buffers_that_differ_are_refused_on_every_rank() {
        let out = run(group(2, Duration::from_secs(10)), |c| {
            c.host(Kind::Sum, HostBuf::F32(vec![0.0; 2 + c.rank()]))
        });
        for r in out {
            assert!(matches!(r, Err(GroupError::Disagree(_))), "{r:?}");
        }
    }
}
