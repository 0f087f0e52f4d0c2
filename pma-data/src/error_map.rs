//! A running map of the training error over the training images, to draw a step's rays where
//! the model is still wrong: the error-map sampling of Instant-NGP (Müller, Evans, Schied,
//! Keller, "Instant Neural Graphics Primitives with a Multiresolution Hash Encoding",
//! SIGGRAPH 2022, section on the accelerated NeRF training).
//!
//! Each image is cut into square cells of `cell` pixels. A cell keeps a running mean of the
//! per-ray error (mean |render − target| over the channels) of the rays drawn in it, updated
//! from each training step's own losses, so the map costs no network work. A cell no ray has
//! visited yet counts at the mean of the visited cells. A step draws `uniform_share` of an
//! image's rays uniformly over its sampling mask, as the sampler always does, and the rest
//! cell by cell with probability proportional to the cell's error times its mask pixels,
//! then uniformly inside the cell.
//!
//! Drawing where the error is biases the mean loss towards those pixels. With `unbiased`
//! every ray carries the weight p_uniform / p_drawn (at most 1 / `uniform_share`), and the
//! weighted mean loss is an unbiased estimate of the uniform one; without it the loss is the
//! plain mean over the drawn rays and favours the pixels the map points at, as Instant-NGP's
//! does.

use serde::{Deserialize, Serialize};

use crate::error::{DataError, Result};

/// How the map is kept and drawn from (`[train.error_map]` of a run).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ErrorMapConfig {
    /// Side of a cell in pixels.
    pub cell: usize,
    /// Share of each image's rays drawn uniformly over its sampling mask; the rest follow
    /// the map.
    pub uniform_share: f64,
    /// Weight of a new error in its cell's running mean.
    pub rate: f64,
    /// Weight every ray by p_uniform / p_drawn so that the loss stays an unbiased estimate of
    /// the uniform one.
    pub unbiased: bool,
}

impl Default for ErrorMapConfig {
    fn default() -> Self {
        Self {
            cell: 8,
            uniform_share: 0.5,
            rate: 0.5,
            unbiased: false,
        }
    }
}

impl ErrorMapConfig {
    /// Every setting the map cannot be kept with, one line each.
    pub fn problems(&self) -> Vec<String> {
        let mut bad = Vec::new();
        if !(1..=4096).contains(&self.cell) {
            bad.push(format!(
                "cell must be in 1..=4096 pixels, found {}",
                self.cell
            ));
        }
        if !(self.uniform_share.is_finite()
            && self.uniform_share > 0.0
            && self.uniform_share <= 1.0)
        {
            bad.push(format!(
                "uniform_share must be in (0, 1], found {}",
                self.uniform_share
            ));
        }
        if !(self.rate.is_finite() && self.rate > 0.0 && self.rate <= 1.0) {
            bad.push(format!("rate must be in (0, 1], found {}", self.rate));
        }
        bad
    }
}

/// Value of a cell no ray has visited yet.
const UNSEEN: f32 = -1.0;

/// The map itself (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct ErrorMap {
    cfg: ErrorMapConfig,
    width: usize,
    height: usize,
    cells_x: usize,
    cells_y: usize,
    /// Per image and cell (row-major), the running mean error; [`UNSEEN`] before a visit.
    values: Vec<f32>,
}

/// The pixels a map drew for one image and the loss weight of each (1 unless unbiased).
#[derive(Debug, Clone, PartialEq)]
pub struct Draw {
    pub pixels: Vec<usize>,
    pub weights: Vec<f32>,
}

