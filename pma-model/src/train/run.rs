//! A whole training run: resolve the configuration, train until the iteration target, the
//! time budget or an interruption, evaluate on held-out data on schedule, and keep the run
//! directory current.
//!
//! The run directory holds everything a run writes (layout: [`crate::network::run_dir`]):
//! `config.toml` (the resolved run configuration), `log.csv` (one row per log interval, see
//! [`super::log`]), the checkpoints `ckpt-<iteration>/` (model, train state, config and log
//! up to that iteration, each written as one transaction by [`super::checkpoint`]) and
//! `model.safetensors`, the newest complete checkpoint's model. One process writes a run
//! directory at a time ([`super::lock`]); a resumed run starts from the newest complete
//! checkpoint after removing what an interrupted one left behind.
//!
//! Checkpoints are written every `ckpt_every` iterations, at the end, and when the
//! interrupt flag ([`crate::interrupt`]) is raised. The
//! flag is polled inside a step (between chunks of rays) and inside held-out evaluations
//! (between chunks of pixels), so an interruption takes effect within one chunk's time:
//! a step cut short is undone (see [`Trainer::step`]) and the checkpoint is that of the
//! last complete step, without the final held-out evaluation. Progress, notes and
//! checkpoints are reported to a [`TrainObserver`], which is how a front end draws a
//! progress bar or plots the log; this module prints nothing (but `PMA_PROFILE=1`'s
//! per-step line, [`crate::compute::profile`]) and installs no signal handler.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use candle_core::Device;
use pma_data::dataset::{Dataset, Profile};

use super::checkpoint::{self, ResumePoint};
use super::error::{write_err, ObserverError, TrainError};
use super::lock::RunLock;
use super::log::{LogRow, TrainLog};
use super::parallel::group::Vote;
use super::trainer::{StepStats, Trainer, MODEL_FILE};
use crate::eval::{evaluate, held_out_images, read_dataset, spread, EvalOptions};
use crate::train::presets::{Preset, RunConfig};

pub use crate::network::run_dir::{CONFIG_FILE, LOG_FILE};

/// The longest time budget (`minutes`) a session accepts: about two years.
pub const MAX_MINUTES: f64 = 1e6;

/// What to train.
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
    /// Overrides `train.chunk_rays` (memory only: the step is the same).
    pub chunk_rays: Option<usize>,
    /// Where the model trains.
    pub device: Device,
    /// How the network computes (not part of the run's configuration: a resumed run may
    /// change it).
    pub numerics: crate::compute::numerics::Numerics,
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
    /// The interrupt flag stopped the session; `iterations` is the checkpoint's iteration,
    /// where a resumed run continues.
    pub interrupted: bool,
    pub model: PathBuf,
}

/// Progress after one step.
#[derive(Debug, Clone)]
pub struct StepReport<'a> {
    /// The iteration just completed.
    pub iter: u64,
    /// The steps whose numbers reached the host with this one (oldest first; empty between
    /// read-backs, see [`crate::train::TrainConfig::read_every`]).
    pub stats: &'a [StepStats],
    /// The run's iteration target.
    pub target: u64,
    /// Iterations per second of this session, held-out evaluations excluded.
    pub it_per_s: f64,
    /// Seconds to the target or to the end of the time budget, whichever comes first.
    pub eta_s: f64,
    /// Exponential moving averages of the loss and the training PSNR (`None` before the
    /// first finite step has been read back).
    pub ema: Option<(f64, f64)>,
}

/// What a front end hears from [`train_run`]. Every method has a do-nothing default.
pub trait TrainObserver {
    /// A dataset or evaluation warning (names the file).
    fn warning(&mut self, _line: &str) {}
    /// Before the first step: the iteration the session starts from and the target.
    fn start(&mut self, _iter: u64, _target: u64) {}
    fn step(&mut self, _report: &StepReport) {}
    /// A line for the user (a skipped step, a held-out score).
    fn note(&mut self, _line: &str) {}
    /// After each checkpoint, with the log as written.
    fn checkpoint(&mut self, _dir: &Path, _log: &TrainLog) -> Result<(), ObserverError> {
        Ok(())
    }
}

