//! Ray caster (the reference's `VolRayCast`): per-ray near/far from the bounding
//! cylinder and the per-bone boxes, coarse samples, deterministic importance samples and the
//! merge of both sample sets.
//!
//! The reference runs all of this under no-grad, so it works on host `f32` slices (row-major,
//! shapes in the doc comments) and follows the reference's float32 operation order, which keeps
//! the results within a few ulp of it. The tensor-facing entry points [`RayCaster::cast`] and
//! [`RayCaster::resample`] wrap the host code for the network; [`device`] has the same steps
//! as tensor ops for GPUs, where a copy to the host would stall the step; [`merge_raw`]
//! reorders the network outputs (differentiably, it is a gather).

use candle_core::Tensor;

use pma_data::skeleton::N_JOINTS;

use crate::compute::host::host_f32_shaped;
use crate::error::{ModelError, Result};
use crate::network::config::Config;
use crate::render::bones::BoneFrames;

pub mod device;
pub mod torch_sort;

/// Tolerance of the box-face test: a plane hit is valid while every coordinate lies within
/// `bound + BOX_EPS`.
pub const BOX_EPS: f64 = 1e-5;

/// Per-ray sampling interval.
#[derive(Debug, Clone, PartialEq)]
pub struct RayBounds {
    /// near: [R]
    pub near: Vec<f32>,
    /// far: [R]
    pub far: Vec<f32>,
    /// box_hit: [R,24] row-major; `true` where ray r crosses part j's enlarged box.
    pub box_hit: Vec<bool>,
    /// ray_hits_body: [R]; `false` for rays that cross no (enlarged) box. Those keep the
    /// cylinder bounds and every sample of theirs lies outside all boxes, where the spatial
    /// window is at most exp(−2·1.1⁶) ≈ 0.03: the candidates for culling.
    pub ray_hits_body: Vec<bool>,
    /// (near, far) given to the rays that miss the bounding cylinder (the batch means in the
    /// reference, so they depend on the whole batch).
    pub miss_fill: (f32, f32),
}

impl RayBounds {
    /// The bounds of the rays `rows` (in that order); the miss fill stays the batch's.
    pub fn select(&self, rows: &[usize]) -> Self {
        Self {
            near: rows.iter().map(|&r| self.near[r]).collect(),
            far: rows.iter().map(|&r| self.far[r]).collect(),
            box_hit: rows
                .iter()
                .flat_map(|&r| {
                    self.box_hit[r * N_JOINTS..(r + 1) * N_JOINTS]
                        .iter()
                        .copied()
                })
                .collect(),
            ray_hits_body: rows.iter().map(|&r| self.ray_hits_body[r]).collect(),
            miss_fill: self.miss_fill,
        }
    }
}

/// Coarse samples of a ray batch, ready for the network.
#[derive(Debug, Clone)]
pub struct CoarseSamples {
    /// Host near/far and box hits; `None` when cast on the device ([`device`]).
    pub bounds: Option<RayBounds>,
    /// z: [R,Sc] ray parameters, ascending (distance along the ray = z·|d|).
    pub z: Tensor,
    /// pts: [R,Sc,3] world points o + z·d.
    pub pts: Tensor,
    /// fine_u: [R,Sf] on the host, where each ray's importance samples invert the CDF when
    /// the pass is jittered ([`Jitter`]); `None`: at linspace(0, 1, Sf) like the reference.
    /// The host copy is what the host resample reads and the device resample uploads, so
    /// neither reads it back.
    pub fine_u: Option<Vec<f32>>,
}

impl CoarseSamples {
    /// The fine places of rows `rows` of these samples ([`Self::fine_u`]).
    pub fn fine_u_of(&self, rows: &[usize]) -> Option<Vec<f32>> {
        let u = self.fine_u.as_ref()?;
        let sf = u.len() / self.z.dims().first().copied().unwrap_or(1).max(1);
        Some(
            rows.iter()
                .flat_map(|&r| u[r * sf..(r + 1) * sf].iter().copied())
                .collect(),
        )
    }
}

/// Stratified samples in training (`[train] jitter`, the `perturb` of the original NeRF;
/// the reference trains on evenly spaced samples): each coarse sample moves to a uniform
/// place in its stratum, the interval between the midpoints to its neighbours (the first
/// and last stay inside the ray's interval), and each ray's importance samples invert the
/// CDF at one uniform place in each of Sf equal parts of [0, 1] instead of at
/// linspace(0, 1, Sf). So the network sees every depth of a ray over the steps, not the
/// same Sc + Sf. The places depend only on the seed and the ray's row in the whole batch:
/// chunks, threads and data-parallel ranks draw the same ones.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Jitter {
    pub seed: u64,
}

impl Jitter {
    /// Uniform in [0, 1): a 24-bit draw, exact in f32.
    fn unit(&self, stage: u64, index: usize) -> f32 {
        let u = crate::render::options::unit_hash(self.seed, stage, index as u64);
        (u * (1u32 << 24) as f64).floor() as f32 / (1u32 << 24) as f32
    }

    /// The coarse samples' places in their strata: [R,S], uniform in [0, 1).
    pub fn coarse_u(&self, n_rays: usize, s: usize) -> Vec<f32> {
        (0..n_rays * s).map(|i| self.unit(0, i)).collect()
    }

    /// The importance samples' CDF places: [R,Sf], (m + ξ)/Sf for sample m.
    pub fn fine_u(&self, n_rays: usize, sf: usize) -> Vec<f32> {
        (0..n_rays * sf)
            .map(|i| ((i % sf) as f32 + self.unit(1, i)) / sf as f32)
            .collect()
    }

