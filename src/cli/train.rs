//! `pma train`: train an avatar on a pma-npz dataset. The run itself is
//! `pma_model::train::train_run`; this command resolves the flags, draws the progress bar
//! and writes `psnr_vs_time.png` (held-out PSNR against wall-clock time) at every
//! checkpoint. Ctrl-C (the handler is `main`'s) stops the run with a checkpoint of its last
//! complete step and exit status 130.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::Context as _;
use pma_model::interrupt::Interrupted;
use pma_model::train::parallel::launch::Launch;
#[cfg(feature = "nccl")]
use pma_model::train::parallel::train_launched;
use pma_model::train::parallel::{train_group, GroupOptions, DEFAULT_GROUP_TIMEOUT};
use pma_model::train::{
    train_run, ObserverError, Preset, RunConfig, StepReport, TrainLog, TrainObserver, TrainOutcome,
    TrainRequest, CONFIG_FILE, LOG_FILE,
};

use super::plot::plot_psnr_vs_time;
use super::{progress, refuse};

/// Arguments of `pma train`.
#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Training dataset (pma-npz, train profile), e.g. `DIR/train.npz` from `pma synth`.
    #[arg(long)]
    pub data: PathBuf,
    /// Run directory (created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// TOML run configuration: `preset = "..."` plus `[model]` / `[train]` overrides.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Preset when no `--config` is given: `default` (the paper's sizes, for GPUs),
    /// `cpu-small` (a 2-core CPU learns in minutes) or `tiny` (tests). Without it: `default`
    /// on a GPU, `cpu-small` on the CPU.
    #[arg(long)]
    pub preset: Option<String>,
    /// Total iterations of the run (a resumed run continues up to this count).
    #[arg(long)]
    pub iters: Option<u64>,
    /// Wall-clock budget of this invocation in minutes; stops with a checkpoint when spent.
    #[arg(long)]
    pub minutes: Option<f64>,
    /// Continue the run in `--out` from its last checkpoint.
    #[arg(long)]
    pub resume: bool,
    /// Held-out data for the periodic evaluation (default: `novel_view.npz` next to `--data`,
    /// if it exists; otherwise no held-out evaluation).
    #[arg(long)]
    pub eval_data: Option<PathBuf>,
    /// Random seed (model initialisation, ray sampling, density noise); overrides the config.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Rays per forward/backward chunk of a training step (gradients accumulate over the
    /// chunks, the step is unchanged; memory is bounded by the chunk). 0 = automatic (128 for
    /// the default preset); overrides the config, also on resume.
    #[arg(long)]
    pub chunk_rays: Option<usize>,
    /// Which parts of the model to build (the paper's ablations: full, only-gnn, only-syn,
    /// only-wp, only-wf, no-window); overrides the config. Not for a resumed run.
    #[arg(long, value_enum)]
    pub variant: Option<pma_model::network::config::Variant>,
    /// Culling in training (docs/numerics.md, "Empty rays and culling"): overrides the
    /// config's `[train.culling]` when `--cull-rays` or `--cull-samples` is given. Not for a
    /// resumed run (its culling is in its config).
    #[command(flatten)]
    pub cull: pma_model::render::Culling,
    /// Build an occupancy grid during training, refresh it every few steps and skip the
    /// samples in its empty cells after the warm-up (`[train.occupancy]` sets its
    /// resolution, threshold and schedule); it is saved with every checkpoint. Not for a
    /// resumed run.
    #[arg(long)]
    pub occupancy: bool,
    /// With `--occupancy`: place each ray's coarse samples in the intervals the grid marks
    /// occupied instead of over its whole box interval (after the grid's warm-up). Not for a
    /// resumed run.
    #[arg(long, requires = "occupancy")]
    pub coarse_from_grid: bool,
    /// Stratified samples: each step places the coarse samples at random in their strata and
    /// the importance samples at random places of their distribution, instead of the
    /// reference's fixed places. Not for a resumed run.
    #[arg(long)]
    pub jitter: bool,
    /// Draw half of each image's rays where a running map of the training error is high
    /// (`[train.error_map]` sets its cells, share and weighting); the map is saved with
    /// every checkpoint. Not for a resumed run.
    #[arg(long)]
    pub error_map: bool,
    /// Anneal the learning rates to a tenth over the run's budget (`--minutes`), or over its
    /// iterations without one (`[train.anneal]`). A run annealed over a wall-clock budget
    /// does not repeat bit for bit. Not for a resumed run.
    #[arg(long)]
    pub anneal: bool,
    /// Start the pose side's rate (`lr_freq`) at 4x and bring it down to its own over the
    /// run's budget (`--minutes`), or over its iterations without one
    /// (`[train.pose_boost]` sets the multiple). Not for a resumed run.
    #[arg(long)]
    pub pose_boost: bool,
    /// Save and score the moving average of the weights over the steps instead of the last
    /// step's weights (`[train.average]` sets its decay); the trained weights stay in the
    /// train state. Not for a resumed run.
    #[arg(long)]
    pub average: bool,
    /// The fast recipe: ray and sample culling at w^p ≤ 0.6 with the occupancy grid,
    /// averaged weights and, with `--minutes`, the pose side's boost over that budget
    /// (`--pose-boost`; a run by iterations has none). `pma demo` trains with it. Not for a
    /// resumed run.
    #[arg(long)]
    pub fast: bool,
    /// No progress bar (log lines only).
    #[arg(long)]
    pub quiet: bool,
    /// Compute device: cpu, cuda, cuda:N, metal (cuda/metal need a binary built with that
    /// feature). A list trains data-parallel, one rank per device, in this process:
    /// `cuda:0,1,2,3` (NCCL: a binary built with `--features nccl`) or `cpu,cpu` (CPU ranks
    /// as threads, the test double of the GPU group; see docs/multi-gpu.md).
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Seconds a rank of a data-parallel group waits for the others at an exchange before
    /// the run stops with an error (a rank hangs or died).
    #[arg(long, value_name = "SECONDS")]
    pub group_timeout: Option<u64>,
    /// Train as one rank of a group of processes started by a launcher (Slurm's `srun`,
    /// `mpirun`, `torchrun`), which says the rank, the group's size and the local rank in its
    /// environment; the process takes GPU `cuda:LOCAL_RANK`. Needs a binary built with
    /// `--features nccl` (docs/multi-gpu.md).
    #[arg(long)]
    pub distributed: bool,
    /// Where rank 0 of `--distributed` posts the group's NCCL id for the others: a new path
    /// per job on a filesystem every rank sees (default: `.rendezvous-<job id>` in `--out`).
    #[arg(long, requires = "distributed", value_name = "FILE")]
    pub rendezvous: Option<PathBuf>,
    /// TF32 matrix products on CUDA: faster, changes results (see docs/numerics.md, "Low
    /// precision"); refused on other devices.
    #[arg(long)]
    pub tf32: bool,
}

