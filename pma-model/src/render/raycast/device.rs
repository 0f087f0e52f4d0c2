//! The ray caster as tensor ops on the rays' device: near/far from the bounding cylinder and
//! the bone boxes, the coarse samples, the deterministic importance samples and the sorted
//! merge of both sets, with nothing copied to the host.
//!
//! [`RayCaster::cast`] and [`RayCaster::resample`] take this path on every device but the
//! CPU, where the host code of the parent module is faster and follows the reference's float
//! order. The arithmetic is the host code's, op for op in f32 (the box transforms, the face
//! hits, the cylinder, the sample positions, the interpolation). What differs: the pdf's total
//! and the cdf are summed in another order, a GPU may fuse a multiply and an add, ties
//! between samples keep their order in `cat(coarse, fine)` (the host follows torch's CPU
//! sort), and nothing is checked on the way (a check would be a read-back): non-finite inputs
//! give non-finite samples, which the training step's finite check catches. The test
//! `raycast_device` (tests/model) runs both paths on the CPU and bounds the differences.

use candle_core::{DType, Device, Tensor, D};
use pma_data::skeleton::N_JOINTS;

use super::{linspace01, CoarseSamples, FineSamples, Jitter, RayCaster, BOX_EPS};
use crate::error::{ModelError, Result};

/// `v` (f32) shaped like `like`, made on the device without a host copy.
fn filled(v: f32, like: &Tensor) -> Result<Tensor> {
    Ok(Tensor::full(v, (), like.device())?.broadcast_as(like.shape())?)
}

/// `mask ? a : b` with a constant `b`.
fn or_const(mask: &Tensor, a: &Tensor, b: f32) -> Result<Tensor> {
    Ok(mask.where_cond(a, &filled(b, a)?)?)
}

/// A host f32 vector as a [1,n] row on `dev`.
fn row(v: Vec<f32>, dev: &Device) -> Result<Tensor> {
    let n = v.len();
    Ok(Tensor::from_vec(v, (1, n), dev)?)
}

/// Mean of the non-NaN entries of `v` (summed in f64, like the host), or `default` when
/// every entry is NaN: a scalar.
fn nan_mean_or(v: &Tensor, default: f32) -> Result<Tensor> {
    let ok = v.eq(v)?;
    let sum = or_const(&ok, v, 0.0)?.to_dtype(DType::F64)?.sum_all()?;
    let count = ok.to_dtype(DType::F64)?.sum_all()?;
    let mean = (sum / &count)?.to_dtype(DType::F32)?;
    Ok(count
        .gt(&Tensor::zeros((), DType::F64, v.device())?)?
        .where_cond(&mean, &Tensor::full(default, (), v.device())?)?)
}

/// `((v0² + v1²) + v2²).sqrt()` over the last dim of size 3 (the host's `norm3` order).
fn norm3(v: &Tensor) -> Result<Tensor> {
    let c = |i: usize| v.narrow(D::Minus1, i, 1)?.squeeze(D::Minus1)?.sqr();
    Ok(((c(0)? + c(1)?)? + c(2)?)?.sqrt()?)
}