/// An observer that ignores everything.
pub struct Silent;

impl TrainObserver for Silent {}

/// Mean loss and training PSNR over a log interval.
#[derive(Default)]
struct Interval {
    loss: f64,
    psnr: f64,
    n: u64,
}

impl Interval {
    fn add(&mut self, stats: &StepStats) {
        self.loss += stats.loss.total;
        self.psnr += stats.loss.psnr;
        self.n += 1;
    }

    fn take(&mut self) -> (f64, f64) {
        let out = if self.n == 0 {
            (f64::NAN, f64::NAN)
        } else {
            (self.loss / self.n as f64, self.psnr / self.n as f64)
        };
        *self = Interval::default();
        out
    }
}

/// The held-out data a run scores itself on, and the images it scores.
pub(crate) struct HeldOut {
    data: Dataset,
    images: Vec<usize>,
    opts: EvalOptions,
}

/// Train until `iters`, the time budget or an interruption ([`crate::interrupt`]),
/// checkpointing as configured. An interruption before the trainer exists returns the
/// error (nothing was written); after that the session ends with a checkpoint and
/// `TrainOutcome::interrupted`.
pub fn train_run(
    req: &TrainRequest,
    observer: &mut dyn TrainObserver,
) -> Result<TrainOutcome, TrainError> {
    if let Some(m) = req.minutes {
        if !(m.is_finite() && m > 0.0 && m <= MAX_MINUTES) {
            return Err(TrainError::Config(format!(
                "minutes must be finite and in (0, {MAX_MINUTES}], found {}",
                pma_data::error::short_number(m)
            )));
        }
    }
    pma_data::fsio::create_dir_all(&req.out).map_err(write_err(&req.out))?;
    // Held until the session ends: one writer per run directory.
    let lock = RunLock::acquire(&req.out)?;
    match start(req, observer) {
        Ok(mut session) => session.run(),
        Err(e) => {
            // Refused before writing anything: the lock file goes if this run made it.
            lock.remove();
            Err(e)
        }
    }
}

/// Everything before the first step, holding the run's lock: the resume point, the
/// configuration, the data and the trainer.
fn start<'a>(
    req: &TrainRequest,
    observer: &'a mut dyn TrainObserver,
) -> Result<Session<'a>, TrainError> {
    let mut prepared = prepare(req, observer, Role::Writer)?;
    let trainer = prepared.trainer(req, &req.device)?;
    prepared.session(req, trainer, observer)
}

/// Who a session is in a data-parallel group: the one writer (rank 0, or a run on one
/// device), or a rank that trains along and writes nothing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Role {
    Writer,
    Follower,
}

/// What a session starts from, before its trainer exists.
pub(crate) struct Prepared {
    role: Role,
    point: Option<ResumePoint>,
    pub(crate) run: RunConfig,
    pub(crate) data: Arc<Dataset>,
    held_out: Option<HeldOut>,
}

/// The resume point, the configuration, the data and the held-out data of `req`. The
/// writer also clears what an interrupted checkpoint left and refuses to replace a run
/// (it holds the lock); a follower only reads, after the writer prepared.
pub(crate) fn prepare(
    req: &TrainRequest,
    observer: &mut dyn TrainObserver,
    role: Role,
) -> Result<Prepared, TrainError> {
    let writer = role == Role::Writer;
    let point = if req.resume {
        if writer {
            let removed = checkpoint::clean_stale(&req.out)?;
            if !removed.is_empty() {
                observer.note(&format!(
                    "removed {} temporary file(s) of an interrupted checkpoint",
                    removed.len()
                ));
            }
        }
        let point = checkpoint::verified_resume_point(&req.out)?;
        for (dir, why) in &point.skipped {
            observer.warning(&format!(
                "{}: skipped, it does not read back ({why}); resuming from {}",
                dir.display(),
                pma_data::fsio::parent_dir(&point.model).display()
            ));
        }
        Some(point)
    } else {
        None
    };
    let run = resolve_run(req, point.as_ref())?;
    if writer && !req.resume && checkpoint::holds_run(&req.out) {
        if !req.overwrite {
            return Err(TrainError::RunExists(req.out.clone()));
        }
        checkpoint::remove_all(&req.out)?;
    }
    let data = Arc::new(read_warned(&req.data, Profile::Train, observer)?);
    let held_out = match (&req.eval_data, role) {
        (Some(p), Role::Writer) => {
            let data = read_warned(p, Profile::Eval, observer)?;
            let images = spread(&held_out_images(&data), run.train.eval_images.max(1));
            Some(HeldOut {
                data,
                images,
                opts: EvalOptions::quick(run.train.render_chunk),
            })
        }
        _ => None,
    };
    if writer && !req.resume {
        checkpoint::clean_stale(&req.out)?;
    }
    Ok(Prepared {
        role,
        point,
        run,
        data,
        held_out,
    })
}

