//! Training batches from a pma-npz dataset (spec data.md §7, PM defaults), as a
//! [`BatchSource`]:
//!
//! 1. images: the next `images_per_step` indices of a random permutation of all training
//!    images (a fresh permutation when it runs out, so a batch across the boundary may repeat
//!    an image), sorted ascending;
//! 2. pixels: `rays_per_step / images_per_step` distinct pixels per image, uniform over the
//!    image's sampling mask (all pixels if the mask has fewer), sorted ascending;
//! 3. rays: the image's camera, unit directions;
//! 4. colours: `target = rgb·fg + (1−fg)·bg` with `bg = (1−fg)·u`, `u ~ U[0,1)³` per ray
//!    (`perturb_bg`; black otherwise), and the renderer composites over the same `bg`;
//! 5. per-image pose data (bones, skts, cyls) once per image, frame code = image index.
//!
//! All draws come from one ChaCha8 stream; the permutation, cursor and stream position are
//! the source's saved state.

use std::sync::Arc;

use candle_core::{Device, Tensor};
use pma_data::dataset::Dataset;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::state::RngState;
use super::trainer::{BatchSource, TrainBatch};
use super::TrainError;
use crate::avatar::{Poses, Rays};

/// The sampler's stream of the run seed (distinct from initialisation and density noise).
const SAMPLER_STREAM: u64 = 0x7361_6d70;

pub struct DatasetSource {
    data: Arc<Dataset>,
    rays_per_image: usize,
    images_per_step: usize,
    perturb_bg: bool,
    device: Device,
    rng: ChaCha8Rng,
    perm: Vec<usize>,
    cursor: usize,
}

#[derive(Serialize, Deserialize)]
struct SourceState {
    rng: RngState,
    perm: Vec<usize>,
    cursor: usize,
}

impl DatasetSource {
    /// Check that `data` can be trained on (pixels, masks, sampling masks, poses, cameras).
    pub fn new(
        data: Arc<Dataset>,
        rays_per_step: usize,
        images_per_step: usize,
        perturb_bg: bool,
        seed: u64,
        device: &Device,
    ) -> Result<Self, TrainError> {
        let bad = |msg: String| TrainError::Config(format!("{}: {msg}", data.source));
        if images_per_step == 0 || rays_per_step % images_per_step != 0 {
            return Err(bad(format!(
                "{rays_per_step} rays cannot be split evenly over {images_per_step} images"
            )));
        }
        let n = data.n_images();
        if n == 0 {
            return Err(bad("no training images".into()));
        }
        let missing: Vec<&str> = [
            ("imgs", data.imgs.is_none()),
            ("masks", data.masks.is_none()),
            ("sampling_masks", data.sampling_masks.is_none()),
            ("skts", data.skts.is_none()),
            ("cyls", data.cyls.is_none()),
            ("c2ws", data.c2ws.is_none()),
        ]
        .into_iter()
        .filter_map(|(k, m)| m.then_some(k))
        .collect();
        if !missing.is_empty() {
            return Err(bad(format!(
                "missing {} (train profile)",
                missing.join(", ")
            )));
        }
        let rays_per_image = rays_per_step / images_per_step;
        if rays_per_image > data.height() * data.width() {
            return Err(bad(format!(
                "{rays_per_image} rays per image exceed the {}x{} pixels of an image",
                data.width(),
                data.height()
            )));
        }
        // Every image must have a camera and a pose: fail now, not mid-run.
        for i in 0..n {
            data.image_camera(i)?;
            data.pose_row(i)?;
        }
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        rng.set_stream(SAMPLER_STREAM);
        Ok(Self {
            data,
            rays_per_image,
            images_per_step,
            perturb_bg,
            device: device.clone(),
            rng,
            perm: Vec::new(),
            cursor: 0,
        })
    }

    fn next_images(&mut self) -> Vec<usize> {
        let mut out = Vec::with_capacity(self.images_per_step);
        while out.len() < self.images_per_step {
            if self.cursor >= self.perm.len() {
                self.perm = (0..self.data.n_images()).collect();
                self.perm.shuffle(&mut self.rng);
                self.cursor = 0;
            }
            out.push(self.perm[self.cursor]);
            self.cursor += 1;
        }
        out.sort_unstable();
        out
    }

