//! Training resumes from a converted reference checkpoint: the model and the
//! `--with-optimizer` training state go into a run directory, the trainer
//! resumes from it and takes one step on the golden batch. The step must
//! continue torch's Adam: step counts follow `global_iter`, and the new
//! moments are the old ones decayed plus one gradient (m' = β₁m + (1−β₁)g,
//! v' = β₂v + (1−β₂)g²), which fails if the moments were not loaded.

use crate::support::{convert_fixture, root};

use candle_core::{Device, Tensor};
use pma_model::{
    doctor::golden::Golden,
    network::checkpoint,
    train::{FixedBatch, Preset, RunConfig, TrainBatch, TrainConfig, Trainer, STATE_FILE},
};

/// The golden 64-ray batch (one unique pose).
fn golden_batch() -> TrainBatch {
    Golden::load(&root().join("fixtures/golden"), &Device::Cpu)
        .unwrap()
        .batch()
        .unwrap()
}

fn flat(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
}

#[test]
fn training_resumes_from_a_converted_reference_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("model.safetensors");
    let rep = convert_fixture("convert/ckpt_adam.th", &model, true).unwrap();
    std::fs::rename(rep.train_state.unwrap(), dir.path().join(STATE_FILE)).unwrap();

    let ck = checkpoint::load(&model, &Device::Cpu).unwrap();
    let run = RunConfig {
        preset: Preset::Paper,
        model: ck.config.clone(),
        train: TrainConfig::paper(),
        numerics: Default::default(),
    };
    let mut trainer = Trainer::resume_with_source(
        dir.path(),
        run,
        Box::new(FixedBatch(golden_batch())),
        &Device::Cpu,
    )
    .unwrap();
    assert_eq!(trainer.iteration(), 1234);
    let names = [
        "graph_net.axis_scale",
        "pts_linears.0.bias",
        "sigma_linear.weight",
    ];
    let before: Vec<(Vec<f32>, Vec<f32>)> = names
        .iter()
        .map(|n| {
            let s = trainer.optimizer().state(n).unwrap().unwrap();
            assert_eq!(s.step, 1234, "{n}");
            (flat(&s.exp_avg), flat(&s.exp_avg_sq))
        })
        .collect();
    // Loaded moments are the converted ones, not zeros.
    assert!(before[0].1.iter().any(|&v| v != 0.0));

    let stats = trainer.step_read().unwrap();
    assert_eq!(stats.skipped, None, "the resumed step was skipped");
    assert_eq!(trainer.iteration(), 1235);
    let [b1, b2] = trainer.optimizer().groups()[0].betas;
    for (n, (m0, v0)) in names.iter().zip(&before) {
        let s = trainer.optimizer().state(n).unwrap().unwrap();
        assert_eq!(s.step, 1235, "{n}");
        let (m1, v1) = (flat(&s.exp_avg), flat(&s.exp_avg_sq));
        // g is recovered from float32 moments by a subtraction that can cancel,
        // so each element is allowed the rounding that recovery carries.
        let eps = f32::EPSILON as f64;
        let mut worst = 0f64;
        for k in 0..m1.len() {
            let (m0, m1, v0, v1) = (m0[k] as f64, m1[k] as f64, v0[k] as f64, v1[k] as f64);
            let g = (m1 - b1 * m0) / (1.0 - b1);
            let dg = 4.0 * eps * (m1.abs() + b1 * m0.abs()) / (1.0 - b1);
            let want = b2 * v0 + (1.0 - b2) * g * g;
            let tol = 4.0 * eps * (v1.abs() + want.abs()) + (1.0 - b2) * (2.0 * g.abs() + dg) * dg;
            worst = worst.max((v1 - want).abs() / tol.max(f64::MIN_POSITIVE));
        }
        assert!(
            worst <= 1.0,
            "{n}: v' disagrees with m' by {worst:.2} x the rounding bound"
        );
    }
}
