//! Volume rendering (the reference's `raw2outputs`), differentiable. The formulas and their
//! guards are listed in docs/numerics.md, "Densities and alpha".
//!
//! candle has no cumprod, so the transmittance `T_i = Π_{k<i}(1 − α_k + 1e-10)` is computed as
//! `exp(Σ_{k<i} ln(1 − α_k + 1e-10))`, the exclusive sum being one matmul with a strictly
//! upper-triangular matrix. The factors are ≥ 1e-10, so the logarithm is finite and its
//! gradient `T_i / f_k` is the same expression torch's cumprod backward uses for non-zero
//! factors.

use candle_core::{DType, Tensor, D};

use crate::compute::account::cpu_route;
use crate::error::{ModelError, Result};

/// Length given to the last interval of every ray (the ray continues to infinity).
pub const LAST_DELTA: f64 = 1e10;

/// Composited outputs of one ray batch.
#[derive(Debug, Clone)]
pub struct RenderOutputs {
    /// rgb: [R,3] colour, composited over the background when one is given.
    pub rgb: Tensor,
    /// depth: [R] Σ w_i z_i (ray-parameter units, not divided by Σw).
    pub depth: Tensor,
    /// disp: [R] 1/max(1e-10, depth/(Σw + 1e-10)), 0 where Σw ≈ 0 (|Σw| ≤ 1e-8).
    pub disp: Tensor,
    /// acc: [R] min(Σw, 1).
    pub acc: Tensor,
    /// weights: [R,M] α_i·T_i.
    pub weights: Tensor,
    /// alpha: [R,M] 1 − exp(−σ_i δ_i).
    pub alpha: Tensor,
    /// transmittance: [R,M] T_i = Π_{k<i}(1 − α_k + 1e-10), T_1 = 1.
    pub transmittance: Tensor,
}

/// Render a batch of rays from per-sample network outputs.
///
/// raw: [R,M,4] (r, g, b, activated density σ ≥ 0) at ray parameters z_vals: [R,M] (ascending)
/// along rays_d: [R,3] of any length (interval lengths are scaled by |d|); bgs: [R,3]
/// background colour composited behind the ray, or `None` for black. Any float dtype; all
/// inputs must share it and the device. Half-precision inputs are composited in f32 (the
/// outputs are then f32).
pub fn raw2outputs(
    raw: &Tensor,
    z_vals: &Tensor,
    rays_d: &Tensor,
    bgs: Option<&Tensor>,
) -> Result<RenderOutputs> {
    let (n_rays, m, c) = raw
        .dims3()
        .map_err(|_| ModelError::shape("raw", "[R,M,4]", raw.dims()))?;
    if c != 4 || m == 0 {
        return Err(ModelError::shape("raw", "[R,M,4] with M >= 1", raw.dims()));
    }
    if z_vals.dims() != [n_rays, m] {
        return Err(ModelError::shape("z_vals", [n_rays, m], z_vals.dims()));
    }
    if rays_d.dims() != [n_rays, 3] {
        return Err(ModelError::shape("rays_d", [n_rays, 3], rays_d.dims()));
    }
    if let Some(bg) = bgs {
        if bg.dims() != [n_rays, 3] {
            return Err(ModelError::shape("bgs", [n_rays, 3], bg.dims()));
        }
    }
    let dtype = raw.dtype();
    if matches!(dtype, DType::F16 | DType::BF16) {
        // The 1e-10 guards underflow to 0 in half precision (f16's smallest subnormal is
        // 6e-8), so an empty ray's disparity becomes 0/0 and an opaque sample's log(1 − α)
        // −inf. Compositing is cheap: do it in f32 and hand back f32 maps.
        let up = |t: &Tensor| t.to_dtype(DType::F32);
        let bg = bgs.map(up).transpose()?;
        return raw2outputs(&up(raw)?, &up(z_vals)?, &up(rays_d)?, bg.as_ref());
    }
    let tracked = [Some(raw), Some(z_vals), Some(rays_d), bgs]
        .into_iter()
        .flatten()
        .any(|t| t.track_op());
    if !tracked && dtype == DType::F32 && host::exact(m) && cpu_route(raw.device()) {
        return host::raw2outputs(raw, z_vals, rays_d, bgs);
    }
    let dev = raw.device();

    // δ_i = (z_{i+1} − z_i)·|d|, δ_M = 1e10·|d|.
    let last = Tensor::full(LAST_DELTA, (n_rays, 1), dev)?.to_dtype(dtype)?;
    let deltas = if m > 1 {
        let inner = (z_vals.narrow(1, 1, m - 1)? - z_vals.narrow(1, 0, m - 1)?)?;
        Tensor::cat(&[&inner, &last], 1)?
    } else {
        last
    };
    let d_norm = rays_d.sqr()?.sum_keepdim(1)?.sqrt()?;
    let deltas = deltas.broadcast_mul(&d_norm)?;

    let rgb = raw.narrow(2, 0, 3)?;
    let sigma = raw.narrow(2, 3, 1)?.squeeze(2)?;
    // α = 1 − exp(−σδ); the two-step `1 − α` then `+ 1e-10` keeps the reference's rounding
    // (a single affine would fold 1 + 1e-10 into 1 in f32).
    let alpha = (sigma * deltas)?.neg()?.exp()?.affine(-1.0, 1.0)?;
    let log_keep = alpha.affine(-1.0, 1.0)?.affine(1.0, 1e-10)?.log()?;
    let transmittance = log_keep.matmul(&strict_upper(m, dtype, dev)?)?.exp()?;
    let weights = (&alpha * &transmittance)?;

    let mut rgb_map = weights.unsqueeze(D::Minus1)?.broadcast_mul(&rgb)?.sum(1)?;
    let depth = (&weights * z_vals)?.sum(1)?;
    let w_sum = weights.sum(1)?;
    let floor = Tensor::full(1e-10, n_rays, dev)?.to_dtype(dtype)?;
    let disp = (depth.clone() / w_sum.affine(1.0, 1e-10)?)?
        .maximum(&floor)?
        .recip()?;
    // isclose(Σw, 0, rtol=1e-5, atol=1e-8) reduces to |Σw| ≤ 1e-8. Multiplying by the mask
    // (rather than selecting) also zeroes the gradient of empty rays.
    let nonempty = w_sum.abs()?.gt(1e-8)?.to_dtype(dtype)?;
    let disp = (disp * nonempty)?;
    // min(Σw, 1) with torch.clamp's gradient: all of it passes where Σw ≤ 1, including the
    // exact ties of opaque rays (candle's `minimum` would halve it there).
    let acc = w_sum.gt(1.0)?.where_cond(&w_sum.ones_like()?, &w_sum)?;
    if let Some(bg) = bgs {
        let see_through = acc.affine(-1.0, 1.0)?.unsqueeze(1)?;
        rgb_map = (rgb_map + see_through.broadcast_mul(bg)?)?;
    }
    Ok(RenderOutputs {
        rgb: rgb_map,
        depth,
        disp,
        acc,
        weights,
        alpha,
        transmittance,
    })
}