impl Prepared {
    /// The same preparation for another rank of the group: it writes nothing.
    pub(crate) fn follower(&self) -> Self {
        Self {
            role: Role::Follower,
            point: self.point.clone(),
            run: self.run.clone(),
            data: self.data.clone(),
            held_out: None,
        }
    }

    /// A trainer on `device`: resumed from the resume point, or fresh (the writer then
    /// writes the run's configuration: the trainer sets the frame-code count from the data).
    pub(crate) fn trainer(
        &self,
        req: &TrainRequest,
        device: &Device,
    ) -> Result<Trainer, TrainError> {
        if let Some(point) = &self.point {
            return Trainer::resume_at(
                &req.out,
                point,
                self.run.clone(),
                self.data.clone(),
                device,
            );
        }
        let mut t = Trainer::new(self.run.clone(), self.data.clone(), device)?;
        let noise = self.run.model.density_noise_std;
        if noise == 0.0 && t.density_closed()? {
            return Err(TrainError::Config(format!(
                "[model] density_noise_std = {noise}: the initial network gives every sample of \
                 the first batch zero density, so no gradient can reach it and the run would \
                 stay empty; keep the density noise (the reference trains with 1.0)"
            )));
        }
        if self.role == Role::Writer {
            checkpoint::write_config(t.run_config(), &req.out.join(CONFIG_FILE))?;
        }
        Ok(t)
    }

    /// The session of `trainer`, with the log the run has so far.
    pub(crate) fn session<'a>(
        &mut self,
        req: &TrainRequest,
        trainer: Trainer,
        observer: &'a mut dyn TrainObserver,
    ) -> Result<Session<'a>, TrainError> {
        let mut log = match self.point.as_ref() {
            Some(ResumePoint { log: Some(p), .. }) => TrainLog::read(p)?,
            Some(_) => TrainLog::read(&req.out.join(LOG_FILE))?,
            None => TrainLog::default(),
        };
        log.truncate_after(trainer.iteration());
        let resumed_at = (trainer.iteration(), log.rows.len());
        let held_out = self.held_out.take();
        let mut session = Session::new(req, self.run.clone(), trainer, log, held_out, observer);
        session.writer = self.role == Role::Writer;
        if req.resume {
            session.saved = Some(resumed_at);
        }
        Ok(session)
    }
}

fn read_warned(
    path: &Path,
    profile: Profile,
    observer: &mut dyn TrainObserver,
) -> Result<Dataset, TrainError> {
    let data = read_dataset(path, profile)?;
    for w in &data.warnings {
        observer.warning(&format!("{}: {w}", path.display()));
    }
    Ok(data)
}

