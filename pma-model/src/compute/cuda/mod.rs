//! pma's own CUDA kernels for the fused ops of [`crate::compute::fused`] (`kernels/*.cu`).
//!
//! The sources are compiled at run time with NVRTC, once per process, like the row
//! kernels of [`crate::compute::ops`]: a CUDA build then needs no CUDA compiler beyond
//! what candle itself needs, and the PTX matches the GPU it runs on.
//! `scripts/check-cuda-kernels.sh` compiles the same sources with nvcc (warnings as
//! errors), and the `pma-cuda-emu` crate compiles them for the host and tests them over an
//! emulated grid against the CPU ops, without a GPU.
//!
//! Every kernel is a grid-stride loop with one thread per output element, no shared memory
//! and no atomics, summing in the CPU op's order: results are the CPU's bits and a run
//! repeats and resumes bit for bit.

/// CUDA source of the window max-pool and its gradients.
pub const WINDOW_POOL_CU: &str = include_str!("kernels/window_pool.cu");

/// Threads per block of every launch here.
#[cfg(feature = "cuda")]
const THREADS: u32 = 256;

#[cfg(feature = "cuda")]
pub(crate) use launch::*;

#[cfg(feature = "cuda")]
mod launch {
    use std::sync::{Arc, OnceLock};

    use candle_core::backend::BackendStorage;
    use candle_core::cuda_backend::cudarc::driver::{
        CudaSlice, DeviceRepr, LaunchConfig, PushKernelArg,
    };
    use candle_core::cuda_backend::{CudaDevice, WrapErr};
    use candle_core::{CudaStorage, Layout, Result};

