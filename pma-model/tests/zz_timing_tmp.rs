#![cfg(feature = "train")]
use std::sync::Arc;
use std::time::Instant;
use candle_core::Device;
use pma_model::train::*;

#[test]
fn timing() {
    let data = pma_data::dataset::Dataset::read("/tmp/tr_cs/scene/train.npz", &pma_data::dataset::ReadOptions::new(pma_data::dataset::Profile::Train)).unwrap();
    let data = Arc::new(data);
    let preset: Preset = std::env::var("PRESET").unwrap_or("cpu-small".into()).parse().unwrap();
    let mut run = RunConfig::from_preset(preset);
    if let Ok(r) = std::env::var("RAYS") { run.train.rays_per_step = r.parse().unwrap(); }
    let mut t = Trainer::new(run, data.clone(), &Device::Cpu).unwrap();
    let mut src = DatasetSource::new(data, t.run_config().train.rays_per_step, t.run_config().train.images_per_step, true, 0, &Device::Cpu).unwrap();
    for i in 0..4 {
        let b = src.next_batch().unwrap();
        let t0 = Instant::now();
        let (loss, _) = t.loss_on(&b).unwrap();
        let t1 = Instant::now();
        let _g = loss.backward().unwrap();
        let t2 = Instant::now();
        let s = t.step_on(&b, None).unwrap();
        let t3 = Instant::now();
        eprintln!("iter {i}: fwd {:.3}s bwd {:.3}s full step {:.3}s loss {:.4}", (t1-t0).as_secs_f64(), (t2-t1).as_secs_f64(), (t3-t2).as_secs_f64(), s.loss.total);
    }
}
