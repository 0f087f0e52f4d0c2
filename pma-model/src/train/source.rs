//! Training batches from a pma-npz dataset (PM defaults; see `docs/conventions.md`,
//! "Ray sampler"), as a [`BatchSource`]:
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
//! The sampling itself is `pma_data::sampler::Sampler` (one ChaCha8 stream); this module adds
//! the tensors and the saved state (the permutation, cursor and stream position). With an
//! error map ([`DatasetSource::with_error_map`], `[train.error_map]`) step 2 draws part of
//! each image's pixels where the map says the training error is; the trainer feeds the map
//! each step's per-ray errors and a checkpoint saves it.

use std::sync::Arc;

use candle_core::{Device, Tensor};
use pma_data::dataset::Dataset;
use pma_data::error_map::{ErrorMap, ErrorMapConfig};
use pma_data::sampler::Sampler;
use serde::{Deserialize, Serialize};

use super::batch::{BatchSource, TrainBatch};
use super::state::RngState;
use super::TrainError;
use crate::render::avatar::{Poses, Rays};

pub struct DatasetSource {
    data: Arc<Dataset>,
    device: Device,
    sampler: Sampler,
    map: Option<ErrorMap>,
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
        let sampler =
            Sampler::for_dataset(&data, rays_per_step, images_per_step, perturb_bg, seed)?;
        Ok(Self {
            data,
            device: device.clone(),
            sampler,
            map: None,
        })
    }

    /// The same source drawing part of its rays from a fresh error map of `cfg` over its
    /// images.
    pub fn with_error_map(mut self, cfg: ErrorMapConfig) -> Result<Self, TrainError> {
        let d = &self.data;
        let map = ErrorMap::new(cfg, d.n_images(), d.width(), d.height())
            .map_err(|e| TrainError::Config(format!("error_map: {e}")))?;
        self.map = Some(map);
        Ok(self)
    }
}

impl BatchSource for DatasetSource {
    fn next_batch(&mut self) -> Result<TrainBatch, TrainError> {
        let data = self.data.clone();
        let b = self.sampler.next_batch_with(&data, self.map.as_ref())?;
        let r = b.len();
        let (all_skts, all_cyls) = (
            data.skts.as_ref().expect("checked"),
            data.cyls.as_ref().expect("checked"),
        );
        let mut bones = Vec::with_capacity(b.images.len());
        let mut skts = Vec::with_capacity(b.images.len() * 16 * 24);
        let mut cyls = Vec::with_capacity(b.images.len() * 5);
        for &p in &b.pose_rows {
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
        let p = b.images.len();
        Ok(TrainBatch {
            rays: Rays {
                origins: Tensor::from_vec(b.origins, (r, 3), dev)?,
                dirs: Tensor::from_vec(b.dirs, (r, 3), dev)?,
                bgs: Some(Tensor::from_vec(b.bgs, (r, 3), dev)?),
                framecodes: b.framecodes,
            },
            poses: Poses {
                bones,
                skts: Tensor::from_vec(skts, (p, 24, 4, 4), dev)?,
                cyls: Tensor::from_vec(cyls, (p, 5), dev)?,
            },
            target: Tensor::from_vec(b.targets, (r, 3), dev)?,
            pixels: Some(b.pixels.iter().map(|&p| p as u32).collect()),
            weights: b.weights.map(|w| Tensor::from_vec(w, r, dev)).transpose()?,
        })
    }

    fn error_map(&self) -> Option<&ErrorMap> {
        self.map.as_ref()
    }

    fn error_map_mut(&mut self) -> Option<&mut ErrorMap> {
        self.map.as_mut()
    }

    fn state(&self) -> serde_json::Value {
        serde_json::to_value(SourceState {
            rng: RngState::capture(self.sampler.rng()),
            perm: self.sampler.permutation().to_vec(),
            cursor: self.sampler.cursor(),
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
        let rng = s.rng.restore()?;
        self.sampler
            .restore(rng, s.perm, s.cursor)
            .map_err(|e| bad(e.to_string()))
    }
}