    /// Evenly spaced z [R,S] moved by u [R,S] within their strata: sample k to
    /// lo + (hi − lo)·u between lo, hi, the midpoints to its neighbours (or the ray's ends).
    pub fn stratify(z: &[f32], u: &[f32], s: usize) -> Vec<f32> {
        let mut out = Vec::with_capacity(z.len());
        for (z, u) in z.chunks_exact(s).zip(u.chunks_exact(s)) {
            for k in 0..s {
                let lo = if k == 0 {
                    z[0]
                } else {
                    (z[k - 1] + z[k]) * 0.5
                };
                let hi = if k + 1 == s {
                    z[s - 1]
                } else {
                    (z[k] + z[k + 1]) * 0.5
                };
                out.push(lo + (hi - lo) * u[k]);
            }
        }
        out
    }
}

/// Importance samples and their merge with the coarse samples.
#[derive(Debug, Clone)]
pub struct FineSamples {
    /// z: [R,Sf] importance ray parameters (ascending per ray).
    pub z: Tensor,
    /// pts: [R,Sf,3] world points of the importance samples.
    pub pts: Tensor,
    /// z_all: [R,Sc+Sf] merged ray parameters, ascending per ray.
    pub z_all: Tensor,
    /// perm: [R,Sc+Sf] u32 with `z_all[r,i] = cat(z_coarse, z_fine)[r, perm[r,i]]`; feed it to
    /// [`merge_raw`].
    pub perm: Tensor,
}

/// The host inputs of a cast ([`RayCaster::cast_placed`]): rays_o, rays_d [R,3], skts
/// [P,24,4,4], scales [24,3], and the bounds cast from them.
pub struct CastInputs<'a> {
    pub bounds: &'a RayBounds,
    pub rays_o: &'a [f32],
    pub rays_d: &'a [f32],
    pub skts: &'a [f32],
    pub scales: &'a [f32],
}

/// Chooses a cast's coarse ray parameters [R,Sc] from its inputs and the evenly spaced ones.
pub type CoarsePlacer<'a> = dyn Fn(&CastInputs, Vec<f32>) -> Result<Vec<f32>> + 'a;

/// The ray caster: sampling configuration plus the bone-alignment transforms `A_j`.
#[derive(Debug, Clone)]
pub struct RayCaster {
    n_samples: usize,
    n_importance: usize,
    near: f32,
    far: f32,
    bound: f64,
    per_ray_fallback: bool,
    /// `quirks.robust_ray_bounds`: signed box crossings, edge/corner hits kept, and a
    /// cylinder behind the camera counted as a miss.
    robust_bounds: bool,
    /// A_j: [24,4,4] row-major (`raycast.transforms`).
    transforms: Vec<f32>,
}

impl RayCaster {
    /// transforms: [24,4,4] row-major `A_j` (buffer `raycast.transforms`).
    pub fn new(cfg: &Config, transforms: &[f32]) -> Result<Self> {
        if cfg.n_samples < 3 {
            // The blurred-max importance weights need a left and a right neighbour.
            return Err(ModelError::Config(format!(
                "n_samples must be >= 3, found {}",
                cfg.n_samples
            )));
        }
        if cfg.n_importance < 2 {
            return Err(ModelError::Config(format!(
                "n_importance must be >= 2, found {}",
                cfg.n_importance
            )));
        }
        if !(cfg.box_bound.is_finite() && cfg.box_bound > 0.0) {
            return Err(ModelError::Config(format!(
                "box_bound must be finite and > 0, found {}",
                cfg.box_bound
            )));
        }
        if !(cfg.near.is_finite() && cfg.far.is_finite() && cfg.near <= cfg.far) {
            return Err(ModelError::Config(format!(
                "near/far must be finite with near <= far, found {} / {}",
                cfg.near, cfg.far
            )));
        }
        check_len("raycast.transforms", transforms, &[N_JOINTS, 4, 4])?;
        check_finite("raycast.transforms", transforms)?;
        Ok(Self {
            n_samples: cfg.n_samples,
            n_importance: cfg.n_importance,
            near: cfg.near as f32,
            far: cfg.far as f32,
            bound: cfg.box_bound,
            per_ray_fallback: cfg.quirks.per_ray_cylinder_fallback,
            robust_bounds: cfg.quirks.robust_ray_bounds,
            transforms: transforms.to_vec(),
        })
    }

    /// transforms: [24,4,4] tensor (any device and float dtype).
    pub fn from_tensor(cfg: &Config, transforms: &Tensor) -> Result<Self> {
        let host = host_f32_shaped("raycast.transforms", transforms, &[N_JOINTS, 4, 4])?;
        Self::new(cfg, &host)
    }

    /// A_j, the bone-alignment transforms the boxes are built from: [24,4,4] row-major.
    pub fn bone_align(&self) -> &[f32] {
        &self.transforms
    }

    /// Coarse samples per ray (S_c).
    pub fn n_samples(&self) -> usize {
        self.n_samples
    }

    /// Importance samples per ray (S_f).
    pub fn n_importance(&self) -> usize {
        self.n_importance
    }