    /// PTX of `kernels/window_pool.cu`, compiled once per process.
    fn window_pool_ptx() -> Result<&'static str> {
        static PTX: OnceLock<std::result::Result<String, String>> = OnceLock::new();
        PTX.get_or_init(|| {
            candle_core::cuda_backend::cudarc::nvrtc::compile_ptx(super::WINDOW_POOL_CU)
                .map(|p| p.to_src())
                .map_err(|e| {
                    format!("compiling pma-model/src/compute/cuda/kernels/window_pool.cu: {e}")
                })
        })
        .as_deref()
        .map_err(|e| candle_core::Error::Msg(e.clone()))
    }

    fn u32_of(v: usize, what: &str) -> Result<u32> {
        u32::try_from(v)
            .map_err(|_| candle_core::Error::Msg(format!("{what} {v} exceeds a kernel's u32")))
    }

    /// The grid for `elements` outputs (grid-stride beyond 65,535 blocks).
    fn config(elements: usize) -> Result<LaunchConfig> {
        let blocks = elements.div_ceil(super::THREADS as usize).clamp(1, 65_535);
        Ok(LaunchConfig {
            grid_dim: (u32_of(blocks, "blocks")?, 1, 1),
            block_dim: (super::THREADS, 1, 1),
            shared_mem_bytes: 0,
        })
    }

    /// `s`'s f32 data from its layout's start (the caller made it contiguous).
    fn f32s<'a>(
        s: &'a CudaStorage,
        l: &Layout,
    ) -> Result<candle_core::cuda_backend::cudarc::driver::CudaView<'a, f32>> {
        Ok(s.as_cuda_slice::<f32>()?.slice(l.start_offset()..))
    }

    /// A buffer every element of which a kernel writes (no memset).
    fn output<T: DeviceRepr>(dev: &CudaDevice, len: usize) -> Result<CudaSlice<T>> {
        // SAFETY: the kernel that receives the buffer writes each of its `len` elements
        // before anything reads it (one thread per element, grid-stride).
        unsafe { dev.alloc::<T>(len.max(1)) }
    }

    /// The arg-max of a window pool, kept by the forward for the backward.
    pub(crate) type ArgMax = Arc<CudaSlice<u32>>;

    /// The window max-pool: q [N,J,H], g [P,J,H], w [N,J] (contiguous f32) -> (the max
    /// [N,H], the arg-max joint [N,H]). One launch.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn window_pool(
        q: &CudaStorage,
        lq: &Layout,
        g: &CudaStorage,
        lg: &Layout,
        w: &CudaStorage,
        lw: &Layout,
        [n, j, h, per_pose]: [usize; 4],
    ) -> Result<(CudaStorage, ArgMax)> {
        let dev = q.device().clone();
        let func = dev.get_or_load_custom_func(
            "pma_window_pool_f32",
            "pma_window_pool",
            window_pool_ptx()?,
        )?;
        let out = output::<f32>(&dev, n * h)?;
        let arg = output::<u32>(&dev, n * h)?;
        let dims = [
            u32_of(n, "N")?,
            u32_of(j, "J")?,
            u32_of(h, "H")?,
            u32_of(per_pose, "points per pose")?,
        ];
        if n * h > 0 {
            let (qv, gv, wv) = (f32s(q, lq)?, f32s(g, lg)?, f32s(w, lw)?);
            let mut b = func.builder();
            b.arg(&qv);
            b.arg(&gv);
            b.arg(&wv);
            b.arg(&out);
            b.arg(&arg);
            for d in &dims {
                b.arg(d);
            }
            // SAFETY: the arguments match `pma_window_pool_f32`'s list; the caller checked
            // the shapes, so every index the kernel forms is inside its buffer.
            unsafe { b.launch(config(n * h)?) }.w()?;
        }
        Ok((CudaStorage::wrap_cuda_slice(out, dev), Arc::new(arg)))
    }

    /// The window pool's gradient of q [N,J,H] from the upstream gradient `grad` [N,H],
    /// the spatial window `w` [N,J] and the forward's arg-max. One launch.
    pub(crate) fn window_pool_grad_q(
        grad: &CudaStorage,
        lgrad: &Layout,
        w: &CudaStorage,
        lw: &Layout,
        arg: &CudaSlice<u32>,
        [n, j, h]: [usize; 3],
    ) -> Result<CudaStorage> {
        let dev = grad.device().clone();
        let gq = output::<f32>(&dev, n * j * h)?;
        if n * j * h > 0 {
            let func = dev.get_or_load_custom_func(
                "pma_window_pool_grad_q_f32",
                "pma_window_pool",
                window_pool_ptx()?,
            )?;
            let (gv, wv) = (f32s(grad, lgrad)?, f32s(w, lw)?);
            let dims = [u32_of(n, "N")?, u32_of(j, "J")?, u32_of(h, "H")?];
            let mut b = func.builder();
            b.arg(&gv);
            b.arg(&wv);
            b.arg(arg);
            b.arg(&gq);
            for d in &dims {
                b.arg(d);
            }
            // SAFETY: the arguments match `pma_window_pool_grad_q_f32`'s list; the shapes
            // were checked by the forward.
            unsafe { b.launch(config(n * j * h)?) }.w()?;
        }
        Ok(CudaStorage::wrap_cuda_slice(gq, dev))
    }

    /// The window pool's gradient of g [P,J,H] (each entry summed over its pose's points
    /// in point order). One launch.
    pub(crate) fn window_pool_grad_g(
        grad: &CudaStorage,
        lgrad: &Layout,
        w: &CudaStorage,
        lw: &Layout,
        arg: &CudaSlice<u32>,
        [n, p, j, h]: [usize; 4],
    ) -> Result<CudaStorage> {
        let dev = grad.device().clone();
        let gg = output::<f32>(&dev, p * j * h)?;
        if p * j * h > 0 {
            let func = dev.get_or_load_custom_func(
                "pma_window_pool_grad_g_f32",
                "pma_window_pool",
                window_pool_ptx()?,
            )?;
            let (gv, wv) = (f32s(grad, lgrad)?, f32s(w, lw)?);
            let dims = [
                u32_of(p, "P")?,
                u32_of(j, "J")?,
                u32_of(h, "H")?,
                u32_of(n / p, "points per pose")?,
            ];
            let mut b = func.builder();
            b.arg(&gv);
            b.arg(&wv);
            b.arg(arg);
            b.arg(&gg);
            for d in &dims {
                b.arg(d);
            }
            // SAFETY: the arguments match `pma_window_pool_grad_g_f32`'s list; the shapes
            // were checked by the forward (P > 0 divides N).
            unsafe { b.launch(config(p * j * h)?) }.w()?;
        }
        Ok(CudaStorage::wrap_cuda_slice(gg, dev))
    }
}