impl RayCaster {
    /// [`RayCaster::near_far`] as tensor ops: near, far: [R] on the rays' device (f32).
    /// Same inputs as [`RayCaster::cast`]; the miss fill is the batch's.
    pub fn near_far_tensors(
        &self,
        rays_o: &Tensor,
        rays_d: &Tensor,
        cyls: &Tensor,
        skts: &Tensor,
        scales: &Tensor,
    ) -> Result<(Tensor, Tensor)> {
        let (r, p) = check_inputs(rays_o, rays_d, cyls, skts, scales)?;
        let k = r / p;
        let dev = rays_o.device();
        let f32c = |t: &Tensor| t.to_dtype(DType::F32);
        let o = f32c(rays_o)?.reshape((p, k, 3))?;
        let d = f32c(rays_d)?.reshape((p, k, 3))?;
        let comp = |t: &Tensor, c: usize| t.narrow(2, c, 1)?.squeeze(2);

        // Cylinder bounds, [P,k]: the pose's circle in the ground plane against each ray.
        let cyl = f32c(cyls)?;
        let cyl_col = |c: usize| cyl.narrow(1, c, 1); // [P,1]
        let (cx, cz, radius) = (cyl_col(0)?, cyl_col(1)?, cyl_col(2)?);
        let (dx, dz) = (comp(&d, 0)?, comp(&d, 2)?);
        let (n0, n1) = ((&dx * 100.0)?, (&dz * 100.0)?);
        let c0 = cx.broadcast_sub(&comp(&o, 0)?)?;
        let c1 = cz.broadcast_sub(&comp(&o, 2)?)?;
        let n_len = (n0.sqr()? + n1.sqr()?)?.sqrt()?;
        let dist = ((&c0 * &n1)? - (&c1 * &n0)?)?.abs()?.div(&n_len)?;
        let q = radius.sqr()?.broadcast_sub(&dist.sqr()?)?.sqrt()?;
        let kk = ((&c0 * &n0)? + (&c1 * &n1)?)?.div(&n_len)?;
        let d_len = (dx.sqr()? + dz.sqr()?)?.sqrt()?;
        let inside_front = q.lt(&kk)?.to_dtype(DType::F32)?;
        let mut near = (inside_front * (&kk - &q)?)?.div(&d_len)?;
        let mut far = (&kk + &q)?.div(&d_len)?;
        if self.robust_bounds {
            let zeros = far.zeros_like()?;
            let front = (far.ge(&near)? * far.gt(&zeros)?)?;
            near = or_const(&front, &near, f32::NAN)?;
            far = or_const(&front, &far, f32::NAN)?;
        }
        let (fill_near, fill_far) = if self.per_ray_fallback {
            (
                Tensor::full(self.near, (), dev)?,
                Tensor::full(self.far, (), dev)?,
            )
        } else {
            (nan_mean_or(&near, self.near)?, nan_mean_or(&far, self.far)?)
        };
        let near = near
            .eq(&near)?
            .where_cond(&near, &fill_near.broadcast_as(near.shape())?)?;
        let far = far
            .eq(&far)?
            .where_cond(&far, &fill_far.broadcast_as(far.shape())?)?;

        // World → box transforms A_j·skt_j, [P,24,4,4], summed in the host's order.
        let align = Tensor::from_vec(self.transforms.clone(), (1, N_JOINTS, 4, 4), dev)?;
        let skt = f32c(skts)?;
        let mut w2b: Option<Tensor> = None;
        for l in 0..4 {
            let term = align
                .narrow(3, l, 1)?
                .broadcast_mul(&skt.narrow(2, l, 1)?)?;
            w2b = Some(match w2b {
                None => term,
                Some(acc) => (acc + term)?,
            });
        }
        let w2b = w2b.expect("four terms");
        // Ray origin and direction in every box frame: [P,k,24,3].
        let col = |c: usize| -> Result<Tensor> {
            Ok(w2b
                .narrow(2, 0, 3)?
                .narrow(3, c, 1)?
                .reshape((p, 1, N_JOINTS, 3))?)
        };
        let at =
            |v: &Tensor, c: usize| -> Result<Tensor> { Ok(comp(v, c)?.reshape((p, k, 1, 1))?) };
        let rotate = |v: &Tensor| -> Result<Tensor> {
            let t0 = col(0)?.broadcast_mul(&at(v, 0)?)?;
            let t1 = col(1)?.broadcast_mul(&at(v, 1)?)?;
            let t2 = col(2)?.broadcast_mul(&at(v, 2)?)?;
            Ok(((t0 + t1)? + t2)?)
        };
        let o_t = rotate(&o)?.broadcast_add(&col(3)?)?;
        let d_t = rotate(&d)?;
        let s = f32c(scales)?.reshape((1, 1, N_JOINTS, 3))?;
        let o_s = o_t.broadcast_div(&s)?;
        let d_s = d_t.broadcast_div(&s)?;
        // The six face planes (axis-major, −bound then +bound), [P,k,24,6].
        let face = self.bound as f32;
        let lim = (self.bound + BOX_EPS) as f32;
        let axis = Tensor::from_vec(vec![0u32, 0, 1, 1, 2, 2], 6, dev)?;
        let planes = Tensor::from_vec(vec![-face, face, -face, face, -face, face], 6, dev)?;
        let o_f = o_s.index_select(&axis, 3)?;
        let d_f = d_s.index_select(&axis, 3)?;
        let t = planes
            .reshape((1, 1, 1, 6))?
            .broadcast_sub(&o_f)?
            .div(&d_f)?;
        // Face hits in the box frame, [P,k,24,6,3], and whether they lie on the box.
        let hit_pts = o_s
            .unsqueeze(3)?
            .broadcast_add(&t.unsqueeze(4)?.broadcast_mul(&d_s.unsqueeze(3)?)?)?;
        let inside = (hit_pts.ge(&filled(-lim, &hit_pts)?)?
            * hit_pts.le(&filled(lim, &hit_pts)?)?)?
        .to_dtype(DType::F32)?
        .min(D::Minus1)?
        .ne(&Tensor::zeros((p, k, N_JOINTS, 6), DType::F32, dev)?)?;
        let (box_near, box_far, box_hit) = if self.robust_bounds {
            // 0·t is 0 for finite t, NaN for ±inf and NaN.
            let finite = t.affine(0.0, 0.0)?.eq(&t.zeros_like()?)?;
            let valid = (&inside * &finite)?;
            let t_min = or_const(&valid, &t, f32::INFINITY)?.min(D::Minus1)?;
            let t_max = or_const(&valid, &t, f32::NEG_INFINITY)?.max(D::Minus1)?;
            let zeros = t_max.zeros_like()?;
            let hit = (t_max.gt(&t_min)? * t_max.gt(&zeros)?)?;
            (t_min.maximum(&zeros)?, t_max, hit)
        } else {
            // Distances along the ray of the face hits; a box counts when exactly two faces do.
            let back = hit_pts
                .broadcast_mul(&s.unsqueeze(3)?)?
                .broadcast_sub(&o_t.unsqueeze(3)?)?;
            let dist = norm3(&back)?.broadcast_div(&norm3(&d_t)?.unsqueeze(3)?)?;
            let n_hits = inside.to_dtype(DType::F32)?.sum(D::Minus1)?;
            let hit = n_hits.eq(&filled(2.0, &n_hits)?)?;
            (
                or_const(&inside, &dist, f32::INFINITY)?.min(D::Minus1)?,
                or_const(&inside, &dist, f32::NEG_INFINITY)?.max(D::Minus1)?,
                hit,
            )
        };
        // Per ray: the union of the boxes it crosses, else the cylinder bounds.
        let ray_near = or_const(&box_hit, &box_near, f32::INFINITY)?.min(D::Minus1)?;
        let ray_far = or_const(&box_hit, &box_far, f32::NEG_INFINITY)?.max(D::Minus1)?;
        let body = ray_near.le(&ray_far)?;
        let near = body.where_cond(&ray_near, &near)?.reshape(r)?;
        let far = body.where_cond(&ray_far, &far)?.reshape(r)?;
        Ok((near, far))
    }