    /// Near/far of every ray: box bounds where the ray crosses at least one part,
    /// cylinder bounds otherwise.
    ///
    /// rays_o, rays_d: [R,3]; cyls: [P,5] (centre_x, centre_z, radius, top, bottom; only the
    /// first three are used); skts: [P,24,4,4] world-to-joint transforms; scales: [24,3] the
    /// effective (clamped) half-extents `s_j`. Rays are grouped by pose: rays
    /// `[p·R/P, (p+1)·R/P)` belong to pose p, so R must be a multiple of P.
    pub fn near_far(
        &self,
        rays_o: &[f32],
        rays_d: &[f32],
        cyls: &[f32],
        skts: &[f32],
        scales: &[f32],
    ) -> Result<RayBounds> {
        let n_rays = ray_count(rays_o, rays_d)?;
        if skts.is_empty() || skts.len() % (N_JOINTS * 16) != 0 {
            return Err(ModelError::shape(
                "skts",
                "[P,24,4,4] with P >= 1",
                skts.len(),
            ));
        }
        let n_poses = skts.len() / (N_JOINTS * 16);
        check_len("cyls", cyls, &[n_poses, 5])?;
        if n_rays % n_poses != 0 {
            return Err(ModelError::Input(format!(
                "{n_rays} rays cannot be split into {n_poses} equal per-pose groups"
            )));
        }
        check_finite("skts", skts)?;
        check_finite("cyls", cyls)?;
        check_scales(scales)?;
        let per_pose = n_rays / n_poses.max(1);
        let pose_of = |r: usize| r / per_pose.max(1);

        let (mut near, mut far) = cylinder_near_far(rays_o, rays_d, |r| {
            let c = &cyls[pose_of(r) * 5..pose_of(r) * 5 + 3];
            [c[0], c[1], c[2]]
        });
        if self.robust_bounds {
            // A circle behind the camera gives far < near (and negative intervals that can
            // overflow exp(σ|δ|) in compositing): treat it like a miss.
            for (n, f) in near.iter_mut().zip(far.iter_mut()) {
                if !(*f >= *n && *f > 0.0) {
                    *n = f32::NAN;
                    *f = f32::NAN;
                }
            }
        }
        let miss_fill = cylinder_miss_fill(&near, &far, self.near, self.far, self.per_ray_fallback);
        fill_cylinder_misses(&mut near, &mut far, miss_fill.0, miss_fill.1, true);

        let mut box_hit = vec![false; n_rays * N_JOINTS];
        let mut ray_hits_body = vec![false; n_rays];
        let frames = BoneFrames::new(&self.transforms, skts)?;
        let mut world_to_box = vec![0f32; N_JOINTS * 16];
        for p in 0..n_poses {
            for j in 0..N_JOINTS {
                world_to_box[j * 16..j * 16 + 16].copy_from_slice(&frames.world_to_box(p, j));
            }
            let spheres: [Option<WorldSphere>; N_JOINTS] = std::array::from_fn(|j| {
                let s = [scales[3 * j], scales[3 * j + 1], scales[3 * j + 2]];
                WorldSphere::around(&world_to_box[j * 16..j * 16 + 16], s, self.bound)
            });
            for r in p * per_pose..(p + 1) * per_pose {
                let o = [rays_o[3 * r], rays_o[3 * r + 1], rays_o[3 * r + 2]];
                let d = [rays_d[3 * r], rays_d[3 * r + 1], rays_d[3 * r + 2]];
                let d2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
                let mut ray_near = f32::INFINITY;
                let mut ray_far = f32::NEG_INFINITY;
                for j in 0..N_JOINTS {
                    if spheres[j].is_some_and(|b| b.missed_by(o, d, d2)) {
                        continue;
                    }
                    let s = [scales[3 * j], scales[3 * j + 1], scales[3 * j + 2]];
                    let w2b = &world_to_box[j * 16..j * 16 + 16];
                    let ray = BoxRay::new(w2b, s, o, d);
                    let hit = if !ray.may_hit(self.bound) {
                        None
                    } else if self.robust_bounds {
                        ray.near_far_robust(self.bound)
                    } else {
                        ray.near_far(s, self.bound)
                    };
                    if let Some((t0, t1)) = hit {
                        box_hit[r * N_JOINTS + j] = true;
                        ray_near = ray_near.min(t0);
                        ray_far = ray_far.max(t1);
                    }
                }
                if ray_near <= ray_far {
                    ray_hits_body[r] = true;
                    near[r] = ray_near;
                    far[r] = ray_far;
                }
            }
        }
        Ok(RayBounds {
            near,
            far,
            box_hit,
            ray_hits_body,
            miss_fill,
        })
    }

    /// Coarse ray parameters: near, far: [R] -> z: [R,Sc],
    /// `z_k = near·(1−t_k) + far·t_k` with `t = linspace(0,1,Sc)`, no jitter.
    pub fn coarse_z(&self, near: &[f32], far: &[f32]) -> Result<Vec<f32>> {
        if near.len() != far.len() {
            return Err(ModelError::shape("far", [near.len()], [far.len()]));
        }
        let t = linspace01(self.n_samples);
        let mut z = Vec::with_capacity(near.len() * t.len());
        for (&n, &f) in near.iter().zip(far) {
            z.extend(t.iter().map(|&t| n * (1.0 - t) + f * t));
        }
        Ok(z)
    }

    /// Importance ray parameters: z_coarse: [R,Sc] ascending, weights: [R,Sc] coarse
    /// render weights -> [R,Sf], ascending per ray. Each ray's CDF is inverted at its own
    /// places `u`: [R,Sf] ascending per ray in [0, 1] ([`Jitter::fine_u`]), or with `None`
    /// at linspace(0, 1, Sf) as the reference does.
    pub fn importance_z(
        &self,
        z_coarse: &[f32],
        weights: &[f32],
        u: Option<&[f32]>,
    ) -> Result<Vec<f32>> {
        let sc = self.n_samples;
        if z_coarse.len() % sc != 0 {
            return Err(ModelError::shape(
                "z_coarse",
                format!("[R,{sc}]"),
                z_coarse.len(),
            ));
        }
        if weights.len() != z_coarse.len() {
            return Err(ModelError::shape(
                "weights",
                format!("[R,{sc}] like z_coarse"),
                weights.len(),
            ));
        }
        let sf = self.n_importance;
        let even = linspace01(sf);
        if let Some(u) = u {
            if u.len() != z_coarse.len() / sc * sf {
                return Err(ModelError::shape("fine_u", format!("[R,{sf}]"), u.len()));
            }
        }
        let mut out = Vec::with_capacity(z_coarse.len() / sc * sf);
        for (r, (z, w)) in z_coarse
            .chunks_exact(sc)
            .zip(weights.chunks_exact(sc))
            .enumerate()
        {
            if let Some(k) = w.iter().position(|v| !v.is_finite()) {
                return Err(ModelError::Input(format!(
                    "importance sampling: coarse weight {k} of ray {r} is {}",
                    w[k]
                )));
            }
            let u = u.map_or(&even[..], |u| &u[r * sf..(r + 1) * sf]);
            sample_pdf_det(z, w, u, &mut out);
        }
        Ok(out)
    }

