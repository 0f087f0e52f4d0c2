//! `pma train`: train an avatar on a pma-npz dataset (spec model.md §5–§6).
//!
//! The run directory holds everything a run writes:
//!
//! | file | content |
//! | --- | --- |
//! | `config.toml` | the resolved run configuration (preset + overrides) |
//! | `model.safetensors` | the latest model (pma checkpoint) |
//! | `train_state.safetensors` | optimizer moments, RNG and sampler state, iteration |
//! | `log.csv` | one row per log interval (see `pma_model::train::log`) |
//! | `psnr_vs_time.png` | held-out PSNR against wall-clock time |
//!
//! Checkpoints are written every `ckpt_every` iterations, at the end, and on Ctrl-C; every
//! file is replaced atomically.

use std::path::PathBuf;

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
    /// `cpu-small` (a 2-core CPU learns in minutes) or `tiny` (tests).
    #[arg(long, default_value = "default")]
    pub preset: String,
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
    /// No progress bar (log lines only).
    #[arg(long)]
    pub quiet: bool,
    /// Compute device: cpu, cuda, cuda:N, metal (cuda/metal need a binary built with that
    /// feature).
    #[arg(long, default_value = "cpu")]
    pub device: String,
}

#[cfg(not(feature = "train"))]
pub fn run(_args: Args) -> anyhow::Result<()> {
    anyhow::bail!("this build of pma has no training support; rebuild with `--features train` (on by default)")
}

#[cfg(feature = "train")]
pub fn run(args: Args) -> anyhow::Result<()> {
    imp::run(args).map(|_| ())
}

#[cfg(feature = "train")]
pub use imp::{train_run, TrainRequest};

#[cfg(feature = "train")]
mod plot {
    use std::path::Path;

    use anyhow::Context as _;

    /// Bundled font for plot text: plotters has no fonts of its own without system libraries.
    static FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");

    /// Plot held-out PSNR (and, lighter, training PSNR) against wall-clock time and write it
    /// atomically as a PNG.
    pub fn plot_psnr_vs_time(
        eval: &[(f64, f64)],
        train: &[(f64, f64)],
        title: &str,
        path: &Path,
    ) -> anyhow::Result<()> {
        use plotters::prelude::*;

        static REGISTER: std::sync::Once = std::sync::Once::new();
        REGISTER.call_once(|| {
            // A font that fails to parse leaves text unrendered; the curves are still drawn.
            let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, FONT);
        });

        let (w, h) = (900u32, 540u32);
        let mut buf = vec![0u8; (w * h * 3) as usize];
        {
            let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
            root.fill(&WHITE)
                .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
            let finite = |v: &&(f64, f64)| v.0.is_finite() && v.1.is_finite();
            let all: Vec<(f64, f64)> = eval.iter().chain(train).filter(finite).copied().collect();
            let minutes = |s: f64| s / 60.0;
            let x_max = all
                .iter()
                .map(|p| minutes(p.0))
                .fold(0.0f64, f64::max)
                .max(1e-3)
                * 1.02;
            let (mut y_min, mut y_max) = all
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
                    (lo.min(p.1), hi.max(p.1))
                });
            if !y_min.is_finite() {
                (y_min, y_max) = (0.0, 30.0);
            }
            let pad = ((y_max - y_min) * 0.08).max(0.5);
            let mut chart = ChartBuilder::on(&root)
                .caption(title, ("sans-serif", 22))
                .margin(16)
                .x_label_area_size(44)
                .y_label_area_size(56)
                .build_cartesian_2d(0.0..x_max, (y_min - pad)..(y_max + pad))
                .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
            chart
                .configure_mesh()
                .x_desc("wall-clock time [min]")
                .y_desc("PSNR [dB]")
                .label_style(("sans-serif", 15))
                .draw()
                .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
            let train_colour = RGBColor(150, 150, 150);
            if !train.is_empty() {
                chart
                    .draw_series(LineSeries::new(
                        train.iter().filter(finite).map(|p| (minutes(p.0), p.1)),
                        train_colour.stroke_width(1),
                    ))
                    .map_err(|e| anyhow::anyhow!("plot: {e}"))?
                    .label("training batch PSNR")
                    .legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 20, y)], train_colour)
                    });
            }
            if !eval.is_empty() {
                let blue = RGBColor(31, 90, 180);
                chart
                    .draw_series(LineSeries::new(
                        eval.iter().filter(finite).map(|p| (minutes(p.0), p.1)),
                        blue.stroke_width(2),
                    ))
                    .map_err(|e| anyhow::anyhow!("plot: {e}"))?
                    .label("held-out PSNR")
                    .legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 20, y)], blue.stroke_width(2))
                    });
                chart
                    .draw_series(
                        eval.iter()
                            .filter(finite)
                            .map(|p| Circle::new((minutes(p.0), p.1), 3, blue.filled())),
                    )
                    .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
            }
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::LowerRight)
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .label_font(("sans-serif", 15))
                .draw()
                .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
            root.present().map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        }
        let img = image::RgbImage::from_raw(w, h, buf).context("plot buffer has the wrong size")?;
        super::super::eval::write_png_atomic(&img, path)
    }
}

