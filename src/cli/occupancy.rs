//! `pma occupancy build`: give a trained model an occupancy grid (for `--occupancy` in
//! render, eval, bench, mesh, view and pma-infer) by evaluating its density in every cell of
//! each joint's box frame over training poses (`pma_model::tools::occupancy`).

use std::path::PathBuf;

use anyhow::Context as _;
use pma_data::dataset::Profile;
use pma_model::network::occupancy::OccupancyConfig;
use pma_model::render::avatar::Avatar;
use pma_model::tools::occupancy::{build, BuildOptions};

use super::{progress, read_dataset, refuse};

#[derive(clap::Subcommand, Debug, Clone)]
pub enum Command {
    /// Build a grid for a trained model from a dataset's poses and save model + grid.
    Build(BuildArgs),
}

#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(clap::Args, Debug, Clone)]
pub struct BuildArgs {
    /// Trained model (`RUN/model.safetensors`, or the run directory: its newest complete model).
    #[arg(long)]
    pub model: PathBuf,
    /// Dataset whose poses the grid is built over (the training set).
    #[arg(long)]
    pub data: PathBuf,
    /// Output checkpoint: the model's tensors unchanged plus the grid (default: beside the
    /// model, `<name>.occupancy.safetensors`).
    #[arg(short = 'o', long)]
    pub out: Option<PathBuf>,
    /// Pose rows to evaluate, spread evenly over the dataset (0 = every pose).
    #[arg(long, default_value_t = 16)]
    pub poses: usize,
    /// Cells per axis of each joint's grid.
    #[arg(long, default_value_t = OccupancyConfig::default().resolution)]
    pub resolution: usize,
    /// The grid covers x̄ ∈ [−extent, extent]³ of each joint's box frame; samples outside it
    /// always run the network.
    #[arg(long, default_value_t = OccupancyConfig::default().extent)]
    pub extent: f64,
    /// The smallest sample-culling threshold the grid will be used with: the grid spans only
    /// where a joint's window can exceed it (at most `--extent`), so its cells are finer.
    /// Renders at a lower threshold stay exact but leave less out.
    #[arg(long, value_name = "T")]
    pub cull_samples: Option<f64>,
    /// Density relu(σ) above which a cell is occupied.
    #[arg(long, default_value_t = OccupancyConfig::default().threshold)]
    pub threshold: f64,
    /// Occupied cells mark their neighbours up to this many cells away occupied too.
    #[arg(long, default_value_t = OccupancyConfig::default().dilation)]
    pub dilation: usize,
    /// Seed of the point drawn inside each cell.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Compute device: cpu, cuda, cuda:N, metal (cuda/metal need a binary built with that
    /// feature).
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    match args.command {
        Command::Build(a) => run_build(a),
    }
}

fn run_build(mut args: BuildArgs) -> anyhow::Result<()> {
    let device = super::device(&args.device)?;
    args.model = super::model_path(&args.model)?;
    let out = args.out.clone().unwrap_or_else(|| {
        let stem = args.model.file_stem().unwrap_or_default().to_string_lossy();
        args.model
            .with_file_name(format!("{stem}.occupancy.safetensors"))
    });
    super::check_paths(
        pma_data::fsio::PathCheck::new()
            .input("--model", &args.model)
            .input("--data", &args.data)
            .output("--out", &out),
    )?;
    let config = OccupancyConfig {
        resolution: args.resolution,
        extent: args.extent,
        threshold: args.threshold,
        dilation: args.dilation,
        ..Default::default()
    };
    config.validate("occupancy (--resolution, --extent, --threshold, --dilation)")?;
    if let Some(t) = args.cull_samples {
        if !(t.is_finite() && (0.0..1.0).contains(&t)) {
            refuse!("--cull-samples: expected a threshold in [0, 1), found {t}");
        }
    }
    let avatar = Avatar::load(&args.model, &device)
        .with_context(|| format!("loading model {}", args.model.display()))?
        .with_numerics(super::numerics());
    let config = config.covering(args.cull_samples, avatar.config());
    let data = read_dataset(&args.data, Profile::Render)?;
    let opts = BuildOptions {
        config,
        poses: args.poses,
        seed: args.seed,
    };
    let bar = progress::bar(args.quiet, 0, "poses");
    let (avatar, stats) = build(avatar, &data, &opts, &mut |done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })?;
    bar.finish_and_clear();
    avatar
        .save(&out)
        .with_context(|| format!("writing {}", out.display()))?;
    println!(
        "occupancy grid: {} poses, {} network points, {:.1} % of cells occupied -> {}",
        stats.poses,
        stats.points,
        100.0 * stats.occupied_fraction,
        out.display()
    );
    Ok(())
}