    /// Tensor entry point for the coarse pass (outputs in `rays_o`'s dtype). rays_o, rays_d: [R,3]; cyls: [P,5];
    /// skts: [P,24,4,4]; scales: [24,3] (used as constants: nothing here is differentiable).
    /// Outputs live on `rays_o`'s device.
    pub fn cast(
        &self,
        rays_o: &Tensor,
        rays_d: &Tensor,
        cyls: &Tensor,
        skts: &Tensor,
        scales: &Tensor,
    ) -> Result<CoarseSamples> {
        self.cast_placed(rays_o, rays_d, cyls, skts, scales, None, None)
    }

    /// [`Self::cast`] with the coarse ray parameters chosen by `place` when given: it gets
    /// the host inputs (bounds, rays_o, rays_d, skts, scales, as [`Self::near_far`] takes
    /// them) and the evenly spaced (or, with `jitter`, stratified) parameters [R,Sc], and
    /// returns the ones to use.
    #[allow(clippy::too_many_arguments)]
    pub fn cast_placed(
        &self,
        rays_o: &Tensor,
        rays_d: &Tensor,
        cyls: &Tensor,
        skts: &Tensor,
        scales: &Tensor,
        place: Option<&CoarsePlacer>,
        jitter: Option<Jitter>,
    ) -> Result<CoarseSamples> {
        let n_rays = rays_o.dims().first().copied().unwrap_or(0);
        let o = host_f32_shaped("rays_o", rays_o, &[n_rays, 3])?;
        let d = host_f32_shaped("rays_d", rays_d, &[n_rays, 3])?;
        let n_poses = skts.dims().first().copied().unwrap_or(0);
        let skts = host_f32_shaped("skts", skts, &[n_poses, N_JOINTS, 4, 4])?;
        let cyls = host_f32_shaped("cyls", cyls, &[n_poses, 5])?;
        let scales = host_f32_shaped("scales", scales, &[N_JOINTS, 3])?;
        let bounds = self.near_far(&o, &d, &cyls, &skts, &scales)?;
        let mut z = self.coarse_z(&bounds.near, &bounds.far)?;
        if let Some(j) = jitter {
            z = Jitter::stratify(&z, &j.coarse_u(n_rays, self.n_samples), self.n_samples);
        }
        if let Some(place) = place {
            z = place(
                &CastInputs {
                    bounds: &bounds,
                    rays_o: &o,
                    rays_d: &d,
                    skts: &skts,
                    scales: &scales,
                },
                z,
            )?;
        }
        let pts = sample_points(&o, &d, &z, self.n_samples)?;
        let (dev, dt) = (rays_o.device(), rays_o.dtype());
        let fine_u = jitter.map(|j| j.fine_u(n_rays, self.n_importance));
        Ok(CoarseSamples {
            bounds: Some(bounds),
            z: Tensor::from_vec(z, (n_rays, self.n_samples), dev)?.to_dtype(dt)?,
            pts: Tensor::from_vec(pts, (n_rays, self.n_samples, 3), dev)?.to_dtype(dt)?,
            fine_u,
        })
    }

    /// Tensor entry point for the fine pass. rays_o, rays_d: [R,3]; z_coarse: [R,Sc];
    /// weights: [R,Sc] coarse render weights (read as constants, like the reference's
    /// detached samples); `fine_u`: each ray's CDF places ([`CoarseSamples::fine_u`], see
    /// [`Self::importance_z`]). Outputs live on `rays_o`'s device.
    pub fn resample(
        &self,
        rays_o: &Tensor,
        rays_d: &Tensor,
        z_coarse: &Tensor,
        weights: &Tensor,
        fine_u: Option<&[f32]>,
    ) -> Result<FineSamples> {
        let n_rays = rays_o.dims().first().copied().unwrap_or(0);
        let (sc, sf) = (self.n_samples, self.n_importance);
        let o = host_f32_shaped("rays_o", rays_o, &[n_rays, 3])?;
        let d = host_f32_shaped("rays_d", rays_d, &[n_rays, 3])?;
        let zc = host_f32_shaped("z_coarse", z_coarse, &[n_rays, sc])?;
        let w = host_f32_shaped("weights", weights, &[n_rays, sc])?;
        let zf = self.importance_z(&zc, &w, fine_u)?;
        let pts = sample_points(&o, &d, &zf, sf)?;
        let (z_all, perm) = merge_sorted(&zc, sc, &zf, sf)?;
        let (dev, dt) = (rays_o.device(), rays_o.dtype());
        Ok(FineSamples {
            z: Tensor::from_vec(zf, (n_rays, sf), dev)?.to_dtype(dt)?,
            pts: Tensor::from_vec(pts, (n_rays, sf, 3), dev)?.to_dtype(dt)?,
            z_all: Tensor::from_vec(z_all, (n_rays, sc + sf), dev)?.to_dtype(dt)?,
            perm: Tensor::from_vec(perm, (n_rays, sc + sf), dev)?,
        })
    }
}