#[cfg(feature = "train")]
pub use plot::plot_psnr_vs_time;

#[cfg(feature = "train")]
mod imp {
    use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
    use std::sync::Arc;
    use std::time::{Duration, Instant};

    use std::path::Path;

    use anyhow::{bail, Context as _};
    use candle_core::Device;
    use pma_data::dataset::Profile;
    use pma_model::train::{
        LogRow, Preset, RunConfig, StepStats, TrainError, TrainLog, Trainer, MODEL_FILE, STATE_FILE,
    };

    use super::super::eval::{evaluate, read_dataset, spread, EvalOptions};
    use super::*;

    /// File names inside a run directory.
    pub const CONFIG_FILE: &str = "config.toml";
    pub const LOG_FILE: &str = "log.csv";
    pub const PLOT_FILE: &str = "psnr_vs_time.png";

    /// What to train (the library-level form of the `pma train` flags, shared with `pma demo`).
    #[derive(Debug, Clone)]
    pub struct TrainRequest {
        pub data: PathBuf,
        pub out: PathBuf,
        /// `None`: the run directory's `config.toml` (resume) or the `default` preset.
        pub run: Option<RunConfig>,
        pub resume: bool,
        /// Start afresh even if `out` holds a run (its files are replaced); otherwise refuse.
        pub overwrite: bool,
        pub iters: Option<u64>,
        pub minutes: Option<f64>,
        /// Held-out data for the periodic evaluation (images with `eval_tag` 1 if tagged).
        pub eval_data: Option<PathBuf>,
        pub quiet: bool,
        /// Overrides `train.chunk_rays` (memory only: the step is the same).
        pub chunk_rays: Option<usize>,
        /// Plot title.
        pub title: String,
        /// Where the model trains.
        pub device: Device,
    }

    /// What a training session did.
    #[derive(Debug, Clone)]
    pub struct TrainOutcome {
        /// Completed iterations of the run (all sessions).
        pub iterations: u64,
        /// Iterations done by this session.
        pub session_iterations: u64,
        /// Wall-clock seconds of the run (all sessions), including held-out evaluations.
        pub wall_s: f64,
        /// Seconds of this session.
        pub session_s: f64,
        /// Seconds of this session spent in held-out evaluation.
        pub eval_s: f64,
        pub skipped: u64,
        pub interrupted: bool,
        pub model: PathBuf,
        #[allow(dead_code)]
        pub plot: PathBuf,
    }

    pub fn run(args: Args) -> anyhow::Result<TrainOutcome> {
        let mut run = match &args.config {
            Some(path) => Some(RunConfig::from_toml_file(path)?),
            None if args.resume => None,
            None => Some(RunConfig::from_preset(args.preset.parse::<Preset>()?)),
        };
        if let (Some(seed), Some(run)) = (args.seed, run.as_mut()) {
            run.train.seed = seed;
        } else if args.seed.is_some() {
            bail!("--seed cannot change a resumed run (its seed is in {CONFIG_FILE})");
        }
        let eval_data = args.eval_data.clone().or_else(|| {
            let beside = args.data.parent()?.join("novel_view.npz");
            (beside.is_file() && beside != args.data).then_some(beside)
        });
        let outcome = train_run(TrainRequest {
            data: args.data,
            out: args.out,
            run,
            resume: args.resume,
            overwrite: false,
            iters: args.iters,
            minutes: args.minutes,
            eval_data,
            quiet: args.quiet,
            chunk_rays: args.chunk_rays,
            title: "pma train: held-out PSNR vs wall-clock time".into(),
            device: super::super::device(&args.device)?,
        })?;
        println!(
            "{} at iteration {} ({} this session, {:.1} it/s, {} skipped); model: {}",
            if outcome.interrupted {
                "stopped"
            } else {
                "done"
            },
            outcome.iterations,
            outcome.session_iterations,
            outcome.session_iterations as f64 / (outcome.session_s - outcome.eval_s).max(1e-9),
            outcome.skipped,
            outcome.model.display()
        );
        Ok(outcome)
    }

