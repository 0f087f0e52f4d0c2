//! A linear layer followed by its activation as one op on a GPU's route: `max(x Wᵀ + b, 0)`
//! (the density trunk, the colour head's hidden layer) and `sin(x Wᵀ + b)` (the pose
//! extractor's SIREN layers, W and b already scaled by ω).
//!
//! On candle's ops the layer is the product, a bias add and the activation (two passes over
//! [rows, out] each after the product's write), and backward the activation's gradient
//! (ReLU: a zero tensor, a comparison, a cast and a product; sine: a cosine and a product)
//! and a column sum for the bias. Here the bias add and the activation are one kernel after
//! cuBLAS's product, and the backward is one kernel that writes the product's gradient and,
//! per block of rows, its column sums, then a small one that adds those in block order (the
//! bias gradient: no atomics, a run repeats bit for bit). What the backward needs is one
//! [rows, out] tensor: the ReLU's output (its gradient passes where it is positive,
//! PyTorch's rule, the reference's; candle's passes where the input is ≥ 0, which differs at
//! an input of exactly 0), or the sine's product before the bias (cos(z + b) is recomputed).
//!
//! On the CPU's route the layer is [`crate::compute::fused::linear`] and candle's
//! activation, whose bits are pma's parity reference. A CUDA device runs cuBLAS and
//! `cuda/kernels/bias_act.cu`; a CPU run accounted as CUDA runs the CPU code here, which
//! forms every sum in the kernels' order and is counted as them.

use std::sync::{Arc, Mutex};

use candle_core::{CpuStorage, CustomOp1, CustomOp2, CustomOp3, Layout, Shape, Tensor};

use crate::compute::fused::{applies_cuda, cpu_product, linear_dims, models_cuda, report_linear};
use crate::compute::numerics::Numerics;
use crate::compute::ops::f32_slice;
use crate::error::Result;

/// Rows per partial sum of the bias gradient (`PMA_BIAS_ACT_ROWS` in the kernel).
pub const ROWS_PER_BLOCK: usize = 256;

/// The activation after the linear layer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Act {
    Relu,
    Sine,
}

/// `max(x Wᵀ + b, 0)`: x [rows,in], W [out,in] (PyTorch's layout), b [out] -> [rows,out].
pub fn linear_relu(x: &Tensor, w: &Tensor, b: &Tensor, k: Numerics) -> Result<Tensor> {
    linear_act(x, w, b, Act::Relu, k)
}

/// `sin(x Wᵀ + b)` (the sine [`crate::compute::fast_sine::sin`] under `k` on candle's route).
pub fn linear_sine(x: &Tensor, w: &Tensor, b: &Tensor, k: Numerics) -> Result<Tensor> {
    linear_act(x, w, b, Act::Sine, k)
}

fn linear_act(x: &Tensor, w: &Tensor, b: &Tensor, act: Act, k: Numerics) -> Result<Tensor> {
    let fits = x.rank() == 2
        && w.rank() == 2
        && b.rank() == 1
        && x.dim(1)? == w.dim(1)?
        && b.dim(0)? == w.dim(0)?;
    let on = [x, w, b];
    if !(fits && (applies_cuda(k, &on) || models_cuda(k, &on))) {
        let pre = crate::compute::fused::linear(x, w, b, k)?;
        return match act {
            Act::Relu => Ok(pre.relu()?),
            Act::Sine => crate::compute::fast_sine::sin(&pre, k.fast_sine),
        };
    }
    let (x, w, b) = (x.contiguous()?, w.contiguous()?, b.contiguous()?);
    let op = LinearAct {
        act,
        fast: k.fast_sine,
        keep: act == Act::Sine && (x.track_op() || w.track_op() || b.track_op()),
        z: Mutex::new(None),
    };
    Ok(candle_core::cuda::with_gemm_reduced_precision_f32(
        k.tf32,
        || x.apply_op3(&w, &b, op),
    )?)
}

/// `y = act(z + b)` row by row (z: [rows, b.len()]); the sine through `trig`.
fn bias_act(z: &[f32], b: &[f32], act: Act, fast: bool) -> Vec<f32> {
    let mut a = Vec::with_capacity(z.len());
    for row in z.chunks_exact(b.len().max(1)) {
        a.extend(row.iter().zip(b).map(|(v, c)| v + c));
    }
    match act {
        Act::Relu => a
            .into_iter()
            .map(|s| if s > 0.0 { s } else { 0.0 })
            .collect(),
        Act::Sine => crate::compute::fast_sine::trig(&a, 0, fast),
    }
}

