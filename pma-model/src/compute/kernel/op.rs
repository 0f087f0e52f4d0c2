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
    /// from their layouts' starts (contiguous). An op whose [`Self::storages`] always
    /// answers need not have one.
    fn device(
        &self,
        _exec: &Exec,
        _srcs: [Src; N],
        _layouts: [&Layout; N],
    ) -> candle_core::Result<(Buf, Shape)> {
        candle_core::bail!("{}: the op runs on its storages", self.name())
    }

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
    fn cpu(&self, _storages: [&CpuStorage; N], _layouts: [&Layout; N]) -> Option<CpuForward> {
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

/// An op of (x, W, a third input) whose forward starts with the product x · Wᵀ on its
/// storages ([`Inputs::product`]): a [`Kernel`] counted under candle's name for a product,
/// "matmul".
pub trait Product: Send + Sync {
    /// The forward, the product included, on either kind of storage (the CPU's included:
    /// [`Inputs::Cpu`]).
    fn forward(&self, inputs: Inputs<'_, 3>, layouts: [&Layout; 3]) -> Forward;

    /// The gradients of the inputs ([`product_grads`] gives x's and W's).
    fn backward(
        &self,
        args: [&Tensor; 3],
        res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<[Option<Tensor>; 3]>;
}

/// A device route's forward: the output buffer and its shape.
pub type Forward = candle_core::Result<(Buf, Shape)>;

/// The CPU route's forward: the output storage and its shape.
pub type CpuForward = candle_core::Result<(CpuStorage, Shape)>;

impl<T: Product> Kernel<3> for T {
    fn name(&self) -> &'static str {
        "matmul"
    }

    fn storages(&self, inputs: Inputs<'_, 3>, layouts: [&Layout; 3]) -> Option<Forward> {
        Some(self.forward(inputs, layouts))
    }

    fn backward(
        &self,
        args: [&Tensor; 3],
        res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<[Option<Tensor>; 3]> {
        Product::backward(self, args, res, grad)
    }
}

/// The gradients of x and W from the gradient `gz` of z = x · Wᵀ: candle's matmul backward
/// for x · (Wᵀ), then the transpose's, so the same products and the same bits. None for an
/// x that takes no gradient (the GNN's pose input): its product is skipped.
pub fn product_grads(
    x: &Tensor,
    w: &Tensor,
    gz: &Tensor,
) -> candle_core::Result<(Option<Tensor>, Tensor)> {
    let wt = w.t()?;
    let gx = x.track_op().then(|| gz.matmul(&wt.t()?)).transpose()?;
    let gw = x.t()?.matmul(gz)?.t()?;
    Ok((gx, gw))
}

/// A [`Kernel`] as candle's custom op.
pub struct Op<T>(pub T);

/// An op's input storages on the device route: the CPU's (the emulated grid) or a GPU's.
#[derive(Clone, Copy)]
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

    /// Every input from its layout's start.
    fn srcs(&self, l: [&Layout; N], what: &str) -> candle_core::Result<[Src<'_>; N]> {
        let srcs = (0..N)
            .map(|i| self.src(i, l[i], what))
            .collect::<candle_core::Result<Vec<_>>>()?;
        srcs.try_into()
            .map_err(|_| candle_core::Error::Msg("inputs".into()))
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

/// The device route from either kind of storage: the op's own work on the storages, or its
/// kernels on views of them.
fn device_route<const N: usize, T: Kernel<N>>(
    op: &T,
    inputs: Inputs<'_, N>,
    l: [&Layout; N],
) -> candle_core::Result<(Buf, Shape)> {
    if let Some(r) = op.storages(inputs, l) {
        return r;
    }
    op.device(&inputs.exec(), inputs.srcs(l, op.name())?, l)
}

fn cpu<const N: usize, T: Kernel<N>>(
    op: &T,
    s: [&CpuStorage; N],
    l: [&Layout; N],
) -> candle_core::Result<(CpuStorage, Shape)> {
    if let Some(r) = op.cpu(s, l) {
        return r;
    }
    let (out, shape) = device_route(op, Inputs::Cpu(s), l)?;
    Ok((out.into_cpu()?, shape))
}

#[cfg(feature = "cuda")]
fn cuda<const N: usize, T: Kernel<N>>(
    op: &T,
    s: [&candle_core::CudaStorage; N],
    l: [&Layout; N],
) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
    let (out, shape) = device_route(op, Inputs::Cuda(s), l)?;
    Ok((out.into_cuda(s[0])?, shape))
}

/// candle's custom-op trait of `$n` inputs for [`Op`]: the storages and layouts as arrays,
/// the gradients back as candle's tuple.
macro_rules! custom_op {
    ($op:ident, $n:tt, [$($s:ident $l:ident),+], [$($a:ident $g:ident),+], $grads:ty, $out:expr) => {
        impl<T: Kernel<$n>> $op for Op<T> {
            fn name(&self) -> &'static str {
                self.0.name()
            }

            fn cpu_fwd(
                &self,
                $($s: &CpuStorage, $l: &Layout),+
            ) -> candle_core::Result<(CpuStorage, Shape)> {
                cpu(&self.0, [$($s),+], [$($l),+])
            }

            #[cfg(feature = "cuda")]
            fn cuda_fwd(
                &self,
                $($s: &candle_core::CudaStorage, $l: &Layout),+
            ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
                cuda(&self.0, [$($s),+], [$($l),+])
            }

            fn bwd(
                &self,
                $($a: &Tensor,)+
                res: &Tensor,
                grad: &Tensor,
            ) -> candle_core::Result<$grads> {
                let [$($g),+] = self.0.backward([$($a),+], res, grad)?;
                Ok($out)
            }
        }
    };
}

custom_op!(CustomOp1, 1, [s l], [a g], Option<Tensor>, g);
custom_op!(
    CustomOp2,
    2,
    [s1 l1, s2 l2],
    [a ga, b gb],
    (Option<Tensor>, Option<Tensor>),
    (ga, gb)
);
custom_op!(
    CustomOp3,
    3,
    [s1 l1, s2 l2, s3 l3],
    [a ga, b gb, c gc],
    (Option<Tensor>, Option<Tensor>, Option<Tensor>),
    (ga, gb, gc)
);

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
            source: concat!(
                include_str!(concat!(
                    env!("CARGO_MANIFEST_DIR"),
                    "/src/compute/kernel/prelude.cuh"
                )),
                include_str!($cu)
            ),
            emulate: $emu,
            check: $check,
        };
    };
}
