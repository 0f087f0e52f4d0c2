//! NCCL's communicator (feature `nccl`): one rank per GPU, in one process (a thread per GPU)
//! or one process per GPU. The collectives go on the stream candle's device uses, so they
//! are ordered with the step's kernels and nothing waits on the host.
//!
//! NCCL has no timeout of its own: a peer that dies mid-collective can leave the others'
//! kernels spinning. A watchdog thread per rank polls `ncclCommGetAsyncError` and the event
//! recorded after each collective; on an asynchronous error, or a collective still running
//! after the group timeout, it aborts the communicator (`ncclCommAbort` ends its kernels)
//! and the rank stops with [`GroupError`] at its next exchange or read-back.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use candle_core::backend::BackendStorage;
use candle_core::cuda_backend::cudarc::driver::{CudaEvent, CudaStream, DevicePtr, DevicePtrMut};
use candle_core::cuda_backend::cudarc::nccl::{result, sys};
use candle_core::{CudaStorage, DType, Device, Layout};

use super::comm::{Communicator, Kind};
use super::error::GroupError;

/// NCCL's unique id of a group: rank 0 makes it, every rank joins with it.
#[derive(Clone, Copy)]
pub struct NcclId(pub [u8; 128]);

impl NcclId {
    /// A new id (rank 0).
    pub fn new() -> Result<Self, GroupError> {
        let id = result::get_uniqueid().map_err(|e| engine("ncclGetUniqueId", e))?;
        Ok(Self(id.internal.map(|c| c as u8)))
    }

    fn raw(&self) -> sys::ncclUniqueId {
        sys::ncclUniqueId {
            internal: self.0.map(|b| b as ::core::ffi::c_char),
        }
    }
}

fn engine(call: &str, e: result::NcclError) -> GroupError {
    GroupError::Engine(format!("NCCL: {call} failed ({:?})", e.0))
}

/// The raw communicator, handed between threads only under [`Inner::comm`]'s lock.
struct Raw(sys::ncclComm_t);

// SAFETY: NCCL communicators may be used from any thread as long as calls on one are not
// concurrent; every use goes through the `Mutex` that holds it.
unsafe impl Send for Raw {}

/// What the rank's thread and its watchdog share.
struct Inner {
    rank: usize,
    size: usize,
    timeout: Duration,
    /// `None` once aborted.
    comm: Mutex<Option<Raw>>,
    broken: Mutex<Option<GroupError>>,
    /// An event recorded after each collective still running, oldest first.
    running: Mutex<Vec<(Instant, CudaEvent)>>,
    stop: AtomicBool,
}

impl Inner {
    /// Abort the communicator for `why` (once; the first reason is kept).
    fn abort(&self, why: GroupError) {
        let mut broken = self.broken.lock().unwrap_or_else(|e| e.into_inner());
        broken.get_or_insert(why);
        if let Some(raw) = self.comm.lock().unwrap_or_else(|e| e.into_inner()).take() {
            // SAFETY: the communicator is live (taken out of the lock) and used by no one
            // else; abort ends its kernels and frees it.
            let _ = unsafe { result::comm_abort(raw.0) };
        }
    }

    /// One look: an asynchronous error, or the oldest collective past the timeout.
    fn watch(&self) {
        let err = {
            let comm = self.comm.lock().unwrap_or_else(|e| e.into_inner());
            let Some(raw) = comm.as_ref() else {
                return;
            };
            let mut state = sys::ncclResult_t::ncclSuccess;
            // SAFETY: a live communicator; NCCL allows this query from another thread.
            let _ = unsafe { sys::ncclCommGetAsyncError(raw.0, &mut state) };
            state
        };
        if !matches!(
            err,
            sys::ncclResult_t::ncclSuccess | sys::ncclResult_t::ncclInProgress
        ) {
            self.abort(GroupError::Engine(format!(
                "NCCL reported {err:?} on rank {} of {} (a peer failed or the network did)",
                self.rank, self.size
            )));
            return;
        }
        let mut running = self.running.lock().unwrap_or_else(|e| e.into_inner());
        running.retain(|(_, ev)| !ev.is_complete());
        let late = running
            .first()
            .is_some_and(|(since, _)| since.elapsed() > self.timeout);
        drop(running);
        if late {
            self.abort(GroupError::Timeout {
                rank: self.rank,
                size: self.size,
                secs: self.timeout.as_secs(),
            });
        }
    }
}

/// One rank of an NCCL group.
pub struct NcclComm {
    inner: Arc<Inner>,
    stream: Arc<CudaStream>,
    watchdog: Option<std::thread::JoinHandle<()>>,
}

