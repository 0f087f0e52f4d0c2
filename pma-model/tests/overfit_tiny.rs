//! The overfit check CI runs: the `tiny` network on a tiny synthetic scene (4 images of
//! 32×32), seed 0, a fixed number of iterations. The PSNR of the fine render on a fixed probe
//! set of training rays (black background, the images' own frame codes) must rise by at
//! least MARGIN_DB.
#![cfg(feature = "train")]

mod train_support;

use candle_core::Device;
use pma_model::avatar::Rays;
use pma_model::train::{psnr_from_mse, BatchSource, DatasetSource, TrainBatch, Trainer};
use train_support::*;

const ITERS: usize = 80;
const MARGIN_DB: f64 = 3.0;

fn probe_psnr(t: &Trainer, probe: &TrainBatch) -> f64 {
    let rays = Rays { bgs: None, ..probe.rays.clone() };
    let out = t.avatar().render_rays(&rays, &probe.poses).unwrap();
    let mse = (&out.fine.rgb - &probe.target).unwrap().sqr().unwrap().mean_all().unwrap().to_scalar::<f32>().unwrap();
    psnr_from_mse(mse as f64)
}

#[test]
fn training_psnr_rises_on_a_tiny_scene() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"));
    let mut t = tiny_trainer(&data);
    // All 4 training images, 64 rays each, black background (no noise), own seed.
    let probe = DatasetSource::new(data.clone(), 256, 4, false, 99, &Device::Cpu).unwrap().next_batch().unwrap();
    let before = probe_psnr(&t, &probe);
    let mut skipped = 0;
    for _ in 0..ITERS {
        skipped += t.step().unwrap().skipped.is_some() as usize;
    }
    let after = probe_psnr(&t, &probe);
    eprintln!("probe PSNR {before:.2} dB -> {after:.2} dB after {ITERS} iterations");
    assert_eq!(skipped, 0);
    assert!(after - before >= MARGIN_DB, "PSNR rose by {:.2} dB only ({before:.2} -> {after:.2})", after - before);
}