    /// Set once per process: the first Ctrl-C asks the loop to checkpoint and stop, a second
    /// one exits at once.
    fn interrupt_flag() -> Arc<AtomicBool> {
        static FLAG: std::sync::OnceLock<Arc<AtomicBool>> = std::sync::OnceLock::new();
        FLAG.get_or_init(|| {
            let flag = Arc::new(AtomicBool::new(false));
            let presses = Arc::new(AtomicUsize::new(0));
            let f = flag.clone();
            let handler = ctrlc::set_handler(move || {
                if presses.fetch_add(1, Ordering::SeqCst) > 0 {
                    eprintln!("\nsecond Ctrl-C: exiting without a checkpoint");
                    std::process::exit(130);
                }
                eprintln!(
                    "\nCtrl-C: writing a checkpoint, then stopping (press again to exit at once)"
                );
                f.store(true, Ordering::SeqCst);
            });
            if let Err(e) = handler {
                eprintln!(
                    "warning: cannot install the Ctrl-C handler ({e}); Ctrl-C will not checkpoint"
                );
            }
            flag
        })
        .clone()
    }

    fn resolve_run(req: &TrainRequest) -> anyhow::Result<RunConfig> {
        let saved = req.out.join(CONFIG_FILE);
        let mut run = if req.resume {
            let from_dir = RunConfig::from_toml_file(&saved)
                .with_context(|| format!("--resume needs the run's {CONFIG_FILE}"))?;
            if let Some(given) = &req.run {
                let mut a = given.clone();
                let mut b = from_dir.clone();
                // Only the length of the run may change on resume (the frame-code count
                // comes from the data).
                a.train.iters = 0;
                b.train.iters = 0;
                a.train.chunk_rays = b.train.chunk_rays;
                a.model.n_framecodes = b.model.n_framecodes;
                if a != b {
                    bail!(
                        "the configuration given differs from the run's {} (beyond `iters`); a resumed run keeps its configuration",
                        saved.display()
                    );
                }
            }
            from_dir
        } else {
            req.run
                .clone()
                .unwrap_or_else(|| RunConfig::from_preset(Preset::Paper))
        };
        if let Some(n) = req.iters {
            run.train.iters = n;
        }
        if let Some(c) = req.chunk_rays {
            run.train.chunk_rays = c;
        }
        run.validate()?;
        Ok(run)
    }

    fn write_config(run: &RunConfig, path: &Path) -> anyhow::Result<()> {
        let text = format!(
            "# Resolved run configuration, written by `pma train`; `--resume` reads it back.\n{}",
            run.to_toml_string()?
        );
        super::super::eval::write_atomic(path, text.as_bytes())
    }

    struct Interval {
        loss: f64,
        psnr: f64,
        n: u64,
    }

    impl Interval {
        fn take(&mut self) -> (f64, f64) {
            let out = if self.n == 0 {
                (f64::NAN, f64::NAN)
            } else {
                (self.loss / self.n as f64, self.psnr / self.n as f64)
            };
            *self = Interval {
                loss: 0.0,
                psnr: 0.0,
                n: 0,
            };
            out
        }
    }

