//! Culling in training (`[train.culling]` of the run config): at threshold 0 a training step —
//! unchunked and in ray chunks — has parity mode's loss and gradients up to float rounding.
//! Not bit for bit: the far-away constant the culled samples get is computed in a call of its
//! own (one point per pose, the colour head per ray), whose products may round differently
//! in the last bit from a row inside a larger call; and the culled samples of a ray share
//! that row, so the weight gradients form aᵀ(Σᵢ δᵢ) over it where parity forms Σᵢ aᵀδᵢ over
//! one row per sample (docs/numerics.md, "Empty rays and culling"). The tolerances are the
//! one of a chunked step (1e-6, relative for the loss); measured: the loss bit-identical,
//! gradients within 1.1e-8.
#![cfg(feature = "train")]

use std::sync::Arc;

use crate::train_support::{first_batch, fixed_batch_trainer, step_grads, tiny_run, tiny_scene};
use pma_data::dataset::Dataset;
use pma_model::render::{Culling, SampleFill};
use pma_model::train::{StepStats, TrainBatch};

struct Step {
    stats: StepStats,
    /// Gradients before clipping, in optimizer order.
    grads: Vec<Vec<f32>>,
    names: Vec<String>,
    /// Network points of the step.
    points: u64,
}

fn one_step(data: &Arc<Dataset>, batch: &TrainBatch, chunk: usize, culling: Culling) -> Step {
    let mut run = tiny_run();
    run.train.culling = culling;
    run.train.chunk_rays = chunk;
    let mut trainer = fixed_batch_trainer(run, data, batch);
    let names = trainer.param_names().to_vec();
    let (stats, grads) = step_grads(&mut trainer);
    let points = trainer.pass_totals().points_evaluated;
    Step {
        stats,
        grads,
        names,
        points,
    }
}

/// (differing values, max |diff|) per named gradient that is not bit-identical.
fn differences(a: &Step, b: &Step) -> Vec<(String, usize, usize, f32)> {
    assert_eq!(a.grads.len(), b.grads.len());
    let mut out = Vec::new();
    for ((name, x), y) in a.names.iter().zip(&a.grads).zip(&b.grads) {
        assert_eq!(x.len(), y.len(), "{name}: present in only one of the steps");
        let bad = x
            .iter()
            .zip(y)
            .filter(|(p, q)| p.to_bits() != q.to_bits())
            .count();
        if bad > 0 {
            let max = x
                .iter()
                .zip(y)
                .map(|(p, q)| (p - q).abs())
                .fold(0f32, f32::max);
            out.push((name.clone(), bad, x.len(), max));
        }
    }
    out
}

#[test]
fn threshold_zero_training_step_has_paritys_loss_and_gradients() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let run = tiny_run();
    let batch = first_batch(&data, &run);
    let r = run.train.rays_per_step;
    let cull = Culling {
        rays: false,
        sample_threshold: Some(0.0),
        sample_fill: SampleFill::Network,
    };
    for chunk in [r, 24] {
        let parity = one_step(&data, &batch, chunk, Culling::default());
        let culled = one_step(&data, &batch, chunk, cull.clone());
        println!(
            "chunk {chunk}: network points {} culled vs {} parity; loss {} vs {}",
            culled.points, parity.points, culled.stats.loss.total, parity.stats.loss.total
        );
        assert!(
            culled.points < parity.points,
            "chunk {chunk}: no sample was culled, the test would not exercise culling"
        );
        let diffs = differences(&culled, &parity);
        for (name, bad, n, max) in &diffs {
            println!("chunk {chunk}: {name}: {bad} of {n} differ, max |diff| {max:e}");
        }
        let (lc, lp) = (culled.stats.loss.total, parity.stats.loss.total);
        assert!(
            (lc - lp).abs() <= 1e-6 * lp.abs().max(1.0),
            "chunk {chunk}: loss {lc} vs {lp}"
        );
        let worst = diffs.iter().map(|d| d.3).fold(0f32, f32::max);
        assert!(
            worst <= 1e-6,
            "chunk {chunk}: gradients differ by {worst:e}"
        );
        assert!(
            (culled.stats.grad_norm - parity.stats.grad_norm).abs()
                <= 1e-6 * parity.stats.grad_norm.max(1.0),
            "chunk {chunk}: grad norm {} vs {}",
            culled.stats.grad_norm,
            parity.stats.grad_norm
        );
    }
}
