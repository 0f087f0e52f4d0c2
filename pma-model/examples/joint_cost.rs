//! What a network point costs by the number of joints its call carries through the per-joint
//! work (`Network::eval_joints`), against all 24: the floor that leaving joints out of a
//! call (`--cull-joints`) approaches, and so a bound on what culled renders can gain from it.
//!
//! cargo run --release -p pma-model --example joint_cost -- [--points 2048] [--preset cpu-small]
//!
//! One thread (a CPU worker's share), a freshly initialised network of the preset (the cost
//! does not depend on the weights), points spread over the rest pose's box; medians of 9
//! timed calls after one warm-up.

#[path = "support/scene.rs"]
mod scene;

use candle_core::{Device, Tensor};
use pma_model::network::config::Config;
use pma_model::render::avatar::Avatar;

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // candle reads these on every op; set at start-up, before any other thread exists.
    std::env::set_var("RAYON_NUM_THREADS", "1");
    std::env::set_var("CANDLE_NUM_THREADS", "1");
    let n: usize = scene::arg("--points", 2048);
    let preset: String = scene::arg("--preset", "cpu-small".to_string());
    let cfg = match preset.as_str() {
        "default" => Config::default(),
        "cpu-small" => Config::cpu_small(),
        other => {
            return Err(format!("--preset: expected default or cpu-small, found {other}").into())
        }
    };
    let dev = Device::Cpu;
    let rest = pma_data::synth::rest_pose();
    let tensors = pma_model::network::init_tensors(&cfg, &rest, 3, &dev)?;
    let avatar = Avatar::from_tensors(cfg, tensors, &dev)?;
    let (poses, _) = avatar.pose_from_bones(&[[0.0; 3]; 24], [0.0; 3])?;
    let pose = avatar.pose_features(&poses, None)?;
    // A low-discrepancy spread over [-0.5, 0.5]³ around the root.
    let pts: Vec<f32> = (0..n)
        .flat_map(|i| {
            let f = |a: f64| ((i as f64 * a).fract() - 0.5) as f32;
            [f(0.754_877_7), f(0.569_840_3), f(0.362_033_6)]
        })
        .collect();
    let pts = Tensor::from_vec(pts, (n, 3), &dev)?;
    let view =
        avatar
            .network()
            .view_features(&Tensor::new(&[[0f32, 0.0, 1.0]], &dev)?, &[-1], false)?;
    let view = view.broadcast_as((n, view.dim(1)?))?.contiguous()?;
    let net = avatar.network();
    println!("{preset}, {n} points per call, 1 thread; medians of 9 calls");
    let mut all = None;
    for k in [24usize, 12, 8, 6, 4, 2, 1] {
        let joints: Vec<u32> = (0..k as u32).collect();
        let secs = scene::median_seconds(9, || {
            net.eval_joints(&pose, 0..1, &pts, &view, Some(&joints), None)?;
            Ok(())
        })?;
        let us = secs * 1e6 / n as f64;
        let of_all = *all.get_or_insert(us);
        println!(
            "{k:>2} joints: {us:6.2} µs/point  {:5.2} of 24 joints' cost",
            us / of_all
        );
    }
    Ok(())
}