    fn pixels(&mut self, n: usize) -> Vec<usize> {
        let hw = self.data.height() * self.data.width();
        let valid: Vec<usize> = match self.data.sampling_mask(n) {
            Some(m) => m
                .outer_iter()
                .enumerate()
                .filter(|(_, v)| v[0] > 0)
                .map(|(i, _)| i)
                .collect(),
            None => Vec::new(),
        };
        let mut px: Vec<usize> = if valid.len() >= self.rays_per_image {
            rand::seq::index::sample(&mut self.rng, valid.len(), self.rays_per_image)
                .into_iter()
                .map(|i| valid[i])
                .collect()
        } else {
            rand::seq::index::sample(&mut self.rng, hw, self.rays_per_image).into_vec()
        };
        px.sort_unstable();
        px
    }
}

impl BatchSource for DatasetSource {
    fn next_batch(&mut self) -> Result<TrainBatch, TrainError> {
        let images = self.next_images();
        let k = self.rays_per_image;
        let r = k * images.len();
        let (mut o, mut d, mut bg, mut target) = (
            Vec::with_capacity(3 * r),
            Vec::with_capacity(3 * r),
            Vec::with_capacity(3 * r),
            Vec::with_capacity(3 * r),
        );
        let mut framecodes = Vec::with_capacity(r);
        let mut bones = Vec::with_capacity(images.len());
        let mut skts = Vec::with_capacity(images.len() * 16 * 24);
        let mut cyls = Vec::with_capacity(images.len() * 5);
        let data = self.data.clone();
        let (all_skts, all_cyls) = (
            data.skts.as_ref().expect("checked"),
            data.cyls.as_ref().expect("checked"),
        );
        for &n in &images {
            let cam = data.image_camera(n)?;
            let p = data.pose_row(n)?;
            let (img, mask) = (
                data.image(n).expect("checked"),
                data.mask(n).expect("checked"),
            );
            let pixels = self.pixels(n);
            let (origins, dirs) = cam.rays(&pixels, true);
            for ((&px, ro), rd) in pixels.iter().zip(origins).zip(dirs) {
                o.extend_from_slice(&ro);
                d.extend_from_slice(&rd);
                let fg = (mask[[px, 0]] > 0) as u8 as f32;
                // Black plates (PM zeroes the stored backgrounds); noise on background pixels.
                let noise: [f32; 3] = if self.perturb_bg {
                    self.rng.gen()
                } else {
                    [0.0; 3]
                };
                for c in 0..3 {
                    let b = (1.0 - fg) * noise[c];
                    bg.push(b);
                    target.push(img[[px, c]] as f32 / 255.0 * fg + (1.0 - fg) * b);
                }
                framecodes.push(n as i64);
            }
            bones.push(data.pose_bones(p));
            skts.extend(
                all_skts
                    .outer_iter()
                    .nth(p)
                    .expect("pose row checked")
                    .iter()
                    .copied(),
            );
            cyls.extend(all_cyls.row(p).iter().copied());
        }
        let dev = &self.device;
        let p = images.len();
        Ok(TrainBatch {
            rays: Rays {
                origins: Tensor::from_vec(o, (r, 3), dev)?,
                dirs: Tensor::from_vec(d, (r, 3), dev)?,
                bgs: Some(Tensor::from_vec(bg, (r, 3), dev)?),
                framecodes,
            },
            poses: Poses {
                bones,
                skts: Tensor::from_vec(skts, (p, 24, 4, 4), dev)?,
                cyls: Tensor::from_vec(cyls, (p, 5), dev)?,
            },
            target: Tensor::from_vec(target, (r, 3), dev)?,
        })
    }

    fn state(&self) -> serde_json::Value {
        serde_json::to_value(SourceState {
            rng: RngState::capture(&self.rng),
            perm: self.perm.clone(),
            cursor: self.cursor,
        })
        .unwrap_or(serde_json::Value::Null)
    }

    fn restore(&mut self, state: &serde_json::Value) -> Result<(), TrainError> {
        // A state converted from a reference checkpoint carries no sampler position: the
        // reference's loader order cannot be reproduced anyway, so start a fresh stream.
        if state.is_null() {
            return Ok(());
        }
        let bad = |msg: String| TrainError::State(vec![format!("sampler state: {msg}")]);
        let s: SourceState =
            serde_json::from_value(state.clone()).map_err(|e| bad(e.to_string()))?;
        let n = self.data.n_images();
        if s.perm.len() != n && !s.perm.is_empty() {
            return Err(bad(format!(
                "permutation of {} images, the dataset has {n}",
                s.perm.len()
            )));
        }
        if s.cursor > s.perm.len() || s.perm.iter().any(|&i| i >= n) {
            return Err(bad("cursor or image index out of range".into()));
        }
        self.rng = s.rng.restore()?;
        self.perm = s.perm;
        self.cursor = s.cursor;
        Ok(())
    }
}
