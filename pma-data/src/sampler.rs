//! The training ray sampler (docs/conventions.md, "Ray sampler"), as plain host
//! data; the model crate turns a [`SampledBatch`] into tensors.
//!
//! 1. images: the next `images_per_step` indices of a random permutation of
//!    all images (a fresh permutation when it runs out, so a batch across the
//!    boundary may repeat an image), sorted ascending;
//! 2. pixels: `rays_per_step / images_per_step` distinct pixels per image,
//!    uniform over the image's sampling mask (all H·W pixels if the mask has
//!    fewer), sorted ascending;
//! 3. rays: the image's camera, unit directions;
//! 4. colours: `target = rgb·fg + (1−fg)·bg` with `bg = (1−fg)·u`,
//!    `u ~ U[0,1)³` per ray (`perturb_bg`; black otherwise), so background
//!    pixels get a fresh random colour every time;
//! 5. rays are image-major and contiguous (rays `k·i … k·i+k−1` belong to the
//!    i-th image): the pose network strides the batch by `k`.
//!
//! Every draw comes from one ChaCha8 stream, in a fixed order (permutation,
//! then per image its pixels followed by its per-ray noise), so a seed fixes
//! the whole sequence and (rng, permutation, cursor) is a complete resume
//! state.
//!
//! With an [`ErrorMap`] ([`Sampler::next_batch_with`]) step 2 draws part of an
//! image's pixels where the map says the error is (with replacement) and gives
//! each ray a loss weight; the map is then part of the resume state.

use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::dataset::Dataset;
use crate::error::{DataError, Result};
use crate::error_map::ErrorMap;

/// The sampler's ChaCha8 stream of a run seed, distinct from the streams a
/// trainer uses for initialisation and noise.
pub const SAMPLER_STREAM: u64 = 0x7361_6d70;

/// One step's rays, image-major.
#[derive(Debug, Clone, PartialEq)]
pub struct SampledBatch {
    /// Image indices, ascending (repeats possible across a permutation boundary).
    pub images: Vec<usize>,
    /// Pose row of each image.
    pub pose_rows: Vec<usize>,
    /// Flattened pixel index `y·W + x` per ray, ascending within an image.
    pub pixels: Vec<usize>,
    /// `[R·3]` world ray origins.
    pub origins: Vec<f32>,
    /// `[R·3]` unit world ray directions.
    pub dirs: Vec<f32>,
    /// `[R·3]` background colour the prediction is composited over.
    pub bgs: Vec<f32>,
    /// `[R·3]` target colour in [0,1].
    pub targets: Vec<f32>,
    /// Frame-code index per ray: the image index.
    pub framecodes: Vec<i64>,
    /// `[R]` loss weight per ray when an error map drew the pixels with its unbiased
    /// weights (`None`: every ray weighs 1).
    pub weights: Option<Vec<f32>>,
}

impl SampledBatch {
    /// Rays in the batch.
    pub fn len(&self) -> usize {
        self.framecodes.len()
    }
    pub fn is_empty(&self) -> bool {
        self.framecodes.is_empty()
    }
}

/// Seeded sampler over the images of one dataset.
#[derive(Debug, Clone)]
pub struct Sampler {
    n_images: usize,
    pixels_per_image: usize,
    rays_per_image: usize,
    images_per_step: usize,
    perturb_bg: bool,
    rng: ChaCha8Rng,
    perm: Vec<usize>,
    cursor: usize,
}

impl Sampler {
    /// A sampler over `n_images` images of `pixels_per_image` pixels,
    /// drawing from stream [`SAMPLER_STREAM`] of `seed`.
    pub fn new(
        n_images: usize,
        pixels_per_image: usize,
        rays_per_step: usize,
        images_per_step: usize,
        perturb_bg: bool,
        seed: u64,
    ) -> Result<Self> {
        if images_per_step == 0 || rays_per_step % images_per_step != 0 {
            return Err(DataError::arg(
                "rays_per_step / images_per_step",
                "a whole number of rays per image",
                format!("{rays_per_step} rays over {images_per_step} images"),
            ));
        }
        if n_images == 0 {
            return Err(DataError::arg("n_images", "at least 1 image", 0));
        }
        let rays_per_image = rays_per_step / images_per_step;
        if rays_per_image > pixels_per_image {
            return Err(DataError::arg(
                "rays per image",
                format!("at most the {pixels_per_image} pixels of an image"),
                rays_per_image,
            ));
        }
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        rng.set_stream(SAMPLER_STREAM);
        Ok(Sampler {
            n_images,
            pixels_per_image,
            rays_per_image,
            images_per_step,
            perturb_bg,
            rng,
            perm: Vec::new(),
            cursor: 0,
        })
    }

