//! Leaving work out: which rays and samples may skip the network, decided on the
//! host before any network work.
//!
//! * **Ray culling.** A ray that crosses no enlarged bone box (`RayBounds::ray_hits_body`
//!   false) is given raw outputs 0 for every sample. Volume rendering then yields exactly the
//!   background colour, zero weights and alpha, transmittance 1, acc, depth and disparity 0;
//!   its (cylinder-fallback) samples are still placed, so the outputs keep their shapes. This
//!   is an approximation: every sample of such a ray lies outside all ±1.1 boxes, where
//!   w^p ≤ exp(−2·1.1⁶) ≈ 0.03 but not 0, and the network learned (not was forced) to be
//!   empty there. Rays that do hit a box are evaluated exactly as in parity mode.
//! * **Empty cells.** With an occupancy grid ([`crate::network::occupancy`]), a sample whose
//!   window is above t for some joints, all of which mark its cell (in their own x̄) empty,
//!   skips the network too and gets what a culled sample gets: the network's far-away
//!   constant ([`SampleFate::Empty`]). A sample in an occupied cell of any such joint is
//!   always evaluated. This changes the render wherever the skipped density was not 0; the
//!   grid's threshold bounds it. A training pass runs a share of these samples anyway
//!   (probes, [`crate::render::options::GridFeed`]) and reports what its evaluated samples
//!   found to the grid.
//! * **Sample culling.** A sample whose spatial window w^p is ≤ t for every joint skips the
//!   network. Where w^p = 0 for all joints the window product w = w^p·w^f is 0, so the max-pool,
//!   f^m and every windowed point feature are 0, and the network's output is a global constant
//!   density with a colour that depends only on the view: evaluating the network once per
//!   ray at a far-away point reproduces it exactly (`SampleFill::Network`). At t = 0 only
//!   samples whose w^p underflows to exactly 0 in f32 are culled (see [`exponent_cut`]), so
//!   the outputs are those of parity mode.
//!
//! The test needs only the per-joint world → box transforms (A_j · skt_j), the effective
//! half-extents s_j and sixth powers: a few dozen flops per sample and joint on the host,
//! stopping at the first joint whose window is above the threshold.
//!
//! **Joint grouping** (`PassOptions::cull_joints`, CPU). A joint whose window is exactly 0 at
//! every point of a network call adds nothing to the call: its windowed features are 0, so
//! it contributes 0 to f^m and to the first modulated layer, and a 0 to the max-pool over
//! joints. [`WindowTest::live_joints`] (at threshold 0) says which joints each sample needs
//! (4–6 of 24 on average for the kept samples of a trained `cpu-small` avatar); the culled
//! route sorts a pose's kept samples by them, limb by limb, and cuts its calls so that each
//! carries few joints (`Network::eval_joints`, with the 0 put back into the max-pool).

use pma_data::skeleton::N_JOINTS;

use crate::error::{ModelError, Result};
use crate::network::occupancy::OccupancyGrid;
use crate::render::bones::BoneFrames;
use crate::render::options::GridObservation;

/// `exp(−x)` is exactly 0 in f32 for x > 103.98 (half the smallest subnormal); culling at
/// threshold 0 uses a cut a little above it so that the host test (f64, composed transform)
/// and the network's window (f32, two-step transform) agree on every culled sample.
pub const EXACT_ZERO_EXPONENT: f64 = 105.0;

/// The exponent α·Σ_k x̄_k⁶ at or above which w^p ≤ `threshold`.
pub fn exponent_cut(threshold: f64) -> f64 {
    if threshold > 0.0 {
        (-threshold.ln()).min(EXACT_ZERO_EXPONENT)
    } else {
        EXACT_ZERO_EXPONENT
    }
}

/// Samples per block of the parallel window test (many blocks keep the workers balanced).
const FATE_BLOCK_SAMPLES: usize = 16_384;

/// `per_block`'s outputs for blocks of the `n_rays` rays of `s` samples each, concatenated
/// in ray order: the blocks go to the workers where there are enough samples to pay for
/// it (the result does not depend on the split).
fn by_ray_blocks<T: Clone + Send>(
    n_rays: usize,
    s: usize,
    per_block: impl Fn(std::ops::Range<usize>) -> Result<Vec<T>> + Sync + Send,
) -> Result<Vec<T>> {
    let workers = crate::compute::parallel::workers();
    let blocks = if workers > 1 && n_rays * s >= 8 * FATE_BLOCK_SAMPLES {
        (n_rays * s).div_ceil(FATE_BLOCK_SAMPLES)
    } else {
        1
    };
    let rays_per_block = n_rays.div_ceil(blocks);
    let parts = crate::compute::parallel::map_ordered(workers, blocks, |b| {
        per_block((b * rays_per_block).min(n_rays)..((b + 1) * rays_per_block).min(n_rays))
    })?;
    Ok(parts.concat())
}

