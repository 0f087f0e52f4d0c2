//! Times one forward and one forward+backward of the golden 64-ray batch (the reference's
//! default configuration). Prints medians over repeats after a warm-up.
//!
//! cargo run --release -p pma-model --example golden_timing

use std::time::Instant;

use candle_core::Device;
use pma_model::render::avatar::{Avatar, Mode, Poses, Rays};
use pma_model::train::loss::{training_loss, LossWeights};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let dev = Device::Cpu;
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures/golden");
    let g = candle_core::safetensors::load(root.join("golden.safetensors"), &dev)?;
    let avatar = Avatar::load(root.join("model.safetensors"), &dev)?;
    let bones = g["input/bones"].get(0)?.to_vec2::<f32>()?;
    let mut joints = [[0f32; 3]; 24];
    for (d, s) in joints.iter_mut().zip(bones) {
        d.copy_from_slice(&s);
    }
    let poses = Poses {
        bones: vec![joints],
        skts: g["input/skts"].narrow(0, 0, 1)?,
        cyls: g["input/cyls"].narrow(0, 0, 1)?,
    };
    let rays = Rays {
        origins: g["input/rays_o"].clone(),
        dirs: g["input/rays_d"].clone(),
        bgs: Some(g["input/bgs"].clone()),
        framecodes: g["input/cam_idxs"].to_vec1::<i64>()?,
    };
    let target = g["input/target_s"].clone();
    let median = |mut v: Vec<f64>| {
        v.sort_by(|a, b| a.partial_cmp(b).unwrap());
        v[v.len() / 2]
    };
    let forward = || -> Result<_, Box<dyn std::error::Error>> {
        Ok(avatar.forward(
            &rays,
            &poses,
            &mut Mode::Train(None),
            &Default::default(),
            None,
        )?)
    };
    let (mut fwd, mut bwd) = (Vec::new(), Vec::new());
    for i in 0..7 {
        let t = Instant::now();
        let out = forward()?;
        let f = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let out2 = forward()?;
        let loss = training_loss(&out2, &target, &LossWeights::default())?;
        loss.total.backward()?;
        let b = t.elapsed().as_secs_f64();
        drop(out);
        if i > 0 {
            fwd.push(f);
            bwd.push(b);
        }
    }
    println!(
        "golden 64 rays x (48 + 24) samples, paper config, {} threads",
        candle_core::utils::get_num_threads()
    );
    println!("forward          median {:.1} ms", 1e3 * median(fwd));
    println!("forward+backward median {:.1} ms", 1e3 * median(bwd));
    Ok(())
}