    /// A sampler for the images of `ds` (its image count and size).
    pub fn for_dataset(
        ds: &Dataset,
        rays_per_step: usize,
        images_per_step: usize,
        perturb_bg: bool,
        seed: u64,
    ) -> Result<Self> {
        Self::new(
            ds.n_images(),
            ds.height() * ds.width(),
            rays_per_step,
            images_per_step,
            perturb_bg,
            seed,
        )
    }

    pub fn rays_per_image(&self) -> usize {
        self.rays_per_image
    }

    pub fn images_per_step(&self) -> usize {
        self.images_per_step
    }

    /// The generator, for saving its position.
    pub fn rng(&self) -> &ChaCha8Rng {
        &self.rng
    }

    /// The current permutation (empty before the first draw).
    pub fn permutation(&self) -> &[usize] {
        &self.perm
    }

    /// Position in the permutation.
    pub fn cursor(&self) -> usize {
        self.cursor
    }

    /// Continue from a saved (rng, permutation, cursor).
    pub fn restore(&mut self, rng: ChaCha8Rng, perm: Vec<usize>, cursor: usize) -> Result<()> {
        if !perm.is_empty() && perm.len() != self.n_images {
            return Err(DataError::arg(
                "permutation",
                format!("{} image indices (or none)", self.n_images),
                perm.len(),
            ));
        }
        if cursor > perm.len() || perm.iter().any(|&i| i >= self.n_images) {
            return Err(DataError::arg(
                "cursor / permutation",
                format!("a cursor <= {} and indices < {}", perm.len(), self.n_images),
                format!("cursor {cursor}"),
            ));
        }
        self.rng = rng;
        self.perm = perm;
        self.cursor = cursor;
        Ok(())
    }

    /// Step 1: the next images, sorted ascending.
    pub fn next_images(&mut self) -> Vec<usize> {
        let mut out = Vec::with_capacity(self.images_per_step);
        while out.len() < self.images_per_step {
            if self.cursor >= self.perm.len() {
                self.perm = (0..self.n_images).collect();
                self.perm.shuffle(&mut self.rng);
                self.cursor = 0;
            }
            out.push(self.perm[self.cursor]);
            self.cursor += 1;
        }
        out.sort_unstable();
        out
    }

    /// Step 2: distinct pixels of one image, uniform over the nonzero
    /// entries of `sampling_mask` (`[H·W]` values, e.g. a column of the
    /// dataset's mask), or over all pixels when it has too few; ascending.
    pub fn pixels(&mut self, sampling_mask: impl IntoIterator<Item = u8>) -> Vec<usize> {
        self.pixels_with(sampling_mask, None).0
    }

    /// [`Self::pixels`], with `map` = (error map, image) part of them drawn where the map's
    /// error is (when the mask has enough pixels); returns the pixels and their loss
    /// weights (`None`: 1 each).
    fn pixels_with(
        &mut self,
        sampling_mask: impl IntoIterator<Item = u8>,
        map: Option<(&ErrorMap, usize)>,
    ) -> (Vec<usize>, Option<Vec<f32>>) {
        let valid: Vec<usize> = sampling_mask
            .into_iter()
            .enumerate()
            .filter(|(_, v)| *v > 0)
            .map(|(i, _)| i)
            .collect();
        if let Some((map, image)) = map.filter(|_| valid.len() >= self.rays_per_image) {
            let d = map.draw(&mut self.rng, image, &valid, self.rays_per_image);
            let weights = map.config().unbiased.then_some(d.weights);
            return (d.pixels, weights);
        }
        let mut px: Vec<usize> = if valid.len() >= self.rays_per_image {
            rand::seq::index::sample(&mut self.rng, valid.len(), self.rays_per_image)
                .into_iter()
                .map(|i| valid[i])
                .collect()
        } else {
            rand::seq::index::sample(&mut self.rng, self.pixels_per_image, self.rays_per_image)
                .into_vec()
        };
        px.sort_unstable();
        (px, None)
    }

