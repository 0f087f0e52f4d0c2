//! Volume rendering (the reference's `raw2outputs`), differentiable. The formulas and their
//! guards are listed in docs/numerics.md, "Densities and alpha".
//!
//! candle has no cumprod, so the transmittance `T_i = Π_{k<i}(1 − α_k + 1e-10)` is computed as
//! `exp(Σ_{k<i} ln(1 − α_k + 1e-10))`, the exclusive sum being one matmul with a strictly
//! upper-triangular matrix. The factors are ≥ 1e-10, so the logarithm is finite and its
//! gradient `T_i / f_k` is the same expression torch's cumprod backward uses for non-zero
//! factors.

use candle_core::{DType, Tensor, D};

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