    /// [`RayCaster::cast`] as tensor ops (no host bounds: `bounds` is `None`). With
    /// `jitter` the samples are stratified ([`Jitter`]): the places are drawn on the host
    /// and copied to the device (no read-back), so the samples are the host cast's.
    pub fn cast_tensors(
        &self,
        rays_o: &Tensor,
        rays_d: &Tensor,
        cyls: &Tensor,
        skts: &Tensor,
        scales: &Tensor,
        jitter: Option<Jitter>,
    ) -> Result<CoarseSamples> {
        let (near, far) = self.near_far_tensors(rays_o, rays_d, cyls, skts, scales)?;
        let dev = rays_o.device();
        let s = self.n_samples;
        let t = linspace01(s);
        let one_minus_t: Vec<f32> = t.iter().map(|&t| 1.0 - t).collect();
        let mut z = near
            .unsqueeze(1)?
            .broadcast_mul(&row(one_minus_t, dev)?)?
            .add(&far.unsqueeze(1)?.broadcast_mul(&row(t, dev)?)?)?;
        let r = z.dim(0)?;
        if let Some(j) = jitter.filter(|_| s > 1) {
            let u = Tensor::from_vec(j.coarse_u(r, s), (r, s), dev)?;
            let mids = ((z.narrow(1, 1, s - 1)? + z.narrow(1, 0, s - 1)?)? * 0.5)?;
            let lo = Tensor::cat(&[&z.narrow(1, 0, 1)?, &mids], 1)?;
            let hi = Tensor::cat(&[&mids, &z.narrow(1, s - 1, 1)?], 1)?;
            z = (&lo + ((&hi - &lo)? * u)?)?;
        }
        let fine_u = jitter.map(|j| j.fine_u(r, self.n_importance));
        let pts = points(rays_o, rays_d, &z)?;
        let dt = rays_o.dtype();
        Ok(CoarseSamples {
            bounds: None,
            z: z.to_dtype(dt)?,
            pts: pts.to_dtype(dt)?,
            fine_u,
        })
    }

