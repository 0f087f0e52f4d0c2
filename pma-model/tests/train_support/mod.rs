//! Shared fixtures of the training tests: a tiny synthetic scene and the `tiny` run.
#![allow(dead_code)]

use std::path::Path;
use std::sync::Arc;

pub use crate::common::flat;
use candle_core::{Device, Tensor};
use pma_data::dataset::{Dataset, Profile, ReadOptions};
use pma_model::render::avatar::Avatar;
use pma_model::train::{FixedBatch, Preset, RunConfig, StepStats, TrainBatch, Trainer};

/// 4 training images (2 cameras × 2 frames) of 32×32 pixels.
pub fn tiny_scene(dir: &Path) -> Arc<Dataset> {
    let cfg = pma_data::synth::SynthConfig {
        novel_view_stride: 2,
        ..pma_data::synth::SynthConfig::small(32, 2, 2)
    };
    pma_data::synth::generate(&cfg, dir, &mut |_, _| {}).expect("synth");
    Arc::new(
        Dataset::read(dir.join("train.npz"), &ReadOptions::new(Profile::Train))
            .expect("read train.npz"),
    )
}

pub fn tiny_run() -> RunConfig {
    let mut run = RunConfig::from_preset(Preset::Tiny);
    run.train.rays_per_step = 64;
    run.train.images_per_step = 2;
    run
}

pub fn tiny_trainer(data: &Arc<Dataset>) -> Trainer {
    Trainer::new(tiny_run(), data.clone(), &Device::Cpu).expect("trainer")
}

/// Every trainable parameter as raw f32 bits, by name.
pub fn param_bits(t: &Trainer) -> Vec<(String, Vec<u32>)> {
    t.avatar()
        .trainable()
        .into_iter()
        .map(|(n, v)| (n, bits(v.as_tensor())))
        .collect()
}

pub fn bits(t: &Tensor) -> Vec<u32> {
    flat(t).into_iter().map(f32::to_bits).collect()
}

/// Optimizer moments and steps as raw bits, in state order.
pub fn adam_bits(t: &Trainer) -> Vec<(String, u64, Vec<u32>, Vec<u32>)> {
    t.optimizer()
        .states()
        .unwrap()
        .into_iter()
        .map(|(n, s)| (n.to_string(), s.step, bits(&s.exp_avg), bits(&s.exp_avg_sq)))
        .collect()
}

/// `run`'s batch sampler on `data`, on the CPU.
pub fn dataset_source(data: &Arc<Dataset>, run: &RunConfig) -> pma_model::train::DatasetSource {
    let t = &run.train;
    pma_model::train::DatasetSource::new(
        data.clone(),
        t.rays_per_step,
        t.images_per_step,
        t.perturb_bg,
        t.seed,
        &candle_core::Device::Cpu,
    )
    .unwrap()
}

/// The first training batch `run`'s sampler draws from `data`.
pub fn first_batch(data: &Arc<Dataset>, run: &RunConfig) -> pma_model::train::TrainBatch {
    use pma_model::train::BatchSource;
    dataset_source(data, run).next_batch().unwrap()
}

/// A fresh avatar of `run` (its frame codes sized to `data`, from the run's seed) trained on
/// `batch` at every step.
pub fn fixed_batch_trainer(mut run: RunConfig, data: &Dataset, batch: &TrainBatch) -> Trainer {
    run.model.n_framecodes = data.n_images();
    let rest = data.rest_pose.unwrap();
    let avatar = Avatar::new(run.model.clone(), &rest, run.train.seed, &Device::Cpu).unwrap();
    Trainer::with_source(run, avatar, Box::new(FixedBatch(batch.clone()))).unwrap()
}

/// One step of `trainer`: its stats and the gradients the optimizer saw (before clipping),
/// in parameter order, each flattened (empty where a parameter has none).
pub fn step_grads(trainer: &mut Trainer) -> (StepStats, Vec<Vec<f32>>) {
    let mut grads = Vec::new();
    let stats = trainer
        .step_hooked(&mut |g: &mut [Option<Tensor>]| {
            grads = g
                .iter()
                .map(|t| t.as_ref().map(flat).unwrap_or_default())
                .collect();
        })
        .unwrap();
    (stats, grads)
}