/// What the culling of one forward pass decided for each sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SampleFate {
    /// Run the network.
    Evaluate,
    /// w^p ≤ t for every joint: the network's far-away constant (or 0 with `SampleFill::Zero`).
    Outside,
    /// Every joint with w^p > t marks the sample's cell empty in the occupancy grid: filled
    /// like [`SampleFate::Outside`].
    Empty,
    /// The ray crosses no bone box: raw outputs 0.
    RayCulled,
    /// Behind the depth where the ray's transmittance fell below the early-stop threshold
    /// (`PassOptions::early_stop`): filled like [`SampleFate::Outside`].
    Behind,
}

/// Host-side spatial-window test for every pose of a batch.
#[derive(Debug, Clone)]
pub struct WindowTest {
    /// Per pose and joint: the affine map world → x̄ (rows already divided by s_j), [P·24][3][4].
    maps: Vec<[[f64; 4]; 3]>,
    alpha: f64,
    /// Half the window exponent β (x̄^β = (x̄²)^(β/2)).
    half_beta: i32,
    cut: f64,
    /// Half-width of the cube |x̄_k| ≤ r in which w^p can exceed the threshold (∞ when α ≤ 0).
    reach: f64,
    /// Per pose and joint: the largest row norm of the world → x̄ map's linear part (how far
    /// x̄ moves per metre), [P·24].
    stretch: Vec<f64>,
    /// World position of each pose's root joint (for the far-away point).
    roots: Vec<[f64; 3]>,
}

/// Joints as bits (bit j = joint j).
pub type JointMask = u32;
pub(crate) const ALL_JOINTS: JointMask = (1 << N_JOINTS) - 1;

impl WindowTest {
    /// align: [24,4,4] A_j (`pts_embedder.transforms`); skts: [P,24,4,4]; scales: [24,3]
    /// effective half-extents; `alpha`, `beta` the window's α and (even) β; `threshold` t ≥ 0.
    pub fn new(
        align: &[f32],
        skts: &[f32],
        scales: &[f32],
        alpha: f64,
        beta: u32,
        threshold: f64,
    ) -> Result<Self> {
        if scales.len() != N_JOINTS * 3 {
            return Err(ModelError::shape(
                "scales",
                [N_JOINTS, 3],
                format!("{} values", scales.len()),
            ));
        }
        if let Some(i) = scales.iter().position(|&s| !(s.is_finite() && s > 0.0)) {
            return Err(ModelError::Input(format!(
                "culling: half-extent of joint {} axis {} is {} (must be finite and > 0)",
                i / 3,
                i % 3,
                scales[i]
            )));
        }
        if !(threshold.is_finite() && threshold >= 0.0) {
            return Err(ModelError::Input(format!(
                "culling: sample threshold must be finite and >= 0, found {threshold}"
            )));
        }
        Ok(Self::from_frames(
            &BoneFrames::new(align, skts)?,
            scales,
            alpha,
            beta,
            threshold,
        ))
    }