    /// Steps 1–5 for one training step of `ds` (which needs images, masks
    /// and cameras; sampling masks are optional: without one every pixel is
    /// eligible).
    pub fn next_batch(&mut self, ds: &Dataset) -> Result<SampledBatch> {
        self.next_batch_with(ds, None)
    }

    /// [`Self::next_batch`], drawing part of each image's pixels from `map` (an error map
    /// over `ds`'s images) when given.
    pub fn next_batch_with(
        &mut self,
        ds: &Dataset,
        map: Option<&ErrorMap>,
    ) -> Result<SampledBatch> {
        if let Some(m) = map {
            let [n, _, _] = m.shape();
            if n != self.n_images {
                return Err(DataError::arg(
                    "error map",
                    format!("{} images (the sampler's)", self.n_images),
                    n,
                ));
            }
        }
        if ds.n_images() != self.n_images || ds.height() * ds.width() != self.pixels_per_image {
            return Err(DataError::arg(
                "dataset",
                format!(
                    "{} images of {} pixels (what the sampler was built for)",
                    self.n_images, self.pixels_per_image
                ),
                format!(
                    "{} images of {} pixels",
                    ds.n_images(),
                    ds.height() * ds.width()
                ),
            ));
        }
        let missing = |key: &str| DataError::MissingKey {
            file: ds.source.clone(),
            key: key.into(),
            profile: "train".into(),
            hint: String::new(),
        };
        let images = self.next_images();
        let r = self.rays_per_image * images.len();
        let mut b = SampledBatch {
            pose_rows: Vec::with_capacity(images.len()),
            images,
            pixels: Vec::with_capacity(r),
            origins: Vec::with_capacity(3 * r),
            dirs: Vec::with_capacity(3 * r),
            bgs: Vec::with_capacity(3 * r),
            targets: Vec::with_capacity(3 * r),
            framecodes: Vec::with_capacity(r),
            weights: None,
        };
        let mut weights: Vec<f32> = Vec::new();
        for k in 0..b.images.len() {
            let n = b.images[k];
            let cam = ds.image_camera(n)?;
            b.pose_rows.push(ds.pose_row(n)?);
            let img = ds.image(n).ok_or_else(|| missing("imgs"))?;
            let mask = ds.mask(n).ok_or_else(|| missing("masks"))?;
            let guide = map.map(|m| (m, n));
            let (pixels, w) = match ds.sampling_mask(n) {
                Some(m) => self.pixels_with(m.column(0).iter().copied(), guide),
                None => self.pixels_with(std::iter::empty(), guide),
            };
            if map.is_some_and(|m| m.config().unbiased) {
                weights.extend(w.unwrap_or_else(|| vec![1.0; pixels.len()]));
            }
            let (origins, dirs) = cam.rays(&pixels, true);
            for ((&px, ro), rd) in pixels.iter().zip(origins).zip(dirs) {
                b.origins.extend_from_slice(&ro);
                b.dirs.extend_from_slice(&rd);
                let fg = (mask[[px, 0]] > 0) as u8 as f32;
                // Black plates (PM zeroes the stored backgrounds); noise on background pixels.
                let noise: [f32; 3] = if self.perturb_bg {
                    self.rng.gen()
                } else {
                    [0.0; 3]
                };
                for c in 0..3 {
                    let bg = (1.0 - fg) * noise[c];
                    b.bgs.push(bg);
                    b.targets
                        .push(img[[px, c]] as f32 / 255.0 * fg + (1.0 - fg) * bg);
                }
                b.framecodes.push(n as i64);
            }
            b.pixels.extend_from_slice(&pixels);
        }
        if !weights.is_empty() {
            b.weights = Some(weights);
        }
        Ok(b)
    }
}
