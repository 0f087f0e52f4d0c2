//! A training step run in chunks of rays with gradient accumulation is the unchunked step:
//! same loss and accumulated gradient (before clipping) to 1e-6 absolute, and parameters
//! after Adam that differ by no more than Adam's first step turns the gradient differences
//! into (plus 1e-6), with density noise on and a ray that misses the bounding cylinder (whose
//! bounds depend on the whole batch).
//!
//! Why a bound and not 1e-6 flat for the parameters: Adam's first step moves an element by
//! `lr · g/(|g| + eps)`, whose slope is up to `lr/eps` = 5e4 for |g| near eps = 1e-8, so a
//! gradient difference of a few 1e-11 (summation order) can move a parameter by 1e-6.
#![cfg(feature = "train")]

use std::sync::Arc;

use crate::common::max_abs_diff;
use crate::train_support::{
    first_batch, fixed_batch_trainer, flat, step_grads, tiny_run, tiny_scene,
};
use candle_core::{Device, Tensor};
use pma_data::dataset::Dataset;
use pma_model::render::raycast::cylinder_near_far;
use pma_model::train::{chunk_rays, RunConfig, StepStats, TrainBatch, TrainConfig};

/// A training batch of the tiny scene in which ray 5 of the second image points along the
/// cylinder's axis from the camera, so it misses the cylinder and every box.
fn batch_with_a_miss(data: &Arc<Dataset>, run: &RunConfig) -> TrainBatch {
    let mut batch = first_batch(data, run);
    let r = batch.rays.origins.dim(0).unwrap();
    let miss = r / run.train.images_per_step + 5;
    let mut dirs = flat(&batch.rays.dirs);
    dirs[3 * miss..3 * miss + 3].copy_from_slice(&[0.0, 1.0, 0.0]);
    batch.rays.dirs = Tensor::from_vec(dirs, (r, 3), &Device::Cpu).unwrap();
    batch
}

/// What one step did.
struct Step {
    stats: StepStats,
    /// The gradients the optimizer saw (before clipping), by name.
    grads: Vec<(String, Vec<f32>)>,
    /// The parameters after the step, by name.
    params: Vec<(String, Vec<f32>)>,
}

/// One step of a fresh tiny avatar on `batch` with `chunk_rays` (and stratified samples).
fn one_step(data: &Arc<Dataset>, batch: &TrainBatch, chunk: usize, jitter: bool) -> Step {
    let mut run = tiny_run();
    run.train.chunk_rays = chunk;
    run.train.jitter = jitter;
    let mut trainer = fixed_batch_trainer(run, data, batch);
    let (stats, grads) = step_grads(&mut trainer);
    let names = trainer.param_names().to_vec();
    let params = trainer
        .avatar()
        .trainable()
        .into_iter()
        .map(|(n, v)| (n, flat(v.as_tensor())))
        .collect();
    Step {
        stats,
        grads: names.into_iter().zip(grads).collect(),
        params,
    }
}

/// Adam's eps of the run.
fn run_eps() -> f64 {
    tiny_run().train.eps
}

#[test]
fn chunked_step_equals_the_unchunked_step() {
    chunked_equals_unchunked(false);
}

/// With stratified samples too: a sample's place belongs to its ray's row in the whole
/// batch, not in its chunk.
#[test]
fn a_jittered_step_is_the_same_in_chunks() {
    chunked_equals_unchunked(true);
}

