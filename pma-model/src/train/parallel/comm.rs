//! What a data-parallel rank needs from its group: a [`Communicator`], which sums or gathers
//! one buffer across the ranks. Its exchange runs as a candle op ([`Exchange`]), dispatched
//! like any kernel on the tensor's device and counted by step accounting (one op, one
//! launch, and the collective itself, [`crate::compute::account::record_collective`]).
//!
//! Two implementations: the CPU group (`cpu`: ranks are threads of one process, the exchange
//! runs over host buffers) is the test double of NCCL (`nccl`, feature `nccl`: one rank per
//! GPU, in one process or many). The trainer sees only this trait.

use candle_core::backend::BackendStorage;
use candle_core::{CpuStorage, CustomOp1, Layout, Shape, Tensor};

use super::error::GroupError;
use crate::compute::account::{record_collective, Collective};
use crate::train::TrainError;

/// What an [`Exchange`] does with the ranks' buffers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// Every rank gets the element-wise sum of all ranks' buffers (in an order the engine
    /// picks).
    Sum,
    /// Every rank gets all ranks' buffers stacked in rank order: `[size, n]`.
    Gather,
}

/// A host buffer in an exchange: the dtypes the trainer exchanges.
#[derive(Debug, Clone, PartialEq)]
pub enum HostBuf {
    F32(Vec<f32>),
    F64(Vec<f64>),
}

impl HostBuf {
    pub fn len(&self) -> usize {
        match self {
            HostBuf::F32(v) => v.len(),
            HostBuf::F64(v) => v.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// One rank's view of its data-parallel group.
pub trait Communicator {
    /// This rank, `0..size`.
    fn rank(&self) -> usize;
    /// Ranks in the group.
    fn size(&self) -> usize;
    /// The engine, for messages (`CPU threads`, `NCCL`).
    fn engine(&self) -> &'static str;
    /// The exchange of host buffers (every rank's has the same length and dtype).
    fn host(&self, kind: Kind, buf: HostBuf) -> Result<HostBuf, GroupError> {
        let _ = (kind, buf);
        Err(GroupError::Engine(format!(
            "{} exchanges device buffers, not host ones",
            self.engine()
        )))
    }
    /// The exchange of a contiguous CUDA buffer on this rank's device.
    #[cfg(feature = "cuda")]
    fn cuda(
        &self,
        kind: Kind,
        storage: &candle_core::CudaStorage,
        layout: &Layout,
    ) -> candle_core::Result<candle_core::CudaStorage> {
        let _ = (kind, storage, layout);
        candle_core::bail!("{} exchanges host buffers, not CUDA ones", self.engine())
    }
    /// `Ok` while the group is whole; the first failure seen otherwise. A rank calls it after
    /// every failed exchange and after reading back results that depend on exchanges.
    fn health(&self) -> Result<(), GroupError>;
}

/// An exchange as a candle op on one rank's buffer.
pub struct Exchange<'a> {
    comm: &'a dyn Communicator,
    kind: Kind,
}

impl Exchange<'_> {
    /// The exchange of `t` (f32 or f64) with the group of `comm`: [`Kind::Sum`] keeps `t`'s
    /// shape, [`Kind::Gather`] puts the ranks in front. A failure is the group's when the
    /// group is broken (every rank then reports why), the op's otherwise.
    pub fn run(comm: &dyn Communicator, kind: Kind, t: &Tensor) -> Result<Tensor, TrainError> {
        let t = t.contiguous()?;
        match t.apply_op1_no_bwd(&Exchange { comm, kind }) {
            Ok(out) => Ok(out),
            Err(e) => Err(match comm.health() {
                Err(g) => g.into(),
                Ok(()) => e.into(),
            }),
        }
    }

    fn shape(&self, l: &Layout) -> Shape {
        match self.kind {
            Kind::Sum => l.shape().clone(),
            Kind::Gather => {
                let mut dims = vec![self.comm.size()];
                dims.extend(l.dims());
                Shape::from(dims)
            }
        }
    }

    fn record(&self, l: &Layout, elem_size: usize) {
        let bytes = (l.shape().elem_count() * elem_size) as u64;
        record_collective(match self.kind {
            Kind::Sum => Collective::AllReduce { bytes },
            Kind::Gather => Collective::AllGather { bytes },
        });
    }
}

impl CustomOp1 for Exchange<'_> {
    fn name(&self) -> &'static str {
        match self.kind {
            Kind::Sum => "all-reduce",
            Kind::Gather => "all-gather",
        }
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
        let Some((start, end)) = l.contiguous_offsets() else {
            candle_core::bail!("{}: a contiguous buffer expected", self.name())
        };
        let buf = match s {
            CpuStorage::F32(v) => HostBuf::F32(v[start..end].to_vec()),
            CpuStorage::F64(v) => HostBuf::F64(v[start..end].to_vec()),
            other => candle_core::bail!(
                "{}: f32 or f64 buffers are exchanged, not {:?}",
                self.name(),
                other.dtype()
            ),
        };
        self.record(l, s.dtype().size_in_bytes());
        let out = self
            .comm
            .host(self.kind, buf)
            .map_err(candle_core::Error::wrap)?;
        let storage = match out {
            HostBuf::F32(v) => CpuStorage::F32(v),
            HostBuf::F64(v) => CpuStorage::F64(v),
        };
        Ok((storage, self.shape(l)))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s: &candle_core::CudaStorage,
        l: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        if !l.is_contiguous() {
            candle_core::bail!("{}: a contiguous buffer expected", self.name())
        }
        self.record(l, s.dtype().size_in_bytes());
        Ok((self.comm.cuda(self.kind, s, l)?, self.shape(l)))
    }
}