/// Cylinder near/far before the miss fallback: rays_o, rays_d: [R,3]; `cyl(r)` gives
/// ray r's (centre_x, centre_z, radius). Returns near, far: [R], NaN for rays that miss the
/// circle in the ground (x–z) plane or run vertically.
pub fn cylinder_near_far(
    rays_o: &[f32],
    rays_d: &[f32],
    cyl: impl Fn(usize) -> [f32; 3],
) -> (Vec<f32>, Vec<f32>) {
    let n_rays = rays_o.len() / 3;
    let mut near = Vec::with_capacity(n_rays);
    let mut far = Vec::with_capacity(n_rays);
    for r in 0..n_rays {
        let [cx, cz, radius] = cyl(r);
        let (dx, dz) = (rays_d[3 * r], rays_d[3 * r + 2]);
        // The reference measures along the segment to the far point o + 100·d.
        let (n0, n1) = (100.0 * dx, 100.0 * dz);
        let (c0, c1) = (cx - rays_o[3 * r], cz - rays_o[3 * r + 2]);
        let n_len = (n0 * n0 + n1 * n1).sqrt();
        let dist = (c0 * n1 - c1 * n0).abs() / n_len;
        let q = (radius * radius - dist * dist).sqrt();
        let k = (c0 * n0 + c1 * n1) / n_len;
        let d_len = (dx * dx + dz * dz).sqrt();
        // Origins inside the circle keep near = 0; the 0/1 factor keeps NaN propagation of the
        // reference (a miss gives NaN in both bounds).
        let inside_front = if q < k { 1.0f32 } else { 0.0 };
        near.push(inside_front * (k - q) / d_len);
        far.push((k + q) / d_len);
    }
    (near, far)
}

/// Replace NaN cylinder bounds (rays missing the cylinder). Reference: the NaN-ignoring mean
/// of the batch's near (far) values, or `near0`/`far0` when every ray misses. With `per_ray`
/// (quirk switched off) every miss gets `near0`/`far0`, independent of the batch.
pub fn fill_cylinder_misses(
    near: &mut [f32],
    far: &mut [f32],
    near0: f32,
    far0: f32,
    per_ray: bool,
) {
    let fill = |v: &mut [f32], default: f32| {
        let value = if per_ray {
            default
        } else {
            nan_mean(v).unwrap_or(default)
        };
        v.iter_mut().filter(|x| x.is_nan()).for_each(|x| *x = value);
    };
    fill(near, near0);
    fill(far, far0);
}

/// The (near, far) that [`fill_cylinder_misses`] gives to misses.
pub fn cylinder_miss_fill(
    near: &[f32],
    far: &[f32],
    near0: f32,
    far0: f32,
    per_ray: bool,
) -> (f32, f32) {
    if per_ray {
        (near0, far0)
    } else {
        (
            nan_mean(near).unwrap_or(near0),
            nan_mean(far).unwrap_or(far0),
        )
    }
}

/// Mean of the non-NaN entries (accumulated in f64), `None` if all are NaN.
fn nan_mean(v: &[f32]) -> Option<f32> {
    let (sum, count) = v
        .iter()
        .filter(|x| !x.is_nan())
        .fold((0f64, 0usize), |(s, c), &x| (s + x as f64, c + 1));
    (count > 0).then(|| (sum / count as f64) as f32)
}

/// A sphere in world space around one part's box (at `bound + BOX_EPS` in normalised units,
/// with a 5 % margin): a ray whose line passes outside it cannot cross the box, which
/// rejects most (ray, box) pairs of an image without mapping the ray into the box frame.
#[derive(Clone, Copy, Debug)]
struct WorldSphere {
    centre: [f32; 3],
    radius2: f32,
}

impl WorldSphere {
    /// The sphere around the box of `world_to_box` ([4,4] row-major `A_j·skt_j`) and scale
    /// s_j, or `None` when the map cannot be inverted (then no pair is rejected early).
    fn around(world_to_box: &[f32], scale: [f32; 3], bound: f64) -> Option<Self> {
        let m = |i: usize, k: usize| world_to_box[4 * i + k] as f64;
        let det = m(0, 0) * (m(1, 1) * m(2, 2) - m(1, 2) * m(2, 1))
            - m(0, 1) * (m(1, 0) * m(2, 2) - m(1, 2) * m(2, 0))
            + m(0, 2) * (m(1, 0) * m(2, 1) - m(1, 1) * m(2, 0));
        if !(det.is_finite() && det.abs() > 1e-12) {
            return None;
        }
        // The inverse of the linear part (adjugate over the determinant).
        let inv = |i: usize, k: usize| {
            let (r0, r1) = ((k + 1) % 3, (k + 2) % 3);
            let (c0, c1) = ((i + 1) % 3, (i + 2) % 3);
            (m(r0, c0) * m(r1, c1) - m(r0, c1) * m(r1, c0)) / det
        };
        let to_world = |v: [f64; 3]| -> [f64; 3] {
            std::array::from_fn(|i| (0..3).map(|k| inv(i, k) * v[k]).sum())
        };
        let centre = to_world([-m(0, 3), -m(1, 3), -m(2, 3)]);
        let lim = bound + BOX_EPS;
        let mut r2 = 0f64;
        for corner in 0..8 {
            let sign = |axis: usize| if corner >> axis & 1 == 1 { 1.0 } else { -1.0 };
            let c = to_world(std::array::from_fn(|a| sign(a) * lim * scale[a] as f64));
            r2 = r2.max(c.iter().map(|v| v * v).sum::<f64>());
        }
        let radius2 = (r2 * 1.05 * 1.05) as f32;
        (centre.iter().all(|v| v.is_finite()) && radius2.is_finite()).then(|| Self {
            centre: centre.map(|v| v as f32),
            radius2,
        })
    }

