//! A training step run in chunks of rays with gradient accumulation is the unchunked step:
//! same loss, same accumulated gradient (before clipping), same parameters after Adam, to
//! 1e-6 absolute, with density noise on and a ray that misses the bounding cylinder (whose
//! bounds depend on the whole batch).
#![cfg(feature = "train")]

use std::sync::Arc;

use crate::train_support::{first_batch, tiny_run, tiny_scene};
use candle_core::{Device, Tensor};
use pma_data::dataset::Dataset;
use pma_model::render::avatar::Avatar;
use pma_model::render::raycast::cylinder_near_far;
use pma_model::train::{
    chunk_rays, FixedBatch, RunConfig, StepStats, TrainBatch, TrainConfig, Trainer,
};

fn flat(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
}

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
    /// The gradients the optimizer saw (before clipping), in optimizer order.
    grads: Vec<Vec<f32>>,
    /// The parameters after the step, by name.
    params: Vec<(String, Vec<f32>)>,
}

/// One step of a fresh tiny avatar on `batch` with `chunk_rays`.
fn one_step(data: &Arc<Dataset>, batch: &TrainBatch, chunk: usize) -> Step {
    let mut run = tiny_run();
    run.model.n_framecodes = data.n_images();
    run.train.chunk_rays = chunk;
    let rest = data.rest_pose.unwrap();
    let avatar = Avatar::new(run.model.clone(), &rest, run.train.seed, &Device::Cpu).unwrap();
    let mut trainer =
        Trainer::with_source(run, avatar, Box::new(FixedBatch(batch.clone()))).unwrap();
    let mut grads = Vec::new();
    let stats = trainer
        .step_hooked(&mut |g: &mut [Option<Tensor>]| {
            grads = g
                .iter()
                .map(|t| t.as_ref().map(flat).unwrap_or_default())
                .collect();
        })
        .unwrap();
    let params = trainer
        .avatar()
        .trainable()
        .into_iter()
        .map(|(n, v)| (n, flat(v.as_tensor())))
        .collect();
    Step {
        stats,
        grads,
        params,
    }
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

#[test]
fn chunked_step_equals_the_unchunked_step() {
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
    } = one_step(&data, &batch, r);
    // 64 rays of 2 images: 12 + 12 + 8 rays per image, the last chunk smaller.
    for chunk in [24, 2] {
        let Step {
            stats: s_chunked,
            grads: g_chunked,
            params: p_chunked,
        } = one_step(&data, &batch, chunk);
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
        for (i, (a, b)) in g_chunked.iter().zip(&g_one).enumerate() {
            assert_eq!(
                a.len(),
                b.len(),
                "gradient {i}: present in only one of the steps"
            );
            let m = max_abs_diff(a, b);
            if m > worst.0 {
                worst = (m, format!("gradient {i}"));
            }
        }
        for ((name, a), (_, b)) in p_chunked.iter().zip(&p_one) {
            let m = max_abs_diff(a, b);
            if m > worst.0 {
                worst = (m, format!("{name} after the step"));
            }
        }
        println!("chunk {chunk}: max abs diff {:.2e} ({})", worst.0, worst.1);
        assert!(
            worst.0 <= 1e-6,
            "chunk {chunk}: {} differs by {:.2e}",
            worst.1,
            worst.0
        );
    }
}

#[test]
fn automatic_chunks_bound_the_paper_step_and_leave_small_nets_whole() {
    let paper = TrainConfig::paper();
    assert_eq!(paper.chunk_rays, 0);
    assert_eq!(
        chunk_rays(&paper, &pma_model::network::config::Config::paper()),
        128
    );
    let small = RunConfig::from_preset(pma_model::train::Preset::CpuSmall);
    assert!(chunk_rays(&small.train, &small.model) >= small.train.rays_per_step);
    let fixed = TrainConfig {
        chunk_rays: 100,
        ..TrainConfig::paper()
    };
    assert_eq!(
        chunk_rays(&fixed, &pma_model::network::config::Config::paper()),
        100
    );
}
