//! `pma convert checkpoint`: a reference `torch.save` checkpoint → pma checkpoint.

use std::path::PathBuf;

use pma_convert::checkpoint::{convert_checkpoint, CheckpointOptions};
use pma_data::fsio::PathCheck;

#[derive(clap::Args)]
pub struct Args {
    /// The reference checkpoint (`{'model', 'optimizer', 'global_iter'}`).
    input: PathBuf,
    /// Output pma checkpoint.
    #[arg(short, long)]
    output: PathBuf,
    /// Also write the Adam state as a training state (`<OUT stem>.optim.safetensors`),
    /// so training can resume from the reference checkpoint.
    #[arg(long)]
    with_optimizer: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let side = pma_convert::train_state::sidecar_path(&args.output);
    crate::cli::check_paths(
        PathCheck::new()
            .input("checkpoint", &args.input)
            .output("--output", &args.output)
            .output_opt(
                "--with-optimizer",
                args.with_optimizer.then_some(side.as_path()),
            ),
    )?;
    let opts = CheckpointOptions {
        with_optimizer: args.with_optimizer,
    };
    let rep = convert_checkpoint(&args.input, &args.output, &opts)?;
    println!(
        "{}: {} tensors, {} parameters, n_framecodes {}, global_iter {}",
        args.output.display(),
        rep.n_tensors,
        rep.n_parameters,
        rep.config.n_framecodes,
        rep.global_iter.map_or("-".into(), |g| g.to_string())
    );
    if let Some(side) = rep.train_state {
        println!(
            "{}: Adam state ({} parameters had moments in the source; the others start from zero)",
            side.display(),
            rep.n_moments
        );
    }
    Ok(())
}
