//! What a training step consumes: [`TrainBatch`], and the [`BatchSource`] it comes from.
//! The trainer and the dataset source both build on these, so they live apart from either.

use candle_core::Tensor;
use pma_data::error_map::ErrorMap;

use super::TrainError;
use crate::render::avatar::{Poses, Rays};

/// One training batch: rays grouped by pose in equal contiguous blocks, their targets.
#[derive(Debug, Clone)]
pub struct TrainBatch {
    /// Unit directions, per-ray backgrounds (random noise on background pixels), and the
    /// training-image index of each ray as its frame code.
    pub rays: Rays,
    pub poses: Poses,
    /// target: [R,3] pixel colour composited over the ray's background.
    pub target: Tensor,
    /// Each ray's pixel in its image (the image is its frame code), where the source knows
    /// it: a source with an error map learns from the step's per-ray errors there.
    pub pixels: Option<Vec<u32>>,
    /// [R] loss weight of each ray (an error map's unbiased draws); `None`: 1 each.
    pub weights: Option<Tensor>,
}

/// Where training batches come from. Its state is saved with every checkpoint, so it must
/// capture everything that decides the next batches (permutation, cursor, RNG position).
pub trait BatchSource {
    fn next_batch(&mut self) -> Result<TrainBatch, TrainError>;
    /// JSON state for the train-state file (`Value::Null` if stateless).
    fn state(&self) -> serde_json::Value;
    fn restore(&mut self, state: &serde_json::Value) -> Result<(), TrainError>;
    /// The error map the source draws its rays from, if it has one: the trainer feeds it
    /// each step's per-ray errors, and a checkpoint saves it.
    fn error_map(&self) -> Option<&ErrorMap> {
        None
    }
    fn error_map_mut(&mut self) -> Option<&mut ErrorMap> {
        None
    }
}

/// The same batch every step (parity tests, overfitting a fixed batch).
pub struct FixedBatch(pub TrainBatch);

impl BatchSource for FixedBatch {
    fn next_batch(&mut self) -> Result<TrainBatch, TrainError> {
        Ok(self.0.clone())
    }
    fn state(&self) -> serde_json::Value {
        serde_json::Value::Null
    }
    fn restore(&mut self, _: &serde_json::Value) -> Result<(), TrainError> {
        Ok(())
    }
}