/// The plot a run directory gets at every checkpoint.
pub const PLOT_FILE: &str = "psnr_vs_time.png";

pub fn run(args: Args) -> anyhow::Result<()> {
    super::check_minutes("--minutes", args.minutes)?;
    for (flag, v, max) in [
        ("--iters", args.iters, pma_model::train::presets::MAX_ITERS),
        ("--seed", args.seed, pma_model::train::presets::MAX_SEED),
    ] {
        if let Some(v) = v.filter(|&v| v > max) {
            refuse!("{flag} {v}: at most {max}");
        }
    }
    let launch = match args.distributed {
        true => Some(Launch::from_env(|k| std::env::var(k).ok())?),
        false => None,
    };
    let devices = match &launch {
        Some(l) => {
            if args.device != "cpu" {
                refuse!("--distributed takes GPU cuda:LOCAL_RANK from the launcher; drop --device");
            }
            super::devices_tf32(&format!("cuda:{}", l.local_rank), args.tf32)?
        }
        None => super::devices_tf32(&args.device, args.tf32)?,
    };
    let device = devices[0].clone();
    if let Some(t) = args.group_timeout {
        if devices.len() < 2 && launch.is_none() {
            refuse!(
                "--group-timeout needs several devices (--device cpu,cpu or cuda:0,1,...) or \
                 --distributed"
            );
        }
        if !(1..=MAX_GROUP_TIMEOUT_S).contains(&t) {
            refuse!("--group-timeout {t}: expected 1 to {MAX_GROUP_TIMEOUT_S} seconds");
        }
    }
    let opts = GroupOptions {
        timeout: args
            .group_timeout
            .map_or(DEFAULT_GROUP_TIMEOUT, Duration::from_secs),
    };
    let ranks = match launch {
        Some(launch) => {
            let rendezvous = match &args.rendezvous {
                Some(p) => p.clone(),
                None => launch.default_rendezvous(&args.out)?,
            };
            Ranks::Launched {
                launch,
                rendezvous,
                opts,
            }
        }
        None if devices.len() > 1 => Ranks::Threads { devices, opts },
        None => Ranks::One,
    };
    let mut run = match (&args.config, &args.preset) {
        (Some(path), _) => Some(RunConfig::from_toml_file(path)?),
        (None, _) if args.resume => None,
        (None, Some(name)) => Some(RunConfig::from_preset(name.parse::<Preset>()?)),
        (None, None) => {
            let preset = Preset::for_device(&device);
            println!("{}", chosen_preset_line(preset));
            Some(RunConfig::from_preset(preset))
        }
    };
    if let (Some(seed), Some(run)) = (args.seed, run.as_mut()) {
        run.train.seed = seed;
    } else if args.seed.is_some() {
        refuse!("--seed cannot change a resumed run (its seed is in {CONFIG_FILE})");
    }
    if let (Some(variant), Some(run)) = (args.variant, run.as_mut()) {
        run.model.variant = variant;
    } else if args.variant.is_some() {
        refuse!("--variant cannot change a resumed run (its variant is in {CONFIG_FILE})");
    }
    if !args.cull.is_off() {
        match run.as_mut() {
            Some(run) => run.train.culling = args.cull.clone(),
            None => refuse!(
                "--cull-rays/--cull-samples cannot change a resumed run (its culling is in {CONFIG_FILE})"
            ),
        }
    }
    if args.occupancy {
        match run.as_mut() {
            Some(run) => {
                run.train.occupancy.get_or_insert_with(Default::default);
            }
            None => refuse!(
                "--occupancy cannot change a resumed run (its occupancy grid settings are in {CONFIG_FILE})"
            ),
        }
    }
    let switches = [
        ("--coarse-from-grid", args.coarse_from_grid),
        ("--jitter", args.jitter),
        ("--error-map", args.error_map),
        ("--anneal", args.anneal),
        ("--pose-boost", args.pose_boost),
        ("--average", args.average),
        ("--fast", args.fast),
    ];
    if let Some((flag, _)) = switches.iter().find(|(_, on)| *on) {
        let Some(run) = run.as_mut() else {
            refuse!("{flag} cannot change a resumed run (its options are in {CONFIG_FILE})");
        };
        run.train.coarse_from_grid |= args.coarse_from_grid;
        run.train.jitter |= args.jitter;
        if args.error_map {
            run.train.error_map.get_or_insert_with(Default::default);
        }
        let budget_s = args.minutes.map(|m| m * 60.0);
        if args.anneal {
            run.train.anneal_over(budget_s);
        }
        if args.pose_boost {
            run.train.boost_pose_over(budget_s);
        }
        if args.average {
            run.train.average.get_or_insert_with(Default::default);
        }
        if args.fast {
            for c in pma_model::train::recipe::fast(run, budget_s) {
                println!("fast recipe: {} ({})", c.option, c.why);
            }
        }
    }
    let eval_data = args.eval_data.clone().or_else(|| {
        let beside = args.data.parent()?.join("novel_view.npz");
        (beside.is_file() && beside != args.data).then_some(beside)
    });
    if args.resume {
        // The run's own refusal ("nothing to resume") before anything about the data.
        pma_model::train::checkpoint::resume_point(&args.out)?;
    }
    super::check_paths(run_dir_paths(
        &args.out,
        args.resume,
        pma_data::fsio::PathCheck::new()
            .input("--data", &args.data)
            .input_opt("--config", args.config.as_deref())
            .input_opt("--eval-data", eval_data.as_deref()),
    ))?;
    let req = TrainRequest {
        data: args.data,
        out: args.out,
        run,
        resume: args.resume,
        overwrite: false,
        iters: args.iters,
        minutes: args.minutes,
        eval_data,
        chunk_rays: args.chunk_rays,
        device,
        numerics: super::numerics(),
    };
    let outcome = train(
        &req,
        &ranks,
        args.quiet,
        "pma train: held-out PSNR vs wall-clock time",
    )?;
    println!(
        "done at iteration {} ({} this session, {:.1} it/s, {} skipped); model: {}",
        outcome.iterations,
        outcome.session_iterations,
        outcome.session_iterations as f64 / (outcome.session_s - outcome.eval_s).max(1e-9),
        outcome.skipped,
        outcome.model.display()
    );
    Ok(())
}