/// (gz, partial column sums [blocks, out]) as the kernel forms them: ReLU from its output
/// `kept`, the sine from its product `kept` and the bias.
fn act_grad(grad: &[f32], kept: &[f32], b: &[f32], act: Act, fast: bool) -> (Vec<f32>, Vec<f32>) {
    let out = b.len();
    let rows = kept.len() / out.max(1);
    let gz: Vec<f32> = match act {
        Act::Relu => grad
            .iter()
            .zip(kept)
            .map(|(&g, &v)| if v > 0.0 { g } else { 0.0 })
            .collect(),
        Act::Sine => {
            let mut a = Vec::with_capacity(kept.len());
            for row in kept.chunks_exact(out.max(1)) {
                a.extend(row.iter().zip(b).map(|(v, c)| v + c));
            }
            let cos = crate::compute::fast_sine::trig(&a, 1, fast);
            grad.iter().zip(&cos).map(|(g, c)| g * c).collect()
        }
    };
    let mut part = Vec::with_capacity(rows.div_ceil(ROWS_PER_BLOCK) * out);
    for first in (0..rows).step_by(ROWS_PER_BLOCK) {
        let mut acc = vec![0f32; out];
        for row in gz[first * out..(first + ROWS_PER_BLOCK).min(rows) * out].chunks_exact(out) {
            for (a, v) in acc.iter_mut().zip(row) {
                *a += v;
            }
        }
        part.extend(acc);
    }
    (gz, part)
}

/// The bias gradient: the partial sums added in block order from zero.
fn bias_grad(part: &[f32], out: usize) -> Vec<f32> {
    let mut gb = vec![0f32; out];
    for blk in part.chunks_exact(out.max(1)) {
        for (s, p) in gb.iter_mut().zip(blk) {
            *s += p;
        }
    }
    gb
}

/// The sine's product z kept from the forward for the backward.
enum Kept {
    /// With its bytes held live on the modeled device while it is kept.
    Cpu(
        Vec<f32>,
        #[allow(dead_code, reason = "a guard: its drop ends the bytes' life")]
        candle_core::account::Held,
    ),
    #[cfg(feature = "cuda")]
    Cuda(candle_core::CudaStorage),
}

struct LinearAct {
    act: Act,
    /// Sine flavour of the CPU code (the kernels take the device's sinf/cosf).
    fast: bool,
    /// Keep z for the backward (a sine whose graph tracks gradients).
    keep: bool,
    z: Mutex<Option<Kept>>,
}

impl LinearAct {
    /// The name the bias-and-activation kernel is counted under.
    fn epilogue(&self) -> &'static str {
        match self.act {
            Act::Relu => "pma-bias-relu",
            Act::Sine => "pma-bias-sine",
        }
    }
}

impl CustomOp3 for LinearAct {
    fn name(&self) -> &'static str {
        "matmul"
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
        let d = linear_dims(l1, l2, l3)?;
        report_linear(true, d, self.epilogue(), 0);
        let (rows, out) = (d.0, d.2);
        let z = cpu_product((s1, l1), (s2, l2), d)?;
        let y = bias_act(&z, f32_slice(s3, l3, "linear act: b")?, self.act, self.fast);
        if self.keep {
            let held = candle_core::account::hold(true, 4 * z.len());
            *self.z.lock().unwrap_or_else(|e| e.into_inner()) = Some(Kept::Cpu(z, held));
        }
        Ok((CpuStorage::F32(y), Shape::from((rows, out))))
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
        use candle_core::backend::BackendStorage;
        let (rows, inn, out) = linear_dims(l1, l2, l3)?;
        report_linear(false, (rows, inn, out), self.epilogue(), 0);
        // cuBLAS, then the bias add and activation; the product is freed on return unless
        // the sine's backward needs it.
        let z = s1.matmul(s2, (1, rows, out, inn), l1, &l2.transpose(0, 1)?)?;
        let y = crate::compute::cuda::bias_act(&z, s3, l3, [rows, out], self.act == Act::Sine)?;
        if self.keep {
            *self.z.lock().unwrap_or_else(|e| e.into_inner()) = Some(Kept::Cuda(z));
        }
        Ok((y, Shape::from((rows, out))))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        b: &Tensor,
        y: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let kept = match self.act {
            Act::Relu => None,
            Act::Sine => Some(
                self.z
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .take()
                    .ok_or_else(|| candle_core::Error::Msg("linear sine: z was not kept".into()))?,
            ),
        };
        let stash = Arc::new(Mutex::new(None));
        let op = ActGrad {
            act: self.act,
            fast: self.fast,
            y,
            z: kept,
            stash: stash.clone(),
        };
        let gz = grad.contiguous()?.apply_op2_no_bwd(b, &op)?;
        drop(op);
        let gb = b.apply_op1_no_bwd(&BiasSum { stash })?;
        // candle's matmul backward for x · (Wᵀ), then the transpose's: the same products.
        let wt = w.t()?;
        // No product for an input that takes no gradient (the GNN's pose input).
        let gx = x.track_op().then(|| gz.matmul(&wt.t()?)).transpose()?;
        let gw = x.t()?.matmul(&gz)?.t()?;
        Ok((gx, Some(gw), Some(gb)))
    }
}

