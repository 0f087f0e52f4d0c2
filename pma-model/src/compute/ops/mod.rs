//! Row gathers whose gradient does not run serially on a GPU.
//!
//! candle's CUDA `index_add` and `scatter_add` (the backward passes of `index_select` and
//! `gather`) give one thread per column and loop over every index in that thread, without
//! atomics: the frame-code lookup's gradient is 128 threads walking all rays of a chunk, the
//! merge of coarse and fine samples 4 threads per ray walking its 72 samples (see
//! docs/gpu.md, "Training graph audit"). [`gather_rows`] and [`select_rows`] compute the
//! same values with one custom op whose backward has one thread per (index, column) and
//! adds with `atomicAdd` on CUDA.
//!
//! On the CPU the op runs the same f32 additions in the same order as candle's kernels
//! (rows in index order, each accumulated from zero), so forward values and gradients are
//! bit-identical to the plain ops (`tests` below). On CUDA, rows that share an index (all
//! rays of an image share its frame code) are summed in no fixed order: the gradient can
//! differ from run to run by float rounding, unless [`Numerics::deterministic`] asks for
//! the ordered kernel. Other dtypes and devices take the plain ops.
//!
//! The kernels (`kernels/rows.cu`) are compiled at run time with NVRTC, once per process;
//! `scripts/check-cuda-kernels.sh` compiles them with nvcc ahead of time.

use candle_core::backend::BackendStorage;
use candle_core::{CpuStorage, CustomOp2, DType, Layout, Shape, Tensor};

use crate::compute::numerics::Numerics;
use crate::error::{ModelError, Result};

/// CUDA source of the row kernels (NVRTC at run time, nvcc in `scripts/check-cuda-kernels.sh`).
pub const ROWS_CU: &str = include_str!("kernels/rows.cu");

fn applies(k: Numerics, x: &Tensor) -> bool {
    k.row_ops && x.dtype() == DType::F32 && (x.device().is_cpu() || x.device().is_cuda())
}

/// `x.index_select(ids, 0)`: x [N,C], ids [M] (u32) -> [M,C].
pub fn select_rows(x: &Tensor, ids: &Tensor, k: Numerics) -> Result<Tensor> {
    let (n, c) = x.dims2()?;
    let m = ids.dims1()?;
    if !applies(k, x) {
        return Ok(x.index_select(&ids.to_dtype(DType::U32)?, 0)?);
    }
    let out = gather_rows(&x.reshape((1, n, c))?, &ids.reshape((1, m))?, k)?;
    Ok(out.reshape((m, c))?)
}

/// Rows of x picked along dim 1, the same index for every column: x [B,N,C], ids [B,M]
/// (u32, < N) -> out [B,M,C] with `out[b,m,:] = x[b, ids[b,m], :]` (candle's
/// `x.gather(ids broadcast to [B,M,C], 1)`).
pub fn gather_rows(x: &Tensor, ids: &Tensor, k: Numerics) -> Result<Tensor> {
    let (b, _n, c) = x.dims3()?;
    let (bi, m) = ids.dims2()?;
    if bi != b {
        return Err(ModelError::shape("row ids", format!("[{b},M]"), ids.dims()));
    }
    let ids = ids.to_dtype(DType::U32)?;
    if !applies(k, x) {
        let idx = ids.unsqueeze(2)?.broadcast_as((b, m, c))?.contiguous()?;
        return Ok(x.gather(&idx, 1)?);
    }
    let op = GatherRows {
        deterministic: k.deterministic,
    };
    Ok(x.contiguous()?.apply_op2(&ids.detach().contiguous()?, op)?)
}

/// A value a custom op's forward leaves for its backward (cos of a sine's argument, a
/// max-pool's arg-max): kept only when the graph tracks gradients, and used once, so a
/// second backward over the same graph finds it gone and computes it again.
pub(crate) struct Kept<T>(Option<std::sync::Mutex<Option<T>>>);

impl<T> Kept<T> {
    pub(crate) fn new(tracked: bool) -> Self {
        Self(tracked.then(Default::default))
    }

    /// Whether the forward should produce the value.
    pub(crate) fn wanted(&self) -> bool {
        self.0.is_some()
    }

    pub(crate) fn put(&self, v: T) {
        if let Some(m) = &self.0 {
            *m.lock().unwrap_or_else(|e| e.into_inner()) = Some(v);
        }
    }

    pub(crate) fn take(&self) -> Option<T> {
        let m = self.0.as_ref()?;
        m.lock().unwrap_or_else(|e| e.into_inner()).take()
    }
}

