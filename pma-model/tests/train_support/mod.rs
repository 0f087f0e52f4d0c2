//! Shared fixtures of the training tests: a tiny synthetic scene and the `tiny` run.
#![allow(dead_code)]

use std::path::Path;
use std::sync::Arc;

use candle_core::{DType, Device, Tensor};
use pma_data::dataset::{Dataset, Profile, ReadOptions};
use pma_model::train::{Preset, RunConfig, Trainer};

/// 4 training images (2 cameras × 2 frames) of 32×32 pixels.
pub fn tiny_scene(dir: &Path) -> Arc<Dataset> {
    let cfg = pma_data::synth::SynthConfig {
        res: 32,
        train_cams: 2,
        test_cams: 1,
        frames: 2,
        novel_view_stride: 2,
        novel_pose_walk: 1,
        novel_pose_dance: 1,
        ..Default::default()
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
    t.to_dtype(DType::F32)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap()
        .into_iter()
        .map(f32::to_bits)
        .collect()
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