fn chunked_equals_unchunked(jitter: bool) {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let run = tiny_run();
    let batch = batch_with_a_miss(&data, &run);
    let r = run.train.rays_per_step;
    assert!(
        run.model.density_noise_std > 0.0,
        "the noise slicing is under test"
    );

    // The batch really has cylinder misses (their bounds are the batch means).
    let o = flat(&batch.rays.origins);
    let d = flat(&batch.rays.dirs);
    let cyls = flat(&batch.poses.cyls);
    let per_pose = r / run.train.images_per_step;
    let (near, _) = cylinder_near_far(&o, &d, |i| {
        let c = &cyls[(i / per_pose) * 5..];
        [c[0], c[1], c[2]]
    });
    assert!(
        near.iter().any(|v| v.is_nan()),
        "no ray misses the cylinder"
    );

    let Step {
        stats: s_one,
        grads: g_one,
        params: p_one,
    } = one_step(&data, &batch, r, jitter);
    // 64 rays of 2 images: 12 + 12 + 8 rays per image, the last chunk smaller.
    for chunk in [24, 2] {
        let Step {
            stats: s_chunked,
            grads: g_chunked,
            params: p_chunked,
        } = one_step(&data, &batch, chunk, jitter);
        assert_eq!(s_chunked.skipped, None);
        assert!(
            (s_chunked.loss.total - s_one.loss.total).abs() <= 1e-6,
            "chunk {chunk}: loss {} vs unchunked {}",
            s_chunked.loss.total,
            s_one.loss.total
        );
        assert!(
            (s_chunked.grad_norm - s_one.grad_norm).abs() <= 1e-6 * s_one.grad_norm.max(1.0),
            "chunk {chunk}: grad norm {} vs {}",
            s_chunked.grad_norm,
            s_one.grad_norm
        );
        assert_eq!(g_chunked.len(), g_one.len());
        let mut worst = (0f32, String::new());
        for ((name, a), (_, b)) in g_chunked.iter().zip(&g_one) {
            assert_eq!(
                a.len(),
                b.len(),
                "gradient of {name}: present in only one of the steps"
            );
            let m = max_abs_diff(a, b);
            if m > worst.0 {
                worst = (m, format!("gradient of {name}"));
            }
        }
        println!(
            "chunk {chunk}: gradients differ by at most {:.2e} ({})",
            worst.0, worst.1
        );
        assert!(
            worst.0 <= 1e-6,
            "chunk {chunk}: {} differs by {:.2e}",
            worst.1,
            worst.0
        );
        // The first Adam step moves element i by lr · s(c g_i) with s(x) = x/(|x| + eps) and
        // c the clip coefficient: the parameters may differ by lr · |s(c₁g₁) − s(c₂g₂)|.
        let eps = run_eps();
        let s = |x: f64| x / (x.abs() + eps);
        let grad_of = |grads: &[(String, Vec<f32>)], name: &str| {
            grads.iter().find(|(n, _)| n == name).unwrap().1.clone()
        };
        let mut worst_param = (0f64, String::new());
        for ((name, a), (_, b)) in p_chunked.iter().zip(&p_one) {
            let lr = s_one.lrs[pma_model::train::adam::reference_group(name)];
            let (ga, gb) = (grad_of(&g_chunked, name), grad_of(&g_one, name));
            for i in 0..a.len() {
                let adam = lr
                    * (s(s_chunked.clip_coef * ga[i] as f64) - s(s_one.clip_coef * gb[i] as f64))
                        .abs();
                let excess = (a[i] as f64 - b[i] as f64).abs() - adam;
                if excess > worst_param.0 {
                    worst_param = (excess, format!("{name}[{i}] after the step"));
                }
            }
        }
        println!(
            "chunk {chunk}: parameters differ by at most {:.2e} beyond Adam's share ({})",
            worst_param.0, worst_param.1
        );
        assert!(
            worst_param.0 <= 1e-6,
            "chunk {chunk}: {} differs by {:.2e} more than its gradient explains",
            worst_param.1,
            worst_param.0
        );
    }
}

#[test]
fn automatic_chunks_bound_the_paper_step_and_leave_small_nets_whole() {
    let paper = TrainConfig::paper();
    assert_eq!(paper.chunk_rays, 0);
    assert_eq!(
        chunk_rays(
            &paper,
            &pma_model::network::config::Config::paper(),
            &Device::Cpu
        ),
        128
    );
    let small = RunConfig::from_preset(pma_model::train::Preset::CpuSmall);
    assert!(chunk_rays(&small.train, &small.model, &Device::Cpu) >= small.train.rays_per_step);
    let fixed = TrainConfig {
        chunk_rays: 100,
        ..TrainConfig::paper()
    };
    assert_eq!(
        chunk_rays(
            &fixed,
            &pma_model::network::config::Config::paper(),
            &Device::Cpu
        ),
        100
    );
}
