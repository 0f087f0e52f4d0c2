//! A SIREN layer on a narrow input with each row scaled, `s_r · sin(x Wᵀ + b)` with
//! x [rows, ≤ 4], as one op on a GPU's route: the two point encoders, which map x̄ (3
//! coordinates per joint and point) to [N·24, 64] each, the second one scaled by the
//! window weight w of the row's joint (x̃ = w ⊙ z, the modulator's input).
//!
//! With three inputs per output the product does no work worth the name; what costs is
//! memory traffic over the [N·24, 64] output. candle's ops write it from the product, read
//! and write it in the bias add and in the sine, and backward run a cosine, a product, a
//! column sum and the weight's product over it, about a dozen passes in all, and the window
//! weight's product and its gradient another eight. Here the forward writes the output
//! once; the backward reads the upstream gradient once, recomputing the argument from x
//! (three products per element) and its cosine, and sums the weight and bias gradients per
//! block of rows, then over the blocks in block order, in two launches without atomics (a
//! run repeats bit for bit); when x or the scale needs a gradient (x̄ does: it is divided by
//! the learned box scales; w does: it holds the learned feature window), a third launch
//! reads it again for both, row by row.
//!
//! On the CPU's route the layer is candle's ops, whose CPU bits are pma's parity
//! reference. A CUDA device runs `cuda/kernels/sine_linear.cu`; a CPU run accounted
//! as CUDA runs the CPU code here, which forms every sum in the kernels' order and is
//! counted as them.

use candle_core::{CpuStorage, CustomOp3, Layout, Shape, Tensor};

use crate::compute::fused::{applies_cuda, models_cuda};
use crate::compute::numerics::Numerics;
use crate::compute::ops::f32_slice;
use crate::error::Result;

/// The widest input the kernels take (their per-thread sums are an array this long + 1).
pub const MAX_IN: usize = 4;

/// Rows per partial sum of the backward (`PMA_SINE_LINEAR_ROWS` in the kernel).
pub const ROWS_PER_BLOCK: usize = 1024;

/// `scale_r · sin(x Wᵀ + b)`: x [rows,in], W [out,in], b [out], scale [rows] (none: 1) ->
/// [rows,out]; the sine is [`crate::compute::fast_sine::sin`] under `k` on candle's route.
pub fn sine_linear(
    x: &Tensor,
    w: &Tensor,
    b: &Tensor,
    scale: Option<&Tensor>,
    k: Numerics,
) -> Result<Tensor> {
    let rows = x.dim(0)?;
    let fits = x.rank() == 2
        && w.rank() == 2
        && b.rank() == 1
        && x.dim(1)? == w.dim(1)?
        && b.dim(0)? == w.dim(0)?
        && (1..=MAX_IN).contains(&x.dim(1)?)
        && scale.is_none_or(|s| s.dims() == [rows]);
    let mut on = vec![x, w, b];
    on.extend(scale);
    let modeled = models_cuda(k, &on);
    if !(fits && (applies_cuda(k, &on) || modeled)) {
        let pre = crate::compute::fused::linear(x, w, b, k)?;
        let y = crate::compute::fast_sine::sin(&pre, k.fast_sine)?;
        return Ok(match scale {
            Some(s) => y.broadcast_mul(&s.unsqueeze(1)?)?,
            None => y,
        });
    }
    // [W | b]: the op's second input, so that one backward output is its gradient.
    let wb = Tensor::cat(&[w, &b.unsqueeze(1)?], 1)?;
    let scale = match scale {
        Some(s) => s.contiguous()?,
        None => Tensor::ones(rows, x.dtype(), x.device())?,
    };
    Ok(x.contiguous()?
        .apply_op3(&wb, &scale, SineLinear { fast: k.fast_sine })?)
}

/// Bytes the forward kernel reads (x, [W|b], s) and writes (y).
fn fwd_bytes((rows, inp, out): (usize, usize, usize)) -> (u64, u64) {
    let f = |v: usize| 4 * v as u64;
    (f(rows * inp + out * (inp + 1) + rows), f(rows * out))
}

