//! What candle's matmul (the gemm crate) reaches on this machine for the network's shapes,
//! as a ceiling for the GFLOP/s a whole training step can show (`throughput`): the three
//! products of a 256→256 linear layer on `rows` rows, as a training step forms them:
//! forward x·Wᵀ, input gradient δ·W and weight gradient δᵀ·x.
//!
//! cargo run --release -p pma-model --example gemm_ceiling -- [--rows 384] [--threads 1]
//!
//! `--threads 1` is how a training step runs its gemms (one per data-parallel worker);
//! medians of 7 timed calls after one warm-up, against `pma_model::compute::flops::fp32_peak()`
//! divided over the cores.

#[path = "support/scene.rs"]
mod scene;

use candle_core::{Device, Tensor};

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

type Product<'a> = Box<dyn Fn() -> candle_core::Result<Tensor> + 'a>;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let rows: usize = scene::arg("--rows", 384);
    let threads: usize = scene::arg("--threads", 1).max(1);
    // candle reads this on every gemm; set at start-up, before any other thread exists.
    std::env::set_var("RAYON_NUM_THREADS", threads.to_string());
    let (k, n) = (256, 256);
    let dev = Device::Cpu;
    let x = Tensor::randn(0f32, 1., (rows, k), &dev)?;
    let w = Tensor::randn(0f32, 1., (n, k), &dev)?;
    let d = Tensor::randn(0f32, 1., (rows, n), &dev)?;
    let flop = 2.0 * (rows * k * n) as f64;
    let (peak, _) = pma_model::compute::flops::fp32_peak();
    let cores = std::thread::available_parallelism().map_or(1, |c| c.get());
    let peak_here = peak / cores as f64 * threads.min(cores) as f64;
    let products: [(&str, Product); 3] = [
        ("forward   x·Wᵀ", Box::new(|| x.matmul(&w.t()?))),
        ("input grad δ·W", Box::new(|| d.matmul(&w))),
        ("weight grad δᵀ·x", Box::new(|| d.t()?.matmul(&x))),
    ];
    println!("{rows} rows × 256 → 256, {threads} thread(s); peak of those cores ≈ {peak_here:.0} GFLOP/s");
    for (name, product) in products {
        let m = scene::median_seconds(7, || {
            product()?;
            Ok(())
        })?;
        let g = flop / m / 1e9;
        println!(
            "{name:<18} {:8.3} ms  {g:6.1} GFLOP/s  {:5.1} % of peak",
            m * 1e3,
            100.0 * g / peak_here
        );
    }
    Ok(())
}
