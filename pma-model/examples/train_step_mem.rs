//! Peak memory of training steps of the paper configuration, chunked or not.
//!
//! cargo build --release -p pma-model --features train --example train_step_mem
//! /usr/bin/time -v target/release/examples/train_step_mem --rays 3072 --chunk-rays 0
//!
//! `--chunk-rays 0` is the automatic chunk size, `--chunk-rays N` (N ≥ rays) one pass.
//! Prints the time of each step and the process's peak RSS (VmHWM) after the steps.

#[path = "support/scene.rs"]
mod scene;

use std::time::Instant;

use candle_core::Device;
use pma_model::train::{chunk_rays, Preset, RunConfig, Trainer};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // As the `pma` binary: one data-parallel worker per core (`--workers 1`: candle threads).
    let workers = pma_model::compute::parallel::configure_cpu(scene::arg("--workers", 0));
    println!("{workers} workers");
    let rays: usize = scene::arg("--rays", 3072);
    let images: usize = scene::arg("--images", 16);
    let chunk: usize = scene::arg("--chunk-rays", 0);
    let steps: usize = scene::arg("--steps", 1);
    let dir = tempfile::tempdir()?;
    let data = scene::scene(dir.path())?;
    let before = scene::peak_rss_mib();
    let mut run = RunConfig::from_preset(Preset::Paper);
    run.train.rays_per_step = rays;
    run.train.images_per_step = images;
    run.train.chunk_rays = chunk;
    let mut trainer = Trainer::new(run, data, &Device::Cpu)?;
    let eff = chunk_rays(
        &trainer.run_config().train,
        &trainer.run_config().model,
        &Device::Cpu,
    );
    println!(
        "paper config, {rays} rays from {images} images per step, chunks of {} rays, {} threads; peak RSS before training {:.0} MiB",
        eff.min(rays),
        candle_core::utils::get_num_threads(),
        before.unwrap_or(f64::NAN)
    );
    for _ in 0..steps {
        let t = Instant::now();
        let s = trainer.step_read()?;
        println!(
            "step {}: {:.2} s, loss {:.4}, peak RSS so far {:.0} MiB",
            s.iter,
            t.elapsed().as_secs_f64(),
            s.loss.total,
            scene::peak_rss_mib().unwrap_or(f64::NAN)
        );
    }
    Ok(())
}
