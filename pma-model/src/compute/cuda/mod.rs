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

/// CUDA source of the narrow-input SIREN layer and its weight gradients.
pub const SINE_LINEAR_CU: &str = include_str!("kernels/sine_linear.cu");

/// CUDA source of the bias add and activation (ReLU or sine) after a product, and their
/// gradients.
pub const BIAS_ACT_CU: &str = include_str!("kernels/bias_act.cu");

/// CUDA source of the flat Adam update.
pub const ADAM_CU: &str = include_str!("kernels/adam.cu");

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
    use candle_core::{CpuStorage, CudaStorage, CustomOp1, Layout, Result, Shape, Storage, Tensor};

    /// PTX of `src`, compiled once per process into `cell` (`file`, the source's path in
    /// pma-model/src, names it in errors). Every NVRTC kernel of pma goes through here.
    pub(crate) fn ptx(
        cell: &'static OnceLock<std::result::Result<String, String>>,
        src: &str,
        file: &str,
    ) -> Result<&'static str> {
        cell.get_or_init(|| {
            candle_core::cuda_backend::cudarc::nvrtc::compile_ptx(src)
                .map(|p| p.to_src())
                .map_err(|e| format!("compiling pma-model/src/{file}: {e}"))
        })
        .as_deref()
        .map_err(|e| candle_core::Error::Msg(e.clone()))
    }

    fn window_pool_ptx() -> Result<&'static str> {
        static PTX: OnceLock<std::result::Result<String, String>> = OnceLock::new();
        ptx(
            &PTX,
            super::WINDOW_POOL_CU,
            "compute/cuda/kernels/window_pool.cu",
        )
    }

    fn adam_ptx() -> Result<&'static str> {
        static PTX: OnceLock<std::result::Result<String, String>> = OnceLock::new();
        ptx(&PTX, super::ADAM_CU, "compute/cuda/kernels/adam.cu")
    }

    fn film_sine_ptx() -> Result<&'static str> {
        static PTX: OnceLock<std::result::Result<String, String>> = OnceLock::new();
        ptx(
            &PTX,
            super::FILM_SINE_CU,
            "compute/cuda/kernels/film_sine.cu",
        )
    }

    fn bias_act_ptx() -> Result<&'static str> {
        static PTX: OnceLock<std::result::Result<String, String>> = OnceLock::new();
        ptx(&PTX, super::BIAS_ACT_CU, "compute/cuda/kernels/bias_act.cu")
    }

    fn sine_linear_ptx() -> Result<&'static str> {
        static PTX: OnceLock<std::result::Result<String, String>> = OnceLock::new();
        ptx(
            &PTX,
            super::SINE_LINEAR_CU,
            "compute/cuda/kernels/sine_linear.cu",
        )
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

    /// `s_r sin(x Wᵀ + b)`: x [R,IN], [W|b] [OUT,IN+1], s [R] (contiguous f32,
    /// 1 ≤ IN ≤ 4) -> [R,OUT]. One launch.
    pub(crate) fn sine_linear(
        (x, lx): (&CudaStorage, &Layout),
        (wb, lwb): (&CudaStorage, &Layout),
        (sc, lsc): (&CudaStorage, &Layout),
        (rows, inp, out): (usize, usize, usize),
    ) -> Result<CudaStorage> {
        let dev = x.device().clone();
        let y = output::<f32>(&dev, rows * out)?;
        if rows * out > 0 {
            let func = dev.get_or_load_custom_func(
                "pma_sine_linear_f32",
                "pma_sine_linear",
                sine_linear_ptx()?,
            )?;
            let (xv, wv, sv) = (f32s(x, lx)?, f32s(wb, lwb)?, f32s(sc, lsc)?);
            let dims = [
                u32_of(rows, "rows")?,
                u32_of(inp, "IN")?,
                u32_of(out, "OUT")?,
            ];
            let mut bld = func.builder();
            bld.arg(&xv);
            bld.arg(&wv);
            bld.arg(&sv);
            bld.arg(&y);
            for d in &dims {
                bld.arg(d);
            }
            // SAFETY: the arguments match `pma_sine_linear_f32`'s list; the caller checked
            // the shapes (x [R,IN], [W|b] [OUT,IN+1], s [R], IN within the kernel's bound).
            unsafe { bld.launch(config(rows * out)?) }.w()?;
        }
        Ok(CudaStorage::wrap_cuda_slice(y, dev))
    }

    /// The gradient [OUT, IN+1] of [W|b] in [`sine_linear`] from the upstream gradient
    /// [R,OUT]: partial sums per block of rows, then their sum in block order (two
    /// launches); or, `of_rows`, [R, IN+1]: x's gradient and s's (one launch).
    pub(crate) fn sine_linear_grad(
        (grad, lg): (&CudaStorage, &Layout),
        (x, lx): (&CudaStorage, &Layout),
        (wb, lwb): (&CudaStorage, &Layout),
        (sc, lsc): (&CudaStorage, &Layout),
        (rows, inp, out): (usize, usize, usize),
        of_rows: bool,
    ) -> Result<CudaStorage> {
        let dev = grad.device().clone();
        let width = inp + 1;
        let dims = [
            u32_of(rows, "rows")?,
            u32_of(inp, "IN")?,
            u32_of(out, "OUT")?,
        ];
        let (gv, xv, wv, sv) = (
            f32s(grad, lg)?,
            f32s(x, lx)?,
            f32s(wb, lwb)?,
            f32s(sc, lsc)?,
        );
        let blocks = rows.div_ceil(crate::compute::sine_linear::ROWS_PER_BLOCK);
        let (len, name, threads) = match of_rows {
            true => (rows * width, "pma_sine_linear_grad_rows_f32", rows),
            false => (
                blocks * out * width,
                "pma_sine_linear_grad_part_f32",
                blocks * out,
            ),
        };
        if len == 0 || (!of_rows && out == 0) {
            // No rows or no outputs: nothing to sum, the gradients are zero.
            let n = if of_rows { rows * width } else { out * width };
            let zero = dev.alloc_zeros::<f32>(n.max(1))?;
            return Ok(CudaStorage::wrap_cuda_slice(zero, dev));
        }
        let first = output::<f32>(&dev, len)?;
        let func = dev.get_or_load_custom_func(name, "pma_sine_linear", sine_linear_ptx()?)?;
        let mut bld = func.builder();
        bld.arg(&gv);
        bld.arg(&xv);
        bld.arg(&wv);
        bld.arg(&sv);
        bld.arg(&first);
        for d in &dims {
            bld.arg(d);
        }
        // SAFETY: the arguments match the list of `name` (both kernels take the same);
        // grad is [R,OUT], x [R,IN], [W|b] [OUT,IN+1], s [R]; `first` holds what the kernel
        // writes: [R,IN+1] per row, or [blocks,OUT,IN+1] for blocks = ceil(R / rows per block).
        unsafe { bld.launch(config(threads)?) }.w()?;
        if of_rows {
            return Ok(CudaStorage::wrap_cuda_slice(first, dev));
        }
        let g = output::<f32>(&dev, out * width)?;
        let func = dev.get_or_load_custom_func(
            "pma_sine_linear_grad_sum_f32",
            "pma_sine_linear",
            sine_linear_ptx()?,
        )?;
        let sums = [u32_of(blocks, "blocks")?, dims[1], dims[2]];
        let mut bld = func.builder();
        bld.arg(&first);
        bld.arg(&g);
        for d in &sums {
            bld.arg(d);
        }
        // SAFETY: the arguments match `pma_sine_linear_grad_sum_f32`'s list; the partial
        // sums were written in full by the launch before, on the same stream.
        unsafe { bld.launch(config(out * width)?) }.w()?;
        Ok(CudaStorage::wrap_cuda_slice(g, dev))
    }

    /// `max(z + b, 0)`, or `sin(z + b)` when `sine`: z [R,OUT] (contiguous from its
    /// start), b [OUT] -> [R,OUT]. One launch.
    pub(crate) fn bias_act(
        z: &CudaStorage,
        b: &CudaStorage,
        lb: &Layout,
        [rows, out]: [usize; 2],
        sine: bool,
    ) -> Result<CudaStorage> {
        let dev = z.device().clone();
        let y = output::<f32>(&dev, rows * out)?;
        if rows * out > 0 {
            let name = if sine {
                "pma_bias_sine_f32"
            } else {
                "pma_bias_relu_f32"
            };
            let func = dev.get_or_load_custom_func(name, "pma_bias_act", bias_act_ptx()?)?;
            let zv = z.as_cuda_slice::<f32>()?;
            let bv = f32s(b, lb)?;
            let dims = [u32_of(rows, "rows")?, u32_of(out, "OUT")?];
            let mut bld = func.builder();
            bld.arg(zv);
            bld.arg(&bv);
            bld.arg(&y);
            for d in &dims {
                bld.arg(d);
            }
            // SAFETY: the arguments match the list of `name` (both kernels take the same);
            // z is the product [R,OUT] just made, b [OUT].
            unsafe { bld.launch(config(rows * out)?) }.w()?;
        }
        Ok(CudaStorage::wrap_cuda_slice(y, dev))
    }

    /// The product's gradient [R,OUT] (ReLU: where the output `kept` is > 0; sine: times
    /// cos(kept + b), `kept` the product), and the bias gradient's partial sums per block of
    /// rows [blocks, OUT]. One launch.
    pub(crate) fn act_grad(
        (grad, lg): (&CudaStorage, &Layout),
        (kept, lk): (&CudaStorage, &Layout),
        (b, lb): (&CudaStorage, &Layout),
        [rows, out]: [usize; 2],
        sine: bool,
    ) -> Result<(CudaStorage, CudaSlice<f32>)> {
        let dev = grad.device().clone();
        let blocks = rows.div_ceil(crate::compute::linear_act::ROWS_PER_BLOCK);
        let gz = output::<f32>(&dev, rows * out)?;
        let part = output::<f32>(&dev, blocks * out)?;
        if blocks * out > 0 {
            let func =
                dev.get_or_load_custom_func("pma_act_grad_f32", "pma_bias_act", bias_act_ptx()?)?;
            let (gv, kv, bv) = (f32s(grad, lg)?, f32s(kept, lk)?, f32s(b, lb)?);
            let dims = [u32_of(rows, "rows")?, u32_of(out, "OUT")?];
            let sine = i32::from(sine);
            let mut bld = func.builder();
            bld.arg(&gv);
            bld.arg(&kv);
            bld.arg(&bv);
            bld.arg(&gz);
            bld.arg(&part);
            for d in &dims {
                bld.arg(d);
            }
            bld.arg(&sine);
            // SAFETY: the arguments match `pma_act_grad_f32`'s list; grad and kept are
            // [R,OUT], b [OUT], `part` [blocks,OUT] for blocks = ceil(R / PMA_BIAS_ACT_ROWS).
            unsafe { bld.launch(config(blocks * out)?) }.w()?;
        }
        Ok((CudaStorage::wrap_cuda_slice(gz, dev), part))
    }

    /// The bias gradient [OUT]: the partial sums [blocks, OUT] added in block order. One
    /// launch (a memset when there are no blocks).
    pub(crate) fn bias_grad_sum(
        like: &CudaStorage,
        part: &CudaSlice<f32>,
        [blocks, out]: [usize; 2],
    ) -> Result<CudaStorage> {
        let dev = like.device().clone();
        if blocks == 0 || out == 0 {
            let zero = dev.alloc_zeros::<f32>(out.max(1))?;
            return Ok(CudaStorage::wrap_cuda_slice(zero, dev));
        }
        let gb = output::<f32>(&dev, out)?;
        let func =
            dev.get_or_load_custom_func("pma_bias_grad_sum_f32", "pma_bias_act", bias_act_ptx()?)?;
        let dims = [u32_of(blocks, "blocks")?, u32_of(out, "OUT")?];
        let mut bld = func.builder();
        bld.arg(part);
        bld.arg(&gb);
        for d in &dims {
            bld.arg(d);
        }
        // SAFETY: the arguments match `pma_bias_grad_sum_f32`'s list; `part` holds
        // [blocks,OUT], written by `act_grad` on the same stream.
        unsafe { bld.launch(config(out)?) }.w()?;
        Ok(CudaStorage::wrap_cuda_slice(gb, dev))
    }

    /// A finished head gradient as a storage.
    pub(crate) fn storage_of(g: CudaSlice<f32>, like: &CudaStorage) -> CudaStorage {
        CudaStorage::wrap_cuda_slice(g, like.device().clone())
    }

    /// Adam's scalar hyper-parameters as the update multiplies by them (f32).
    #[derive(Debug, Clone, Copy)]
    pub(crate) struct AdamScalars {
        pub one_minus_b1: f32,
        pub b2: f32,
        pub one_minus_b2: f32,
        pub eps: f32,
    }

    /// The flat Adam update in one launch (`kernels/adam.cu`): from the flat gradient `g`,
    /// parameters, moments [N] (f32), the slot of every element [N] (u32), per slot the
    /// step size and `1/sqrt(1 − b2^t)` (f32) and whether it has a gradient (u8), the
    /// device flag `ok` (u8 scalar) and the clip factor (f32 scalar, if any), the new
    /// (parameters, first moments, second moments). Every tensor contiguous on CUDA.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn adam(
        g: &Tensor,
        p_old: &Tensor,
        m_old: &Tensor,
        v_old: &Tensor,
        slot_of: &Tensor,
        step_size: &Tensor,
        inv_bias2: &Tensor,
        has: &Tensor,
        ok: &Tensor,
        coef: Option<&Tensor>,
        scalars: AdamScalars,
    ) -> Result<(Tensor, Tensor, Tensor)> {
        let mut others = vec![
            p_old.clone(),
            m_old.clone(),
            v_old.clone(),
            slot_of.clone(),
            step_size.clone(),
            inv_bias2.clone(),
            has.clone(),
            ok.clone(),
        ];
        others.extend(coef.cloned());
        let op = AdamOp {
            others,
            scalars,
            moments: std::sync::Mutex::new(None),
        };
        let p = g.apply_op1_no_bwd(&op)?;
        let (m, v) = op
            .moments
            .into_inner()
            .unwrap_or_else(|e| e.into_inner())
            .ok_or_else(|| candle_core::Error::Msg("adam: the kernel did not run".into()))?;
        let n = g.elem_count();
        let m = g.apply_op1_no_bwd(&Wrap::new(m, n))?;
        let v = g.apply_op1_no_bwd(&Wrap::new(v, n))?;
        Ok((p, m, v))
    }

    /// The update as a custom op on the gradient, the other inputs held (custom ops take
    /// at most three); its output is the parameters, the moments are left in `moments`.
    struct AdamOp {
        others: Vec<Tensor>,
        scalars: AdamScalars,
        moments: std::sync::Mutex<Option<(CudaSlice<f32>, CudaSlice<f32>)>>,
    }

    impl CustomOp1 for AdamOp {
        fn name(&self) -> &'static str {
            "pma-adam"
        }

        fn cpu_fwd(&self, _: &CpuStorage, _: &Layout) -> Result<(CpuStorage, Shape)> {
            candle_core::bail!("adam: the CUDA kernel got a CPU tensor")
        }

        fn cuda_fwd(&self, g: &CudaStorage, lg: &Layout) -> Result<(CudaStorage, Shape)> {
            candle_core::account::report_launches(1, 0);
            let n = lg.shape().elem_count();
            // g, p, m, v, slot_of, per slot step size, 1/sqrt(1 − b2^t) and the flag, ok,
            // the clip factor; p, m and v written.
            let slots = self.others.get(5).map_or(0, |t| t.elem_count()) as u64;
            let n64 = n as u64;
            candle_core::account::report_bytes(5 * 4 * n64 + 9 * slots + 5, 3 * 4 * n64);
            let guards: Vec<_> = self.others.iter().map(|t| t.storage_and_layout()).collect();
            let mut cuda = Vec::with_capacity(guards.len());
            for (guard, l) in &guards {
                match &**guard {
                    Storage::Cuda(c) => cuda.push((c, *l)),
                    _ => candle_core::bail!("adam: expected CUDA tensors"),
                }
            }
            for (i, (_, l)) in cuda.iter().enumerate().take(4) {
                if l.shape().elem_count() != n {
                    candle_core::bail!("adam: flat input {i} does not have {n} elements")
                }
            }
            let dev = g.device().clone();
            let (p, m, v) = (
                output::<f32>(&dev, n)?,
                output::<f32>(&dev, n)?,
                output::<f32>(&dev, n)?,
            );
            if n > 0 {
                let func = dev.get_or_load_custom_func("pma_adam_f32", "pma_adam", adam_ptx()?)?;
                let f = |i: usize| f32s(cuda[i].0, cuda[i].1);
                let (gv, po, mo, vo) = (f32s(g, lg)?, f(0)?, f(1)?, f(2)?);
                let slot_of = cuda[3]
                    .0
                    .as_cuda_slice::<u32>()?
                    .slice(cuda[3].1.start_offset()..);
                let (step, inv) = (f(4)?, f(5)?);
                let has = cuda[6]
                    .0
                    .as_cuda_slice::<u8>()?
                    .slice(cuda[6].1.start_offset()..);
                let ok = cuda[7]
                    .0
                    .as_cuda_slice::<u8>()?
                    .slice(cuda[7].1.start_offset()..);
                let clip = i32::from(cuda.len() > 8);
                // Without a clip factor the kernel never reads `coef`: any f32 buffer will do.
                let coef = if cuda.len() > 8 { f(8)? } else { f(4)? };
                let n32 = u32_of(n, "N")?;
                let s = self.scalars;
                let mut b = func.builder();
                for x in [&gv, &po, &mo, &vo] {
                    b.arg(x);
                }
                b.arg(&p);
                b.arg(&m);
                b.arg(&v);
                b.arg(&slot_of);
                b.arg(&step);
                b.arg(&inv);
                b.arg(&has);
                b.arg(&ok);
                b.arg(&coef);
                b.arg(&clip);
                b.arg(&n32);
                b.arg(&s.one_minus_b1);
                b.arg(&s.b2);
                b.arg(&s.one_minus_b2);
                b.arg(&s.eps);
                // SAFETY: the arguments match `pma_adam_f32`'s list; the flat buffers have n
                // elements (checked), slot_of indexes the per-slot buffers (built so by
                // the optimizer), `ok` and `coef` are scalars.
                unsafe { b.launch(config(n)?) }.w()?;
            }
            *self.moments.lock().unwrap_or_else(|e| e.into_inner()) = Some((m, v));
            Ok((CudaStorage::wrap_cuda_slice(p, dev), lg.shape().clone()))
        }
    }

    /// Hands a finished f32 device buffer of `n` elements to candle as a tensor (no launch).
    struct Wrap {
        buf: std::sync::Mutex<Option<CudaSlice<f32>>>,
        n: usize,
    }

    impl Wrap {
        fn new(buf: CudaSlice<f32>, n: usize) -> Self {
            Self {
                buf: std::sync::Mutex::new(Some(buf)),
                n,
            }
        }
    }

    impl CustomOp1 for Wrap {
        fn name(&self) -> &'static str {
            "pma-wrap"
        }

        fn cpu_fwd(&self, _: &CpuStorage, _: &Layout) -> Result<(CpuStorage, Shape)> {
            candle_core::bail!("wrap: a CUDA buffer for a CPU tensor")
        }

        fn cuda_fwd(&self, s: &CudaStorage, _: &Layout) -> Result<(CudaStorage, Shape)> {
            candle_core::account::report_launches(0, 0);
            candle_core::account::report_bytes(0, 0);
            let buf = self.buf.lock().unwrap_or_else(|e| e.into_inner()).take();
            let buf =
                buf.ok_or_else(|| candle_core::Error::Msg("wrap: buffer used twice".into()))?;
            Ok((
                CudaStorage::wrap_cuda_slice(buf, s.device().clone()),
                Shape::from(self.n),
            ))
        }
    }
}