impl ErrorMap {
    /// An unvisited map over `n_images` images of `width`×`height` pixels.
    pub fn new(cfg: ErrorMapConfig, n_images: usize, width: usize, height: usize) -> Result<Self> {
        if let Some(p) = cfg.problems().first() {
            return Err(DataError::arg("error map", "valid settings", p));
        }
        if n_images == 0 || width == 0 || height == 0 {
            return Err(DataError::arg(
                "error map",
                "at least one image of at least one pixel",
                format!("{n_images} images of {width}x{height}"),
            ));
        }
        let (cells_x, cells_y) = (width.div_ceil(cfg.cell), height.div_ceil(cfg.cell));
        Ok(Self {
            values: vec![UNSEEN; n_images * cells_x * cells_y],
            cfg,
            width,
            height,
            cells_x,
            cells_y,
        })
    }

    pub fn config(&self) -> &ErrorMapConfig {
        &self.cfg
    }

    /// [images, cells_y, cells_x].
    pub fn shape(&self) -> [usize; 3] {
        [
            self.values.len() / (self.cells_x * self.cells_y),
            self.cells_y,
            self.cells_x,
        ]
    }

    /// The cell values in the layout of [`Self::shape`] (−1: not visited yet).
    pub fn values(&self) -> &[f32] {
        &self.values
    }

    /// Replace the values (a saved map): the same count, each finite and ≥ 0 or −1.
    pub fn set_values(&mut self, values: Vec<f32>) -> Result<()> {
        if values.len() != self.values.len() {
            return Err(DataError::arg(
                "error map values",
                format!("{} cells", self.values.len()),
                values.len(),
            ));
        }
        if let Some(i) = values
            .iter()
            .position(|&v| !(v == UNSEEN || (v.is_finite() && v >= 0.0)))
        {
            return Err(DataError::arg(
                "error map values",
                "finite values >= 0 (or -1 for a cell not visited)",
                format!("{} at cell {i}", values[i]),
            ));
        }
        self.values = values;
        Ok(())
    }

    fn cell_of(&self, pixel: usize) -> usize {
        let (x, y) = (pixel % self.width, pixel / self.width);
        (y / self.cfg.cell) * self.cells_x + x / self.cfg.cell
    }

    fn cells_per_image(&self) -> usize {
        self.cells_x * self.cells_y
    }

    /// Take a step's per-ray errors in: ray i was drawn at `pixels[i]` of image
    /// `images[i]` and rendered with mean absolute error `errors[i]`. Non-finite errors (a
    /// step the optimizer skips) are left out.
    pub fn observe(&mut self, images: &[usize], pixels: &[usize], errors: &[f32]) -> Result<()> {
        if images.len() != errors.len() || pixels.len() != errors.len() {
            return Err(DataError::arg(
                "error map observation",
                "an image and a pixel per error",
                format!(
                    "{} images, {} pixels, {} errors",
                    images.len(),
                    pixels.len(),
                    errors.len()
                ),
            ));
        }
        let n_images = self.shape()[0];
        let rate = self.cfg.rate as f32;
        for ((&img, &px), &e) in images.iter().zip(pixels).zip(errors) {
            if img >= n_images || px >= self.width * self.height {
                return Err(DataError::arg(
                    "error map observation",
                    format!("images < {n_images}, pixels < {}", self.width * self.height),
                    format!("image {img}, pixel {px}"),
                ));
            }
            if !e.is_finite() {
                continue;
            }
            let i = img * self.cells_per_image() + self.cell_of(px);
            let v = &mut self.values[i];
            *v = match *v == UNSEEN {
                true => e.max(0.0),
                false => *v + rate * (e.max(0.0) - *v),
            };
        }
        Ok(())
    }

    /// The mean over the visited cells (1 when none is).
    fn seen_mean(&self) -> f32 {
        let (sum, n) = self
            .values
            .iter()
            .filter(|&&v| v != UNSEEN)
            .fold((0f64, 0usize), |(s, n), &v| (s + v as f64, n + 1));
        match n {
            0 => 1.0,
            n => (sum / n as f64) as f32,
        }
    }

