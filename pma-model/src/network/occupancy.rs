//! The occupancy grid: for each joint, which cells of its bone-normalised frame x̄ (the
//! frame the spatial window w^p is computed in) have held density.
//!
//! **Domain and resolution.** Each joint has `resolution`³ cells over x̄ ∈ [−extent, extent]³.
//! The default, 32³ over [−2, 2]³, covers every point where the joint's window can be non-zero
//! in f32: w^p = exp(−α Σ x̄_k⁶) is exactly 0 once α Σ x̄_k⁶ ≥ 105 (α = 2), i.e. beyond
//! |x̄_k| = 52.5^(1/6) ≈ 1.94 on any axis, so the grid answers for every joint a sample can be
//! tested against, at any culling threshold. A cell is 1/8 of a box half-extent wide (the body
//! inside a box spans about [−1, 1], 16 cells): fine enough to leave out the empty corners
//! of a limb's box, small enough to keep (24·32³ f32 = 3 MiB in a checkpoint) and to refresh
//! in a fraction of a training step's time. Twice the resolution would cost 8× both.
//!
//! **A grid for a culling threshold.** With sample culling at threshold t, a joint's grid is
//! only asked where that joint's window is above t, which bounds every axis:
//! |x̄_k| < (ln(1/t)/α)^(1/β) ([`window_extent`]; 0.797 at t = 0.6). A grid meant for t
//! ([`OccupancyConfig::covering`]) spans only that cube, so the same cells are finer (at
//! t = 0.6, 2.5× per axis) and none is spent where the window has already culled the
//! sample. A point outside the span counts as occupied, so such a grid stays exact at a
//! lower threshold: it only leaves less out there. Training with culling and the grid
//! builds its grid for the run's threshold; `pma occupancy build --cull-samples T` and
//! `pma bench` do the same.
//!
//! **Update rule.** A cell keeps the largest density relu(σ) (no noise) seen in it, and
//! is occupied when that value is above min(`threshold`, mean of all cell values) —
//! Instant-NGP's rule: early in training, when the density is still small everywhere, the
//! cells with more than the average stay occupied instead of the whole grid emptying and
//! starving the body of gradients; occupancy is then dilated by `dilation` cells in every
//! direction, so that a surface that moves inside its bone frame with the pose (skin near a
//! joint, cloth) is not cut where the training poses did not put it. A grid that was never
//! refreshed counts every cell as occupied.
//!
//! In training the grid is built at the end of the warm-up (one random point per cell, for
//! a pose of the batch) and then kept by three things, none of which costs a network point
//! beyond the step's own but the last:
//! * every sample a step evaluates raises the cells it lies in (of each joint whose window
//!   is above the threshold there) to what the network found: `cell = max(cell, σ)`;
//! * a share `probe_share` of the samples the grid would leave out run anyway (probes), so
//!   a body that grows into empty cells is found by the rays that cross it;
//! * every `refresh_every` steps every cell decays by `decay` (Instant-NGP's all-cell
//!   decay: a cell no sample finds dense again empties), a share `refresh_share` of cells
//!   (half at random, half among the occupied ones) is evaluated afresh, and the occupancy
//!   is thresholded and dilated again.
//!
//! The grid only leaves work out ([`crate::render::cull`] asks it): a model renders the same
//! way without it, and its checkpoint tensors are a separate, optional group
//! ([`crate::network::checkpoint`]).

use pma_data::skeleton::N_JOINTS;
use serde::{Deserialize, Serialize};

use crate::error::{ModelError, Result};

/// Largest grid resolution accepted (per axis; 24·128³ cells are 200 MiB of f32).
pub const MAX_RESOLUTION: usize = 128;