    /// [`RayCaster::importance_z`] as tensor ops: z_coarse, weights: [R,Sc] -> [R,Sf] (f32);
    /// `fine_u` [R,Sf] (copied to the device) or linspace(0, 1, Sf).
    pub fn importance_z_tensors(
        &self,
        z_coarse: &Tensor,
        weights: &Tensor,
        fine_u: Option<&[f32]>,
    ) -> Result<Tensor> {
        let (r, sc) = z_coarse.dims2()?;
        if sc != self.n_samples || weights.dims() != [r, sc] {
            return Err(ModelError::shape(
                "z_coarse/weights",
                format!("[R,{}] both", self.n_samples),
                format!("{:?} and {:?}", z_coarse.dims(), weights.dims()),
            ));
        }
        let dev = z_coarse.device();
        let z = z_coarse.to_dtype(DType::F32)?;
        let w = weights.to_dtype(DType::F32)?;
        let cut = |t: &Tensor, from: usize, len: usize| t.narrow(1, from, len);
        // Bins between the samples; a 3-tap max filter of the interior weights, floored.
        let bins = ((cut(&z, 1, sc - 1)? + cut(&z, 0, sc - 1)?)? * 0.5)?;
        let mid = cut(&w, 1, sc - 2)?;
        let blurred =
            ((cut(&w, 0, sc - 2)?.maximum(&mid)? + mid.maximum(&cut(&w, 2, sc - 2)?)?)? * 0.5)?
                .affine(1.0, 0.01)?
                .affine(1.0, 1e-5)?;
        let total = blurred.sum_keepdim(1)?;
        // cdf: [R,Sc−1] with a leading 0, accumulated in f64 like the host.
        let cdf = blurred
            .broadcast_div(&total)?
            .to_dtype(DType::F64)?
            .cumsum(1)?
            .to_dtype(DType::F32)?;
        let cdf = Tensor::cat(&[&Tensor::zeros((r, 1), DType::F32, dev)?, &cdf], 1)?;
        let last = (sc - 2) as f64;
        // searchsorted(right): how many cdf entries are <= u.
        let sf = self.n_importance;
        let u = match fine_u {
            Some(u) if u.len() == r * sf => Tensor::from_slice(u, (r, sf), dev)?,
            Some(u) => return Err(ModelError::shape("fine_u", [r, sf], u.len())),
            None => row(linspace01(sf), dev)?, // [1,Sf]
        };
        let idx = cdf
            .unsqueeze(1)?
            .broadcast_le(&u.unsqueeze(2)?)?
            .to_dtype(DType::F32)?
            .sum(2)?;
        let below = (idx.affine(1.0, -1.0)?.maximum(&idx.zeros_like()?)?).to_dtype(DType::U32)?;
        let above = idx
            .minimum(&filled(last as f32, &idx)?)?
            .to_dtype(DType::U32)?;
        let (cdf_b, cdf_a) = (cdf.gather(&below, 1)?, cdf.gather(&above, 1)?);
        let (bins_b, bins_a) = (bins.gather(&below, 1)?, bins.gather(&above, 1)?);
        let denom = (&cdf_a - &cdf_b)?;
        let small = denom.lt(&filled(1e-5, &denom)?)?;
        let denom = small.where_cond(&filled(1.0, &denom)?, &denom)?;
        let t = u.broadcast_sub(&cdf_b)?.div(&denom)?;
        Ok((&bins_b + (t * (bins_a - &bins_b)?)?)?)
    }