/// (rows, in, out) of x [rows,in], [W|b] [out,in+1] and s [rows], checked.
fn dims(l1: &Layout, l2: &Layout, l3: &Layout) -> candle_core::Result<(usize, usize, usize)> {
    let (rows, inp) = l1.shape().dims2()?;
    let (out, inp1) = l2.shape().dims2()?;
    if inp1 != inp + 1 || l3.shape().dims1()? != rows || !(1..=MAX_IN).contains(&inp) {
        candle_core::bail!(
            "sine linear: x {:?}, [W|b] {:?}, s {:?} do not agree (at most {MAX_IN} inputs)",
            l1.shape(),
            l2.shape(),
            l3.shape()
        )
    }
    Ok((rows, inp, out))
}

/// Every argument `x Wᵀ + b`, row-major [rows,out], in the kernels' order.
fn arguments(x: &[f32], wb: &[f32], inp: usize) -> Vec<f32> {
    let out = wb.len() / (inp + 1);
    let mut a = Vec::with_capacity(x.len() / inp * out);
    for xr in x.chunks_exact(inp) {
        for wj in wb.chunks_exact(inp + 1) {
            let mut s = xr[0] * wj[0];
            for c in 1..inp {
                s += xr[c] * wj[c];
            }
            a.push(s + wj[inp]);
        }
    }
    a
}

/// The gradient of [W|b], [out, in+1], from the upstream gradient, the scales and cos of
/// the arguments, summed as the kernels do: per block of rows from zero, then the blocks in
/// order from zero.
fn weight_grads(
    grad: &[f32],
    sc: &[f32],
    cos: &[f32],
    x: &[f32],
    (inp, out): (usize, usize),
) -> Vec<f32> {
    let rows = sc.len();
    let width = inp + 1;
    let mut g = vec![0f32; out * width];
    let mut part = vec![0f32; out * width];
    for first in (0..rows).step_by(ROWS_PER_BLOCK) {
        part.fill(0.0);
        for r in first..(first + ROWS_PER_BLOCK).min(rows) {
            let xr = &x[r * inp..(r + 1) * inp];
            for j in 0..out {
                let ga = grad[r * out + j] * sc[r] * cos[r * out + j];
                let acc = &mut part[j * width..(j + 1) * width];
                for c in 0..inp {
                    acc[c] += ga * xr[c];
                }
                acc[inp] += ga;
            }
        }
        for (s, p) in g.iter_mut().zip(&part) {
            *s += p;
        }
    }
    g
}

/// Per row, [rows, in+1]: x's gradient (the sum over the outputs in order from zero of
/// grad·s·cos times W's column) and, in the last column, s's (the sum of grad·sin).
fn row_grads(
    grad: &[f32],
    sc: &[f32],
    (sin, cos): (&[f32], &[f32]),
    wb: &[f32],
    inp: usize,
) -> Vec<f32> {
    let (rows, out) = (sc.len(), wb.len() / (inp + 1));
    let mut g = vec![0f32; rows * (inp + 1)];
    for (r, acc) in g.chunks_exact_mut(inp + 1).enumerate() {
        for (j, wj) in wb.chunks_exact(inp + 1).enumerate() {
            let at = r * out + j;
            let ga = grad[at] * sc[r] * cos[at];
            for c in 0..inp {
                acc[c] += ga * wj[c];
            }
            acc[inp] += grad[at] * sin[at];
        }
    }
    g
}

struct SineLinear {
    /// Sine flavour of the CPU code (the kernels take the device's sinf/cosf).
    fast: bool,
}