    /// Whether the line through o along d (d2 = |d|²) passes outside the sphere. Non-finite
    /// rays are not rejected (the exact tests decide them). The cross product's f32 rounding
    /// grows with the distance to the centre (a few ulps of |v|²·|d|²), so the margin grows
    /// with it (1e-5·|v|²) rather than relying on the 5 % alone.
    fn missed_by(&self, o: [f32; 3], d: [f32; 3], d2: f32) -> bool {
        let v = [
            self.centre[0] - o[0],
            self.centre[1] - o[1],
            self.centre[2] - o[2],
        ];
        let c = [
            v[1] * d[2] - v[2] * d[1],
            v[2] * d[0] - v[0] * d[2],
            v[0] * d[1] - v[1] * d[0],
        ];
        let v2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
        c[0] * c[0] + c[1] * c[1] + c[2] * c[2] > (self.radius2 + 1e-5 * v2) * d2
    }
}

/// A world ray in one part's box frame: `t` (`A_j·skt_j` applied; the direction only
/// rotated) and `s` (divided by the part's scale s_j, the normalised box units). Computed once
/// per ray and box for [`BoxRay::may_hit`] and the exact crossing that follows it.
#[derive(Clone, Copy, Debug)]
pub struct BoxRay {
    o_t: [f32; 3],
    d_t: [f32; 3],
    o_s: [f32; 3],
    d_s: [f32; 3],
}

impl BoxRay {
    /// world_to_box: [4,4] row-major `A_j·skt_j`; scale: s_j; o, d: the world ray.
    pub fn new(world_to_box: &[f32], scale: [f32; 3], o: [f32; 3], d: [f32; 3]) -> Self {
        let m = world_to_box;
        let rot =
            |v: [f32; 3], i: usize| m[4 * i] * v[0] + m[4 * i + 1] * v[1] + m[4 * i + 2] * v[2];
        let o_t = [rot(o, 0) + m[3], rot(o, 1) + m[7], rot(o, 2) + m[11]];
        let d_t = [rot(d, 0), rot(d, 1), rot(d, 2)];
        let o_s = [o_t[0] / scale[0], o_t[1] / scale[1], o_t[2] / scale[2]];
        let d_s = [d_t[0] / scale[0], d_t[1] / scale[1], d_t[2] / scale[2]];
        Self { o_t, d_t, o_s, d_s }
    }

    /// A cheap test that passes every ray [`Self::near_far`] or [`Self::near_far_robust`]
    /// could find crossing the box: both accept only face points inside the box, so a
    /// crossing ray passes within the box's circumradius (√3·bound in normalised units) of
    /// its centre. Most of an image's rays miss most boxes; this rejects them without the six
    /// face intersections. The 1 % margin is far above f32 rounding, and non-finite values
    /// pass (the exact tests decide them).
    pub fn may_hit(&self, bound: f64) -> bool {
        let (o_s, d_s) = (self.o_s, self.d_s);
        // |o_s × d_s|² / |d_s|²: the squared distance from the centre to the ray's line.
        let c = [
            o_s[1] * d_s[2] - o_s[2] * d_s[1],
            o_s[2] * d_s[0] - o_s[0] * d_s[2],
            o_s[0] * d_s[1] - o_s[1] * d_s[0],
        ];
        let cross2 = c[0] * c[0] + c[1] * c[1] + c[2] * c[2];
        let d2 = d_s[0] * d_s[0] + d_s[1] * d_s[1] + d_s[2] * d_s[2];
        let lim = (bound + BOX_EPS) as f32;
        let r2 = 3.0 * lim * lim * 1.01;
        // NaN compares as not greater: such rays go to the exact tests.
        cross2.partial_cmp(&(r2 * d2)) != Some(std::cmp::Ordering::Greater)
    }

    /// The (near, far) ray parameters of the crossing as the reference computes them
    /// (scale: s_j; bound: half-size of the box in normalised units, 1.1), or `None` unless
    /// exactly two of the six face hits are valid (misses, and grazing rays through an edge
    /// or corner).
    pub fn near_far(&self, scale: [f32; 3], bound: f64) -> Option<(f32, f32)> {
        let Self { o_t, d_t, .. } = *self;
        let mut hits = [[0f32; 3]; 2];
        let mut n_hits = 0;
        self.face_hits(bound, |_, p| {
            if n_hits < 2 {
                hits[n_hits] = p;
            }
            n_hits += 1;
        });
        if n_hits != 2 {
            return None;
        }
        let d_len = norm3(d_t);
        let dist = |p: [f32; 3]| {
            norm3([
                p[0] * scale[0] - o_t[0],
                p[1] * scale[1] - o_t[1],
                p[2] * scale[2] - o_t[2],
            ]) / d_len
        };
        let (t0, t1) = (dist(hits[0]), dist(hits[1]));
        Some((t0.min(t1), t0.max(t1)))
    }

    /// [`Self::near_far`] without the reference's blind spots (`quirks.robust_ray_bounds`): the
    /// face hits are kept as signed ray parameters (the box frame is an affine image of the world
    /// ray, so a face's `t` is the world ray parameter), every valid hit counts (rays through an
    /// edge or corner validate 3–6 faces, which the reference drops), the part behind the camera
    /// is cut off (near ≥ 0, so a camera inside a box samples from its origin), and boxes
    /// entirely behind the camera are misses.
    pub fn near_far_robust(&self, bound: f64) -> Option<(f32, f32)> {
        let (mut t_min, mut t_max) = (f32::INFINITY, f32::NEG_INFINITY);
        self.face_hits(bound, |t, _| {
            if t.is_finite() {
                t_min = t_min.min(t);
                t_max = t_max.max(t);
            }
        });
        (t_max > t_min && t_max > 0.0).then(|| (t_min.max(0.0), t_max))
    }

