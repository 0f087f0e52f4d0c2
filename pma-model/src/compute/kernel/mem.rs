//! The memory a device kernel reads and writes: a GPU's, or, on the emulated grid, host
//! memory standing in for it. An op's device code is written once against these types and
//! runs on both ([`super::launch::launch`]).

use candle_core::backend::BackendStorage;
use candle_core::{CpuStorage, Device, Layout, Storage};

#[cfg(feature = "cuda")]
use candle_core::cuda_backend::cudarc::driver::{CudaSlice, CudaView};
#[cfg(feature = "cuda")]
use candle_core::cuda_backend::CudaDevice;
#[cfg(feature = "cuda")]
use candle_core::CudaStorage;

/// Where device kernels run.
#[derive(Clone)]
pub enum Exec {
    /// On the host, over an emulated grid (a CPU run that takes the CUDA route).
    Emulated,
    #[cfg(feature = "cuda")]
    Cuda(CudaDevice),
}

impl std::fmt::Debug for Exec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Exec::Emulated => f.write_str("emulated"),
            #[cfg(feature = "cuda")]
            Exec::Cuda(_) => f.write_str("cuda"),
        }
    }
}

impl Exec {
    /// The executor of a GPU device (`None` for the CPU and devices without pma kernels).
    pub fn of_device(device: &Device) -> Option<Self> {
        match device {
            #[cfg(feature = "cuda")]
            Device::Cuda(d) => Some(Exec::Cuda(d.clone())),
            _ => None,
        }
    }

    /// The device whose tensors this executor's kernels take.
    pub fn device(&self) -> Device {
        match self {
            Exec::Emulated => Device::Cpu,
            #[cfg(feature = "cuda")]
            Exec::Cuda(d) => Device::Cuda(d.clone()),
        }
    }

    /// Whether tensors of this executor live in host memory (counted as host storage by the
    /// step account).
    pub fn is_host(&self) -> bool {
        matches!(self, Exec::Emulated)
    }

    /// An f32 buffer of `len` elements that a kernel writes in full (uninitialised on a
    /// GPU: no memset).
    pub fn output(&self, len: usize) -> candle_core::Result<Buf> {
        match self {
            Exec::Emulated => Ok(Buf::F32(vec![0f32; len])),
            // SAFETY: the kernel that receives the buffer writes each of its `len` elements
            // before anything reads it (one thread per element, grid-stride).
            #[cfg(feature = "cuda")]
            Exec::Cuda(d) => Ok(Buf::CudaF32(unsafe { d.alloc::<f32>(len.max(1))? })),
        }
    }

    /// A zeroed f32 buffer of `len` elements (a memset on a GPU).
    pub fn zeros(&self, len: usize) -> candle_core::Result<Buf> {
        match self {
            Exec::Emulated => Ok(Buf::F32(vec![0f32; len])),
            #[cfg(feature = "cuda")]
            Exec::Cuda(d) => Ok(Buf::CudaF32(d.alloc_zeros::<f32>(len.max(1))?)),
        }
    }

    /// A u32 buffer of `len` elements that a kernel writes in full.
    pub fn output_u32(&self, len: usize) -> candle_core::Result<Buf> {
        match self {
            Exec::Emulated => Ok(Buf::U32(vec![0u32; len])),
            // SAFETY: as in `output`.
            #[cfg(feature = "cuda")]
            Exec::Cuda(d) => Ok(Buf::CudaU32(unsafe { d.alloc::<u32>(len.max(1))? })),
        }
    }
}