    /// Train until `iters` or the time budget or Ctrl-C, checkpointing as configured.
    pub fn train_run(req: TrainRequest) -> anyhow::Result<TrainOutcome> {
        let run = resolve_run(&req)?;
        let device = req.device.clone();
        if !req.resume && !req.overwrite && req.out.join(STATE_FILE).exists() {
            bail!(
                "{} already holds a run (pass --resume to continue it, or choose another --out)",
                req.out.display()
            );
        }
        let data = Arc::new(read_dataset(&req.data, Profile::Train)?);
        std::fs::create_dir_all(&req.out)
            .with_context(|| format!("creating {}", req.out.display()))?;
        let held_out = match &req.eval_data {
            Some(p) => Some(read_dataset(p, Profile::Eval)?),
            None => None,
        };
        let eval_images: Vec<usize> = match &held_out {
            Some(d) => {
                let tagged: Vec<usize> = match &d.eval_tag {
                    Some(t) if t.iter().any(|&v| v == 1) => {
                        (0..d.n_images()).filter(|&i| t[i] == 1).collect()
                    }
                    _ => (0..d.n_images()).collect(),
                };
                spread(&tagged, run.train.eval_images.max(1))
            }
            None => Vec::new(),
        };

        let mut trainer = if req.resume {
            Trainer::resume(&req.out, run.clone(), data.clone(), &device)?
        } else {
            let t = Trainer::new(run.clone(), data.clone(), &device)?;
            // Written after construction: the trainer sets the frame-code count from the data.
            write_config(t.run_config(), &req.out.join(CONFIG_FILE))?;
            t
        };
        let log_path = req.out.join(LOG_FILE);
        let plot_path = req.out.join(PLOT_FILE);
        let mut log = if req.resume {
            TrainLog::read(&log_path)?
        } else {
            TrainLog::default()
        };
        log.truncate_after(trainer.iteration());

        let cfg = run.train.clone();
        let target = cfg.iters;
        let start_iter = trainer.iteration();
        let base_wall = trainer.progress().wall_s;
        let session = Instant::now();
        let budget = req
            .minutes
            .map(|m| Duration::from_secs_f64((m * 60.0).max(0.0)));
        let stop = interrupt_flag();
        let bar = progress_bar(req.quiet, start_iter, target);
        let mut eval_s = 0.0f64;
        let mut interval = Interval {
            loss: 0.0,
            psnr: 0.0,
            n: 0,
        };
        let mut ema: Option<(f64, f64)> = None;

        let eval_opts = EvalOptions::quick(cfg.render_chunk);
        let evaluate_now =
            |trainer: &Trainer, eval_s: &mut f64| -> anyhow::Result<Option<(f64, f64)>> {
                let Some(d) = &held_out else { return Ok(None) };
                let t = Instant::now();
                let r = evaluate(
                    trainer.avatar(),
                    d,
                    "held-out",
                    &eval_images,
                    &eval_opts,
                    &mut |_, _| {},
                )?;
                *eval_s += t.elapsed().as_secs_f64();
                Ok(Some((r.psnr, r.ssim)))
            };
        let wall = |session: &Instant| base_wall + session.elapsed().as_secs_f64();

        // The curve starts at the initial model.
        if start_iter == 0 && held_out.is_some() {
            let e = evaluate_now(&trainer, &mut eval_s)?;
            log.push(LogRow {
                iter: 0,
                wall_s: wall(&session),
                loss: f64::NAN,
                train_psnr: f64::NAN,
                eval_psnr: e.map(|v| v.0),
                eval_ssim: e.map(|v| v.1),
                lr: trainer.lrs().last().copied().unwrap_or(f64::NAN),
                skipped: 0,
            });
        }

        let mut interrupted = false;
        let mut last_logged = trainer.iteration();
        let mut failure: Option<TrainError> = None;
        while trainer.iteration() < target {
            if stop.load(Ordering::SeqCst) {
                interrupted = true;
                break;
            }
            if budget.is_some_and(|b| session.elapsed() >= b) {
                break;
            }
            let stats = match trainer.step() {
                Ok(s) => s,
                Err(e @ TrainError::Diverged { .. }) => {
                    failure = Some(e);
                    break;
                }
                Err(e) => return Err(e.into()),
            };
            trainer.set_wall_s(wall(&session));
            let it = stats.iter;
            if let Some(reason) = stats.skipped {
                bar.println(format!(
                    "iteration {it}: {reason}; step skipped (weights unchanged)"
                ));
            } else {
                interval.loss += stats.loss.total;
                interval.psnr += stats.loss.psnr;
                interval.n += 1;
                ema = Some(match ema {
                    None => (stats.loss.total, stats.loss.psnr),
                    Some((l, p)) => (
                        0.9 * l + 0.1 * stats.loss.total,
                        0.9 * p + 0.1 * stats.loss.psnr,
                    ),
                });
            }
            update_bar(
                &bar, &stats, ema, &session, start_iter, target, budget, eval_s,
            );

            let eval_due = cfg.eval_every > 0 && it % cfg.eval_every == 0;
            if it % cfg.log_every == 0 || eval_due {
                let e = if eval_due {
                    evaluate_now(&trainer, &mut eval_s)?
                } else {
                    None
                };
                let (loss, psnr) = interval.take();
                log.push(LogRow {
                    iter: it,
                    wall_s: wall(&session),
                    loss,
                    train_psnr: psnr,
                    eval_psnr: e.map(|v| v.0),
                    eval_ssim: e.map(|v| v.1),
                    lr: trainer.lrs().last().copied().unwrap_or(f64::NAN),
                    skipped: trainer.progress().skipped,
                });
                last_logged = it;
                if let Some((p, s)) = e {
                    bar.println(format!(
                        "iteration {it}: held-out PSNR {p:.2} dB, SSIM {s:.4}"
                    ));
                }
                log.write(&log_path)?;
            }
            if it % cfg.ckpt_every == 0 {
                trainer.set_wall_s(wall(&session));
                trainer.save_checkpoint(&req.out)?;
                plot_psnr_vs_time(
                    &log.eval_curve(),
                    &log.train_curve(),
                    &req.title,
                    &plot_path,
                )?;
            }
        }

        // Final row (with a held-out evaluation), checkpoint, log and plot.
        let it = trainer.iteration();
        let evaluated_here = log
            .rows
            .last()
            .is_some_and(|r| r.iter == it && r.eval_psnr.is_some());
        if failure.is_none() && !evaluated_here && (it > last_logged || held_out.is_some()) {
            let e = evaluate_now(&trainer, &mut eval_s)?;
            let (loss, psnr) = interval.take();
            log.push(LogRow {
                iter: it,
                wall_s: wall(&session),
                loss,
                train_psnr: psnr,
                eval_psnr: e.map(|v| v.0),
                eval_ssim: e.map(|v| v.1),
                lr: trainer.lrs().last().copied().unwrap_or(f64::NAN),
                skipped: trainer.progress().skipped,
            });
        }
        trainer.set_wall_s(wall(&session));
        trainer.save_checkpoint(&req.out)?;
        log.write(&log_path)?;
        plot_psnr_vs_time(
            &log.eval_curve(),
            &log.train_curve(),
            &req.title,
            &plot_path,
        )?;
        bar.finish_and_clear();
        if let Some(e) = failure {
            return Err(e).context(format!(
                "training stopped; checkpoint of iteration {it} written to {}",
                req.out.display()
            ));
        }
        if interrupted {
            eprintln!(
                "interrupted at iteration {it}; continue with `pma train --resume --out {}`",
                req.out.display()
            );
        }
        Ok(TrainOutcome {
            iterations: it,
            session_iterations: it - start_iter,
            wall_s: wall(&session),
            session_s: session.elapsed().as_secs_f64(),
            eval_s,
            skipped: trainer.progress().skipped,
            interrupted,
            model: req.out.join(MODEL_FILE),
            plot: plot_path,
        })
    }