/// How the grid is laid out and kept (the `[train.occupancy]` table of a run; saved with the
/// grid in the checkpoint).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OccupancyConfig {
    /// Cells per axis of each joint's grid.
    pub resolution: usize,
    /// The grid covers x̄ ∈ [−extent, extent]³ of each joint. A training run with sample
    /// culling narrows it to where its threshold lets the window through
    /// ([`OccupancyConfig::covering`]).
    pub extent: f64,
    /// Density relu(σ) above which a cell is occupied.
    pub threshold: f64,
    /// Factor every cell's value is multiplied by at each training refresh.
    pub decay: f64,
    /// Occupied cells mark their neighbours up to this many cells away occupied too.
    pub dilation: usize,
    /// Training: steps between refreshes.
    pub refresh_every: u64,
    /// Training: share of each joint's cells evaluated by a refresh (half at random, half
    /// among the occupied cells); the refresh that ends the warm-up evaluates every cell.
    pub refresh_share: f64,
    /// Training: share of the samples a step would leave out as empty that run anyway
    /// (probes), so that cells the body grows into are found by the rays that cross them.
    pub probe_share: f64,
    /// Training: steps that run without the grid while it is being built.
    pub warmup_steps: u64,
}

impl Default for OccupancyConfig {
    fn default() -> Self {
        Self {
            resolution: 32,
            extent: 2.0,
            threshold: 0.5,
            decay: 0.8,
            dilation: 1,
            refresh_every: 16,
            refresh_share: 1.0 / 256.0,
            probe_share: 0.05,
            warmup_steps: 200,
        }
    }
}

/// Half-width of the cube in x̄ outside which the window w^p = exp(−α Σ x̄_k^β) is at most
/// `threshold` on any axis: (ln(1/t)/α)^(1/β); the whole domain (2) for t ≤ 0 or t so small
/// that the cube reaches past it.
pub fn window_extent(threshold: f64, alpha: f64, beta: u32) -> f64 {
    const FULL: f64 = 2.0;
    if !(threshold > 0.0 && threshold < 1.0 && alpha > 0.0 && beta > 0) {
        return if threshold >= 1.0 { 0.0 } else { FULL };
    }
    ((1.0 / threshold).ln() / alpha)
        .powf(1.0 / beta as f64)
        .min(FULL)
}

impl OccupancyConfig {
    /// The same grid spanning only where a joint's window can exceed the culling `threshold`
    /// (`None`: no sample culling, the span is kept): extent = min(extent,
    /// [`window_extent`]). The resolution is kept, so the cells get finer.
    pub fn covering(mut self, threshold: Option<f64>, model: &crate::Config) -> Self {
        if let Some(t) = threshold {
            let e = window_extent(t, model.window_alpha, model.window_beta);
            if e > 0.0 {
                self.extent = self.extent.min(e);
            }
        }
        self
    }

    /// Refuse settings the grid cannot be built or used with; `what` names the source.
    pub fn validate(&self, what: &str) -> Result<()> {
        let bad = self.problems();
        match bad.is_empty() {
            true => Ok(()),
            false => Err(ModelError::Input(format!("{what}: {}", bad.join("; ")))),
        }
    }

    /// Every setting the grid cannot be built or used with, one line each.
    pub fn problems(&self) -> Vec<String> {
        let mut bad = Vec::new();
        if !(2..=MAX_RESOLUTION).contains(&self.resolution) {
            bad.push(format!(
                "resolution must be in 2..={MAX_RESOLUTION}, found {}",
                self.resolution
            ));
        }
        if !(self.extent.is_finite() && self.extent > 0.0 && self.extent <= 100.0) {
            bad.push(format!(
                "extent must be finite and in (0, 100], found {}",
                self.extent
            ));
        }
        if !(self.threshold.is_finite() && self.threshold >= 0.0) {
            bad.push(format!(
                "threshold must be finite and >= 0, found {}",
                self.threshold
            ));
        }
        if !(self.decay.is_finite() && self.decay > 0.0 && self.decay <= 1.0) {
            bad.push(format!("decay must be in (0, 1], found {}", self.decay));
        }
        if self.dilation > self.resolution.max(2) / 2 {
            bad.push(format!(
                "dilation must be at most half the resolution ({}), found {}",
                self.resolution / 2,
                self.dilation
            ));
        }
        if self.refresh_every == 0 {
            bad.push("refresh_every must be >= 1".to_string());
        }
        if !(self.refresh_share.is_finite()
            && self.refresh_share > 0.0
            && self.refresh_share <= 1.0)
        {
            bad.push(format!(
                "refresh_share must be in (0, 1], found {}",
                self.refresh_share
            ));
        }
        if !(self.probe_share.is_finite() && (0.0..=1.0).contains(&self.probe_share)) {
            bad.push(format!(
                "probe_share must be in [0, 1], found {}",
                self.probe_share
            ));
        }
        bad
    }