/// A buffer a kernel reads: a view of a storage from its layout's start (the caller made it
/// contiguous), or of a buffer an earlier kernel wrote.
pub enum Src<'a> {
    F32(&'a [f32]),
    U32(&'a [u32]),
    U8(&'a [u8]),
    #[cfg(feature = "cuda")]
    CudaF32(CudaView<'a, f32>),
    #[cfg(feature = "cuda")]
    CudaU32(CudaView<'a, u32>),
    #[cfg(feature = "cuda")]
    CudaU8(CudaView<'a, u8>),
}

impl<'a> Src<'a> {
    /// A contiguous CPU storage under `l` (f32, u32 or u8).
    pub fn cpu(s: &'a CpuStorage, l: &Layout, what: &str) -> candle_core::Result<Self> {
        use super::storage::slice;
        Ok(match s {
            CpuStorage::F32(_) => Src::F32(slice(s, l, what)?),
            CpuStorage::U32(_) => Src::U32(slice(s, l, what)?),
            CpuStorage::U8(_) => Src::U8(slice(s, l, what)?),
            other => candle_core::bail!(
                "{what}: a kernel takes f32, u32 or u8, not {:?}",
                other.dtype()
            ),
        })
    }

    /// A CUDA storage from `l`'s start (f32, u32 or u8).
    #[cfg(feature = "cuda")]
    pub fn cuda(s: &'a CudaStorage, l: &Layout, what: &str) -> candle_core::Result<Self> {
        use candle_core::backend::BackendStorage;
        // An empty view may start past its storage's end.
        let at = if l.shape().elem_count() == 0 {
            0
        } else {
            l.start_offset()
        };
        Ok(match s.dtype() {
            candle_core::DType::F32 => Src::CudaF32(s.as_cuda_slice::<f32>()?.slice(at..)),
            candle_core::DType::U32 => Src::CudaU32(s.as_cuda_slice::<u32>()?.slice(at..)),
            candle_core::DType::U8 => Src::CudaU8(s.as_cuda_slice::<u8>()?.slice(at..)),
            d => candle_core::bail!("{what}: a kernel takes f32, u32 or u8, not {d:?}"),
        })
    }

    /// A tensor's storage (behind `storage_and_layout`'s guard), on the CPU or on CUDA.
    pub fn of(s: &'a Storage, l: &Layout, what: &str) -> candle_core::Result<Self> {
        match s {
            Storage::Cpu(c) => Self::cpu(c, l, what),
            #[cfg(feature = "cuda")]
            Storage::Cuda(c) => Self::cuda(c, l, what),
            #[allow(unreachable_patterns)]
            _ => candle_core::bail!("{what}: pma's kernels run on CUDA or the emulated grid only"),
        }
    }
}

/// A buffer a kernel writes, then handed to candle as a storage.
pub enum Buf {
    F32(Vec<f32>),
    U32(Vec<u32>),
    #[cfg(feature = "cuda")]
    CudaF32(CudaSlice<f32>),
    #[cfg(feature = "cuda")]
    CudaU32(CudaSlice<u32>),
}

impl Buf {
    /// The buffer as a later kernel's input.
    pub fn src(&self) -> Src<'_> {
        match self {
            Buf::F32(v) => Src::F32(v),
            Buf::U32(v) => Src::U32(v),
            #[cfg(feature = "cuda")]
            Buf::CudaF32(s) => Src::CudaF32(s.slice(..)),
            #[cfg(feature = "cuda")]
            Buf::CudaU32(s) => Src::CudaU32(s.slice(..)),
        }
    }

    /// Bytes of the buffer.
    pub fn bytes(&self) -> usize {
        match self {
            Buf::F32(v) => 4 * v.len(),
            Buf::U32(v) => 4 * v.len(),
            #[cfg(feature = "cuda")]
            Buf::CudaF32(s) => 4 * s.len(),
            #[cfg(feature = "cuda")]
            Buf::CudaU32(s) => 4 * s.len(),
        }
    }

    /// The buffer as a CPU storage (the emulated grid's).
    pub fn into_cpu(self) -> candle_core::Result<CpuStorage> {
        match self {
            Buf::F32(v) => Ok(CpuStorage::F32(v)),
            Buf::U32(v) => Ok(CpuStorage::U32(v)),
            #[cfg(feature = "cuda")]
            _ => candle_core::bail!("a GPU buffer for a CPU tensor"),
        }
    }

    /// The buffer as a storage of `like`'s device.
    #[cfg(feature = "cuda")]
    pub fn into_cuda(self, like: &CudaStorage) -> candle_core::Result<CudaStorage> {
        let dev = like.device().clone();
        match self {
            Buf::CudaF32(s) => Ok(CudaStorage::wrap_cuda_slice(s, dev)),
            Buf::CudaU32(s) => Ok(CudaStorage::wrap_cuda_slice(s, dev)),
            _ => candle_core::bail!("a host buffer for a CUDA tensor"),
        }
    }

    /// A CUDA storage's buffer (f32 or u32), taken over.
    #[cfg(feature = "cuda")]
    pub fn from_cuda(s: CudaStorage) -> candle_core::Result<Self> {
        use candle_core::cuda_backend::CudaStorageSlice;
        match s.slice {
            CudaStorageSlice::F32(v) => Ok(Buf::CudaF32(v)),
            CudaStorageSlice::U32(v) => Ok(Buf::CudaU32(v)),
            _ => candle_core::bail!("a kernel buffer is f32 or u32"),
        }
    }

    /// The buffer as a storage of the device of `like` (a CPU or a CUDA storage).
    pub fn into_storage_like(self, like: &Storage) -> candle_core::Result<Storage> {
        match like {
            Storage::Cpu(_) => Ok(Storage::Cpu(self.into_cpu()?)),
            #[cfg(feature = "cuda")]
            Storage::Cuda(c) => Ok(Storage::Cuda(self.into_cuda(c)?)),
            #[allow(unreachable_patterns)]
            _ => candle_core::bail!("pma's kernels run on CUDA or the emulated grid only"),
        }
    }
}

/// One argument of a launch, in the kernel's parameter order.
pub enum Arg<'a> {
    Src(Src<'a>),
    Dst(&'a mut Buf),
    U32(u32),
    I32(i32),
    F32(f32),
}