/// The f32 data of a contiguous CPU tensor.
/// The f32 values of a contiguous CPU storage under `l` (every CPU kernel of pma reads its
/// inputs this way).
pub(crate) fn f32_slice<'a>(
    s: &'a CpuStorage,
    l: &Layout,
    what: &str,
) -> candle_core::Result<&'a [f32]> {
    let CpuStorage::F32(v) = s else {
        candle_core::bail!("{what}: expected f32, found {:?}", s.dtype())
    };
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&v[a..b]),
        None => candle_core::bail!("{what}: expected a contiguous tensor"),
    }
}

fn u32_slice<'a>(s: &'a CpuStorage, l: &Layout, what: &str) -> candle_core::Result<&'a [u32]> {
    let CpuStorage::U32(v) = s else {
        candle_core::bail!("{what}: expected u32 indices, found {:?}", s.dtype())
    };
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&v[a..b]),
        None => candle_core::bail!("{what}: expected contiguous indices"),
    }
}

/// For step accounting: on a CUDA device each row op is a memset of its zeroed output and
/// one kernel (`cuda::launch`); the CPU forward reports the same.
fn report_cuda_launches() {
    candle_core::account::report_launches(2, 0);
}

/// (B, M, C) of a gradient/output against ids [B,M].
fn dims_bmc(l_vals: &Layout, l_ids: &Layout, what: &str) -> candle_core::Result<[usize; 4]> {
    let (b, n, c) = l_vals.shape().dims3()?;
    let (bi, m) = l_ids.shape().dims2()?;
    if bi != b {
        candle_core::bail!("{what}: values [{b},{n},{c}] but ids [{bi},{m}]")
    }
    Ok([b, n, m, c])
}

/// Forward: x [B,N,C], ids [B,M] -> [B,M,C].
struct GatherRows {
    /// Sum the backward's rows in index order, without atomics ([`Numerics::deterministic`]).
    deterministic: bool,
}

impl CustomOp2 for GatherRows {
    fn name(&self) -> &'static str {
        "pma-gather-rows"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let [b, n, m, c] = dims_bmc(l1, l2, "gather rows")?;
        report_cuda_launches();
        let x = f32_slice(s1, l1, "gather rows: x")?;
        let ids = u32_slice(s2, l2, "gather rows: ids")?;
        let mut out = Vec::with_capacity(b * m * c);
        for (row, &i) in ids.iter().enumerate() {
            let i = i as usize;
            if i >= n {
                candle_core::bail!("gather rows: index {i} out of range for {n} rows")
            }
            let start = ((row / m) * n + i) * c;
            out.extend_from_slice(&x[start..start + c]);
        }
        Ok((CpuStorage::F32(out), Shape::from((b, m, c))))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        let [b, n, m, c] = dims_bmc(l1, l2, "gather rows")?;
        let out = cuda::launch(
            "pma_gather_rows_f32",
            s1,
            l1,
            s2,
            l2,
            [b, n, m, c],
            b * m * c,
            b * m * c,
        )?;
        Ok((out, Shape::from((b, m, c))))
    }

    fn bwd(
        &self,
        x: &Tensor,
        ids: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let n = x.dim(1)?;
        let gx = grad.contiguous()?.apply_op2_no_bwd(
            ids,
            &ScatterAddRows {
                n,
                deterministic: self.deterministic,
            },
        )?;
        Ok((Some(gx), None))
    }
}

/// Backward: grad [B,M,C], ids [B,M] -> grad_x [B,N,C], rows summed from zero.
struct ScatterAddRows {
    n: usize,
    /// The CUDA kernel sums in index order (the CPU always does).
    #[cfg_attr(not(feature = "cuda"), allow(dead_code))]
    deterministic: bool,
}

impl CustomOp2 for ScatterAddRows {
    fn name(&self) -> &'static str {
        "pma-scatter-add-rows"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let [b, m, _, c] = dims_bmc(l1, l2, "scatter-add rows")?;
        report_cuda_launches();
        let n = self.n;
        let g = f32_slice(s1, l1, "scatter-add rows: grad")?;
        let ids = u32_slice(s2, l2, "scatter-add rows: ids")?;
        // Index order, each slot from +0: the additions candle's index_add/scatter_add make.
        let mut dst = vec![0f32; b * n * c];
        for (row, &i) in ids.iter().enumerate() {
            let i = i as usize;
            if i >= n {
                candle_core::bail!("scatter-add rows: index {i} out of range for {n} rows")
            }
            let d = ((row / m) * n + i) * c;
            for (a, v) in dst[d..d + c].iter_mut().zip(&g[row * c..(row + 1) * c]) {
                *a += v;
            }
        }
        Ok((CpuStorage::F32(dst), Shape::from((b, n, c))))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        let [b, m, _, c] = dims_bmc(l1, l2, "scatter-add rows")?;
        let n = self.n;
        // Ordered: a thread per element of the output; atomics: one per element of grad.
        let (kernel, threads) = if self.deterministic {
            ("pma_scatter_add_rows_ordered_f32", b * n * c)
        } else {
            ("pma_scatter_add_rows_f32", b * m * c)
        };
        let out = cuda::launch(kernel, s1, l1, s2, l2, [b, n, m, c], threads, b * n * c)?;
        Ok((out, Shape::from((b, n, c))))
    }
}