    /// Cells of one joint's grid.
    pub fn cells_per_joint(&self) -> usize {
        self.resolution.pow(3)
    }
}

/// The grid itself (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct OccupancyGrid {
    cfg: OccupancyConfig,
    /// Per joint and cell, the decayed largest density seen: [24,R,R,R] (z, y, x; x fastest).
    density: Vec<f32>,
    /// `density > threshold`, dilated, in the same layout.
    occupied: Vec<bool>,
    /// Refreshes applied so far (0: never built, every cell counts as occupied).
    refreshes: u64,
}

/// What a checkpoint's metadata says about its grid.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OccupancyMeta {
    pub config: OccupancyConfig,
    pub refreshes: u64,
}

impl OccupancyGrid {
    /// An empty grid that was never refreshed (every cell counts as occupied).
    pub fn new(cfg: OccupancyConfig) -> Result<Self> {
        cfg.validate("occupancy")?;
        let n = N_JOINTS * cfg.cells_per_joint();
        Ok(Self {
            density: vec![0.0; n],
            occupied: vec![true; n],
            refreshes: 0,
            cfg,
        })
    }

    /// A grid from saved values: `density` [24·R³] in the layout of [`Self::density`]; values
    /// must be finite and >= 0.
    pub fn from_parts(meta: OccupancyMeta, density: Vec<f32>) -> Result<Self> {
        let mut g = Self::new(meta.config)?;
        if density.len() != g.density.len() {
            return Err(ModelError::shape(
                "occupancy.density",
                g.shape(),
                format!("{} values", density.len()),
            ));
        }
        if let Some(i) = density.iter().position(|v| !(v.is_finite() && *v >= 0.0)) {
            return Err(ModelError::Input(format!(
                "occupancy.density: value {} at flat index {i} (must be finite and >= 0)",
                density[i]
            )));
        }
        g.density = density;
        g.refreshes = meta.refreshes;
        g.update_occupied();
        Ok(g)
    }

    pub fn config(&self) -> &OccupancyConfig {
        &self.cfg
    }

    /// [24, R, R, R].
    pub fn shape(&self) -> [usize; 4] {
        let r = self.cfg.resolution;
        [N_JOINTS, r, r, r]
    }

    pub fn meta(&self) -> OccupancyMeta {
        OccupancyMeta {
            config: self.cfg.clone(),
            refreshes: self.refreshes,
        }
    }

    /// Refreshes applied so far.
    pub fn refreshes(&self) -> u64 {
        self.refreshes
    }

    /// Whether the grid was ever refreshed (before, every cell counts as occupied).
    pub fn is_built(&self) -> bool {
        self.refreshes > 0
    }

    /// The cell values, [24·R³] (joint, z, y, x; x fastest).
    pub fn density(&self) -> &[f32] {
        &self.density
    }

    /// Width of a cell in x̄.
    pub fn cell_size(&self) -> f64 {
        2.0 * self.cfg.extent / self.cfg.resolution as f64
    }

    /// The cell of joint j's grid holding x̄ (flat index within the joint), or `None` outside
    /// the domain.
    pub fn cell_of(&self, x_bar: [f64; 3]) -> Option<usize> {
        let r = self.cfg.resolution;
        let (e, w) = (self.cfg.extent, self.cell_size());
        let mut idx = [0usize; 3];
        for k in 0..3 {
            let u = (x_bar[k] + e) / w;
            // NaN fails both tests and stays outside.
            if !(u >= 0.0 && u < r as f64) {
                return None;
            }
            idx[k] = u as usize;
        }
        Some((idx[2] * r + idx[1]) * r + idx[0])
    }

