//! Data-parallel workers (`pma_model::compute::parallel`) change nothing but the speed: a chunked
//! training step, an inference pass (plain and culled) and a whole image rendered in
//! parallel ray chunks give bit-identical results with 1 and with 3 workers.
#![cfg(feature = "train")]

mod common;
mod train_support;

use candle_core::Device;
use pma_model::compute::parallel::{set_workers, workers};
use pma_model::render::avatar::Avatar;
use pma_model::render::PassOptions;
use pma_model::train::{BatchSource, DatasetSource};
use train_support::{first_batch, fixed_batch_trainer, flat, step_grads, tiny_run, tiny_scene};

// One test function: the worker count is process-wide.
#[test]
fn worker_count_does_not_change_results() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let mut run = tiny_run();
    run.model.n_framecodes = data.n_images();
    run.train.chunk_rays = 2;
    let rest = data.rest_pose.unwrap();
    let batch = first_batch(&data, &run);

    let step = |w: usize| {
        set_workers(w);
        assert_eq!(workers(), w);
        let mut trainer = fixed_batch_trainer(run.clone(), &data, &batch);
        let (stats, grads) = step_grads(&mut trainer);
        let params: Vec<Vec<f32>> = trainer
            .avatar()
            .trainable()
            .into_iter()
            .map(|(_, v)| flat(v.as_tensor()))
            .collect();
        (stats.loss.total, grads, params)
    };
    let one = step(1);
    let three = step(3);
    assert_eq!(one.0.to_bits(), three.0.to_bits(), "loss");
    assert!(one.1.iter().any(|g| !g.is_empty()), "no gradients");
    assert_eq!(one.1, three.1, "accumulated gradients");
    assert_eq!(one.2, three.2, "parameters after the step");

    // Inference: enough rays for several point chunks per pose.
    let mut src = DatasetSource::new(data.clone(), 1024, 2, false, 3, &Device::Cpu).unwrap();
    let batch = src.next_batch().unwrap();
    let avatar = Avatar::new(run.model.clone(), &rest, 1, &Device::Cpu).unwrap();
    let render = |w: usize| {
        set_workers(w);
        let out = avatar
            .render_rays(&batch.rays, &batch.poses, &PassOptions::parity())
            .unwrap();
        (flat(&out.fine.rgb), flat(&out.fine.acc))
    };
    let (rgb1, acc1) = render(1);
    let (rgb3, acc3) = render(3);
    assert!(acc1.iter().any(|&a| a > 0.0), "the batch sees the body");
    assert_eq!(rgb1, rgb3, "rendered colour");
    assert_eq!(acc1, acc3, "accumulated opacity");

    // The culled route sizes its network calls by the worker count: still the same result.
    let culled = PassOptions::culled(pma_model::render::Culling {
        rays: true,
        sample_threshold: Some(0.2),
        sample_fill: pma_model::render::SampleFill::Network,
    });
    let render = |w: usize| {
        set_workers(w);
        let out = avatar
            .render_rays(&batch.rays, &batch.poses, &culled)
            .unwrap();
        (flat(&out.fine.rgb), flat(&out.raw))
    };
    let (rgb1, raw1) = render(1);
    let (rgb3, raw3) = render(3);
    assert_eq!(rgb1, rgb3, "culled: rendered colour");
    assert_eq!(raw1, raw3, "culled: raw outputs");

    // A whole image in several ray chunks, which the workers render at the same time.
    let (poses, kp3d) = pma_model::eval::dataset_pose(&data, 0, &Device::Cpu).unwrap();
    let cam = data.camera(data.camera_row(0).unwrap()).unwrap();
    let image = |w: usize, pass: &PassOptions| {
        set_workers(w);
        let opts = pma_model::render::image::ImageOptions {
            chunk: 97,
            pass: pass.clone(),
            ..Default::default()
        };
        avatar
            .render_image(&poses, &kp3d, &cam, None, &opts)
            .unwrap()
    };
    for pass in [PassOptions::parity(), culled] {
        let (one, three) = (image(1, &pass), image(3, &pass));
        assert!(one.stats.points_evaluated > 0, "the image ran the network");
        assert!(one.acc.iter().any(|&a| a > 0.0), "the image sees the body");
        assert_eq!(one, three, "image rendered in parallel chunks");
    }
    set_workers(1);
}