    /// Each of the six face planes ±bound whose hit lies on the box (within `BOX_EPS`), in
    /// the reference's order (x−, x+, y−, y+, z−, z+): `hit(t, point in the box frame)`.
    fn face_hits(&self, bound: f64, mut hit: impl FnMut(f32, [f32; 3])) {
        let (o_s, d_s) = (self.o_s, self.d_s);
        // The reference compares float32 tensors with Python-float thresholds: both end up f32.
        let face = bound as f32;
        let lim = (bound + BOX_EPS) as f32;
        for axis in 0..3 {
            for plane in [-face, face] {
                // Zero direction components give ±inf/NaN here; such points fail the range test.
                let t = (plane - o_s[axis]) / d_s[axis];
                let p = [
                    o_s[0] + t * d_s[0],
                    o_s[1] + t * d_s[1],
                    o_s[2] + t * d_s[2],
                ];
                if p.iter().all(|&c| c >= -lim && c <= lim) {
                    hit(t, p);
                }
            }
        }
    }
}

/// Whether the world-space sphere pre-test lets one ray through to the box tests of one part
/// (arguments as [`BoxRay::new`]); `true` where the map has no sphere.
pub fn box_sphere_may_hit(
    world_to_box: &[f32],
    scale: [f32; 3],
    o: [f32; 3],
    d: [f32; 3],
    bound: f64,
) -> bool {
    let d2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
    WorldSphere::around(world_to_box, scale, bound).is_none_or(|b| !b.missed_by(o, d, d2))
}

/// Sample points: rays_o, rays_d: [R,3], z: [R,S] -> [R,S,3] with `o + d·z`.
pub fn sample_points(rays_o: &[f32], rays_d: &[f32], z: &[f32], s: usize) -> Result<Vec<f32>> {
    let n_rays = ray_count(rays_o, rays_d)?;
    check_len("z", z, &[n_rays, s])?;
    let mut pts = Vec::with_capacity(z.len() * 3);
    for (r, zr) in z.chunks_exact(s.max(1)).enumerate() {
        for &zk in zr {
            pts.extend((0..3).map(|c| rays_o[3 * r + c] + rays_d[3 * r + c] * zk));
        }
    }
    Ok(pts)
}

/// Merge coarse and importance ray parameters: z_coarse: [R,Sc], z_fine: [R,Sf] ->
/// (z_all: [R,Sc+Sf] ascending, perm: [R,Sc+Sf] indices into `cat(z_coarse, z_fine)` per ray).
/// Ties are broken as `torch.sort` on CPU breaks them (see [`torch_sort`]); NaN sorts last.
pub fn merge_sorted(
    z_coarse: &[f32],
    sc: usize,
    z_fine: &[f32],
    sf: usize,
) -> Result<(Vec<f32>, Vec<u32>)> {
    if sc == 0 || z_coarse.len() % sc != 0 {
        return Err(ModelError::shape(
            "z_coarse",
            format!("[R,{sc}]"),
            z_coarse.len(),
        ));
    }
    let n_rays = z_coarse.len() / sc;
    check_len("z_fine", z_fine, &[n_rays, sf])?;
    let m = sc + sf;
    let mut z_all = Vec::with_capacity(n_rays * m);
    let mut perm = Vec::with_capacity(n_rays * m);
    let mut pairs: Vec<(f32, u32)> = Vec::with_capacity(m);
    for r in 0..n_rays {
        pairs.clear();
        let coarse = z_coarse[r * sc..(r + 1) * sc].iter();
        pairs.extend(
            coarse
                .chain(&z_fine[r * sf..(r + 1) * sf])
                .zip(0u32..)
                .map(|(&z, i)| (z, i)),
        );
        torch_sort::sort(&mut pairs);
        z_all.extend(pairs.iter().map(|p| p.0));
        perm.extend(pairs.iter().map(|p| p.1));
    }
    Ok((z_all, perm))
}

/// Reorder network outputs with the merge permutation (a gather, so gradients reach both
/// inputs): raw_coarse: [R,Sc,C], raw_fine: [R,Sf,C], perm: [R,Sc+Sf] u32 -> [R,Sc+Sf,C].
pub fn merge_raw(
    raw_coarse: &Tensor,
    raw_fine: &Tensor,
    perm: &Tensor,
    k: crate::compute::numerics::Numerics,
) -> Result<Tensor> {
    let (r, sc, c) = raw_coarse.dims3()?;
    let (rf, sf, cf) = raw_fine.dims3()?;
    if (rf, cf) != (r, c) {
        return Err(ModelError::shape(
            "raw_fine",
            format!("[{r},S,{c}]"),
            raw_fine.dims(),
        ));
    }
    if perm.dims() != [r, sc + sf] {
        return Err(ModelError::shape("perm", [r, sc + sf], perm.dims()));
    }
    let cat = Tensor::cat(&[raw_coarse, raw_fine], 1)?;
    // candle's gather backward (scatter_add) loops over the samples serially on CUDA; the
    // row op's does not, and is bit-identical on the CPU.
    crate::compute::ops::rows::gather_rows(&cat, perm, k)
}

/// `torch.linspace(0, 1, n)` in float32: the step is rounded once and the second half is
/// counted down from 1, so the ends are exact.
fn linspace01(n: usize) -> Vec<f32> {
    if n == 1 {
        return vec![0.0];
    }
    let step = 1.0f32 / (n - 1) as f32;
    let half = n / 2;
    (0..n)
        .map(|k| {
            if k < half {
                step * k as f32
            } else {
                1.0 - step * (n - 1 - k) as f32
            }
        })
        .collect()
}