/// The first log line of a run whose preset was chosen by device.
fn chosen_preset_line(preset: Preset) -> String {
    match preset {
        Preset::CpuSmall => format!(
            "preset {preset} (chosen for the CPU; --preset {} for the paper's network)",
            Preset::Paper
        ),
        _ => format!(
            "preset {preset} (chosen for the GPU; --preset {} for a 2-core CPU's network)",
            Preset::CpuSmall
        ),
    }
}

/// `check` with the run directory `out` as an output: the files a run writes at its top
/// (a resumed run keeps its `config.toml`).
fn run_dir_paths(
    out: &Path,
    resume: bool,
    check: pma_data::fsio::PathCheck,
) -> pma_data::fsio::PathCheck {
    use pma_model::network::run_dir::{LOCK_FILE, MODEL_FILE};
    let mut files = vec![MODEL_FILE, LOG_FILE, LOCK_FILE, PLOT_FILE];
    if !resume {
        files.push(CONFIG_FILE);
    }
    check.output_dir("--out", out, files)
}

/// Who trains a run: this process on one device, a group of threads (one rank per device),
/// or this process as one rank of a launched group.
pub enum Ranks {
    One,
    Threads {
        devices: Vec<candle_core::Device>,
        opts: GroupOptions,
    },
    Launched {
        launch: Launch,
        rendezvous: PathBuf,
        opts: GroupOptions,
    },
}