/// The run's configuration: the request's, or on resume the checkpoint's (which the request
/// may change only as [`RunConfig::check_resume`] allows).
fn resolve_run(req: &TrainRequest, point: Option<&ResumePoint>) -> Result<RunConfig, TrainError> {
    let mut run = match point {
        Some(point) => {
            let resume_error = |reason: String| TrainError::Resume {
                dir: req.out.clone(),
                reason,
            };
            let saved = RunConfig::from_toml_file(&point.config).map_err(|e| {
                resume_error(format!(
                    "it needs the run's {CONFIG_FILE}: {}",
                    pma_data::error::one_line(&e.to_string())
                ))
            })?;
            if let Some(given) = &req.run {
                let mut given = given.clone();
                // The frame-code count comes from the data (the trainer checks it), not
                // from a preset or TOML.
                given.model.n_framecodes = saved.model.n_framecodes;
                saved.check_resume(&given).map_err(resume_error)?;
            }
            saved
        }
        None => req
            .run
            .clone()
            .unwrap_or_else(|| RunConfig::from_preset(Preset::Paper)),
    };
    if let Some(n) = req.iters {
        run.train.iters = n;
    }
    if let Some(c) = req.chunk_rays {
        run.train.chunk_rays = c;
    }
    run.numerics = req.numerics;
    run.validate()?;
    Ok(run)
}

/// One invocation's state while the loop runs.
pub(crate) struct Session<'a> {
    out: PathBuf,
    run: RunConfig,
    trainer: Trainer,
    log: TrainLog,
    held_out: Option<HeldOut>,
    observer: &'a mut dyn TrainObserver,
    start_iter: u64,
    base_wall: f64,
    clock: Instant,
    budget: Option<Duration>,
    eval_s: f64,
    interval: Interval,
    ema: Option<(f64, f64)>,
    /// (iteration, log rows) of the checkpoint on disk, if this session knows it: a
    /// checkpoint of the same state is not written twice.
    saved: Option<(u64, usize)>,
    /// This session writes the run directory (log, evaluations, checkpoints); the other
    /// ranks of a data-parallel group train along and write nothing.
    writer: bool,
}

impl<'a> Session<'a> {
    fn new(
        req: &TrainRequest,
        run: RunConfig,
        trainer: Trainer,
        log: TrainLog,
        held_out: Option<HeldOut>,
        observer: &'a mut dyn TrainObserver,
    ) -> Self {
        Self {
            out: req.out.clone(),
            start_iter: trainer.iteration(),
            base_wall: trainer.progress().wall_s,
            clock: Instant::now(),
            budget: req
                .minutes
                .map(|m| Duration::from_secs_f64((m * 60.0).clamp(0.0, MAX_MINUTES * 60.0))),
            run,
            trainer,
            log,
            held_out,
            observer,
            eval_s: 0.0,
            interval: Interval::default(),
            ema: None,
            saved: None,
            writer: true,
        }
    }

    pub(crate) fn run(&mut self) -> Result<TrainOutcome, TrainError> {
        let target = self.run.train.iters;
        self.observer.start(self.start_iter, target);
        let mut interrupted = false;
        // The curve starts at the initial model.
        if self.start_iter == 0 && self.held_out.is_some() {
            match self.evaluate_now() {
                Ok(e) => {
                    let row = self.row(0, (f64::NAN, f64::NAN), e);
                    self.log.push(LogRow { skipped: 0, ..row });
                }
                Err(e) if e.is_interrupted() => interrupted = true,
                Err(e) => return Err(e),
            }
        }
        let mut last_logged = self.trainer.iteration();
        let mut failure = None;
        while !interrupted && self.trainer.iteration() < target {
            let spent = self.budget.is_some_and(|b| self.clock.elapsed() >= b);
            if self.trainer.group().is_some() {
                // A group stops only where every rank stops: after the step whose numbers
                // brought a vote to stop, as they all read it back at the same iteration.
                if let Some(stop) = self.trainer.group_stop() {
                    if let Some(sig) = stop.signal {
                        if !crate::interrupt::requested() {
                            crate::interrupt::request_by(sig);
                        }
                        interrupted = true;
                    }
                    break;
                }
                let signal = match crate::interrupt::requested() {
                    true => crate::interrupt::signal().max(1),
                    false => 0,
                };
                self.trainer.set_vote(Vote {
                    signal,
                    budget: spent,
                });
            } else {
                if crate::interrupt::requested() {
                    interrupted = true;
                    break;
                }
                if spent {
                    break;
                }
            }
            let mut stats = match self.trainer.step() {
                Ok(s) => s,
                Err(e) if e.is_interrupted() => {
                    interrupted = true;
                    break;
                }
                Err(e @ TrainError::Diverged { .. }) => {
                    failure = Some(e);
                    break;
                }
                Err(e) => return Err(e),
            };
            for line in self.trainer.take_notes() {
                self.observer.warning(&line);
            }
            let it = self.trainer.iteration();
            self.trainer.set_wall_s(self.wall());
            crate::compute::profile::print_step(it);
            // A log row, an evaluation or a checkpoint needs every step's numbers.
            if self.due(it) {
                match self.trainer.read_back() {
                    Ok(more) => stats.extend(more),
                    Err(e @ TrainError::Diverged { .. }) => {
                        failure = Some(e);
                        break;
                    }
                    Err(e) => return Err(e),
                }
            }
            self.record_numbers(&stats);
            self.report(it, &stats, target);
            match self.after_step(it) {
                Ok(logged) => {
                    if logged {
                        last_logged = it;
                    }
                }
                // The step is complete; only its held-out score is missing.
                Err(e) if e.is_interrupted() => {
                    interrupted = true;
                    break;
                }
                Err(e) => return Err(e),
            }
        }
        // Completed steps whose numbers are still on the device.
        match self.trainer.read_back() {
            Ok(rest) => self.record_numbers(&rest),
            Err(e @ TrainError::Diverged { .. }) => failure = failure.or(Some(e)),
            Err(e) => return Err(e),
        }
        self.finish(last_logged, failure, interrupted)
    }