/// The bias gradient's partial sums, from [`ActGrad`] to [`BiasSum`].
enum Partial {
    Cpu(Vec<f32>),
    #[cfg(feature = "cuda")]
    Cuda(candle_core::cuda_backend::cudarc::driver::CudaSlice<f32>),
}

type Stash = Arc<Mutex<Option<(Partial, usize)>>>;

/// The product's gradient on (grad, b), from the ReLU's output `y` or the sine's kept `z`,
/// leaving the bias gradient's partial sums (and the number of blocks) in the stash. One
/// kernel.
struct ActGrad<'a> {
    act: Act,
    fast: bool,
    y: &'a Tensor,
    z: Option<Kept>,
    stash: Stash,
}

impl ActGrad<'_> {
    fn dims(&self, l1: &Layout, l2: &Layout) -> candle_core::Result<(usize, usize)> {
        let (rows, out) = l1.shape().dims2()?;
        if l2.shape().dims1()? != out || self.y.dims() != [rows, out] {
            candle_core::bail!(
                "linear act: grad {:?}, b {:?} and the output {:?} do not agree",
                l1.shape(),
                l2.shape(),
                self.y.shape()
            )
        }
        let blocks = rows.div_ceil(ROWS_PER_BLOCK);
        let (ro, bo) = ((rows * out * 4) as u64, (blocks * out * 4) as u64);
        candle_core::account::report_bytes(2 * ro + (out * 4) as u64, ro + bo);
        Ok((rows, out))
    }

    fn put(&self, part: Partial, rows: usize) {
        let blocks = rows.div_ceil(ROWS_PER_BLOCK);
        *self.stash.lock().unwrap_or_else(|e| e.into_inner()) = Some((part, blocks));
    }
}

impl CustomOp2 for ActGrad<'_> {
    fn name(&self) -> &'static str {
        match self.act {
            Act::Relu => "pma-relu-grad",
            Act::Sine => "pma-sine-grad",
        }
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let (rows, out) = self.dims(l1, l2)?;
        let grad = f32_slice(s1, l1, "linear act: grad")?;
        let b = f32_slice(s2, l2, "linear act: b")?;
        let (ys, yl) = self.y.storage_and_layout();
        let (gz, part) = match (&self.z, &*ys) {
            (Some(Kept::Cpu(z, _)), _) => act_grad(grad, z, b, self.act, self.fast),
            (None, candle_core::Storage::Cpu(y)) => {
                let y = f32_slice(y, yl, "linear act: y")?;
                act_grad(grad, y, b, self.act, self.fast)
            }
            _ => candle_core::bail!("linear act: what the backward needs is not on the CPU"),
        };
        self.put(Partial::Cpu(part), rows);
        Ok((CpuStorage::F32(gz), Shape::from((rows, out))))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        let (rows, out) = self.dims(l1, l2)?;
        let (ys, yl) = self.y.storage_and_layout();
        let whole = Layout::contiguous((rows, out));
        let kept = match (&self.z, &*ys) {
            (Some(Kept::Cuda(z)), _) => (z, &whole),
            (None, candle_core::Storage::Cuda(y)) => (y, yl),
            _ => candle_core::bail!("linear act: what the backward needs is not on the GPU"),
        };
        let (gz, part) = crate::compute::cuda::act_grad(
            (s1, l1),
            kept,
            (s2, l2),
            [rows, out],
            self.act == Act::Sine,
        )?;
        self.put(Partial::Cuda(part), rows);
        Ok((gz, Shape::from((rows, out))))
    }
}