/// Deterministic inverse-CDF sampling of one ray, appending `u.len()` samples to `out`.
/// z: [Sc] ascending; w: [Sc] coarse weights; u: [Sf] in [0,1].
fn sample_pdf_det(z: &[f32], w: &[f32], u: &[f32], out: &mut Vec<f32>) {
    let sc = z.len();
    // Bins: the Sc−1 midpoints; weights: a 3-tap max filter over the interior Sc−2 samples,
    // floored at 0.01 (plus 1e-5 against an all-zero pdf).
    let bins: Vec<f32> = (0..sc - 1).map(|i| 0.5 * (z[i + 1] + z[i])).collect();
    let blurred: Vec<f32> = (1..sc - 1)
        .map(|k| 0.5 * (w[k - 1].max(w[k]) + w[k].max(w[k + 1])) + 0.01 + 1e-5)
        .collect();
    let total: f32 = pairwise_sum(&blurred);
    // cdf: [Sc−1], leading 0; the running sum is kept in f64 like torch's CPU cumsum.
    let mut cdf = Vec::with_capacity(sc - 1);
    cdf.push(0f32);
    let mut acc = 0f64;
    for &b in &blurred {
        acc += (b / total) as f64;
        cdf.push(acc as f32);
    }
    let last = cdf.len() - 1;
    for &uk in u {
        // searchsorted(right): number of cdf entries <= u.
        let idx = cdf.partition_point(|&c| c <= uk);
        let below = idx.saturating_sub(1);
        let above = idx.min(last);
        let mut denom = cdf[above] - cdf[below];
        if denom < 1e-5 {
            denom = 1.0;
        }
        let t = (uk - cdf[below]) / denom;
        out.push(bins[below] + t * (bins[above] - bins[below]));
    }
}

/// Float32 sum in the blocked order of a vectorised reduction is unknowable; a pairwise sum
/// keeps the error at the same few-ulp level as torch's.
fn pairwise_sum(v: &[f32]) -> f32 {
    if v.len() <= 8 {
        return v.iter().sum();
    }
    let (a, b) = v.split_at(v.len() / 2);
    pairwise_sum(a) + pairwise_sum(b)
}

fn norm3(v: [f32; 3]) -> f32 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

fn ray_count(rays_o: &[f32], rays_d: &[f32]) -> Result<usize> {
    if rays_o.len() % 3 != 0 {
        return Err(ModelError::shape("rays_o", "[R,3]", rays_o.len()));
    }
    let n = rays_o.len() / 3;
    check_len("rays_d", rays_d, &[n, 3])?;
    check_finite("rays_o", rays_o)?;
    check_finite("rays_d", rays_d)?;
    if let Some(r) = rays_d
        .chunks_exact(3)
        .position(|d| d.iter().all(|&c| c == 0.0))
    {
        return Err(ModelError::Input(format!(
            "rays_d: ray {r} has a zero direction"
        )));
    }
    Ok(n)
}

fn check_len(what: &str, v: &[f32], shape: &[usize]) -> Result<()> {
    let n: usize = shape.iter().product();
    if v.len() != n {
        return Err(ModelError::shape(
            what,
            format!("{shape:?} ({n} values)"),
            format!("{} values", v.len()),
        ));
    }
    Ok(())
}

fn check_finite(what: &str, v: &[f32]) -> Result<()> {
    match v.iter().position(|x| !x.is_finite()) {
        Some(i) => Err(ModelError::Input(format!("{what}: value {i} is {}", v[i]))),
        None => Ok(()),
    }
}

fn check_scales(scales: &[f32]) -> Result<()> {
    check_len("scales", scales, &[N_JOINTS, 3])?;
    match scales.iter().position(|&s| !(s.is_finite() && s > 0.0)) {
        Some(i) => Err(ModelError::Input(format!(
            "scales: half-extent of joint {} axis {} is {} (must be finite and > 0)",
            i / 3,
            i % 3,
            scales[i]
        ))),
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::torch_sort::sort_with_depth;
    use rand::{Rng, SeedableRng};

    /// Sorted ascending (NaN last) and a permutation of the input, for the quicksort path and
    /// for the heapsort fallback (depth 0), on inputs with many ties.
    #[test]
    fn torch_sort_sorts_on_both_paths() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for depth in [0usize, 1, 12] {
            for n in [0usize, 1, 2, 15, 16, 17, 72, 200] {
                let mut v: Vec<(f32, u32)> = (0..n as u32)
                    .map(|i| {
                        let z = if rng.gen_bool(0.05) {
                            f32::NAN
                        } else {
                            (rng.gen_range(0..20) as f32) * 0.5
                        };
                        (z, i)
                    })
                    .collect();
                let input = v.clone();
                sort_with_depth(&mut v, depth);
                let mut idx: Vec<u32> = v.iter().map(|p| p.1).collect();
                idx.sort_unstable();
                assert_eq!(
                    idx,
                    (0..n as u32).collect::<Vec<_>>(),
                    "not a permutation (n {n}, depth {depth})"
                );
                for p in &v {
                    assert_eq!(
                        p.0.to_bits(),
                        input[p.1 as usize].0.to_bits(),
                        "value detached from its index"
                    );
                }
                for w in v.windows(2) {
                    let ok = w[1].0.is_nan() || (!w[0].0.is_nan() && w[0].0 <= w[1].0);
                    assert!(
                        ok,
                        "out of order: {:?} before {:?} (n {n}, depth {depth})",
                        w[0], w[1]
                    );
                }
            }
        }
    }
}