    fn wall(&self) -> f64 {
        self.base_wall + self.clock.elapsed().as_secs_f64()
    }

    /// Held-out (PSNR, SSIM, LPIPS) now, if the run has held-out data.
    fn evaluate_now(&mut self) -> Result<Option<(f64, f64, f64)>, TrainError> {
        let Some(h) = &self.held_out else {
            return Ok(None);
        };
        let t = Instant::now();
        let r = self.trainer.with_model(|a| {
            evaluate(a, &h.data, "held-out", &h.images, &h.opts, &mut |_, _| {})
                .map_err(TrainError::from)
        })?;
        for n in &r.empty_masks {
            self.observer.warning(&format!(
                "{}: image {n} has an empty mask; skipped",
                h.data.source
            ));
        }
        self.eval_s += t.elapsed().as_secs_f64();
        Ok(Some((r.psnr, r.ssim, r.lpips)))
    }

    /// A log row at `iter` with the interval means and an optional held-out score.
    fn row(&self, iter: u64, (loss, psnr): (f64, f64), e: Option<(f64, f64, f64)>) -> LogRow {
        LogRow {
            iter,
            wall_s: self.wall(),
            loss,
            train_psnr: psnr,
            eval_psnr: e.map(|v| v.0),
            eval_ssim: e.map(|v| v.1),
            eval_lpips: e.map(|v| v.2).filter(|v| !v.is_nan()),
            lr: self.trainer.lrs().last().copied().unwrap_or(f64::NAN),
            skipped: self.trainer.progress().skipped,
        }
    }

    /// Whether step `it` ends with a log row, an evaluation or a checkpoint.
    fn due(&self, it: u64) -> bool {
        let cfg = &self.run.train;
        it % cfg.log_every == 0
            || it % cfg.ckpt_every == 0
            || (cfg.eval_every > 0 && it % cfg.eval_every == 0)
    }

    /// Account for the steps whose numbers arrived: skipped steps are noted, the others
    /// enter the interval means and the moving averages.
    fn record_numbers(&mut self, arrived: &[StepStats]) {
        for stats in arrived {
            if let Some(reason) = &stats.skipped {
                self.observer.note(&format!(
                    "iteration {}: {reason}; step skipped (weights unchanged)",
                    stats.iter
                ));
                continue;
            }
            self.interval.add(stats);
            self.ema = Some(match self.ema {
                None => (stats.loss.total, stats.loss.psnr),
                Some((l, p)) => (
                    0.9 * l + 0.1 * stats.loss.total,
                    0.9 * p + 0.1 * stats.loss.psnr,
                ),
            });
        }
    }