    /// The lower corner of cell `c` of a joint's grid, in x̄.
    pub fn cell_corner(&self, c: usize) -> [f64; 3] {
        let r = self.cfg.resolution;
        let (e, w) = (self.cfg.extent, self.cell_size());
        [
            (c % r) as f64 * w - e,
            ((c / r) % r) as f64 * w - e,
            (c / (r * r)) as f64 * w - e,
        ]
    }

    /// Whether joint j's grid marks the cell of x̄ occupied. Outside the domain, and before
    /// the first refresh, every point counts as occupied.
    pub fn occupied(&self, j: usize, x_bar: [f64; 3]) -> bool {
        match self.cell_of(x_bar) {
            Some(c) => self.occupied[j * self.cfg.cells_per_joint() + c],
            None => true,
        }
    }

    /// The value joint j's grid keeps for the cell of x̄ (the decayed largest density seen
    /// there); 0 outside the domain, where the joint's window is 0.
    pub fn density_at(&self, j: usize, x_bar: [f64; 3]) -> f32 {
        match self.cell_of(x_bar) {
            Some(c) => self.density[j * self.cfg.cells_per_joint() + c],
            None => 0.0,
        }
    }

    /// Joint j's cells, occupied or not (flat cell index as in [`Self::cell_of`]).
    pub fn joint_occupied(&self, j: usize) -> &[bool] {
        let n = self.cfg.cells_per_joint();
        &self.occupied[j * n..(j + 1) * n]
    }

    /// Every cell's occupancy, [24·R³] in the layout of [`Self::density`]. It follows the
    /// values at each refresh only, so between refreshes it is not what the values give:
    /// a resumed training run restores it ([`Self::set_occupied`]) to continue exactly.
    pub fn occupied_cells(&self) -> &[bool] {
        &self.occupied
    }

    /// Replace every cell's occupancy (as [`Self::occupied_cells`] gives it).
    pub fn set_occupied(&mut self, occupied: Vec<bool>) -> Result<()> {
        if occupied.len() != self.occupied.len() {
            return Err(ModelError::shape(
                "occupancy.occupied",
                self.shape(),
                format!("{} values", occupied.len()),
            ));
        }
        self.occupied = occupied;
        Ok(())
    }

    /// Whether cell c of joint j is occupied.
    pub fn cell_occupied(&self, j: usize, c: usize) -> bool {
        self.occupied[j * self.cfg.cells_per_joint() + c]
    }

    /// One fresh density sample σ for cell c of joint j: `cell = max(cell, σ)` (the decay is
    /// [`Self::decay_all`]'s). The occupancy follows at [`Self::finish_refresh`]. Non-finite
    /// or negative σ is refused (callers pass relu(σ) of the network, without noise).
    pub fn update_max(&mut self, j: usize, c: usize, sigma: f32) -> Result<()> {
        if !(sigma.is_finite() && sigma >= 0.0) {
            return Err(ModelError::Input(format!(
                "occupancy: density {sigma} for joint {j} cell {c} (must be finite and >= 0)"
            )));
        }
        let i = j * self.cfg.cells_per_joint() + c;
        self.density[i] = self.density[i].max(sigma);
        Ok(())
    }

    /// Multiply every cell's value by the decay (a training refresh, before its updates):
    /// a cell that no sample finds dense again empties.
    pub fn decay_all(&mut self) {
        let d = self.cfg.decay as f32;
        for v in &mut self.density {
            *v *= d;
        }
    }

    /// After a refresh's updates: threshold and dilate again, count the refresh.
    pub fn finish_refresh(&mut self) {
        self.refreshes += 1;
        self.update_occupied();
    }

    /// Share of all cells marked occupied.
    pub fn occupied_fraction(&self) -> f64 {
        self.occupied.iter().filter(|o| **o).count() as f64 / self.occupied.len().max(1) as f64
    }

    /// The threshold cells are compared with: min(`threshold`, mean cell value).
    pub fn effective_threshold(&self) -> f64 {
        let mean =
            self.density.iter().map(|&v| v as f64).sum::<f64>() / self.density.len().max(1) as f64;
        self.cfg.threshold.min(mean)
    }