#[cfg(feature = "cuda")]
mod cuda {
    use std::sync::OnceLock;

    use candle_core::backend::BackendStorage;
    use candle_core::cuda_backend::cudarc::driver::{LaunchConfig, PushKernelArg};
    use candle_core::cuda_backend::WrapErr;
    use candle_core::{CudaStorage, Layout};

    /// PTX of `kernels/rows.cu`, compiled once per process.
    fn ptx() -> candle_core::Result<&'static str> {
        static PTX: OnceLock<Result<String, String>> = OnceLock::new();
        crate::compute::cuda::ptx(&PTX, super::ROWS_CU, "compute/ops/kernels/rows.cu")
    }

    /// Run `kernel` (one of rows.cu's, same argument list) with values s1 and ids s2 into a
    /// zeroed f32 buffer of `out_len` elements, over `threads` elements (grid-stride).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn launch(
        kernel: &str,
        s1: &CudaStorage,
        l1: &Layout,
        s2: &CudaStorage,
        l2: &Layout,
        [b, n, m, c]: [usize; 4],
        threads: usize,
        out_len: usize,
    ) -> candle_core::Result<CudaStorage> {
        super::report_cuda_launches();
        let dev = s1.device().clone();
        let to_u32 = |v: usize, what: &str| {
            u32::try_from(v).map_err(|_| {
                candle_core::Error::Msg(format!("{kernel}: {what} {v} exceeds the kernel's u32"))
            })
        };
        let dims = [
            to_u32(b, "B")?,
            to_u32(n, "N")?,
            to_u32(m, "M")?,
            to_u32(c, "C")?,
        ];
        let blocks = to_u32(threads.div_ceil(256).clamp(1, 65_535), "blocks")?;
        let func = dev.get_or_load_custom_func(kernel, "pma_rows", ptx()?)?;
        let vals = s1.as_cuda_slice::<f32>()?.slice(l1.start_offset()..);
        let ids = s2.as_cuda_slice::<u32>()?.slice(l2.start_offset()..);
        let out = dev.alloc_zeros::<f32>(out_len.max(1))?;
        if threads > 0 {
            let cfg = LaunchConfig {
                grid_dim: (blocks, 1, 1),
                block_dim: (256, 1, 1),
                shared_mem_bytes: 0,
            };
            let mut builder = func.builder();
            builder.arg(&vals);
            builder.arg(&ids);
            builder.arg(&out);
            for d in &dims {
                builder.arg(d);
            }
            // SAFETY: the argument list matches rows.cu's kernels; every index is bounds-checked
            // inside the kernel and the grid-stride loop covers `threads` elements.
            unsafe { builder.launch(cfg) }.w()?;
        }
        Ok(CudaStorage::wrap_cuda_slice(out, dev))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};

    fn bits(t: &Tensor) -> Vec<u32> {
        t.flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap()
            .iter()
            .map(|v| v.to_bits())
            .collect()
    }

    /// d/dx of `sum(y ⊙ up)`: the gradient `up` pulled back through whatever made `y`.
    fn grad_of(y: &Tensor, up: &Tensor, x: &Var) -> Tensor {
        let g = (y * up).unwrap().sum_all().unwrap().backward().unwrap();
        g.get(x).unwrap().clone()
    }

    /// Values with mixed magnitudes, so that a different summation order shows in the bits.
    fn values(len: usize, seed: u32) -> Vec<f32> {
        (0..len as u32)
            .map(|i| {
                let h = (i.wrapping_mul(2_654_435_761) ^ seed).wrapping_mul(40_503);
                let u = (h >> 8) as f32 / (1u32 << 24) as f32 - 0.5;
                u * [1.0, 1e-3, 37.0, 1e4][(h & 3) as usize]
            })
            .collect()
    }

    #[test]
    fn select_rows_matches_index_select_bitwise() {
        let dev = Device::Cpu;
        let (n, c, m) = (7, 5, 40);
        let x = Var::from_vec(values(n * c, 1), (n, c), &dev).unwrap();
        // Many rays per code, repeats in any order (like a chunk's frame codes).
        let ids: Vec<u32> = (0..m as u32).map(|i| (i * 5 + i / 3) % n as u32).collect();
        let ids = Tensor::from_vec(ids, m, &dev).unwrap();
        let up = Tensor::from_vec(values(m * c, 2), (m, c), &dev).unwrap();

        let plain = x.as_tensor().index_select(&ids, 0).unwrap();
        let ours = select_rows(x.as_tensor(), &ids, Numerics::PARITY).unwrap();
        assert_eq!(bits(&ours), bits(&plain));
        let (a, b) = (grad_of(&ours, &up, &x), grad_of(&plain, &up, &x));
        assert_eq!(bits(&a), bits(&b));
        // The gradient really accumulates: a row picked k times gets k contributions.
        assert!(bits(&a).iter().any(|&v| v != 0));
    }

    #[test]
    fn gather_rows_matches_gather_bitwise() {
        let dev = Device::Cpu;
        let (b, n, c) = (6, 9, 4);
        let x = Var::from_vec(values(b * n * c, 3), (b, n, c), &dev).unwrap();
        // A permutation per row (merge_raw) for some rows, repeats for others.
        let ids: Vec<u32> = (0..b)
            .flat_map(|r| {
                (0..n).map(move |i| match r % 2 {
                    0 => ((i * 4 + r) % n) as u32,
                    _ => ((i * i + r) % 3) as u32,
                })
            })
            .collect();
        let ids = Tensor::from_vec(ids, (b, n), &dev).unwrap();
        let up = Tensor::from_vec(values(b * n * c, 4), (b, n, c), &dev).unwrap();

        let idx = ids.unsqueeze(2).unwrap().broadcast_as((b, n, c)).unwrap();
        let plain = x.as_tensor().gather(&idx.contiguous().unwrap(), 1).unwrap();
        let ours = gather_rows(x.as_tensor(), &ids, Numerics::PARITY).unwrap();
        assert_eq!(bits(&ours), bits(&plain));
        assert_eq!(
            bits(&grad_of(&ours, &up, &x)),
            bits(&grad_of(&plain, &up, &x))
        );
    }

    #[test]
    fn bad_index_is_an_error() {
        let x = Tensor::zeros((3, 2), DType::F32, &Device::Cpu).unwrap();
        let ids = Tensor::new(&[0u32, 3], &Device::Cpu).unwrap();
        let e = select_rows(&x, &ids, Numerics::PARITY)
            .unwrap_err()
            .to_string();
        assert!(e.contains("index 3 out of range for 3 rows"), "{e}");
        let ids = Tensor::new(&[[0u32, 1]], &Device::Cpu).unwrap();
        assert!(gather_rows(
            &x.reshape((1, 3, 2)).unwrap(),
            &ids.repeat((2, 1)).unwrap(),
            Numerics::PARITY
        )
        .is_err());
    }

    /// CUDA against the CPU (skipped without a GPU): values identical, gradients equal up to
    /// the order of the atomic additions.
    #[test]
    fn cuda_matches_cpu() {
        let Ok(cuda) = Device::new_cuda(0) else {
            return;
        };
        let (b, n, c, m) = (3, 11, 128, 300);
        let run = |dev: &Device| {
            let x = Var::from_vec(values(b * n * c, 5), (b, n, c), dev).unwrap();
            let ids: Vec<u32> = (0..b * m).map(|i| ((i * 7 + i / 5) % n) as u32).collect();
            let ids = Tensor::from_vec(ids, (b, m), dev).unwrap();
            let up = Tensor::from_vec(values(b * m * c, 6), (b, m, c), dev).unwrap();
            let y = gather_rows(x.as_tensor(), &ids, Numerics::PARITY).unwrap();
            let gx = grad_of(&y, &up, &x).to_device(&Device::Cpu).unwrap();
            (y.to_device(&Device::Cpu).unwrap(), gx)
        };
        let (y_cpu, g_cpu) = run(&Device::Cpu);
        let (y_gpu, g_gpu) = run(&cuda);
        assert_eq!(bits(&y_gpu), bits(&y_cpu));
        let max_abs = |t: &Tensor| {
            t.abs()
                .unwrap()
                .max_all()
                .unwrap()
                .to_scalar::<f32>()
                .unwrap()
        };
        let (diff, scale) = (max_abs(&(g_gpu - &g_cpu).unwrap()), max_abs(&g_cpu));
        assert!(
            diff <= 1e-5 * scale.max(1.0),
            "max |cuda - cpu| {diff} (scale {scale})"
        );
    }
}