    fn progress_bar(quiet: bool, pos: u64, len: u64) -> indicatif::ProgressBar {
        if quiet {
            return indicatif::ProgressBar::hidden();
        }
        let bar = indicatif::ProgressBar::new(len);
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "[{elapsed_precise}] {bar:30} {pos}/{len} {msg}",
            )
            .expect("static template")
            .progress_chars("=> "),
        );
        bar.set_position(pos);
        bar
    }

    #[allow(clippy::too_many_arguments)]
    fn update_bar(
        bar: &indicatif::ProgressBar,
        stats: &StepStats,
        ema: Option<(f64, f64)>,
        session: &Instant,
        start_iter: u64,
        target: u64,
        budget: Option<Duration>,
        eval_s: f64,
    ) {
        bar.set_position(stats.iter);
        let elapsed = session.elapsed().as_secs_f64();
        let done = (stats.iter - start_iter) as f64;
        let rate = done / (elapsed - eval_s).max(1e-9);
        let mut eta = (target - stats.iter) as f64 / rate.max(1e-9);
        if let Some(b) = budget {
            eta = eta.min((b.as_secs_f64() - elapsed).max(0.0));
        }
        let (loss, psnr) = ema.unwrap_or((f64::NAN, f64::NAN));
        bar.set_message(format!(
            "{rate:.2} it/s  loss {loss:.4}  train PSNR {psnr:.2} dB  ETA {}",
            indicatif::HumanDuration(Duration::from_secs_f64(eta.min(1e9)))
        ));
    }
}