    fn update_occupied(&mut self) {
        if self.refreshes == 0 {
            self.occupied.fill(true);
            return;
        }
        let t = self.effective_threshold() as f32;
        let n = self.cfg.cells_per_joint();
        for (occ, dens) in self.occupied.chunks_mut(n).zip(self.density.chunks(n)) {
            for (o, d) in occ.iter_mut().zip(dens) {
                *o = *d > t;
            }
            dilate(occ, self.cfg.resolution, self.cfg.dilation);
        }
    }
}

/// Box dilation of one joint's cells (x fastest) by `d` cells: a maximum over ±d along each
/// axis in turn, which is the cube of side 2d + 1. Each row of x is one bit mask (the
/// resolution is at most 128), so the x pass is shifts and the y and z passes OR whole rows:
/// a refresh dilates every joint's grid (24·32³ cells at the default resolution) on the
/// training step's serial path.
fn dilate(occ: &mut [bool], r: usize, d: usize) {
    if d == 0 || r == 0 {
        return;
    }
    debug_assert!(r <= 128 && occ.len() == r * r * r);
    let full = if r >= 128 {
        u128::MAX
    } else {
        (1u128 << r) - 1
    };
    let reach = d.min(r - 1);
    let rows: Vec<u128> = occ
        .chunks_exact(r)
        .map(|row| {
            let m = row
                .iter()
                .enumerate()
                .fold(0u128, |m, (x, &o)| m | (u128::from(o) << x));
            (1..=reach).fold(m, |acc, k| acc | (m << k) | (m >> k)) & full
        })
        .collect();
    // Rows (z, y) at index z·r + y: the y pass ORs rows of one plane, the z pass rows of
    // the same y in neighbouring planes.
    let spread = |src: &[u128], stride: usize, block: usize| -> Vec<u128> {
        let mut out = vec![0u128; src.len()];
        for base in (0..src.len()).step_by(block) {
            let line = block / stride;
            for i in 0..line {
                let (lo, hi) = (i.saturating_sub(reach), (i + reach).min(line - 1));
                for off in 0..stride {
                    out[base + i * stride + off] =
                        (lo..=hi).fold(0, |acc, k| acc | src[base + k * stride + off]);
                }
            }
        }
        out
    };
    let rows = spread(&rows, 1, r);
    let rows = spread(&rows, r, r * r);
    for (row, m) in occ.chunks_exact_mut(r).zip(rows) {
        for (x, o) in row.iter_mut().enumerate() {
            *o = (m >> x) & 1 == 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cfg(resolution: usize, dilation: usize) -> OccupancyConfig {
        OccupancyConfig {
            resolution,
            dilation,
            ..Default::default()
        }
    }

    #[test]
    fn cells_cover_the_domain_and_outside_counts_as_occupied() {
        let mut g = OccupancyGrid::new(cfg(4, 0)).unwrap();
        assert!(g.occupied(0, [0.1, 0.1, 0.1]), "never built: occupied");
        g.finish_refresh();
        // extent 2, 4 cells: [-2,-1), [-1,0), [0,1), [1,2).
        assert_eq!(g.cell_of([-2.0, -2.0, -2.0]), Some(0));
        assert_eq!(g.cell_of([1.99, -2.0, -2.0]), Some(3));
        assert_eq!(g.cell_of([0.5, 0.5, 0.5]), Some((2 * 4 + 2) * 4 + 2));
        assert_eq!(g.cell_of([2.0, 0.0, 0.0]), None);
        assert_eq!(g.cell_of([f64::NAN, 0.0, 0.0]), None);
        assert!(!g.occupied(3, [0.5, 0.5, 0.5]));
        assert!(g.occupied(3, [2.5, 0.0, 0.0]), "outside the domain");
        for c in 0..64 {
            assert_eq!(g.cell_of(g.cell_corner(c).map(|v| v + 1e-9)), Some(c));
        }
    }

    /// The row-and-plane dilation is the cube of side 2d + 1 around every occupied cell,
    /// checked against the definition on sparse random grids, edges and corners included.
    #[test]
    fn dilation_is_the_cube_around_every_occupied_cell() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        for (r, d) in [
            (2, 1),
            (5, 1),
            (8, 2),
            (9, 3),
            (16, 1),
            (7, 0),
            (3, 5),
            (1, 1),
        ] {
            let cells: Vec<bool> = (0..r * r * r).map(|_| rng.gen_bool(0.03)).collect();
            let mut fast = cells.clone();
            dilate(&mut fast, r, d);
            let xyz = |c: usize| [c % r, (c / r) % r, c / (r * r)];
            for (c, &got) in fast.iter().enumerate() {
                let p = xyz(c);
                let want = (0..r * r * r).any(|o| {
                    let q = xyz(o);
                    cells[o] && (0..3).all(|k| p[k].abs_diff(q[k]) <= d)
                });
                assert_eq!(got, want, "r {r} d {d} cell {p:?}");
            }
        }
    }

    /// Up to the largest resolution (a row is then a full 128-bit mask, and 127 leaves its
    /// top bit): every cell is checked against the occupied cells of its own cube.
    #[test]
    fn dilation_holds_up_to_the_largest_resolution() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(12);
        for (r, d) in [(127, 1), (MAX_RESOLUTION, 2), (64, 3)] {
            let mut cells: Vec<bool> = (0..r * r * r).map(|_| rng.gen_bool(0.002)).collect();
            // The corners and the faces' rows, where shifts fall off the mask.
            for c in [0, r - 1, r * r - 1, r * r * r - 1, r * r * (r - 1)] {
                cells[c] = true;
            }
            let mut fast = cells.clone();
            dilate(&mut fast, r, d);
            let at = |x: usize, y: usize, z: usize| (z * r + y) * r + x;
            let span = |i: usize| i.saturating_sub(d)..=(i + d).min(r - 1);
            for z in 0..r {
                for y in 0..r {
                    for x in 0..r {
                        let want = span(z)
                            .any(|zz| span(y).any(|yy| span(x).any(|xx| cells[at(xx, yy, zz)])));
                        assert_eq!(fast[at(x, y, z)], want, "r {r} d {d} cell {x},{y},{z}");
                    }
                }
            }
        }
    }

    #[test]
    fn decay_max_threshold_and_dilation() {
        let mut g = OccupancyGrid::new(cfg(8, 1)).unwrap();
        let c = g.cell_of([0.1, 0.1, 0.1]).unwrap();
        g.update_max(5, c, 2.0).unwrap();
        g.finish_refresh();
        assert!(g.cell_occupied(5, c));
        assert!(!g.cell_occupied(4, c), "other joints untouched");
        // The 3×3×3 block around c is occupied, nothing further.
        let r = 8;
        let (x, y, z) = (c % r, (c / r) % r, c / (r * r));
        for cz in 0..r {
            for cy in 0..r {
                for cx in 0..r {
                    let near = cx.abs_diff(x) <= 1 && cy.abs_diff(y) <= 1 && cz.abs_diff(z) <= 1;
                    assert_eq!(g.cell_occupied(5, (cz * r + cy) * r + cx), near);
                }
            }
        }
        assert_eq!(g.occupied_fraction(), 27.0 / (24.0 * 512.0));
        // Alone, the cell is above the mean however far it decays: it stays occupied.
        for _ in 0..100 {
            g.decay_all();
            g.update_max(5, c, 0.0).unwrap();
            g.finish_refresh();
        }
        assert!(g.cell_occupied(5, c) && g.effective_threshold() < 1e-5);
        // With density 1 in every cell of the other joints the threshold is 0.5 again; a cell
        // with a smaller sample decays, stays above 0.5 for a while, then empties.
        let others = |g: &mut OccupancyGrid| {
            for j in (0..24).filter(|&j| j != 5) {
                for cell in 0..512 {
                    g.update_max(j, cell, 1.0).unwrap();
                }
            }
        };
        others(&mut g);
        g.update_max(5, c, 2.0).unwrap();
        g.finish_refresh();
        let mut n = 0;
        while g.cell_occupied(5, c) {
            g.decay_all();
            g.update_max(5, c, 0.1).unwrap();
            others(&mut g);
            g.finish_refresh();
            n += 1;
        }
        // 2·0.8^n <= 0.5 first at n = 7 (the default decay).
        assert_eq!(n, 7);
        assert_eq!(g.effective_threshold(), 0.5);
        assert!(g.update_max(0, 0, f32::NAN).is_err());
        assert!(g.update_max(0, 0, -1.0).is_err());
    }

    /// The window w^p = exp(−α Σ x̄_k^β) of `x`, in f64.
    fn window(x: [f64; 3], alpha: f64, beta: u32) -> f64 {
        (-alpha * x.iter().map(|v| v.powi(beta as i32)).sum::<f64>()).exp()
    }

    #[test]
    fn the_window_extent_bounds_every_point_above_the_threshold_and_is_tight() {
        let (alpha, beta) = (2.0, 6);
        let mut seed = 0x2545_f491_4f6c_dd1d_u64;
        let mut uniform = || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        for t in [1e-6, 0.05, 0.3, 0.6, 0.9] {
            let e = window_extent(t, alpha, beta);
            assert!(e > 0.0 && e <= 2.0, "t {t}: {e}");
            // On an axis the window crosses t at the extent.
            assert!(window([e * (1.0 - 1e-9), 0.0, 0.0], alpha, beta) > t);
            assert!(window([0.0, -e * (1.0 + 1e-9), 0.0], alpha, beta) < t);
            let mut inside = 0;
            for _ in 0..20_000 {
                let x = [(); 3].map(|_| 4.0 * uniform() - 2.0);
                if window(x, alpha, beta) > t {
                    inside += 1;
                    assert!(x.iter().all(|v| v.abs() < e), "t {t}: {x:?} past {e}");
                }
            }
            assert!(inside > 0, "t {t}: no point above the threshold drawn");
        }
        assert_eq!(window_extent(0.0, alpha, beta), 2.0);
        assert!((window_extent(0.6, alpha, beta) - 0.79654).abs() < 1e-5);
    }

    #[test]
    fn a_grid_for_a_threshold_narrows_its_span_and_keeps_its_cells() {
        let model = crate::Config::tiny();
        let base = cfg(16, 1);
        assert_eq!(base.clone().covering(None, &model), base);
        assert_eq!(base.clone().covering(Some(0.0), &model).extent, 2.0);
        let narrow = base.clone().covering(Some(0.6), &model);
        let e = window_extent(0.6, model.window_alpha, model.window_beta);
        assert_eq!(narrow.extent, e);
        assert_eq!((narrow.resolution, narrow.dilation), (16, 1));
        // Never wider than asked.
        let small = OccupancyConfig {
            extent: 0.5,
            ..base.clone()
        };
        assert_eq!(small.clone().covering(Some(0.6), &model).extent, 0.5);
        // Outside its span a narrowed grid counts every point occupied.
        let mut g = OccupancyGrid::new(narrow).unwrap();
        g.finish_refresh();
        assert!(!g.occupied(0, [0.0, 0.0, 0.0]));
        assert!(g.occupied(0, [e * 1.001, 0.0, 0.0]));
    }

    #[test]
    fn saved_values_are_checked() {
        let g = OccupancyGrid::new(cfg(4, 0)).unwrap();
        let meta = OccupancyMeta {
            config: cfg(4, 0),
            refreshes: 3,
        };
        let ok = OccupancyGrid::from_parts(meta.clone(), vec![1.0; 24 * 64]).unwrap();
        assert_eq!(ok.refreshes(), 3);
        assert_eq!(ok.occupied_fraction(), 1.0);
        assert!(OccupancyGrid::from_parts(meta.clone(), vec![1.0; 24 * 63]).is_err());
        let mut nan = vec![0.0; 24 * 64];
        nan[17] = f32::NAN;
        let err = OccupancyGrid::from_parts(meta.clone(), nan).unwrap_err();
        assert!(err.to_string().contains("flat index 17"), "{err}");
        let bad = OccupancyMeta {
            config: cfg(1, 0),
            refreshes: 0,
        };
        assert!(OccupancyGrid::from_parts(bad, vec![0.0; 24]).is_err());
        assert_eq!(g.shape(), [24, 4, 4, 4]);
    }
}
