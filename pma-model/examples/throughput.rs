//! CPU throughput of the paper configuration in parity mode: seconds per training step or
//! inference pass and network samples per second (rays × (48 + 24)). Raw figures only; to
//! compare with the official code, run both on the same machine in the same session
//! (`bench/official/compare.sh` does).
//!
//! cargo run --release -p pma-model --features train --example throughput -- [--train-rays 512]
//!     [--infer-rays 4096] [--repeats 3]
//!
//! Medians over `--repeats` after one warm-up each; a training step includes backward, clip and
//! Adam. Inference is `Avatar::render_rays` (no gradient, bounded chunks). GFLOP/s are the
//! network's matmul FLOPs over the median time, also as a share of this machine's estimated
//! fp32 peak (`pma_model::compute::flops`).

#[path = "support/scene.rs"]
mod scene;

use candle_core::Device;
use pma_model::train::{BatchSource, DatasetSource, Preset, RunConfig, Trainer};

// The same allocator as the `pma` binary, so these figures are the CLI's.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // Data-parallel workers with candle's intra-op threads off (0 = one per core), as the
    // `pma` binary does; `--workers 1` keeps candle's own threading.
    let workers = pma_model::compute::parallel::configure_cpu(scene::arg("--workers", 0));
    let train_rays: usize = scene::arg("--train-rays", 512);
    let infer_rays: usize = scene::arg("--infer-rays", 4096);
    let repeats: usize = scene::arg("--repeats", 3).max(1);
    let numerics = pma_model::compute::numerics::Numerics {
        // `--no-fused`: plain candle ops instead of the fused CPU kernels (A/B measurement).
        fused: !std::env::args().any(|a| a == "--no-fused"),
        // `--fast-sine`: the vectorised sine (not parity mode: last-bit differences).
        fast_sine: std::env::args().any(|a| a == "--fast-sine"),
        ..Default::default()
    };
    let dir = tempfile::tempdir()?;
    let data = scene::scene(dir.path())?;
    let mut run = RunConfig::from_preset(Preset::Paper);
    run.numerics = numerics;
    let samples = (run.model.n_samples + run.model.n_importance) as f64;
    let flops_per_point = pma_model::compute::flops::per_point(&run.model);
    let (peak, peak_how) = pma_model::compute::flops::fp32_peak();
    let gflops = |points: f64, factor: f64, secs: f64| {
        let g = points * flops_per_point * factor / secs / 1e9;
        format!("{g:.1} GFLOP/s matmul = {:.1} % of peak", 100.0 * g / peak)
    };
    println!(
        "paper config, {}, {workers} workers x {} candle threads, fused kernels {}",
        if numerics.fast_sine {
            "fast sine (not parity)"
        } else {
            "parity mode"
        },
        candle_core::utils::get_num_threads(),
        if numerics.fused { "on" } else { "off" }
    );

    if train_rays > 0 {
        run.train.rays_per_step = train_rays;
        let mut trainer = Trainer::new(run.clone(), data.clone(), &Device::Cpu)?;
        let m = scene::median_seconds(repeats, || {
            trainer.step()?;
            Ok(())
        })?;
        let sps = train_rays as f64 * samples / m;
        println!(
            "training  {train_rays:>5} rays: median {m:.3} s/step, {sps:.0} samples/s, {}",
            gflops(
                train_rays as f64 * samples,
                pma_model::compute::flops::TRAIN_FACTOR,
                m
            )
        );
    }

    if infer_rays > 0 {
        run.model.n_framecodes = data.n_images();
        let rest = data.rest_pose.ok_or("scene without rest pose")?;
        let avatar =
            pma_model::render::avatar::Avatar::new(run.model.clone(), &rest, 0, &Device::Cpu)?
                .with_numerics(numerics);
        let mut src = DatasetSource::new(data, infer_rays, 16, false, 0, &Device::Cpu)?;
        let batch = src.next_batch()?;
        let m = scene::median_seconds(repeats, || {
            avatar.render_rays(&batch.rays, &batch.poses, &Default::default())?;
            Ok(())
        })?;
        let sps = infer_rays as f64 * samples / m;
        println!(
            "inference {infer_rays:>5} rays: median {m:.3} s, {sps:.0} samples/s, {}",
            gflops(infer_rays as f64 * samples, 1.0, m)
        );
    }
    println!(
        "{:.3} MFLOP/point; estimated peak {peak:.0} GFLOP/s: {peak_how}",
        flops_per_point / 1e6
    );
    println!(
        "peak RSS {:.0} MiB",
        scene::peak_rss_mib().unwrap_or(f64::NAN)
    );
    Ok(())
}
