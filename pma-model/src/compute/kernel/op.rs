//! What candle needs of a custom op, written once for every op of pma: an op implements
//! [`Kernel`] (its device forward on views of its inputs, its CPU forward where the CPU has
//! one, its backward) and candle gets [`Op`], which turns CPU and CUDA storages into the
//! views and the kernels' buffers back into storages.

use candle_core::{CpuStorage, CustomOp1, CustomOp2, CustomOp3, Layout, Shape, Tensor};

use super::mem::{Buf, Exec, Src};

/// An op of `N` inputs (see the module docs).
pub trait Kernel<const N: usize>: Send + Sync {
    /// The name the step account counts it under.
    fn name(&self) -> &'static str;

    /// The forward on the device route: `exec` a GPU or the emulated grid, `srcs` the inputs
    /// from their layouts' starts (contiguous).
    fn device(
        &self,
        exec: &Exec,
        srcs: [Src; N],
        layouts: [&Layout; N],
    ) -> candle_core::Result<(Buf, Shape)>;

    /// The forward from the storages themselves, for an op that starts with work on them (a
    /// product through candle's CPU matmul or cuBLAS): taken before [`Self::device`] when
    /// `Some`.
    fn storages(
        &self,
        _inputs: Inputs<'_, N>,
        _layouts: [&Layout; N],
    ) -> Option<candle_core::Result<(Buf, Shape)>> {
        None
    }

    /// The forward on the CPU's route, for an op that takes it (then `Some`).
    fn cpu(
        &self,
        _storages: [&CpuStorage; N],
        _layouts: [&Layout; N],
    ) -> Option<candle_core::Result<(CpuStorage, Shape)>> {
        None
    }

    /// The gradients of the inputs.
    fn backward(
        &self,
        _args: [&Tensor; N],
        _res: &Tensor,
        _grad: &Tensor,
    ) -> candle_core::Result<[Option<Tensor>; N]> {
        candle_core::bail!("{} has no backward", self.name())
    }
}

/// A [`Kernel`] as candle's custom op.
pub struct Op<T>(pub T);

/// An op's input storages on the device route: the CPU's (the emulated grid) or a GPU's.
pub enum Inputs<'a, const N: usize> {
    Cpu([&'a CpuStorage; N]),
    #[cfg(feature = "cuda")]
    Cuda([&'a candle_core::CudaStorage; N]),
}

impl<const N: usize> Inputs<'_, N> {
    /// Where their kernels run.
    pub fn exec(&self) -> Exec {
        match self {
            Inputs::Cpu(_) => Exec::Emulated,
            #[cfg(feature = "cuda")]
            Inputs::Cuda(s) => Exec::Cuda(s[0].device.clone()),
        }
    }

    /// Input `i` from its layout's start.
    pub fn src(&self, i: usize, l: &Layout, what: &str) -> candle_core::Result<Src<'_>> {
        match self {
            Inputs::Cpu(s) => Src::cpu(s[i], l, what),
            #[cfg(feature = "cuda")]
            Inputs::Cuda(s) => Src::cuda(s[i], l, what),
        }
    }

    /// `x · Wᵀ` of inputs `x` [rows,in] and `w` [out,in], exactly as `Tensor::matmul` calls
    /// it (candle's CPU product, or cuBLAS): [rows,out].
    pub fn product(
        &self,
        (x, lx): (usize, &Layout),
        (w, lw): (usize, &Layout),
        (rows, inn, out): (usize, usize, usize),
    ) -> candle_core::Result<Buf> {
        use candle_core::backend::BackendStorage;
        let dims = (1, rows, out, inn);
        match self {
            Inputs::Cpu(s) => match s[x].matmul(s[w], dims, lx, &lw.transpose(0, 1)?)? {
                CpuStorage::F32(y) => Ok(Buf::F32(y)),
                _ => candle_core::bail!("a product that is not f32"),
            },
            #[cfg(feature = "cuda")]
            Inputs::Cuda(s) => Buf::from_cuda(s[x].matmul(s[w], dims, lx, &lw.transpose(0, 1)?)?),
        }
    }

    /// `y + b` for `y` [rows,out] and input `b` [out] broadcast over the rows: the host's
    /// row loop (the same additions as candle's), or candle's broadcast add on a GPU.
    pub fn bias_add(
        &self,
        y: Buf,
        (b, lb): (usize, &Layout),
        (rows, out): (usize, usize),
    ) -> candle_core::Result<Buf> {
        match (self, y) {
            (Inputs::Cpu(s), Buf::F32(mut y)) => {
                let bias = super::storage::f32_slice(s[b], lb, "bias")?;
                for row in y.chunks_exact_mut(out.max(1)) {
                    for (a, c) in row.iter_mut().zip(bias) {
                        *a += c;
                    }
                }
                Ok(Buf::F32(y))
            }
            #[cfg(feature = "cuda")]
            (Inputs::Cuda(s), Buf::CudaF32(y)) => {
                use candle_core::backend::BackendStorage;
                let y = candle_core::CudaStorage::wrap_cuda_slice(y, s[0].device.clone());
                let (ly, lb) = (
                    Layout::contiguous((rows, out)),
                    lb.broadcast_as((rows, out))?,
                );
                Buf::from_cuda(y.binary_impl::<candle_core::op::Add>(s[b], &ly, &lb)?)
            }
            _ => {
                let _ = rows;
                candle_core::bail!("a bias add on buffers of another device")
            }
        }
    }
}

fn cpu<const N: usize, T: Kernel<N>>(
    op: &T,
    s: [&CpuStorage; N],
    l: [&Layout; N],
) -> candle_core::Result<(CpuStorage, Shape)> {
    if let Some(r) = op.cpu(s, l) {
        return r;
    }
    if let Some(r) = op.storages(Inputs::Cpu(s), l) {
        let (out, shape) = r?;
        return Ok((out.into_cpu()?, shape));
    }
    let mut srcs = Vec::with_capacity(N);
    for i in 0..N {
        srcs.push(Src::cpu(s[i], l[i], op.name())?);
    }
    let srcs: [Src; N] = srcs
        .try_into()
        .map_err(|_| candle_core::Error::Msg("inputs".into()))?;
    let (out, shape) = op.device(&Exec::Emulated, srcs, l)?;
    Ok((out.into_cpu()?, shape))
}

#[cfg(feature = "cuda")]
fn cuda<const N: usize, T: Kernel<N>>(
    op: &T,
    s: [&candle_core::CudaStorage; N],
    l: [&Layout; N],
) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
    if let Some(r) = op.storages(Inputs::Cuda(s), l) {
        let (out, shape) = r?;
        return Ok((out.into_cuda(s[0])?, shape));
    }
    let mut srcs = Vec::with_capacity(N);
    for i in 0..N {
        srcs.push(Src::cuda(s[i], l[i], op.name())?);
    }
    let srcs: [Src; N] = srcs
        .try_into()
        .map_err(|_| candle_core::Error::Msg("inputs".into()))?;
    let (out, shape) = op.device(&Exec::Cuda(s[0].device.clone()), srcs, l)?;
    Ok((out.into_cuda(s[0])?, shape))
}