/// The longest `--group-timeout` (a day).
const MAX_GROUP_TIMEOUT_S: u64 = 86_400;

/// Run `req` on `ranks` with a progress bar (unless `quiet`, or a rank other than 0 of a
/// launched group) and the plot titled `title`. A run stopped by Ctrl-C is an
/// [`Interrupted`] error (exit status 130) that says where `--resume` continues.
pub fn train(
    req: &TrainRequest,
    ranks: &Ranks,
    quiet: bool,
    title: &str,
) -> anyhow::Result<TrainOutcome> {
    let follower = matches!(ranks, Ranks::Launched { launch, .. } if launch.rank != 0);
    let mut view = Terminal {
        quiet: quiet || follower,
        title,
        eval_label: eval_label(req),
        bar: indicatif::ProgressBar::hidden(),
    };
    let result = match ranks {
        Ranks::One => train_run(req, &mut view),
        Ranks::Threads { devices, opts } => train_group(req, devices, opts, &mut view),
        Ranks::Launched {
            launch,
            rendezvous,
            opts,
        } => launched(req, launch, rendezvous, opts, &mut view),
    };
    view.bar.finish_and_clear();
    let outcome = result?;
    if outcome.interrupted {
        return Err(anyhow::Error::new(Interrupted).context(format!(
            "interrupted at iteration {n}; the checkpoint in {dir} is complete, and \
             `pma train --resume --out {dir}` continues from iteration {n}",
            n = outcome.iterations,
            dir = req.out.display()
        )));
    }
    Ok(outcome)
}

/// One rank of a launched group: NCCL's group.
#[cfg(feature = "nccl")]
fn launched(
    req: &TrainRequest,
    launch: &Launch,
    rendezvous: &Path,
    opts: &GroupOptions,
    view: &mut Terminal,
) -> Result<TrainOutcome, pma_model::train::TrainError> {
    let engine = pma_model::train::parallel::NcclEngine {
        timeout: opts.timeout,
    };
    train_launched(req, launch, rendezvous, &engine, opts, view)
}

#[cfg(not(feature = "nccl"))]
fn launched(
    _: &TrainRequest,
    _: &Launch,
    _: &Path,
    _: &GroupOptions,
    _: &mut Terminal,
) -> Result<TrainOutcome, pma_model::train::TrainError> {
    Err(pma_model::train::TrainError::Config(
        "--distributed needs a binary built with `--features nccl` (NCCL runs the group's \
         exchanges)"
            .into(),
    ))
}

/// What the plot's held-out curve scores: the periodic evaluation renders a few images of
/// the held-out file (`eval_images`, evenly spread), not the whole split a final `pma eval`
/// or `pma demo` scores.
pub fn eval_label(req: &TrainRequest) -> String {
    let file = req
        .eval_data
        .as_ref()
        .and_then(|p| p.file_name())
        .map_or_else(String::new, |f| format!(" of {}", f.to_string_lossy()));
    match &req.run {
        Some(run) => format!(
            "held-out PSNR ({} image{}{file})",
            run.train.eval_images,
            if run.train.eval_images == 1 { "" } else { "s" }
        ),
        None => format!("held-out PSNR (the run's eval_images{file})"),
    }
}

/// The training run as the terminal shows it.
struct Terminal<'a> {
    quiet: bool,
    title: &'a str,
    eval_label: String,
    bar: indicatif::ProgressBar,
}

impl TrainObserver for Terminal<'_> {
    fn warning(&mut self, line: &str) {
        self.bar.suspend(|| eprintln!("warning: {line}"));
    }

    fn start(&mut self, iter: u64, target: u64) {
        self.bar = progress::bar_without_eta(self.quiet, target, "train");
        self.bar.set_position(iter);
    }

    fn step(&mut self, r: &StepReport) {
        self.bar.set_position(r.iter);
        let (loss, psnr) = r.ema.unwrap_or((f64::NAN, f64::NAN));
        self.bar.set_message(format!(
            "{:.2} it/s  loss {loss:.4}  train PSNR {psnr:.2} dB  ETA {}",
            r.it_per_s,
            indicatif::HumanDuration(Duration::from_secs_f64(r.eta_s.min(1e9)))
        ));
    }

    fn note(&mut self, line: &str) {
        self.bar.println(line);
    }

    fn checkpoint(&mut self, dir: &Path, log: &TrainLog) -> Result<(), ObserverError> {
        plot_psnr_vs_time(
            &log.eval_curve(),
            &self.eval_label,
            &log.train_curve(),
            self.title,
            &dir.join(PLOT_FILE),
        )
        .context("writing the PSNR plot")
        .map_err(Into::into)
    }
}
