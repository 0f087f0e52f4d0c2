//! `pma`: Pose Modulated Avatars from video, on candle.
//!
//! The binary only parses arguments and calls the libraries (`pma-data`,
//! `pma-model`, `pma-convert`); each subcommand lives in `src/cli/<name>.rs` (or
//! `src/cli/<name>/` when it has subcommands or parts of its own).

use std::process::ExitCode;

use clap::{Parser, Subcommand};

mod cli;

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[derive(Parser)]
#[command(
    name = "pma",
    version,
    about = "Pose Modulated Avatars (PM-Avatar, ICLR 2024) in Rust"
)]
struct Cli {
    /// CPU worker threads, each running whole chunks of points or rays with candle's own
    /// threading off (0 = one per core). Renders do not depend on it; a training batch that
    /// fits one chunk is split over the workers, which changes only the float summation
    /// order. Setting RAYON_NUM_THREADS or CANDLE_NUM_THREADS keeps candle's threading instead.
    #[arg(long, global = true, default_value_t = 0)]
    workers: usize,
    /// Vectorised sine in the SIREN and modulated layers (CPU, f32) instead of libm's: faster,
    /// and different from parity mode in the last bit of a few values (`pma bench` measures
    /// the error). Off by default.
    #[arg(long, global = true)]
    fast_sine: bool,
    /// On CUDA, sum every gradient in a fixed order (no atomics), so a training run repeats
    /// and resumes bit for bit; a little slower. The CPU is deterministic anyway.
    #[arg(long, global = true)]
    deterministic: bool,
    /// The density trunk's matrix products with bf16 inputs, weights and outputs (f32
    /// accumulation), as bf16 tensor cores compute them; emulated by rounding on the CPU.
    /// Not parity: docs/numerics.md gives its measured PSNR cost. Off by default.
    #[arg(long, global = true)]
    bf16_trunk: bool,
    /// Run every op on candle's generic ops instead of pma's kernels (fused CPU ops, CUDA
    /// kernels, row gathers, the flat Adam update): the same numbers up to float rounding,
    /// slower. A kernel that fails on a device is switched off on its own (`pma doctor`).
    #[arg(long, global = true)]
    generic_kernels: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render the built-in synthetic multi-view dataset (an articulated, textured figure).
    Synth(cli::synth::Args),
    /// Print a dataset's schema summary, or its validation errors (non-zero exit).
    Inspect(cli::inspect::Args),
    /// Run the model on a ray batch npz and write its outputs (parity hook).
    Forward(cli::forward::Args),
    /// Convert reference checkpoints, A-NeRF/DANBO datasets and motion into pma formats.
    Convert(cli::convert::Args),
    /// Train an avatar on a pma-npz dataset.
    #[cfg(feature = "train")]
    Train(cli::train::Args),
    /// Evaluate a trained avatar (PSNR/SSIM/LPIPS per image and mean, side-by-side PNGs).
    Eval(cli::eval::Args),
    /// PSNR, SSIM and LPIPS of two images (optionally under a mask), as `pma eval` scores.
    Metrics(cli::metrics::Args),
    /// The main job on the embedded default: synthesise the scene, train, evaluate, render.
    #[cfg(feature = "train")]
    Demo(cli::demo::Args),
    /// The paper's ablations: train each model variant on the same budget, score novel views
    /// and poses, and tabulate error against run time.
    #[cfg(feature = "train")]
    Ablate(cli::ablate::Args),
    /// Render a trained avatar: dataset views, an orbit, bullet time, or retargeted motion (PNG + GIF).
    Render(cli::render::Args),
    /// Extract a coloured mesh (PLY) of a trained avatar in one pose by marching cubes.
    Mesh(cli::mesh::Args),
    /// Occupancy grids: build one for a trained model (`build`).
    Occupancy(cli::occupancy::Args),
    /// Parity mode against each culling option: speed, memory and error side by side.
    #[cfg(feature = "train")]
    Bench(cli::bench::Args),
    /// A device's self-test before a long run: every kernel against candle's ops, the
    /// official code's golden case, a training burst (exit 0 when every check passes).
    #[cfg(feature = "train")]
    Doctor(cli::doctor::Args),
    /// Drive an avatar through extreme poses, frequencies, scales, densities and ray geometry.
    CheckStability(cli::check_stability::Args),
    /// Look at an avatar or a training run in the browser, posed and turned by hand.
    View(cli::view::Args),
}

/// Errors go to stderr as one `error: ...` line with their causes, as clap reports usage
/// errors. Exit status (one rule for every command, see `cli::exit_code`): 0 success,
/// 2 input refused, 130/143/129 interrupted by SIGINT/SIGTERM/SIGHUP, 1 any other failure.
fn main() -> ExitCode {
    let cli = Cli::parse();
    cli::install_interrupt_handler();
    let result = cli::check_workers(cli.workers).and_then(|()| {
        // Before any candle op: candle sizes its thread pool once.
        pma_model::compute::parallel::configure_cpu(cli.workers);
        cli::set_numerics(cli.fast_sine, cli.deterministic, cli.bf16_trunk);
        pma_model::compute::kernel::health::set_generic(cli.generic_kernels);
        run(cli.command)
    });
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            // Output directories this command made and left empty go with it.
            pma_data::fsio::remove_empty_created_dirs();
            let code = cli::exit_code(&e);
            let line = if pma_data::ErrorKind::Interrupted == cli::error_kind(&e) {
                cli::interrupted_report(&e)
            } else {
                format!("error: {}", cli::report(&e))
            };
            // Best effort: stderr may be gone (a terminal closed with SIGHUP).
            use std::io::Write as _;
            let _ = writeln!(std::io::stderr(), "{line}");
            ExitCode::from(code)
        }
    }
}

fn run(command: Command) -> anyhow::Result<()> {
    match command {
        Command::Synth(a) => cli::synth::run(a),
        Command::Inspect(a) => cli::inspect::run(a),
        Command::Forward(a) => cli::forward::run(a),
        Command::Convert(a) => cli::convert::run(a),
        #[cfg(feature = "train")]
        Command::Train(a) => cli::train::run(a),
        Command::Eval(a) => cli::eval::run(a),
        Command::Metrics(a) => cli::metrics::run(a),
        #[cfg(feature = "train")]
        Command::Demo(a) => cli::demo::run(a),
        #[cfg(feature = "train")]
        Command::Ablate(a) => cli::ablate::run(a),
        Command::Render(a) => cli::render::run(a),
        #[cfg(feature = "train")]
        Command::Doctor(a) => cli::doctor::run(a),
        Command::Mesh(a) => cli::mesh::run(a),
        Command::Occupancy(a) => cli::occupancy::run(a),
        #[cfg(feature = "train")]
        Command::Bench(a) => cli::bench::run(a),
        Command::CheckStability(a) => cli::check_stability::run(a),
        Command::View(a) => cli::view::run(a),
    }
}