/// [M,M] matrix with ones strictly above the diagonal: `x·U` is the exclusive cumulative sum
/// of the rows of x.
fn strict_upper(m: usize, dtype: DType, dev: &candle_core::Device) -> Result<Tensor> {
    let data: Vec<f32> = (0..m * m)
        .map(|i| if i / m < i % m { 1.0 } else { 0.0 })
        .collect();
    Ok(Tensor::from_vec(data, (m, m), dev)?.to_dtype(dtype)?)
}

/// The same compositing on the host, for inference on the CPU: one pass per ray instead of
/// some forty tensor ops over small [R,M] tensors (each allocating), which cost a culled
/// render about as much as its ray casting. Every value is computed with the operations, in
/// the order, that the tensor ops above use on the CPU (candle's element-wise kernels, its
/// sums, and the exclusive sum that the triangular product accumulates term after term), so
/// the outputs are the same bits (unit-tested against the tensor ops).
mod host {
    use candle_core::Tensor;

    use super::{RenderOutputs, LAST_DELTA};
    use crate::compute::host::host_f32;
    use crate::error::Result;

    /// Whether the host path reproduces the tensor path's sums over M samples on this CPU:
    /// candle sums a row of fewer than 32 values one after the other, and longer rows in the
    /// AVX2 order that [`row_sum`] follows (x86-64 with AVX2; elsewhere the tensor ops run).
    pub(super) fn exact(m: usize) -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            m < BLOCK || std::is_x86_feature_detected!("avx2")
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            m < BLOCK
        }
    }

    /// Values per block of candle's AVX2 row sum (four 8-wide accumulators).
    const BLOCK: usize = 32;

    /// candle's CPU sum of a contiguous f32 row: whole blocks of 32 into four 8-lane
    /// accumulators, reduced pairwise and horizontally, then the rest one by one.
    pub(super) fn row_sum(xs: &[f32]) -> f32 {
        let whole = xs.len() / BLOCK * BLOCK;
        let mut acc = [[0f32; 8]; 4];
        for block in xs[..whole].chunks_exact(BLOCK) {
            for (a, part) in acc.iter_mut().zip(block.chunks_exact(8)) {
                for (l, v) in a.iter_mut().zip(part) {
                    *l += v;
                }
            }
        }
        let lane = |l: usize| (acc[0][l] + acc[1][l]) + (acc[2][l] + acc[3][l]);
        let t: [f32; 4] = std::array::from_fn(|l| lane(l) + lane(l + 4));
        let mut sum = (t[0] + t[1]) + (t[2] + t[3]);
        for v in &xs[whole..] {
            sum += v;
        }
        sum
    }

    /// [`super::raw2outputs`] for f32 inputs without a graph, on the CPU (validated shapes).
    pub(super) fn raw2outputs(
        raw: &Tensor,
        z_vals: &Tensor,
        rays_d: &Tensor,
        bgs: Option<&Tensor>,
    ) -> Result<RenderOutputs> {
        let (r, m, _) = raw.dims3()?;
        let (raw_h, z, d) = (host_f32(raw)?, host_f32(z_vals)?, host_f32(rays_d)?);
        let bg = bgs.map(host_f32).transpose()?;
        let last = LAST_DELTA as f32;
        let (mut alpha, mut trans, mut weights) =
            (vec![0f32; r * m], vec![0f32; r * m], vec![0f32; r * m]);
        let (mut rgb, mut depth, mut disp, mut acc) = (
            vec![0f32; r * 3],
            vec![0f32; r],
            vec![0f32; r],
            vec![0f32; r],
        );
        let (mut wz, mut keep) = (vec![0f32; m], vec![0f32; m]);
        // The constants as the tensor ops make them: f64 scalars rounded to f32. Their affine
        // maps x·(−1) + 1 and x·1 + c are 1 − x and x + c exactly.
        let (eps, floor, tiny) = (1e-10f64 as f32, 1e-10f64 as f32, 1e-8f64 as f32);
        for i in 0..r {
            let (zi, row) = (&z[i * m..(i + 1) * m], &raw_h[i * m * 4..(i + 1) * m * 4]);
            let di = &d[3 * i..3 * i + 3];
            let norm = ((0f32 + di[0] * di[0]) + di[1] * di[1] + di[2] * di[2]).sqrt();
            let (a, t, w) = (
                &mut alpha[i * m..(i + 1) * m],
                &mut trans[i * m..(i + 1) * m],
                &mut weights[i * m..(i + 1) * m],
            );
            for s in 0..m {
                let delta = match s + 1 < m {
                    true => zi[s + 1] - zi[s],
                    false => last,
                } * norm;
                a[s] = 1.0 - (-(row[4 * s + 3] * delta)).exp();
                keep[s] = ((1.0 - a[s]) + eps).ln();
            }
            // The triangular product adds its terms k < s one after the other from +0, and
            // every other term times 0, so a NaN anywhere on the ray reaches every sample.
            let poisoned = keep.iter().any(|l| l.is_nan());
            let mut prefix = 0f32;
            let mut c = [0f32; 3];
            for s in 0..m {
                t[s] = if poisoned { f32::NAN } else { prefix.exp() };
                prefix += keep[s];
                w[s] = a[s] * t[s];
                for (cc, v) in c.iter_mut().zip(&row[4 * s..4 * s + 3]) {
                    *cc += w[s] * v;
                }
                wz[s] = w[s] * zi[s];
            }
            depth[i] = row_sum(&wz);
            let w_sum = row_sum(w);
            let ratio = depth[i] / (w_sum + eps);
            let floored = if ratio < floor { floor } else { ratio };
            let nonempty = if w_sum.abs() > tiny { 1f32 } else { 0f32 };
            disp[i] = floored.recip() * nonempty;
            acc[i] = if w_sum > 1.0 { 1.0 } else { w_sum };
            if let Some(bg) = &bg {
                let see_through = 1.0 - acc[i];
                for (k, cc) in c.iter_mut().enumerate() {
                    *cc += see_through * bg[3 * i + k];
                }
            }
            rgb[3 * i..3 * i + 3].copy_from_slice(&c);
        }
        let dev = raw.device();
        let t2 = |v: Vec<f32>| Tensor::from_vec(v, (r, m), dev);
        Ok(RenderOutputs {
            rgb: Tensor::from_vec(rgb, (r, 3), dev)?,
            depth: Tensor::from_vec(depth, r, dev)?,
            disp: Tensor::from_vec(disp, r, dev)?,
            acc: Tensor::from_vec(acc, r, dev)?,
            weights: t2(weights)?,
            alpha: t2(alpha)?,
            transmittance: t2(trans)?,
        })
    }
}

