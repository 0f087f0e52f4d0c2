//! `pma check-stability`: run the numerical-stability probes (`pma_model::tools::stability`)
//! on a checkpoint or a freshly initialised avatar and print one table row per case. Exits
//! non-zero when any output or gradient is non-finite (with `--strict`, also on broken
//! invariants such as far < near). A model with an occupancy grid is probed with the grid on
//! (the route `--occupancy` renders and trains with), unless `--no-occupancy`.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};

use super::refuse;
use pma_model::render::avatar::Avatar;
use pma_model::render::PassOptions;
use pma_model::tools::stability::{self, ProbeOptions};
use pma_model::Config;

#[derive(clap::Args)]
pub struct Args {
    /// Checkpoint to probe (.safetensors). Default: a freshly initialised avatar of `--preset`
    /// on the synthetic figure's rest pose.
    #[arg(long)]
    model: Option<PathBuf>,
    /// Network size of the fresh avatar: default (the paper's), cpu-small or tiny.
    #[arg(long, default_value = "default")]
    preset: String,
    /// Switch on the opt-in stability fixes (`quirks.robust_ray_bounds`,
    /// `quirks.per_ray_cylinder_fallback`) before probing.
    #[arg(long)]
    fixes: bool,
    /// Also fail on broken invariants (weights outside [0,1], far < near, batch dependence).
    #[arg(long)]
    strict: bool,
    /// Run every forward probe with the occupancy grid on (the default when the model has a
    /// grid); refused for a model without one.
    #[arg(long, conflicts_with = "no_occupancy")]
    occupancy: bool,
    /// Probe the parity route even when the model has an occupancy grid.
    #[arg(long)]
    no_occupancy: bool,
    /// Compute device: cpu, cuda, cuda:N, metal.
    #[arg(long, default_value = "cpu")]
    device: String,
    /// Hide the progress bar.
    #[arg(long)]
    quiet: bool,
}

pub fn run(args: Args) -> Result<()> {
    let model = args.model.as_deref().map(super::model_path).transpose()?;
    super::check_paths(pma_data::fsio::PathCheck::new().input_opt("--model", model.as_deref()))?;
    let device = super::device(&args.device)?;
    let mut avatar = match &model {
        Some(path) => {
            Avatar::load(path, &device).with_context(|| format!("loading {}", path.display()))?
        }
        None => {
            let cfg = match args.preset.as_str() {
                "default" | "paper" => Config::paper(),
                "cpu-small" => Config::cpu_small(),
                "tiny" => Config::tiny(),
                other => refuse!("--preset: expected default, cpu-small or tiny, found `{other}`"),
            };
            Avatar::new(cfg, &pma_data::synth::rest_pose(), 0, &device)?
        }
    };
    if args.fixes {
        let tensors = avatar.tensors();
        let mut cfg = avatar.config().clone();
        cfg.quirks.robust_ray_bounds = true;
        cfg.quirks.per_ray_cylinder_fallback = true;
        let grid = avatar.occupancy().cloned();
        avatar = Avatar::from_tensors(cfg, tensors, &device)?.with_occupancy(grid);
    }
    let avatar = avatar.with_numerics(super::numerics());
    if args.occupancy && avatar.occupancy().is_none() {
        let which = model.as_deref().map_or_else(
            || format!("the fresh `{}` avatar", args.preset),
            |p| p.display().to_string(),
        );
        refuse!(
            "--occupancy: {which} has no occupancy grid (train with `--occupancy` or build one \
             with `pma occupancy build`)"
        );
    }
    let opts = ProbeOptions {
        pass: PassOptions {
            occupancy: avatar.occupancy().is_some() && !args.no_occupancy,
            ..PassOptions::parity()
        },
        ..ProbeOptions::default()
    };
    let bar = super::progress::bar(args.quiet, stability::case_count(&opts)? as u64, "probes");
    let report = stability::run_all(&avatar, &opts, &mut |row| {
        bar.set_message(row.case.clone());
        bar.inc(1);
    })?;
    bar.finish_and_clear();
    print!("{}", report.table());
    println!("{}", report.pass_summary());
    let (bad, broken) = (report.non_finite(), report.violations());
    println!("non-finite values: {bad}; broken invariants: {broken}");
    if bad > 0 {
        bail!("{bad} non-finite output or gradient values");
    }
    if args.strict && broken > 0 {
        bail!("{broken} broken invariants (--strict)");
    }
    Ok(())
}
