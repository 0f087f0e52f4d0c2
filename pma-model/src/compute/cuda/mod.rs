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

/// CUDA source of one FiLM-sine layer and its gradient.
pub const FILM_SINE_CU: &str = include_str!("kernels/film_sine.cu");

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

    /// PTX of `src`, compiled once per process into `cell` (`file` names it in errors).
    fn ptx(
        cell: &'static OnceLock<std::result::Result<String, String>>,
        src: &str,
        file: &str,
    ) -> Result<&'static str> {
        cell.get_or_init(|| {
            candle_core::cuda_backend::cudarc::nvrtc::compile_ptx(src)
                .map(|p| p.to_src())
                .map_err(|e| format!("compiling pma-model/src/compute/cuda/kernels/{file}: {e}"))
        })
        .as_deref()
        .map_err(|e| candle_core::Error::Msg(e.clone()))
    }

    fn window_pool_ptx() -> Result<&'static str> {
        static PTX: OnceLock<std::result::Result<String, String>> = OnceLock::new();
        ptx(&PTX, super::WINDOW_POOL_CU, "window_pool.cu")
    }

    fn film_sine_ptx() -> Result<&'static str> {
        static PTX: OnceLock<std::result::Result<String, String>> = OnceLock::new();
        ptx(&PTX, super::FILM_SINE_CU, "film_sine.cu")
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

    /// Sizes of one FiLM-sine layer: N rows, F features, layer k of K; γ = mul·Θ + add.
    #[derive(Debug, Clone, Copy)]
    pub(crate) struct Film {
        pub n: usize,
        pub f: usize,
        pub k: usize,
        pub n_layers: usize,
        pub mul: f32,
        pub add: f32,
    }

    impl Film {
        fn dims(&self) -> Result<[u32; 4]> {
            Ok([
                u32_of(self.n, "N")?,
                u32_of(self.f, "F")?,
                u32_of(self.k, "layer")?,
                u32_of(self.n_layers, "layers")?,
            ])
        }
    }

    /// One FiLM-sine layer: pre [N,F], o [N,2KF] (contiguous f32) -> (sin [N,F], cos [N,F]
    /// when `keep_cos`). One launch.
    pub(crate) fn film_sine(
        pre: &CudaStorage,
        lp: &Layout,
        o: &CudaStorage,
        lo: &Layout,
        d: Film,
        keep_cos: bool,
    ) -> Result<(CudaStorage, Option<CudaSlice<f32>>)> {
        let dev = pre.device().clone();
        let len = d.n * d.f;
        let out = output::<f32>(&dev, len)?;
        let cos = output::<f32>(&dev, if keep_cos { len } else { 1 })?;
        if len > 0 {
            let func = dev.get_or_load_custom_func(
                "pma_film_sine_f32",
                "pma_film_sine",
                film_sine_ptx()?,
            )?;
            let (pv, ov) = (f32s(pre, lp)?, f32s(o, lo)?);
            let keep = i32::from(keep_cos);
            let mut b = func.builder();
            b.arg(&pv);
            b.arg(&ov);
            b.arg(&out);
            b.arg(&cos);
            let dims = d.dims()?;
            for x in &dims {
                b.arg(x);
            }
            b.arg(&d.mul);
            b.arg(&d.add);
            b.arg(&keep);
            // SAFETY: the arguments match `pma_film_sine_f32`'s list; the caller checked
            // that pre is [N,F] and o [N,2KF]; `cos` is written only when `keep`.
            unsafe { b.launch(config(len)?) }.w()?;
        }
        Ok((
            CudaStorage::wrap_cuda_slice(out, dev),
            keep_cos.then_some(cos),
        ))
    }

    /// The layer's gradient of pre [N,F]; layer k's blocks of the head gradient are written
    /// into `g_o` [N,2KF] (zeroed first when `None`, which it then holds). One launch
    /// (two with the zeroing).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn film_sine_grad(
        grad: &CudaStorage,
        lg: &Layout,
        pre: &CudaStorage,
        lp: &Layout,
        o: &CudaStorage,
        lo: &Layout,
        cos: Option<&CudaSlice<f32>>,
        g_o: &mut Option<CudaSlice<f32>>,
        d: Film,
    ) -> Result<CudaStorage> {
        let dev = grad.device().clone();
        let len = d.n * d.f;
        let w = 2 * d.n_layers * d.f;
        if g_o.is_none() {
            *g_o = Some(dev.alloc_zeros::<f32>((d.n * w).max(1))?);
        }
        let head = g_o.as_mut().expect("allocated above");
        let g_pre = output::<f32>(&dev, len)?;
        if len > 0 {
            let func = dev.get_or_load_custom_func(
                "pma_film_sine_grad_f32",
                "pma_film_sine",
                film_sine_ptx()?,
            )?;
            let (gv, pv, ov) = (f32s(grad, lg)?, f32s(pre, lp)?, f32s(o, lo)?);
            let dummy;
            let cos_in = match cos {
                Some(c) => c,
                None => {
                    dummy = dev.alloc_zeros::<f32>(1)?;
                    &dummy
                }
            };
            let have = i32::from(cos.is_some());
            let mut b = func.builder();
            b.arg(&gv);
            b.arg(&pv);
            b.arg(&ov);
            b.arg(cos_in);
            b.arg(&g_pre);
            b.arg(head);
            let dims = d.dims()?;
            for x in &dims {
                b.arg(x);
            }
            b.arg(&d.mul);
            b.arg(&d.add);
            b.arg(&have);
            // SAFETY: the arguments match `pma_film_sine_grad_f32`'s list; grad and pre are
            // [N,F], o and the head gradient [N,2KF]; `cos_in` is read only when `have`.
            unsafe { b.launch(config(len)?) }.w()?;
        }
        Ok(CudaStorage::wrap_cuda_slice(g_pre, dev))
    }

    /// A finished head gradient as a storage.
    pub(crate) fn storage_of(g: CudaSlice<f32>, like: &CudaStorage) -> CudaStorage {
        CudaStorage::wrap_cuda_slice(g, like.device().clone())
    }
}