impl<T: Kernel<1>> CustomOp1 for Op<T> {
    fn name(&self) -> &'static str {
        self.0.name()
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
        cpu(&self.0, [s], [l])
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s: &candle_core::CudaStorage,
        l: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        cuda(&self.0, [s], [l])
    }

    fn bwd(&self, a: &Tensor, res: &Tensor, grad: &Tensor) -> candle_core::Result<Option<Tensor>> {
        let [g] = self.0.backward([a], res, grad)?;
        Ok(g)
    }
}

impl<T: Kernel<2>> CustomOp2 for Op<T> {
    fn name(&self) -> &'static str {
        self.0.name()
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        cpu(&self.0, [s1, s2], [l1, l2])
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        cuda(&self.0, [s1, s2], [l1, l2])
    }

    fn bwd(
        &self,
        a: &Tensor,
        b: &Tensor,
        res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let [ga, gb] = self.0.backward([a, b], res, grad)?;
        Ok((ga, gb))
    }
}

impl<T: Kernel<3>> CustomOp3 for Op<T> {
    fn name(&self) -> &'static str {
        self.0.name()
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        cpu(&self.0, [s1, s2, s3], [l1, l2, l3])
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
        s3: &candle_core::CudaStorage,
        l3: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        cuda(&self.0, [s1, s2, s3], [l1, l2, l3])
    }

    fn bwd(
        &self,
        a: &Tensor,
        b: &Tensor,
        c: &Tensor,
        res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let [ga, gb, gc] = self.0.backward([a, b, c], res, grad)?;
        Ok((ga, gb, gc))
    }
}

/// Declare an op's kernel module: its host build (`pma_emu_<name>` of the op's `emu.c`) and
/// its [`super::Module`] static `MODULE`.
#[macro_export]
macro_rules! kernel_module {
    ($name:literal, $cu:literal, $emu:ident, $check:path) => {
        extern "C" {
            fn $emu(
                name: *const std::ffi::c_char,
                blocks: u32,
                threads: u32,
                params: *mut *mut std::ffi::c_void,
            ) -> std::ffi::c_int;
        }

        #[doc = concat!("`", $cu, "`.")]
        pub static MODULE: $crate::compute::kernel::Module = $crate::compute::kernel::Module {
            name: $name,
            file: concat!("compute/ops/", $name, "/", $cu),
            source: include_str!($cu),
            emulate: $emu,
            check: $check,
        };
    };
}