    /// `k` pixels of `image` among `valid` (its sampling-mask pixels, ascending, at least
    /// `k` of them): `uniform_share` of them distinct and uniform, the rest drawn from the
    /// map (with replacement); ascending, each with its loss weight.
    pub fn draw<R: rand::Rng>(&self, rng: &mut R, image: usize, valid: &[usize], k: usize) -> Draw {
        let n = valid.len();
        let n_uniform = ((k as f64 * self.cfg.uniform_share).round() as usize).clamp(0, k);
        let mut drawn: Vec<usize> = rand::seq::index::sample(rng, n, n_uniform)
            .into_iter()
            .map(|i| valid[i])
            .collect();
        // Per cell: its error and its mask pixels (`valid` grouped by cell).
        let cells = self.cells_per_image();
        let base = image * cells;
        let unseen = self.seen_mean();
        let value = |c: usize| match self.values[base + c] {
            UNSEEN => unseen,
            v => v,
        };
        let mut start = vec![0usize; cells + 1];
        for &p in valid {
            start[self.cell_of(p) + 1] += 1;
        }
        for c in 0..cells {
            start[c + 1] += start[c];
        }
        let mut by_cell = vec![0usize; n];
        let mut fill = start.clone();
        for &p in valid {
            let c = self.cell_of(p);
            by_cell[fill[c]] = p;
            fill[c] += 1;
        }
        let mut cdf = Vec::with_capacity(cells);
        let mut total = 0f64;
        for c in 0..cells {
            total += value(c) as f64 * (start[c + 1] - start[c]) as f64;
            cdf.push(total);
        }
        let guided = total > 0.0 && total.is_finite();
        for _ in n_uniform..k {
            let i = match guided {
                true => {
                    let u = rng.gen::<f64>() * total;
                    let c = cdf.partition_point(|&x| x <= u).min(cells - 1);
                    // A cell with mass has pixels; `u` below its upper bound lands in one.
                    let (lo, hi) = (start[c], start[c + 1]);
                    by_cell[rng.gen_range(lo..hi.max(lo + 1)).min(n - 1)]
                }
                false => valid[rng.gen_range(0..n)],
            };
            drawn.push(i);
        }
        drawn.sort_unstable();
        let weights = match self.cfg.unbiased {
            false => vec![1.0; k],
            true => {
                let share = n_uniform as f64 / k.max(1) as f64;
                let p_uniform = 1.0 / n as f64;
                drawn
                    .iter()
                    .map(|&p| {
                        let p_map = match guided {
                            true => value(self.cell_of(p)) as f64 / total,
                            false => p_uniform,
                        };
                        (p_uniform / (share * p_uniform + (1.0 - share) * p_map)) as f32
                    })
                    .collect()
            }
        };
        Draw {
            pixels: drawn,
            weights,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn map(cfg: ErrorMapConfig) -> ErrorMap {
        ErrorMap::new(cfg, 2, 16, 16).unwrap()
    }

    /// Rays follow the error: a cell with all the error gets the guided draws, the uniform
    /// share stays spread, and without any error seen the draw is uniform.
    #[test]
    fn draws_follow_the_error_and_keep_their_uniform_share() {
        let cfg = ErrorMapConfig {
            cell: 4,
            uniform_share: 0.25,
            ..Default::default()
        };
        let mut m = map(cfg);
        let valid: Vec<usize> = (0..256).collect();
        // Every cell of image 1 seen with error 0 but the cell holding pixel (9, 5).
        let pixels: Vec<usize> = (0..256).collect();
        let mut errors = vec![0f32; 256];
        errors[5 * 16 + 9] = 0.8;
        m.observe(&[1; 256], &pixels, &errors).unwrap();
        let hot = m.cell_of(5 * 16 + 9);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let (mut in_hot, mut total) = (0, 0);
        for _ in 0..200 {
            let d = m.draw(&mut rng, 1, &valid, 64);
            assert_eq!(d.pixels.len(), 64);
            assert!(d.pixels.windows(2).all(|w| w[0] <= w[1]));
            assert!(d.weights.iter().all(|&w| w == 1.0));
            in_hot += d.pixels.iter().filter(|&&p| m.cell_of(p) == hot).count();
            total += 64;
        }
        // 75 % guided into the hot cell plus its 1/16 of the uniform quarter.
        let share = in_hot as f64 / total as f64;
        assert!((share - (0.75 + 0.25 / 16.0)).abs() < 0.02, "{share}");
        // Image 0 was never seen: every cell counts at the seen mean, a uniform draw.
        let mut per_cell = vec![0usize; 16];
        for _ in 0..400 {
            for p in m.draw(&mut rng, 0, &valid, 64).pixels {
                per_cell[m.cell_of(p)] += 1;
            }
        }
        let expect = 400.0 * 64.0 / 16.0;
        assert!(
            per_cell
                .iter()
                .all(|&c| (c as f64 - expect).abs() < 0.1 * expect),
            "{per_cell:?}"
        );
    }

    /// With `unbiased` the weighted mean of a per-pixel quantity over many draws matches
    /// its uniform mean, and the weights stay under 1 / uniform_share.
    #[test]
    fn unbiased_weights_recover_the_uniform_mean() {
        let cfg = ErrorMapConfig {
            cell: 4,
            uniform_share: 0.5,
            unbiased: true,
            ..Default::default()
        };
        let mut m = map(cfg);
        let valid: Vec<usize> = (0..256).filter(|p| p % 3 != 0).collect();
        let pixels: Vec<usize> = (0..256).collect();
        let errors: Vec<f32> = (0..256).map(|p| ((p / 16) as f32 / 15.0).powi(2)).collect();
        m.observe(&[0; 256], &pixels, &errors).unwrap();
        let f = |p: usize| (p % 16) as f64 + 3.0 * (p / 16) as f64;
        let uniform = valid.iter().map(|&p| f(p)).sum::<f64>() / valid.len() as f64;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let (mut weighted, mut plain, mut n) = (0f64, 0f64, 0usize);
        for _ in 0..4000 {
            let d = m.draw(&mut rng, 0, &valid, 32);
            for (&p, &w) in d.pixels.iter().zip(&d.weights) {
                assert!(w > 0.0 && w <= 2.0 + 1e-6, "{w}");
                weighted += w as f64 * f(p);
                plain += f(p);
                n += 1;
            }
        }
        let (weighted, plain) = (weighted / n as f64, plain / n as f64);
        assert!(
            (weighted - uniform).abs() < 0.01 * uniform,
            "{weighted} vs {uniform}"
        );
        assert!(
            plain > uniform * 1.1,
            "the draws favour the bottom rows: {plain} vs {uniform}"
        );
    }

    #[test]
    fn observations_and_saved_values_are_checked() {
        let mut m = map(ErrorMapConfig::default());
        assert_eq!(m.shape(), [2, 2, 2]);
        m.observe(&[1], &[17], &[0.5]).unwrap();
        m.observe(&[1], &[17], &[f32::NAN]).unwrap();
        m.observe(&[1], &[18], &[0.1]).unwrap();
        // Rate 0.5: 0.5, then halfway to 0.1.
        assert!((m.values()[4] - 0.3).abs() < 1e-6, "{:?}", m.values());
        assert!(m.observe(&[2], &[0], &[0.1]).is_err());
        assert!(m.observe(&[0], &[256], &[0.1]).is_err());
        assert!(m.observe(&[0, 0], &[0], &[0.1]).is_err());
        let v = m.values().to_vec();
        let mut back = map(ErrorMapConfig::default());
        back.set_values(v).unwrap();
        assert_eq!(back, m);
        assert!(back.set_values(vec![0.0; 7]).is_err());
        assert!(back.set_values(vec![-0.5; 8]).is_err());
        assert!(ErrorMap::new(
            ErrorMapConfig {
                uniform_share: 0.0,
                ..Default::default()
            },
            1,
            4,
            4
        )
        .is_err());
    }
}