    /// The test for the bone boxes of `frames` (validated inputs: see [`Self::new`]).
    fn from_frames(
        frames: &BoneFrames,
        scales: &[f32],
        alpha: f64,
        beta: u32,
        threshold: f64,
    ) -> Self {
        let n_poses = frames.n_poses();
        let mut maps = Vec::with_capacity(n_poses * N_JOINTS);
        for p in 0..n_poses {
            for j in 0..N_JOINTS {
                let mut m = frames.world_to_box_f64(p, j);
                for (i, row) in m.iter_mut().enumerate() {
                    for v in row.iter_mut() {
                        *v /= scales[3 * j + i] as f64;
                    }
                }
                maps.push(m);
            }
        }
        let cut = exponent_cut(threshold);
        // α·Σ_k x̄_k^β ≥ α·|x̄_k|^β for each k, so outside this cube the exponent is ≥ the cut
        // (the relative 1e-9 covers the rounding of powf).
        let reach = match alpha > 0.0 && beta > 0 {
            true => (cut / alpha).powf(1.0 / beta as f64) * (1.0 + 1e-9),
            false => f64::INFINITY,
        };
        let stretch = maps
            .iter()
            .map(|m| {
                m.iter()
                    .map(|r| (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt())
                    .fold(0.0, f64::max)
            })
            .collect();
        Self {
            maps,
            alpha,
            half_beta: (beta / 2) as i32,
            cut,
            reach,
            stretch,
            roots: (0..n_poses).map(|p| frames.root_origin(p)).collect(),
        }
    }

    pub fn n_poses(&self) -> usize {
        self.roots.len()
    }

    /// x̄ of joint j of pose p at world point x, and α·Σ_k x̄_k⁶ (w^p = exp(−that)).
    pub fn x_bar(&self, p: usize, j: usize, x: [f32; 3]) -> ([f64; 3], f64) {
        let m = &self.maps[p * N_JOINTS + j];
        let mut xb = [0f64; 3];
        let mut sum = 0f64;
        for (row, v) in m.iter().zip(xb.iter_mut()) {
            *v = row[0] * x[0] as f64 + row[1] * x[1] as f64 + row[2] * x[2] as f64 + row[3];
            let sq = *v * *v;
            // β = 6 (every preset) without the libcall; s·(s·s) is what powi(3) computes.
            sum += match self.half_beta {
                3 => sq * (sq * sq),
                n => sq.powi(n),
            };
        }
        (xb, self.alpha * sum)
    }

    /// The joints whose window can exceed the threshold somewhere on the ray through the
    /// samples xs ([S,3] of one ray of pose p): those whose cube |x̄_k| ≤ reach, widened by
    /// how far a sample strays from the segment between the first and the last sample, the
    /// segment crosses. Every other joint's exponent is ≥ the cut at every sample, so the
    /// per-sample test may skip it. Samples come in depth order, so the segment spans them
    /// and the stray is f32 rounding off the line; a sample out of order only lies farther
    /// from the segment (the distance is to its nearest point, ends included) and widens the
    /// margin, so the mask stays safe in any order.
    fn ray_joints(&self, p: usize, xs: &[f32]) -> JointMask {
        let n = xs.len() / 3;
        if n < 2 || !self.reach.is_finite() {
            return ALL_JOINTS;
        }
        let at = |k: usize| [xs[3 * k] as f64, xs[3 * k + 1] as f64, xs[3 * k + 2] as f64];
        let dist2 =
            |a: [f64; 3], b: [f64; 3]| (0..3).map(|i| (a[i] - b[i]) * (a[i] - b[i])).sum::<f64>();
        let (a, b) = (at(0), at(n - 1));
        let ab = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
        let len2 = dist2(a, b);
        // Largest distance of a sample from the segment [a, b] (one square root per ray).
        let inv_len2 = if len2 > 0.0 { 1.0 / len2 } else { 0.0 };
        let mut stray2 = 0f64;
        for k in 1..n - 1 {
            let x = at(k);
            let t = ((0..3).map(|i| (x[i] - a[i]) * ab[i]).sum::<f64>() * inv_len2).clamp(0.0, 1.0);
            let q = [a[0] + t * ab[0], a[1] + t * ab[1], a[2] + t * ab[2]];
            stray2 = stray2.max(dist2(x, q));
        }
        let stray = stray2.sqrt();
        let mut mask = 0;
        for j in 0..N_JOINTS {
            let m = &self.maps[p * N_JOINTS + j];
            // Margin for the stray samples plus a little for this test's own rounding.
            let half =
                self.reach + self.stretch[p * N_JOINTS + j] * stray + 1e-6 * (1.0 + self.reach);
            let rows: [(f64, f64); 3] = std::array::from_fn(|k| {
                let r = &m[k];
                (
                    r[0] * a[0] + r[1] * a[1] + r[2] * a[2] + r[3],
                    r[0] * ab[0] + r[1] * ab[1] + r[2] * ab[2],
                )
            });
            // Most joints are out of reach along one axis at both ends of the segment: no
            // divisions for those (the segment's x̄_k runs between its ends).
            let beyond = |&(xa, dx): &(f64, f64)| {
                let xb = xa + dx;
                (xa > half && xb > half) || (xa < -half && xb < -half)
            };
            if rows.iter().any(beyond) {
                continue;
            }
            let (mut t0, mut t1) = (0f64, 1f64);
            for &(xa, dx) in &rows {
                if dx == 0.0 {
                    if xa.abs() > half {
                        t1 = -1.0;
                    }
                } else {
                    let (u, v) = ((-half - xa) / dx, (half - xa) / dx);
                    t0 = t0.max(u.min(v));
                    t1 = t1.min(u.max(v));
                }
            }
            if t0 <= t1 {
                mask |= 1 << j;
            }
        }
        mask
    }

    /// α·Σ_k x̄_k⁶ of joint j of pose p at world point x (w^p = exp(−that)).
    pub fn exponent(&self, p: usize, j: usize, x: [f32; 3]) -> f64 {
        self.x_bar(p, j, x).1
    }

    /// The joints of pose p whose window is above the threshold at x (bit j); with
    /// threshold 0, those whose window is not exactly 0 in f32.
    pub fn point_joints(&self, p: usize, x: [f32; 3]) -> JointMask {
        (0..N_JOINTS)
            .filter(|&j| self.exponent(p, j, x) < self.cut)
            .fold(0, |mask, j| mask | 1 << j)
    }

    /// Largest spatial window over the joints of pose p at x (f64; for tests and reports).
    pub fn max_window(&self, p: usize, x: [f32; 3]) -> f64 {
        (0..N_JOINTS)
            .map(|j| (-self.exponent(p, j, x)).exp())
            .fold(0.0, f64::max)
    }

    /// True when w^p ≤ the threshold for every joint of pose p at x.
    pub fn outside(&self, p: usize, x: [f32; 3]) -> bool {
        (0..N_JOINTS).all(|j| self.exponent(p, j, x) >= self.cut)
    }

    /// The fate of a sample of pose p at x on a ray that is not culled: evaluated as soon as
    /// one joint with w^p above the threshold marks its cell occupied (any such joint when
    /// there is no grid), [`SampleFate::Empty`] when there are such joints and all mark it
    /// empty, [`SampleFate::Outside`] when there are none.
    pub fn fate(&self, p: usize, x: [f32; 3], grid: Option<&OccupancyGrid>) -> SampleFate {
        self.fate_among(p, x, grid, ALL_JOINTS)
    }

    /// [`Self::fate`] testing only the joints of `joints` (the others known to be below the
    /// threshold at x).
    fn fate_among(
        &self,
        p: usize,
        x: [f32; 3],
        grid: Option<&OccupancyGrid>,
        joints: JointMask,
    ) -> SampleFate {
        let mut active = false;
        let mut left = joints;
        while left != 0 {
            let j = left.trailing_zeros() as usize;
            left &= left - 1;
            let (xb, e) = self.x_bar(p, j, x);
            if e < self.cut {
                match grid {
                    Some(g) if !g.occupied(j, xb) => active = true,
                    _ => return SampleFate::Evaluate,
                }
            }
        }
        match active {
            true => SampleFate::Empty,
            false => SampleFate::Outside,
        }
    }

    /// For the points xs [S,3] along one ray of pose p, in depth order: whether each would
    /// run the network with `grid` ([`Self::fate`] is [`SampleFate::Evaluate`]).
    pub(crate) fn evaluated_along(&self, p: usize, xs: &[f32], grid: &OccupancyGrid) -> Vec<bool> {
        let joints = self.ray_joints(p, xs);
        xs.chunks_exact(3)
            .map(|x| {
                self.fate_among(p, [x[0], x[1], x[2]], Some(grid), joints) == SampleFate::Evaluate
            })
            .collect()
    }

    /// What a training pass saw of the grid ([`crate::render::options::GridFeed`]): for each
    /// evaluated sample of one ray (xs [S,3] of pose p, `evaluated[k]`, relu σ `sigma[k]`),
    /// every joint whose window is above the threshold there, with the sample's cell in that
    /// joint's grid (the joints the grid is asked about at that sample).
    pub(crate) fn observe_ray(
        &self,
        p: usize,
        xs: &[f32],
        evaluated: &[bool],
        sigma: &[f32],
        grid: &OccupancyGrid,
        out: &mut Vec<GridObservation>,
    ) {
        let joints = self.ray_joints(p, xs);
        for ((x, &e), &sigma) in xs.chunks_exact(3).zip(evaluated).zip(sigma) {
            if !e {
                continue;
            }
            let mut left = joints;
            while left != 0 {
                let j = left.trailing_zeros() as usize;
                left &= left - 1;
                let (xb, ex) = self.x_bar(p, j, [x[0], x[1], x[2]]);
                if ex < self.cut {
                    if let Some(cell) = grid.cell_of(xb) {
                        out.push(GridObservation {
                            joint: j as u16,
                            cell: cell as u32,
                            sigma,
                        });
                    }
                }
            }
        }
    }

    /// The grid's density at a sample of pose p at x: the largest value the cells of x hold
    /// over the joints whose window is above the threshold (0 where there are none).
    pub fn grid_density(&self, p: usize, x: [f32; 3], grid: &OccupancyGrid) -> f32 {
        let mut d = 0f32;
        for j in 0..N_JOINTS {
            let (xb, e) = self.x_bar(p, j, x);
            if e < self.cut {
                d = d.max(grid.density_at(j, xb));
            }
        }
        d
    }

    /// Importance-sampling weights of the coarse samples pts: [R,S,3] at ray parameters
    /// z: [R,S] along dirs: [R,3] taken from the grid instead of the network: the grid's
    /// density composited as the coarse render composites the network's (α = 1 − exp(−σδ),
    /// w = α·T). Culled rays (`ray_alive[r]` false) get zero weights. Returns [R,S].
    #[allow(clippy::too_many_arguments)]
    pub fn grid_weights(
        &self,
        pts: &[f32],
        z: &[f32],
        dirs: &[f32],
        n_rays: usize,
        s: usize,
        ray_alive: Option<&[bool]>,
        grid: &OccupancyGrid,
    ) -> Result<Vec<f32>> {
        check_samples(pts, n_rays, s, self.n_poses())?;
        if z.len() != n_rays * s || dirs.len() != n_rays * 3 {
            return Err(ModelError::shape(
                "z, dirs",
                format!("[{n_rays},{s}], [{n_rays},3]"),
                format!("{} and {} values", z.len(), dirs.len()),
            ));
        }
        let per_pose = n_rays / self.n_poses();
        by_ray_blocks(n_rays, s, |rays| {
            let mut out = Vec::with_capacity(rays.len() * s);
            for r in rays {
                if !ray_alive.is_none_or(|a| a[r]) {
                    out.extend(std::iter::repeat_n(0f32, s));
                    continue;
                }
                let p = r / per_pose;
                let d = &dirs[3 * r..3 * r + 3];
                let norm = ((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) as f64).sqrt();
                let mut transmittance = 1f64;
                for k in 0..s {
                    let i = r * s + k;
                    let x = [pts[3 * i], pts[3 * i + 1], pts[3 * i + 2]];
                    let sigma = self.grid_density(p, x, grid) as f64;
                    let delta = match k + 1 < s {
                        true => (z[i + 1] - z[i]) as f64,
                        false => crate::render::volume::LAST_DELTA,
                    } * norm;
                    let alpha = 1.0 - (-sigma * delta).exp();
                    out.push((alpha * transmittance) as f32);
                    transmittance *= 1.0 - alpha + 1e-10;
                }
            }
            Ok(out)
        })
    }

    /// A world point where every joint's window of pose p is exactly 0: 1 km (or further)
    /// from the root along +x.
    pub fn far_point(&self, p: usize) -> Result<[f32; 3]> {
        let r = self.roots[p];
        let mut d = 1e3;
        for _ in 0..6 {
            let x = [(r[0] + d) as f32, r[1] as f32, r[2] as f32];
            if (0..N_JOINTS).all(|j| self.exponent(p, j, x) >= EXACT_ZERO_EXPONENT) {
                return Ok(x);
            }
            d *= 10.0;
        }
        Err(ModelError::Input(format!(
            "culling: no point with a zero window found for pose {p} (root at {r:?})"
        )))
    }

    /// Fate of each sample of pts: [R,S,3] (host, row-major), rays grouped by pose in equal
    /// contiguous blocks; `ray_alive[r]` false marks a culled ray; `grid` the occupancy grid
    /// to consult (see [`Self::fate`]).
    pub fn fates(
        &self,
        pts: &[f32],
        n_rays: usize,
        s: usize,
        ray_alive: Option<&[bool]>,
        grid: Option<&OccupancyGrid>,
    ) -> Result<Vec<SampleFate>> {
        check_samples(pts, n_rays, s, self.n_poses())?;
        if let Some(a) = ray_alive {
            if a.len() != n_rays {
                return Err(ModelError::shape("ray_hits_body", [n_rays], [a.len()]));
            }
        }
        let per_pose = n_rays / self.n_poses();
        // The test is a few hundred host flops per culled sample, as much as a fifth of a
        // culled render on one core: worth the workers.
        by_ray_blocks(n_rays, s, |rays| {
            let mut out = Vec::with_capacity(rays.len() * s);
            for r in rays {
                if !ray_alive.is_none_or(|a| a[r]) {
                    out.extend(std::iter::repeat_n(SampleFate::RayCulled, s));
                    continue;
                }
                let p = r / per_pose;
                let xs = &pts[3 * r * s..3 * (r + 1) * s];
                // Most rays cross a few joints' reach: the rest are not tested per sample.
                let joints = self.ray_joints(p, xs);
                for x in xs.chunks_exact(3) {
                    out.push(self.fate_among(p, [x[0], x[1], x[2]], grid, joints));
                }
            }
            Ok(out)
        })
    }

    /// For each sample `samples[i]` of pts: [R,S,3] (rays grouped by pose in equal blocks),
    /// the joints (bit j) whose window is above the threshold there; with threshold 0, the
    /// joints whose window is not exactly 0 in f32. Samples are taken in ascending order.
    pub fn live_joints(
        &self,
        pts: &[f32],
        n_rays: usize,
        s: usize,
        samples: &[usize],
    ) -> Result<Vec<JointMask>> {
        check_samples(pts, n_rays, s, self.n_poses())?;
        let per_pose = n_rays / self.n_poses();
        let mut out = Vec::with_capacity(samples.len());
        // The ray test once per ray that has samples in the list.
        let mut ray_mask = (usize::MAX, 0);
        for &i in samples {
            let (r, p) = (i / s, i / s / per_pose);
            if ray_mask.0 != r {
                ray_mask = (r, self.ray_joints(p, &pts[3 * r * s..3 * (r + 1) * s]));
            }
            let x = [pts[3 * i], pts[3 * i + 1], pts[3 * i + 2]];
            let mut mask = 0u32;
            let mut left = ray_mask.1;
            while left != 0 {
                let j = left.trailing_zeros() as usize;
                left &= left - 1;
                if self.exponent(p, j, x) < self.cut {
                    mask |= 1 << j;
                }
            }
            out.push(mask);
        }
        Ok(out)
    }

    /// Per pose, which joints have a window above the threshold at some sample of pts:
    /// [R,S,3] (the "optional joints" measurement). Returns [P][24].
    pub fn active_joints(&self, pts: &[f32], n_rays: usize, s: usize) -> Result<Vec<[bool; 24]>> {
        check_samples(pts, n_rays, s, self.n_poses())?;
        let per_pose = n_rays / self.n_poses();
        let mut active = vec![[false; N_JOINTS]; self.n_poses()];
        for r in 0..n_rays {
            let p = r / per_pose;
            for k in 0..s {
                let i = 3 * (r * s + k);
                let x = [pts[i], pts[i + 1], pts[i + 2]];
                for (j, a) in active[p].iter_mut().enumerate() {
                    if !*a && self.exponent(p, j, x) < self.cut {
                        *a = true;
                    }
                }
            }
        }
        Ok(active)
    }
}

/// Fates when only rays are culled.
pub fn ray_fates(n_rays: usize, s: usize, ray_alive: &[bool]) -> Result<Vec<SampleFate>> {
    if ray_alive.len() != n_rays {
        return Err(ModelError::shape(
            "ray_hits_body",
            [n_rays],
            [ray_alive.len()],
        ));
    }
    Ok(ray_alive
        .iter()
        .flat_map(|&a| {
            std::iter::repeat_n(
                if a {
                    SampleFate::Evaluate
                } else {
                    SampleFate::RayCulled
                },
                s,
            )
        })
        .collect())
}

fn check_samples(pts: &[f32], n_rays: usize, s: usize, n_poses: usize) -> Result<()> {
    if pts.len() != n_rays * s * 3 {
        return Err(ModelError::shape(
            "pts",
            [n_rays, s, 3],
            format!("{} values", pts.len()),
        ));
    }
    if n_poses == 0 || n_rays % n_poses != 0 {
        return Err(ModelError::Input(format!(
            "culling: {n_rays} rays cannot be split into {n_poses} equal per-pose blocks"
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::network::occupancy::{OccupancyConfig, OccupancyGrid};

    /// Uniform draws in [0, 1) from a 64-bit LCG seeded with `seed`.
    fn lcg(seed: u64) -> impl FnMut() -> f32 {
        let mut state = seed;
        move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 40) as f32 / (1u64 << 24) as f32
        }
    }

    /// A resolution-8 grid without dilation where each cell of each joint holds density 1
    /// with probability `share` (draws from `rnd`), else 0.
    fn random_grid(rnd: &mut impl FnMut() -> f32, share: f32) -> OccupancyGrid {
        let mut grid = OccupancyGrid::new(OccupancyConfig {
            resolution: 8,
            dilation: 0,
            ..Default::default()
        })
        .unwrap();
        for j in 0..N_JOINTS {
            for c in 0..512 {
                grid.update_max(j, c, if rnd() < share { 1.0 } else { 0.0 })
                    .unwrap();
            }
        }
        grid.finish_refresh();
        grid
    }

    fn identity_setup(scale: f32) -> WindowTest {
        let mut eye = vec![0f32; N_JOINTS * 16];
        for j in 0..N_JOINTS {
            for d in 0..4 {
                eye[j * 16 + 5 * d] = 1.0;
            }
        }
        let scales = vec![scale; N_JOINTS * 3];
        WindowTest::new(&eye, &eye, &scales, 2.0, 6, 0.0).unwrap()
    }

    #[test]
    fn window_matches_the_formula_and_the_cut_is_exact_zero_in_f32() {
        let w = identity_setup(0.5);
        // x̄ = x / 0.5: at x = (0.5, 0, 0) the window is exp(−2).
        assert!((w.max_window(0, [0.5, 0.0, 0.0]) - (-2f64).exp()).abs() < 1e-12);
        // Right at the cut, f32's exp is already exactly 0.
        assert_eq!((-(EXACT_ZERO_EXPONENT as f32)).exp(), 0.0);
        assert!((-(EXACT_ZERO_EXPONENT as f32 - 2.0)).exp() > 0.0);
        // x̄ = 2 on one axis: 2·64 = 128 > 105: outside at threshold 0.
        assert!(w.outside(0, [1.0, 0.0, 0.0]));
        assert!(!w.outside(0, [0.9, 0.0, 0.0]));
        let far = w.far_point(0).unwrap();
        assert!(w.outside(0, far));
    }

    #[test]
    fn thresholds_cut_where_the_window_crosses_them() {
        for t in [1e-6, 1e-4, 1e-2] {
            assert!((exponent_cut(t) - (-t.ln())).abs() < 1e-12);
        }
        assert_eq!(exponent_cut(0.0), EXACT_ZERO_EXPONENT);
        assert_eq!(exponent_cut(1e-60), EXACT_ZERO_EXPONENT);
    }

    #[test]
    fn bad_inputs_are_errors() {
        let eye = vec![0f32; N_JOINTS * 16];
        let scales = vec![0.5f32; N_JOINTS * 3];
        assert!(WindowTest::new(&eye[..10], &eye, &scales, 2.0, 6, 0.0).is_err());
        let mut bad = scales.clone();
        bad[7] = 0.0;
        let err = WindowTest::new(&eye, &eye, &bad, 2.0, 6, 0.0).unwrap_err();
        assert!(err.to_string().contains("joint 2 axis 1"), "{err}");
        assert!(WindowTest::new(&eye, &eye, &scales, 2.0, 6, f64::NAN).is_err());
        let w = identity_setup(0.5);
        assert!(w.fates(&[0.0; 5], 1, 2, None, None).is_err());
    }

    /// A sample in an occupied cell of any joint whose window is above the threshold is
    /// evaluated; it is left out only when every such joint marks its cell empty.
    #[test]
    fn a_sample_in_an_occupied_cell_is_never_skipped() {
        let mut eye = vec![0f32; N_JOINTS * 16];
        for j in 0..N_JOINTS {
            for d in 0..4 {
                eye[j * 16 + 5 * d] = 1.0;
            }
            // Joint j's box sits at x = 0.1·j, so neighbouring joints overlap.
            eye[j * 16 + 3] = -0.1 * j as f32;
        }
        let scales = vec![0.3f32; N_JOINTS * 3];
        let mut rnd = lcg(99);
        let grid = random_grid(&mut rnd, 0.3);
        for t in [0.0, 0.2] {
            let w = WindowTest::new(&eye, &eye, &scales, 2.0, 6, t).unwrap();
            let n = 4000;
            let pts: Vec<f32> = (0..3 * n)
                .map(|i| match i % 3 {
                    0 => rnd() * 8.0 - 1.5,
                    _ => rnd() * 0.8 - 0.4,
                })
                .collect();
            let fates = w.fates(&pts, n, 1, None, Some(&grid)).unwrap();
            let mut seen = [0usize; 3];
            for (i, fate) in fates.iter().enumerate() {
                let x = [pts[3 * i], pts[3 * i + 1], pts[3 * i + 2]];
                let active: Vec<usize> = (0..N_JOINTS)
                    .filter(|&j| w.exponent(0, j, x) < exponent_cut(t))
                    .collect();
                let any_occupied = active.iter().any(|&j| grid.occupied(j, w.x_bar(0, j, x).0));
                let expected = match (active.is_empty(), any_occupied) {
                    (true, _) => SampleFate::Outside,
                    (false, true) => SampleFate::Evaluate,
                    (false, false) => SampleFate::Empty,
                };
                assert_eq!(*fate, expected, "sample {i} at {x:?}, threshold {t}");
                seen[match fate {
                    SampleFate::Evaluate => 0,
                    SampleFate::Empty => 1,
                    _ => 2,
                }] += 1;
            }
            assert!(seen.iter().all(|&k| k > 50), "every fate occurs: {seen:?}");
            // Without a grid, the same samples are evaluated or outside, never empty.
            let plain = w.fates(&pts, n, 1, None, None).unwrap();
            for (a, b) in plain.iter().zip(&fates) {
                match b {
                    SampleFate::Empty => assert_eq!(*a, SampleFate::Evaluate),
                    _ => assert_eq!(a, b),
                }
            }
        }
    }

    /// Testing per sample only the joints a ray's segment reaches gives every sample the
    /// fate the test over all 24 joints gives, and leaves most joints out.
    #[test]
    fn joints_out_of_a_rays_reach_are_left_out_without_changing_a_fate() {
        let mut align = vec![0f32; N_JOINTS * 16];
        let mut skt = vec![0f32; N_JOINTS * 16];
        for j in 0..N_JOINTS {
            let (c, s) = ((0.3 * j as f32).cos(), (0.3 * j as f32).sin());
            // A rotation about z and a shift per joint, so the boxes are not axis-aligned.
            align[j * 16..j * 16 + 16].copy_from_slice(&[
                c, -s, 0.0, 0.0, s, c, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
            ]);
            for d in 0..4 {
                skt[j * 16 + 5 * d] = 1.0;
            }
            skt[j * 16 + 3] = -0.15 * (j % 8) as f32;
            skt[j * 16 + 7] = -0.2 * (j / 8) as f32;
        }
        let scales: Vec<f32> = (0..N_JOINTS * 3)
            .map(|i| 0.05 + 0.01 * (i % 5) as f32)
            .collect();
        let mut rnd = lcg(7);
        let grid = random_grid(&mut rnd, 0.4);
        let (n, s) = (600, 16);
        let mut pts = Vec::with_capacity(n * s * 3);
        for _ in 0..n {
            // Rays from a ring of cameras 3 m away towards a point among the boxes.
            let a = rnd() * 6.3;
            let o = [3.0 * a.cos() + 0.5, 3.0 * a.sin() + 0.2, rnd() - 0.5];
            let target = [rnd() * 1.2 - 0.1, rnd() * 0.7 - 0.1, rnd() * 0.4 - 0.2];
            let d: Vec<f32> = (0..3).map(|i| target[i] - o[i]).collect();
            for k in 0..s {
                let z = 0.6 + 0.8 * (k as f32 + rnd()) / s as f32;
                pts.extend((0..3).map(|i| o[i] + z * d[i]));
            }
        }
        // The same samples out of depth order (k -> 7k mod 16 within each ray): the per-ray
        // joint mask must stay safe in any order.
        let mut shuffled = Vec::with_capacity(pts.len());
        for r in 0..n {
            for k in 0..s {
                let q = 3 * (r * s + (7 * k) % s);
                shuffled.extend_from_slice(&pts[q..q + 3]);
            }
        }
        for (t, pts, ordered) in [
            (0.0, &pts, true),
            (0.6, &pts, true),
            (0.6, &shuffled, false),
        ] {
            for g in [None, Some(&grid)] {
                let w = WindowTest::new(&align, &skt, &scales, 2.0, 6, t).unwrap();
                let fates = w.fates(pts, n, s, None, g).unwrap();
                let mut kinds = [0usize; 3];
                for (i, fate) in fates.iter().enumerate() {
                    let x = [pts[3 * i], pts[3 * i + 1], pts[3 * i + 2]];
                    assert_eq!(*fate, w.fate(0, x, g), "sample {i}, threshold {t}");
                    kinds[match fate {
                        SampleFate::Evaluate => 0,
                        SampleFate::Empty => 1,
                        _ => 2,
                    }] += 1;
                }
                assert!(kinds[0] > 100 && kinds[2] > 100, "{kinds:?}");
                let tested: u32 = (0..n)
                    .map(|r| {
                        w.ray_joints(0, &pts[3 * r * s..3 * (r + 1) * s])
                            .count_ones()
                    })
                    .sum();
                // In depth order the masks leave most joints out; out of order they are
                // only looser.
                assert!(
                    !ordered || (tested as f64) < 0.5 * (n * N_JOINTS) as f64,
                    "{tested} joint tests for {n} rays at threshold {t}"
                );
            }
        }
    }

    /// The grid's weights are the compositing weights of its densities along the ray.
    #[test]
    fn grid_weights_composite_the_grid_density() {
        let w = identity_setup(0.5);
        let mut grid = OccupancyGrid::new(OccupancyConfig {
            resolution: 8,
            ..Default::default()
        })
        .unwrap();
        for j in 0..N_JOINTS {
            for c in 0..512 {
                // Density 2 in the cells with x̄ > 0 (x > 0 here), 0 elsewhere.
                let v = if grid.cell_corner(c)[0] >= 0.0 {
                    2.0
                } else {
                    0.0
                };
                grid.update_max(j, c, v).unwrap();
            }
        }
        grid.finish_refresh();
        let s = 7;
        let z: Vec<f32> = (0..s).map(|k| (k as f32 - 3.0) * 0.125).collect();
        // Ray 0 along +x through the origin with |d| = 2; ray 1 the same ray, culled.
        let mut pts = Vec::new();
        for _ in 0..2 {
            for &t in &z {
                pts.extend([2.0 * t, 0.0, 0.0]);
            }
        }
        let zz: Vec<f32> = z.iter().chain(&z).copied().collect();
        let dirs = [2.0, 0.0, 0.0, 2.0, 0.0, 0.0];
        let got = w
            .grid_weights(&pts, &zz, &dirs, 2, s, Some(&[true, false]), &grid)
            .unwrap();
        let mut t = 1f64;
        for k in 0..s {
            let sigma = if 2.0 * z[k] >= 0.0 { 2.0 } else { 0.0 };
            let delta: f64 = if k + 1 < s { 0.25 } else { 2e10 };
            let alpha = 1.0 - (-sigma * delta).exp();
            let expected = alpha * t;
            assert!(
                (got[k] as f64 - expected).abs() < 1e-6,
                "sample {k}: {} vs {expected}",
                got[k]
            );
            t *= 1.0 - alpha + 1e-10;
        }
        assert!(got[..3].iter().all(|&v| v == 0.0) && got[3] > 0.35);
        assert!(got[s..].iter().all(|&v| v == 0.0));
        assert!(w
            .grid_weights(&pts, &zz[1..], &dirs, 2, s, None, &grid)
            .is_err());
    }
}