impl CustomOp3 for SineLinear {
    fn name(&self) -> &'static str {
        "pma-sine-linear"
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
        let d = dims(l1, l2, l3)?;
        let (read, written) = fwd_bytes(d);
        candle_core::account::report_bytes(read, written);
        let x = f32_slice(s1, l1, "sine linear: x")?;
        let wb = f32_slice(s2, l2, "sine linear: [W|b]")?;
        let sc = f32_slice(s3, l3, "sine linear: s")?;
        let mut y = crate::compute::fast_sine::trig(&arguments(x, wb, d.1), 0, self.fast);
        for (row, &s) in y.chunks_exact_mut(d.2.max(1)).zip(sc) {
            for v in row {
                *v *= s;
            }
        }
        Ok((CpuStorage::F32(y), Shape::from((d.0, d.2))))
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
        let d = dims(l1, l2, l3)?;
        let (read, written) = fwd_bytes(d);
        candle_core::account::report_bytes(read, written);
        let y = crate::compute::cuda::sine_linear((s1, l1), (s2, l2), (s3, l3), d)?;
        Ok((y, Shape::from((d.0, d.2))))
    }

    fn bwd(
        &self,
        x: &Tensor,
        wb: &Tensor,
        sc: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let grad = grad.contiguous()?;
        let op = |of_rows| SineLinearGrad {
            x: x.clone(),
            fast: self.fast,
            of_rows,
        };
        let gwb = grad.apply_op3_no_bwd(wb, sc, &op(false))?;
        let (gx, gs) = match x.track_op() || sc.track_op() {
            // Narrowed views of an empty tensor would point past its storage.
            true if x.dim(0)? == 0 => (
                x.track_op().then(|| x.zeros_like()).transpose()?,
                sc.track_op().then(|| sc.zeros_like()).transpose()?,
            ),
            true => {
                let g = grad.apply_op3_no_bwd(wb, sc, &op(true))?;
                let inp = x.dim(1)?;
                (
                    x.track_op().then(|| g.narrow(1, 0, inp)).transpose()?,
                    sc.track_op()
                        .then(|| g.narrow(1, inp, 1)?.squeeze(1))
                        .transpose()?,
                )
            }
            false => (None, None),
        };
        Ok((gx, Some(gwb), gs))
    }
}

/// The backward as ops on (grad, [W|b], s) with x held: the gradient of [W|b] (two
/// kernels), or, `of_rows`, [rows, in+1]: x's gradient and s's (one kernel).
struct SineLinearGrad {
    x: Tensor,
    fast: bool,
    of_rows: bool,
}

impl SineLinearGrad {
    /// (rows, in, out), checked, and the op counted as its kernels.
    fn count(
        &self,
        l1: &Layout,
        l2: &Layout,
        l3: &Layout,
    ) -> candle_core::Result<(usize, usize, usize)> {
        let (rows, inp, out) = dims(self.x.layout(), l2, l3)?;
        if l1.shape().dims2()? != (rows, out) {
            candle_core::bail!("sine linear: grad {:?} is not [{rows},{out}]", l1.shape())
        }
        let f = |v: usize| 4 * v as u64;
        let inputs = f(rows * out + rows * inp + out * (inp + 1) + rows);
        let (launches, read, written) = match self.of_rows {
            true => (1, inputs, f(rows * (inp + 1))),
            false => {
                let part = rows.div_ceil(ROWS_PER_BLOCK) * out * (inp + 1);
                (2, inputs + f(part), f(part + out * (inp + 1)))
            }
        };
        candle_core::account::report_launches(launches, 0);
        candle_core::account::report_bytes(read, written);
        Ok((rows, inp, out))
    }
}