#[cfg(test)]
mod tests {
    use candle_core::{Device, Tensor, Var};

    use super::*;

    /// Bit patterns, with every NaN alike.
    fn bits(t: &Tensor) -> Vec<u32> {
        let v = t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        v.iter()
            .map(|x| if x.is_nan() { u32::MAX } else { x.to_bits() })
            .collect()
    }

    #[test]
    fn the_host_compositing_is_the_tensor_compositing_bit_for_bit() {
        let dev = Device::Cpu;
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut rnd = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        let r = 37;
        for m in [1usize, 2, 16, 24, 31, 32, 33, 48, 72, 100] {
            if !host::exact(m) {
                continue;
            }
            let mut z = Vec::with_capacity(r * m);
            let mut raw = Vec::with_capacity(r * m * 4);
            for i in 0..r {
                let mut at = 0.5 + rnd();
                for s in 0..m {
                    // Some equal depths (δ = 0), the rest ascending.
                    if !(i % 5 == 1 && s % 3 == 0) {
                        at += 0.002 + 0.05 * rnd();
                    }
                    z.push(at);
                    let sigma = match (i % 7, s % 4) {
                        (0, _) => 0.0,
                        (1, 0) => 1e6 * rnd(),
                        (2, _) => 1e-4 * rnd(),
                        (3, 1) => f32::INFINITY,
                        (4, 2) if i == 4 => f32::NAN,
                        _ => 40.0 * rnd(),
                    };
                    raw.extend([rnd(), rnd(), rnd(), sigma]);
                }
            }
            let d: Vec<f32> = (0..r * 3).map(|_| 2.0 * rnd() - 1.0).collect();
            let bg: Vec<f32> = (0..r * 3).map(|_| rnd()).collect();
            let raw = Tensor::from_vec(raw, (r, m, 4), &dev).unwrap();
            let z = Tensor::from_vec(z, (r, m), &dev).unwrap();
            let d = Tensor::from_vec(d, (r, 3), &dev).unwrap();
            let bg = Tensor::from_vec(bg, (r, 3), &dev).unwrap();
            // A variable keeps the graph, so the public function takes the tensor ops.
            let tracked = Var::from_tensor(&raw).unwrap();
            for bgs in [None, Some(&bg)] {
                let host = host::raw2outputs(&raw, &z, &d, bgs).unwrap();
                let ops = raw2outputs(tracked.as_tensor(), &z, &d, bgs).unwrap();
                let pairs = [
                    ("rgb", &host.rgb, &ops.rgb),
                    ("depth", &host.depth, &ops.depth),
                    ("disp", &host.disp, &ops.disp),
                    ("acc", &host.acc, &ops.acc),
                    ("weights", &host.weights, &ops.weights),
                    ("alpha", &host.alpha, &ops.alpha),
                    ("transmittance", &host.transmittance, &ops.transmittance),
                ];
                for (name, a, b) in pairs {
                    assert_eq!(a.dims(), b.dims(), "{name}, M = {m}");
                    assert!(
                        bits(a) == bits(b),
                        "{name} differs, M = {m}, bg {}",
                        bgs.is_some()
                    );
                }
                // Without a graph the public function takes the host path.
                let plain = raw2outputs(&raw, &z, &d, bgs).unwrap();
                assert!(!plain.rgb.track_op() && bits(&plain.rgb) == bits(&host.rgb));
            }
        }
    }

    #[test]
    fn row_sums_follow_the_tensor_sum() {
        let v: Vec<f32> = (0..200)
            .map(|i| ((i * 7919) % 1000) as f32 * 1.37e-3 + 1e-7)
            .collect();
        for n in [0usize, 1, 3, 31, 32, 33, 64, 95, 200] {
            if !host::exact(n) {
                continue;
            }
            let t = Tensor::from_vec(v[..n].to_vec(), (1, n), &Device::Cpu).unwrap();
            let want = t.sum(1).unwrap().to_vec1::<f32>().unwrap()[0];
            assert_eq!(host::row_sum(&v[..n]).to_bits(), want.to_bits(), "n = {n}");
        }
    }
}