    /// Report the progress after step `it`.
    fn report(&mut self, it: u64, arrived: &[StepStats], target: u64) {
        let elapsed = self.clock.elapsed().as_secs_f64();
        let done = (it - self.start_iter) as f64;
        let it_per_s = done / (elapsed - self.eval_s).max(1e-9);
        let mut eta_s = (target - it) as f64 / it_per_s.max(1e-9);
        if let Some(b) = self.budget {
            eta_s = eta_s.min((b.as_secs_f64() - elapsed).max(0.0));
        }
        self.observer.step(&StepReport {
            iter: it,
            stats: arrived,
            target,
            it_per_s,
            eta_s,
            ema: self.ema,
        });
    }

    /// Log, evaluate and checkpoint as scheduled after step `it`; true if a row was logged.
    fn after_step(&mut self, it: u64) -> Result<bool, TrainError> {
        if !self.writer {
            return Ok(false);
        }
        let cfg = &self.run.train;
        let (log_every, ckpt_every) = (cfg.log_every, cfg.ckpt_every);
        let eval_due = cfg.eval_every > 0 && it % cfg.eval_every == 0;
        let logged = it % log_every == 0 || eval_due;
        if logged {
            let e = if eval_due { self.evaluate_now()? } else { None };
            let means = self.interval.take();
            self.log.push(self.row(it, means, e));
            if let Some((p, s, l)) = e {
                let lpips = if l.is_nan() {
                    String::new()
                } else {
                    format!(", LPIPS {l:.4}")
                };
                self.observer.note(&format!(
                    "iteration {it}: held-out PSNR {p:.2} dB, SSIM {s:.4}{lpips}"
                ));
            }
            self.log.write(&self.out.join(LOG_FILE))?;
        }
        if it % ckpt_every == 0 {
            self.trainer.set_wall_s(self.wall());
            checkpoint::save(&self.out, &self.trainer, Some(&self.log))?;
            self.saved = Some((it, self.log.rows.len()));
            self.observer
                .checkpoint(&self.out, &self.log)
                .map_err(TrainError::Observer)?;
        }
        Ok(logged)
    }

    /// Final row (with a held-out evaluation unless interrupted), checkpoint and log.
    fn finish(
        &mut self,
        last_logged: u64,
        failure: Option<TrainError>,
        interrupted: bool,
    ) -> Result<TrainOutcome, TrainError> {
        let it = self.trainer.iteration();
        if !self.writer {
            return match failure {
                Some(e) => Err(e),
                None => Ok(self.outcome(interrupted)),
            };
        }
        let evaluated_here = self
            .log
            .rows
            .last()
            .is_some_and(|r| r.iter == it && r.eval_psnr.is_some());
        let evaluate = self.held_out.is_some() && !interrupted;
        if failure.is_none() && !evaluated_here && (it > last_logged || evaluate) {
            let e = if interrupted {
                None
            } else {
                self.evaluate_now()?
            };
            let means = self.interval.take();
            self.log.push(self.row(it, means, e));
        }
        self.trainer.set_wall_s(self.wall());
        self.log.write(&self.out.join(LOG_FILE))?;
        if self.saved != Some((it, self.log.rows.len())) {
            checkpoint::save(&self.out, &self.trainer, Some(&self.log))?;
        }
        self.observer
            .checkpoint(&self.out, &self.log)
            .map_err(TrainError::Observer)?;
        if let Some(e) = failure {
            return Err(TrainError::Stopped {
                iter: it,
                dir: self.out.clone(),
                source: Box::new(e),
            });
        }
        Ok(self.outcome(interrupted))
    }

    fn outcome(&self, interrupted: bool) -> TrainOutcome {
        let it = self.trainer.iteration();
        TrainOutcome {
            iterations: it,
            session_iterations: it - self.start_iter,
            wall_s: self.wall(),
            session_s: self.clock.elapsed().as_secs_f64(),
            eval_s: self.eval_s,
            skipped: self.trainer.progress().skipped,
            interrupted,
            model: self.out.join(MODEL_FILE),
        }
    }
}