impl CustomOp3 for SineLinearGrad {
    fn name(&self) -> &'static str {
        match self.of_rows {
            true => "pma-sine-linear-grad-rows",
            false => "pma-sine-linear-grad",
        }
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
        let (rows, inp, _) = self.count(l1, l2, l3)?;
        let (xs, lx) = self.x.storage_and_layout();
        let candle_core::Storage::Cpu(xs) = &*xs else {
            candle_core::bail!("sine linear: x is not on the CPU")
        };
        let x = f32_slice(xs, lx, "sine linear: x")?;
        let grad = f32_slice(s1, l1, "sine linear: grad")?;
        let wb = f32_slice(s2, l2, "sine linear: [W|b]")?;
        let sc = f32_slice(s3, l3, "sine linear: s")?;
        let a = arguments(x, wb, inp);
        let (g, shape) = match self.of_rows {
            true => {
                let (sin, cos) = crate::compute::fast_sine::trig_pair(&a, self.fast);
                (
                    row_grads(grad, sc, (&sin, &cos), wb, inp),
                    Shape::from((rows, inp + 1)),
                )
            }
            false => {
                let cos = crate::compute::fast_sine::trig(&a, 1, self.fast);
                let out = wb.len() / (inp + 1);
                (
                    weight_grads(grad, sc, &cos, x, (inp, out)),
                    Shape::from((out, inp + 1)),
                )
            }
        };
        Ok((CpuStorage::F32(g), shape))
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
        let d = self.count(l1, l2, l3)?;
        let (xs, lx) = self.x.storage_and_layout();
        let candle_core::Storage::Cuda(xs) = &*xs else {
            candle_core::bail!("sine linear: x is not on the GPU")
        };
        let g = crate::compute::cuda::sine_linear_grad(
            (s1, l1),
            (xs, lx),
            (s2, l2),
            (s3, l3),
            d,
            self.of_rows,
        )?;
        let shape = match self.of_rows {
            true => Shape::from((d.0, d.1 + 1)),
            false => Shape::from((d.2, d.1 + 1)),
        };
        Ok((g, shape))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};

    fn random(shape: &[usize], seed: u64, lo: f32, hi: f32) -> Tensor {
        let n: usize = shape.iter().product();
        let mut s = seed;
        let v: Vec<f32> = (0..n)
            .map(|_| {
                s = s
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1_442_695_040_888_963_407);
                lo + (s >> 40) as f32 / (1u64 << 24) as f32 * (hi - lo)
            })
            .collect();
        Tensor::from_vec(v, shape, &Device::Cpu).unwrap()
    }

    /// Output and the gradients of x, W, b and the scale for upstream gradient `up`.
    fn run(x: &Tensor, w: &Tensor, b: &Tensor, sc: &Tensor, up: &Tensor) -> [Vec<f32>; 5] {
        let [xv, wv, bv, sv] = [x, w, b, sc].map(|t| Var::from_tensor(t).unwrap());
        let y = sine_linear(
            xv.as_tensor(),
            wv.as_tensor(),
            bv.as_tensor(),
            Some(sv.as_tensor()),
            Numerics::PARITY,
        )
        .unwrap();
        let grads = (&y * up).unwrap().sum_all().unwrap().backward().unwrap();
        let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        [
            flat(&y),
            flat(grads.get(&xv).unwrap()),
            flat(grads.get(&wv).unwrap()),
            flat(grads.get(&bv).unwrap()),
            flat(grads.get(&sv).unwrap()),
        ]
    }

    fn counted_as_cuda<T>(f: impl FnOnce() -> T) -> (T, crate::compute::account::Report) {
        let acc = crate::compute::account::Account::start(
            &Device::Cpu,
            crate::compute::account::Route::Cuda,
        )
        .unwrap();
        let out = f();
        (out, acc.finish())
    }

    /// |a − b| within `tol` times the sum of the magnitudes of the terms of the sum.
    fn close(a: &[f32], b: &[f32], mag: impl Fn(usize) -> f32, tol: f32, what: &str) {
        assert_eq!(a.len(), b.len(), "{what}: lengths");
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            assert!(
                (x - y).abs() <= tol * mag(i).max(1.0),
                "{what}[{i}]: {x} vs {y}"
            );
        }
    }

    /// The fused op (taken on the CUDA route) against candle's ops (the CPU route): the
    /// same values up to the order of the sums. Output within 5e-7 (four f32 ulps) times
    /// the argument's magnitude bound Σ|x W| + |b|: the argument's products and bias add
    /// round differently from the gemm's, by an ulp or two of an argument up to ~70, and
    /// sin' ≤ 1; gradients, sums of up to 3,000 terms, within 1e-5 times the sum of their
    /// magnitudes.
    #[test]
    fn counted_as_cuda_matches_candles_ops() {
        for (rows, inp, out, seed) in [(3000, 3, 64, 1), (1500, 1, 5, 2), (7, 4, 3, 3)] {
            let x = random(&[rows, inp], seed, -1.2, 1.2);
            let w = random(&[out, inp], seed + 10, -16.0, 16.0);
            let b = random(&[out], seed + 20, -16.0, 16.0);
            let sc = random(&[rows], seed + 40, 0.0, 1.0);
            let up = random(&[rows, out], seed + 30, -1.0, 1.0);
            let plain = run(&x, &w, &b, &sc, &up);
            let (fused, report) = counted_as_cuda(|| run(&x, &w, &b, &sc, &up));
            let launches = |name: &str| report.ops.get(name).map_or(0, |c| c.launches);
            assert_eq!(launches("pma-sine-linear"), 1, "one forward launch");
            assert_eq!(launches("pma-sine-linear-grad"), 2, "W and b: two launches");
            assert_eq!(
                launches("pma-sine-linear-grad-rows"),
                1,
                "x and s: one launch"
            );
            assert_eq!(launches("sin") + launches("cos"), 0);
            // The test's own loss is the one reduction.
            assert_eq!(launches("reduce-sum"), 1);
            let [xs, ups, ws] = [&x, &up, &w].map(|t| t.to_vec2::<f32>().unwrap());
            let (scs, bs) = (sc.to_vec1::<f32>().unwrap(), b.to_vec1::<f32>().unwrap());
            let y_mag = |i: usize| {
                let (r, j) = (i / out, i % out);
                (0..inp).map(|c| (xs[r][c] * ws[j][c]).abs()).sum::<f32>() + bs[j].abs()
            };
            close(&plain[0], &fused[0], y_mag, 5e-7, "y");
            let gx_mag = |i: usize| {
                let (r, c) = (i / inp, i % inp);
                (0..out)
                    .map(|j| (ups[r][j] * scs[r] * ws[j][c]).abs())
                    .sum()
            };
            close(&plain[1], &fused[1], gx_mag, 1e-5, "grad x");
            let gw_mag = |i: usize| {
                let (j, c) = (i / inp, i % inp);
                (0..rows)
                    .map(|r| (ups[r][j] * scs[r] * xs[r][c]).abs())
                    .sum()
            };
            close(&plain[2], &fused[2], gw_mag, 1e-5, "grad W");
            let gb_mag = |j: usize| (0..rows).map(|r| (ups[r][j] * scs[r]).abs()).sum();
            close(&plain[3], &fused[3], gb_mag, 1e-5, "grad b");
            let gs_mag = |r: usize| (0..out).map(|j| ups[r][j].abs()).sum();
            close(&plain[4], &fused[4], gs_mag, 1e-5, "grad scale");
        }
    }

    /// Without a scale, and with an x that needs no gradient: no row kernel runs.
    #[test]
    fn an_untracked_input_and_no_scale_cost_no_row_launch() {
        let x = random(&[10, 3], 4, -1.0, 1.0);
        let w = Var::from_tensor(&random(&[6, 3], 5, -2.0, 2.0)).unwrap();
        let b = random(&[6], 6, -2.0, 2.0);
        let (g, report) = counted_as_cuda(|| {
            let y = sine_linear(&x, w.as_tensor(), &b, None, Numerics::PARITY).unwrap();
            y.sum_all().unwrap().backward().unwrap()
        });
        assert!(report.ops.contains_key("pma-sine-linear-grad"));
        assert!(!report.ops.contains_key("pma-sine-linear-grad-rows"));
        assert!(g.get(&w).is_some());
    }

    /// Sums run per block of [`ROWS_PER_BLOCK`] rows, then over blocks: checked on a row
    /// count that leaves a partial last block, against sums formed in that order by hand.
    #[test]
    fn weight_grads_sum_per_block_then_over_blocks() {
        let rows = ROWS_PER_BLOCK + 37;
        let x: Vec<f32> = (0..rows).map(|r| 1.0 + (r % 7) as f32 * 0.25).collect();
        let grad: Vec<f32> = (0..rows).map(|r| 0.1 + (r % 5) as f32 * 0.3).collect();
        let (sc, cos) = (vec![1.0f32; rows], vec![1.0f32; rows]);
        let g = weight_grads(&grad, &sc, &cos, &x, (1, 1));
        let block = |rs: std::ops::Range<usize>| {
            rs.fold((0f32, 0f32), |(w, b), r| (w + grad[r] * x[r], b + grad[r]))
        };
        let (w0, b0) = block(0..ROWS_PER_BLOCK);
        let (w1, b1) = block(ROWS_PER_BLOCK..rows);
        assert_eq!(g, vec![0.0 + w0 + w1, 0.0 + b0 + b1]);
    }
}