impl NcclComm {
    /// Join the group `id` as `rank` of `size` on `device` (a CUDA device). Every rank must
    /// call it (NCCL's setup waits for all); waits at most `timeout` for the others.
    pub fn join(
        device: &Device,
        rank: usize,
        size: usize,
        id: NcclId,
        timeout: Duration,
    ) -> Result<Self, GroupError> {
        let Device::Cuda(cuda) = device else {
            return Err(GroupError::Engine(format!(
                "NCCL needs a CUDA device, not {device:?}"
            )));
        };
        let stream = cuda.cuda_stream();
        let ctx = stream.context().clone();
        let (tx, rx) = std::sync::mpsc::channel();
        // Setup blocks until every rank has joined; a helper thread lets this one give up.
        std::thread::Builder::new()
            .name(format!("nccl-init-{rank}"))
            .spawn(move || {
                let out = ctx
                    .bind_to_thread()
                    .map_err(|e| GroupError::Engine(format!("CUDA: {e}")))
                    .and_then(|()| {
                        let mut comm = std::mem::MaybeUninit::uninit();
                        // SAFETY: `comm` is written by NCCL on success.
                        unsafe {
                            result::comm_init_rank(
                                comm.as_mut_ptr(),
                                size as i32,
                                id.raw(),
                                rank as i32,
                            )
                            .map_err(|e| engine("ncclCommInitRank", e))?;
                            Ok(Raw(comm.assume_init()))
                        }
                    });
                let _ = tx.send(out);
            })
            .map_err(|e| GroupError::Engine(format!("cannot start NCCL's setup thread: {e}")))?;
        let raw = match rx.recv_timeout(timeout) {
            Ok(r) => r?,
            Err(_) => {
                return Err(GroupError::Timeout {
                    rank,
                    size,
                    secs: timeout.as_secs(),
                })
            }
        };
        let inner = Arc::new(Inner {
            rank,
            size,
            timeout,
            comm: Mutex::new(Some(raw)),
            broken: Mutex::new(None),
            running: Mutex::new(Vec::new()),
            stop: AtomicBool::new(false),
        });
        let watched = inner.clone();
        let watchdog = std::thread::Builder::new()
            .name(format!("nccl-watchdog-{rank}"))
            .spawn(move || {
                while !watched.stop.load(Ordering::Relaxed) {
                    watched.watch();
                    std::thread::sleep(Duration::from_millis(200));
                }
            })
            .map_err(|e| GroupError::Engine(format!("cannot start NCCL's watchdog: {e}")))?;
        Ok(Self {
            inner,
            stream,
            watchdog: Some(watchdog),
        })
    }

    fn launch<T: candle_core::cuda_backend::cudarc::driver::DeviceRepr>(
        &self,
        kind: Kind,
        src: &impl DevicePtr<T>,
        dst: &mut impl DevicePtrMut<T>,
        count: usize,
        dtype: sys::ncclDataType_t,
    ) -> Result<(), GroupError> {
        self.health()?;
        let comm = self.inner.comm.lock().unwrap_or_else(|e| e.into_inner());
        let Some(raw) = comm.as_ref() else {
            drop(comm);
            return self.health();
        };
        let stream = &self.stream;
        let (s, _read) = src.device_ptr(stream);
        let (d, _write) = dst.device_ptr_mut(stream);
        let cu_stream = stream.cu_stream() as sys::cudaStream_t;
        // SAFETY: live communicator (under its lock), device buffers of `count` (send) and
        // `count` or `size · count` (receive) elements on this rank's stream.
        unsafe {
            match kind {
                Kind::Sum => result::all_reduce(
                    s as _,
                    d as _,
                    count,
                    dtype,
                    sys::ncclRedOp_t::ncclSum,
                    raw.0,
                    cu_stream,
                ),
                Kind::Gather => result::all_gather(s as _, d as _, count, dtype, raw.0, cu_stream),
            }
        }
        .map_err(|e| engine("the collective", e))?;
        let ev = stream
            .record_event(None)
            .map_err(|e| GroupError::Engine(format!("CUDA: {e}")))?;
        self.inner
            .running
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push((Instant::now(), ev));
        Ok(())
    }
}

impl Communicator for NcclComm {
    fn rank(&self) -> usize {
        self.inner.rank
    }

    fn size(&self) -> usize {
        self.inner.size
    }

    fn engine(&self) -> &'static str {
        "NCCL"
    }

    fn cuda(&self, kind: Kind, s: &CudaStorage, l: &Layout) -> candle_core::Result<CudaStorage> {
        let n = l.shape().elem_count();
        let start = l.start_offset();
        let out = match kind {
            Kind::Sum => n,
            Kind::Gather => n * self.inner.size,
        };
        let dev = s.device().clone();
        macro_rules! exchange {
            ($t:ty, $nccl:expr) => {{
                let src = s.as_cuda_slice::<$t>()?.slice(start..start + n);
                // SAFETY: every element is written by the collective before it is read.
                let mut dst = unsafe { dev.alloc::<$t>(out) }?;
                self.launch(kind, &src, &mut dst, n, $nccl)
                    .map_err(candle_core::Error::wrap)?;
                CudaStorage::wrap_cuda_slice(dst, dev)
            }};
        }
        Ok(match s.dtype() {
            DType::F32 => exchange!(f32, sys::ncclDataType_t::ncclFloat32),
            DType::F64 => exchange!(f64, sys::ncclDataType_t::ncclFloat64),
            d => candle_core::bail!("NCCL exchange: f32 or f64 buffers, not {d:?}"),
        })
    }

    fn health(&self) -> Result<(), GroupError> {
        match &*self.inner.broken.lock().unwrap_or_else(|e| e.into_inner()) {
            Some(e) => Err(e.clone()),
            None => Ok(()),
        }
    }
}

impl Drop for NcclComm {
    fn drop(&mut self) {
        self.inner.stop.store(true, Ordering::Relaxed);
        if let Some(w) = self.watchdog.take() {
            let _ = w.join();
        }
        // Peers still waiting for this rank learn it left from their own watchdogs.
        self.inner.abort(GroupError::Left {
            rank: self.inner.rank,
            size: self.inner.size,
            why: "it stopped".into(),
        });
    }
}