/// The bias gradient [out] from the stash (applied to b, for its device and shape). One
/// kernel.
struct BiasSum {
    stash: Stash,
}

impl BiasSum {
    fn take(&self, out: usize) -> candle_core::Result<(Partial, usize)> {
        let got = self.stash.lock().unwrap_or_else(|e| e.into_inner()).take();
        let (part, blocks) =
            got.ok_or_else(|| candle_core::Error::Msg("linear act: no partial sums".into()))?;
        let (r, w) = ((blocks * out * 4) as u64, (out * 4) as u64);
        candle_core::account::report_bytes(r, w);
        Ok((part, blocks))
    }
}

impl CustomOp1 for BiasSum {
    fn name(&self) -> &'static str {
        "pma-bias-grad"
    }

    fn cpu_fwd(&self, _: &CpuStorage, l: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
        let out = l.shape().elem_count();
        match self.take(out)? {
            (Partial::Cpu(part), _) => {
                Ok((CpuStorage::F32(bias_grad(&part, out)), Shape::from(out)))
            }
            #[cfg(feature = "cuda")]
            _ => candle_core::bail!("linear act: the partial sums are not on the CPU"),
        }
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s: &candle_core::CudaStorage,
        l: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        let out = l.shape().elem_count();
        match self.take(out)? {
            (Partial::Cuda(part), blocks) => Ok((
                crate::compute::cuda::bias_grad_sum(s, &part, [blocks, out])?,
                Shape::from(out),
            )),
            _ => candle_core::bail!("linear act: the partial sums are not on the GPU"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};

    fn random(shape: &[usize], seed: u64, scale: f32) -> Tensor {
        let n: usize = shape.iter().product();
        let mut s = seed;
        let v: Vec<f32> = (0..n)
            .map(|_| {
                s = s
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1_442_695_040_888_963_407);
                ((s >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0) * scale
            })
            .collect();
        Tensor::from_vec(v, shape, &Device::Cpu).unwrap()
    }

    fn flat(t: &Tensor) -> Vec<f32> {
        t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
    }

    /// Output and the gradients of x, W and b for upstream gradient `up`.
    fn run(x: &Tensor, w: &Tensor, b: &Tensor, up: &Tensor, act: Act) -> [Vec<f32>; 4] {
        let [xv, wv, bv] = [x, w, b].map(|t| Var::from_tensor(t).unwrap());
        let y = linear_act(
            xv.as_tensor(),
            wv.as_tensor(),
            bv.as_tensor(),
            act,
            Numerics::PARITY,
        )
        .unwrap();
        let g = (&y * up).unwrap().sum_all().unwrap().backward().unwrap();
        [
            flat(&y),
            flat(g.get(&xv).unwrap()),
            flat(g.get(&wv).unwrap()),
            flat(g.get(&bv).unwrap()),
        ]
    }

    /// The op on the CUDA route against candle's (the CPU route): output and the gradients
    /// of x and W bit for bit (the same product, bias add and activation, the sine and
    /// cosine the same libm recipe, and the same products backward on the same gradient;
    /// no ReLU input is exactly 0 here); the bias gradient sums per block of 256 rows, then
    /// over blocks, so within 1e-5 times the sum of the magnitudes. Counted as its kernels:
    /// no comparison, cast, sine, cosine, product or reduction of candle's beyond the loss's.
    #[test]
    fn counted_as_cuda_matches_candles_ops() {
        for act in [Act::Relu, Act::Sine] {
            for (rows, inn, out, seed) in [(1000, 7, 33, 1), (256, 3, 4, 2), (3, 5, 2, 3)] {
                let x = random(&[rows, inn], seed, 1.0);
                let w = random(&[out, inn], seed + 10, 8.0);
                let b = random(&[out], seed + 20, 4.0);
                let up = random(&[rows, out], seed + 30, 1.0);
                let plain = run(&x, &w, &b, &up, act);
                let acc = crate::compute::account::Account::start(
                    &Device::Cpu,
                    crate::compute::account::Route::Cuda,
                )
                .unwrap();
                let fused = run(&x, &w, &b, &up, act);
                let report = acc.finish();
                let launches = |name: &str| report.ops.get(name).map_or(0, |c| c.launches);
                let (fwd, bwd) = match act {
                    Act::Relu => ("pma-bias-relu", "pma-relu-grad"),
                    Act::Sine => ("pma-bias-sine", "pma-sine-grad"),
                };
                assert_eq!(launches(fwd), 1);
                assert_eq!(launches(bwd) + launches("pma-bias-grad"), 2);
                for name in ["relu", "sin", "cos", "cmp-ge", "to-dtype", "add"] {
                    assert_eq!(launches(name), 0, "{name}");
                }
                // The test's own loss (y·up summed) is the one reduction and every product.
                assert_eq!(launches("reduce-sum"), 1);
                assert_eq!(launches("mul"), 3);
                for (i, what) in ["y", "grad x", "grad W"].iter().enumerate() {
                    assert_eq!(plain[i], fused[i], "{what} ({act:?})");
                }
                let ups = up.to_vec2::<f32>().unwrap();
                for (j, (a, c)) in plain[3].iter().zip(&fused[3]).enumerate() {
                    let mag: f32 = (0..rows).map(|r| ups[r][j].abs()).sum();
                    assert!(
                        (a - c).abs() <= 1e-5 * mag.max(1.0),
                        "grad b[{j}] ({act:?}): {a} vs {c}"
                    );
                }
            }
        }
    }

    /// The ReLU's gradient passes where the output is positive only (PyTorch's rule): at an
    /// input of exactly 0 it is 0, where candle's ReLU passes it.
    #[test]
    fn the_gradient_stops_where_the_output_is_zero() {
        let (grad, y) = (vec![1.0f32, 2.0, 3.0, 4.0], vec![0.5f32, 0.0, 0.0, 2.0]);
        let (gz, part) = act_grad(&grad, &y, &[0.0, 0.0], Act::Relu, false);
        assert_eq!(gz, vec![1.0, 0.0, 0.0, 4.0]);
        assert_eq!(part, vec![1.0, 4.0]);
    }

    /// Column sums per block of [`ROWS_PER_BLOCK`] rows, then over blocks in order.
    #[test]
    fn the_bias_gradient_sums_per_block_then_over_blocks() {
        let rows = 2 * ROWS_PER_BLOCK + 3;
        let grad: Vec<f32> = (0..rows).map(|r| 0.1 + (r % 9) as f32 * 0.37).collect();
        let y = vec![1.0f32; rows];
        let (_, part) = act_grad(&grad, &y, &[0.0], Act::Relu, false);
        let block = |rs: std::ops::Range<usize>| rs.fold(0f32, |s, r| s + grad[r]);
        let want = [
            block(0..ROWS_PER_BLOCK),
            block(ROWS_PER_BLOCK..2 * ROWS_PER_BLOCK),
            block(2 * ROWS_PER_BLOCK..rows),
        ];
        assert_eq!(part, want);
        assert_eq!(bias_grad(&part, 1), vec![0.0 + want[0] + want[1] + want[2]]);
    }

    /// A sine layer keeps its product for the backward only when the graph tracks
    /// gradients: an inference pass holds nothing.
    #[test]
    fn a_sine_keeps_its_product_only_for_a_backward() {
        let (x, w, b) = (
            random(&[300, 4], 1, 1.0),
            random(&[8, 4], 2, 1.0),
            random(&[8], 3, 1.0),
        );
        let acc = crate::compute::account::Account::start(
            &Device::Cpu,
            crate::compute::account::Route::Cuda,
        )
        .unwrap();
        let y = linear_sine(&x, &w, &b, Numerics::PARITY).unwrap();
        let untracked = acc.finish();
        drop(y);
        let wv = Var::from_tensor(&w).unwrap();
        let acc = crate::compute::account::Account::start(
            &Device::Cpu,
            crate::compute::account::Route::Cuda,
        )
        .unwrap();
        let y = linear_sine(&x, wv.as_tensor(), &b, Numerics::PARITY).unwrap();
        let tracked = acc.finish();
        drop(y);
        // The kept product is one more [300, 8] f32 buffer alive at the peak.
        assert_eq!(
            tracked.peak_live_bytes,
            untracked.peak_live_bytes + 300 * 8 * 4
        );
    }
}