    /// [`RayCaster::resample`] as tensor ops.
    pub fn resample_tensors(
        &self,
        rays_o: &Tensor,
        rays_d: &Tensor,
        z_coarse: &Tensor,
        weights: &Tensor,
        fine_u: Option<&[f32]>,
    ) -> Result<FineSamples> {
        let zc = z_coarse.to_dtype(DType::F32)?;
        let zf = self.importance_z_tensors(&zc, weights, fine_u)?;
        let pts = points(rays_o, rays_d, &zf)?;
        let (z_all, perm) = merge_sorted_tensors(&zc, &zf)?;
        let dt = rays_o.dtype();
        Ok(FineSamples {
            z: zf.to_dtype(dt)?,
            pts: pts.to_dtype(dt)?,
            z_all: z_all.to_dtype(dt)?,
            perm,
        })
    }
}

/// `o + d·z`: rays_o, rays_d: [R,3], z: [R,S] (f32) -> [R,S,3] f32.
fn points(rays_o: &Tensor, rays_d: &Tensor, z: &Tensor) -> Result<Tensor> {
    let o = rays_o.to_dtype(DType::F32)?.unsqueeze(1)?;
    let d = rays_d.to_dtype(DType::F32)?.unsqueeze(1)?;
    Ok(o.broadcast_add(&d.broadcast_mul(&z.unsqueeze(2)?)?)?)
}

/// [`super::merge_sorted`] as tensor ops: z_coarse: [R,Sc], z_fine: [R,Sf], each ascending
/// per ray -> (z_all [R,Sc+Sf], perm [R,Sc+Sf] u32 into `cat(z_coarse, z_fine)`). Every
/// sample's place is counted (the samples of the other set below it), so equal values keep
/// their order in the concatenation: a stable merge.
pub fn merge_sorted_tensors(z_coarse: &Tensor, z_fine: &Tensor) -> Result<(Tensor, Tensor)> {
    let (r, sc) = z_coarse.dims2()?;
    let (rf, sf) = z_fine.dims2()?;
    if rf != r {
        return Err(ModelError::shape(
            "z_fine",
            format!("[{r},S]"),
            z_fine.dims(),
        ));
    }
    let dev = z_coarse.device();
    // coarse i goes after the fine samples strictly below it, fine k after the coarse
    // samples at or below it.
    let before_coarse = z_fine
        .unsqueeze(1)?
        .broadcast_lt(&z_coarse.unsqueeze(2)?)?
        .to_dtype(DType::F32)?
        .sum(2)?;
    let before_fine = z_coarse
        .unsqueeze(1)?
        .broadcast_le(&z_fine.unsqueeze(2)?)?
        .to_dtype(DType::F32)?
        .sum(2)?;
    let pos = Tensor::cat(
        &[
            before_coarse.broadcast_add(&Tensor::arange(0f32, sc as f32, dev)?.unsqueeze(0)?)?,
            before_fine.broadcast_add(&Tensor::arange(0f32, sf as f32, dev)?.unsqueeze(0)?)?,
        ],
        1,
    )?;
    let perm = pos.arg_sort_last_dim(true)?;
    let z_all = Tensor::cat(&[z_coarse, z_fine], 1)?.gather(&perm, 1)?;
    Ok((z_all, perm))
}

/// Shapes of the cast inputs; returns (rays, poses).
fn check_inputs(
    rays_o: &Tensor,
    rays_d: &Tensor,
    cyls: &Tensor,
    skts: &Tensor,
    scales: &Tensor,
) -> Result<(usize, usize)> {
    let r = rays_o.dims().first().copied().unwrap_or(0);
    let p = skts.dims().first().copied().unwrap_or(0);
    for (what, t, shape) in [
        ("rays_o", rays_o, vec![r, 3]),
        ("rays_d", rays_d, vec![r, 3]),
        ("cyls", cyls, vec![p, 5]),
        ("skts", skts, vec![p, N_JOINTS, 4, 4]),
        ("scales", scales, vec![N_JOINTS, 3]),
    ] {
        if t.dims() != shape.as_slice() {
            return Err(ModelError::shape(what, shape, t.dims()));
        }
    }
    if p == 0 || r % p != 0 {
        return Err(ModelError::Input(format!(
            "{r} rays cannot be split into {p} equal per-pose groups"
        )));
    }
    Ok((r, p))
}
