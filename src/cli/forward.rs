//! `pma forward`: run the model on a ray batch stored as npz (the parity hook for outside
//! tools; the file format is `pma_model::render::batch_file`'s).
//!
//! No gradient is needed here, so by default the batch runs on the inference path
//! (`Mode::Infer`: detached, chunked, on the data-parallel workers), which writes the same
//! bytes as the graph-keeping path (`--grad`, `Mode::Train`/`Mode::Eval`) that this command
//! ran before; `tests/cli/forward.rs` compares the two output files byte for byte.

use std::path::PathBuf;

use anyhow::Result;
use pma_model::render::avatar::{Avatar, Mode};
use pma_model::render::batch_file::{
    load_model, write_outputs, BatchInput, ModelOptions, RayBatchFile,
};

use super::refuse;

#[derive(clap::Args)]
pub struct Args {
    /// Model checkpoint (.safetensors), or a run directory (its newest complete model).
    #[arg(long)]
    model: PathBuf,
    /// Load a model with NaN or infinite weights (refused otherwise), to see what it computes.
    #[arg(long)]
    allow_non_finite: bool,
    /// Ray batch npz: rays_o, rays_d [R,3], kp3d [R,24,3], skts [R,24,4,4], bones [R,24,3],
    /// cyls [R,5], cam_idxs [R], bgs [R,3], rest_pose [24,3]; optional N_unique.
    #[arg(long)]
    batch: PathBuf,
    /// Output npz.
    #[arg(long)]
    out: PathBuf,
    /// safetensors whose tensors replace the model's (e.g. the golden `dense` case's sigma head).
    #[arg(long)]
    sigma_override: Option<PathBuf>,
    /// Frame codes as in training: looked up by index, and a batch whose indices are all −1 is
    /// refused (with `false`, as in evaluation, such a batch gets the mean code). No density
    /// noise either way.
    #[arg(long, default_value_t = true, action = clap::ArgAction::Set)]
    train_mode: bool,
    /// Keep the autograd graph (the pass gradients would need): one network call per pose
    /// instead of the inference path's detached chunks on all cores. Same outputs, slower.
    #[arg(long)]
    grad: bool,
    #[command(flatten)]
    device: super::DeviceArgs,
    /// After the forward whose outputs are written, run this many more and print their
    /// median wall time (the first call pays one-off costs such as GPU kernel loading).
    #[arg(long, default_value_t = 0)]
    time: usize,
}

pub fn run(mut args: Args) -> Result<()> {
    if args.time > 1000 {
        refuse!("--time {}: at most 1000 repetitions", args.time);
    }
    args.model = super::model_path(&args.model)?;
    super::check_paths(
        pma_data::fsio::PathCheck::new()
            .input("--model", &args.model)
            .input("--batch", &args.batch)
            .input_opt("--sigma-override", args.sigma_override.as_deref())
            .output("--out", &args.out),
    )?;
    let dev = args.device.open()?;
    let batch = RayBatchFile::read(&args.batch)?;
    let file = batch.file().to_string();
    let input = batch.input(&dev)?;
    let model_opts = ModelOptions {
        allow_non_finite: args.allow_non_finite,
        overrides: args.sigma_override.clone(),
    };
    let avatar = load_model(&args.model, &batch, &input.rest, &model_opts, &dev)?
        .with_numerics(super::numerics());
    let mut opts = match (args.grad, args.train_mode) {
        (true, true) => Mode::Train(None),
        (true, false) => Mode::Eval,
        (false, train_mode) => {
            if train_mode && avatar.config().use_framecodes {
                check_training_codes(&input.rays.framecodes, &file)?;
            }
            Mode::Infer
        }
    };
    let parity = pma_model::render::PassOptions::parity();
    let out = avatar.forward(&input.rays, &input.poses, &mut opts, &parity, None)?;
    if args.time > 0 {
        time_forward(&args, &avatar, &input, &mut opts, &dev)?;
    }
    write_outputs(&out, &args.out)?;
    println!(
        "wrote {} ({} rays, {} pose(s))",
        args.out.display(),
        input.rays.framecodes.len(),
        input.poses.bones.len()
    );
    Ok(())
}

/// The inference path looks frame codes up as evaluation does; the two rules differ only on
/// a batch whose indices are all negative (evaluation: the mean code; training: an error),
/// so `--train-mode` refuses that batch up front, as the graph path in training mode does.
fn check_training_codes(codes: &[i64], file: &str) -> Result<()> {
    if let Some(bad) = codes.iter().find(|&&i| i < 0) {
        refuse!(
            "{file}: key `cam_idxs`: frame-code index {bad} is negative in training mode \
             (pass `--train-mode false` for the mean code)"
        );
    }
    Ok(())
}

/// `--time`: more forwards, and their median wall time.
fn time_forward(
    args: &Args,
    avatar: &Avatar,
    input: &BatchInput,
    opts: &mut Mode,
    dev: &candle_core::Device,
) -> Result<()> {
    let mut secs = Vec::with_capacity(args.time);
    for _ in 0..args.time {
        // Synchronise on both sides: GPU work is queued asynchronously, so the clock
        // must not start before earlier work ends nor stop before this work does.
        dev.synchronize()?;
        let t0 = std::time::Instant::now();
        let parity = pma_model::render::PassOptions::parity();
        let o = avatar.forward(&input.rays, &input.poses, opts, &parity, None)?;
        dev.synchronize()?;
        secs.push(t0.elapsed().as_secs_f64());
        drop(o);
    }
    secs.sort_by(f64::total_cmp);
    println!(
        "forward on {}: median {:.4} s, min {:.4} s over {} runs ({} rays)",
        args.device.device,
        secs[secs.len() / 2],
        secs[0],
        secs.len(),
        input.rays.framecodes.len()
    );
    Ok(())
}
