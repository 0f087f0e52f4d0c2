//! Checkpoints of a run directory, written as transactions and read back for `--resume`.
//!
//! The layout and the reader's side are [`crate::network::run_dir`]'s. Writing a checkpoint
//! of iteration N ([`save`]):
//!
//! 1. `ckpt-N.tmp/` receives `model.safetensors`, `train_state.safetensors` (tied to the
//!    model by its fingerprint), `config.toml` and `log.csv`; each file is synced, then the
//!    directory;
//! 2. the directory is renamed to `ckpt-N/` and the run directory synced: this rename is the
//!    commit, and until it the previous complete checkpoint is the newest;
//! 3. `RUN/model.safetensors` is replaced by a hard link to the new model (a copy where the
//!    filesystem has no hard links), renamed into place;
//! 4. checkpoints older than the previous one are removed, with a train state left at the
//!    top of the run by an older layout.
//!
//! A crash or a failed write (a full disk) at any point leaves the previous complete
//! checkpoint in place; [`clean_stale`] removes what a crash left behind (`*.tmp`
//! directories and the atomic writer's `.pma-*.tmp` files), and `--resume` starts from
//! [`verified_resume_point`], the newest complete checkpoint whose files read back.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use candle_core::Device;
use pma_data::dataset::Dataset;

use super::batch::BatchSource;
use super::error::{read_err, write_atomic, write_err, TrainError};
use super::log::TrainLog;
use super::presets::RunConfig;
use super::state::{fingerprint, TrainState};
use super::trainer::Trainer;
use crate::network::checkpoint::MAX_CHECKPOINT_BYTES;
use crate::network::run_dir::{
    self, CheckpointDir, CKPT_PREFIX, CONFIG_FILE, LOG_FILE, MODEL_FILE, STATE_FILE, TMP_SUFFIX,
};
use crate::render::Avatar;

/// How many complete checkpoints a run keeps (the newest and the one before it).
pub const KEEP: usize = 2;

/// Where a resumed run starts: the newest complete checkpoint, or a model and train state
/// at the top of the run directory (a run from before checkpoint directories, or a
/// converted reference checkpoint put there by hand).
#[derive(Debug, Clone)]
pub struct ResumePoint {
    pub model: PathBuf,
    pub state: PathBuf,
    /// The run configuration saved with it.
    pub config: PathBuf,
    /// The log up to its iteration (`None`: the run's `log.csv`, cut at the iteration).
    pub log: Option<PathBuf>,
    /// Newer checkpoints passed over by [`verified_resume_point`], newest first, each with
    /// why it does not verify.
    pub skipped: Vec<(PathBuf, String)>,
}

impl ResumePoint {
    fn of_checkpoint(run: &Path, c: &CheckpointDir) -> ResumePoint {
        let config = if c.config().is_file() {
            c.config()
        } else {
            run.join(CONFIG_FILE)
        };
        ResumePoint {
            model: c.model(),
            state: c.state(),
            config,
            log: c.log().is_file().then(|| c.log()),
            skipped: Vec::new(),
        }
    }

    /// Whether every file of this point reads back: the train state loads, the model is the
    /// one it was saved with (its fingerprint; a model without one must load), and the
    /// config and the log, where there are, parse. A file truncated or corrupted after the
    /// commit (a disk error) fails here; the reason is one line naming the file.
    pub fn verify(&self) -> Result<(), String> {
        let line = |e: TrainError| pma_data::error::one_line(&e.to_string());
        let state = TrainState::load(&self.state, &Device::Cpu).map_err(line)?;
        let bytes = read_back(&self.model).map_err(line)?;
        if state.model_fingerprint.is_some() {
            check_model(self, &state, &bytes)?;
        } else {
            Avatar::load(&self.model, &Device::Cpu).map_err(|e| line(e.into()))?;
        }
        if self.config.is_file() {
            RunConfig::from_toml_file(&self.config).map_err(line)?;
        }
        if let Some(log) = &self.log {
            TrainLog::read(log).map_err(line)?;
        }
        Ok(())
    }
}

/// The newest complete checkpoint of `run` (see [`ResumePoint`]), by its files' presence
/// alone: cheap, and what a reader without the run's lock may ask.
/// [`verified_resume_point`] is where a resumed run starts.
pub fn resume_point(run: &Path) -> Result<ResumePoint, TrainError> {
    let newest = run_dir::newest_checkpoint(run).map_err(read_err(run))?;
    if let Some(c) = newest {
        return Ok(ResumePoint::of_checkpoint(run, &c));
    }
    flat_point(run)
}

/// A run directory with a model and train state at its top and no checkpoint directory.
fn flat_point(run: &Path) -> Result<ResumePoint, TrainError> {
    let (model, state) = (run.join(MODEL_FILE), run.join(STATE_FILE));
    if model.is_file() && state.is_file() {
        return Ok(ResumePoint {
            model,
            state,
            config: run.join(CONFIG_FILE),
            log: None,
            skipped: Vec::new(),
        });
    }
    Err(TrainError::Resume {
        dir: run.to_path_buf(),
        reason: format!(
            "no complete checkpoint to continue (a {CKPT_PREFIX}*/ directory, or {MODEL_FILE}, {STATE_FILE} and {CONFIG_FILE} in it)"
        ),
    })
}

/// Where a resumed run of `run` starts: the newest complete checkpoint that
/// [verifies](ResumePoint::verify). A newer one that does not (its model or train state
/// truncated or corrupted after its commit) is passed over and listed in
/// [`ResumePoint::skipped`]; the previous checkpoint is kept for exactly this. When none
/// verifies, the run is refused with each one's reason. Call it holding the run's lock.
pub fn verified_resume_point(run: &Path) -> Result<ResumePoint, TrainError> {
    let all = run_dir::checkpoints(run).map_err(pma_data::FileError::reading(run))?;
    let refuse = |reason: String| TrainError::Resume {
        dir: run.to_path_buf(),
        reason,
    };
    if all.is_empty() {
        let point = flat_point(run)?;
        point.verify().map_err(refuse)?;
        return Ok(point);
    }
    let mut skipped = Vec::new();
    for c in all.iter().rev() {
        let point = ResumePoint::of_checkpoint(run, c);
        match point.verify() {
            Ok(()) => return Ok(ResumePoint { skipped, ..point }),
            Err(why) => skipped.push((c.path.clone(), why)),
        }
    }
    let reasons: Vec<String> = skipped
        .iter()
        .map(|(dir, why)| format!("{} ({why})", dir.display()))
        .collect();
    Err(refuse(format!(
        "no complete checkpoint reads back: {}",
        reasons.join("; ")
    )))
}

/// Refuse a model whose bytes are not the ones `state` was saved with.
fn check_model(point: &ResumePoint, state: &TrainState, bytes: &[u8]) -> Result<(), String> {
    match &state.model_fingerprint {
        Some(fp) if *fp != fingerprint(bytes) => Err(format!(
            "{} does not belong to {} (truncated, corrupt, or from another checkpoint)",
            point.model.display(),
            point.state.display()
        )),
        _ => Ok(()),
    }
}

/// Whether `run` holds a run (a complete checkpoint, or a train state of an older layout).
pub fn holds_run(run: &Path) -> bool {
    run_dir::newest_checkpoint(run).is_ok_and(|c| c.is_some()) || run.join(STATE_FILE).is_file()
}

/// Remove what an interrupted checkpoint or write left in `run`: `ckpt-*.tmp` directories
/// and the atomic writer's temporary files (`.pma-*.tmp`, and `.tmp*` of older versions). Call it only while holding the
/// run's lock ([`super::lock::RunLock`]): another writer's temporaries would go too.
pub fn clean_stale(run: &Path) -> Result<Vec<PathBuf>, TrainError> {
    let mut removed = Vec::new();
    let entries = match std::fs::read_dir(run) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(removed),
        Err(source) => return Err(write_err(run)(source)),
    };
    for entry in entries {
        let entry = entry.map_err(write_err(run))?;
        let name = entry.file_name();
        let Some(name) = name.to_str() else { continue };
        let path = entry.path();
        let stale_dir = name.starts_with(CKPT_PREFIX) && name.ends_with(TMP_SUFFIX);
        // `.tmpXXXXXX`: the temporary files of pma versions before `.pma-*.tmp`.
        let stale_file =
            (name.starts_with(".pma-") && name.ends_with(TMP_SUFFIX)) || name.starts_with(".tmp");
        if stale_dir && path.is_dir() {
            std::fs::remove_dir_all(&path).map_err(write_err(&path))?;
            removed.push(path);
        } else if stale_file && path.is_file() {
            std::fs::remove_file(&path).map_err(write_err(&path))?;
            removed.push(path);
        }
    }
    if !removed.is_empty() {
        pma_data::fsio::sync_dir(run).map_err(write_err(run))?;
    }
    Ok(removed)
}

/// Write a checkpoint of `trainer` (and `log`, the rows up to its iteration) into `run` as
/// one transaction (see the module docs); returns the new checkpoint.
pub fn save(
    run: &Path,
    trainer: &Trainer,
    log: Option<&TrainLog>,
) -> Result<CheckpointDir, TrainError> {
    let iteration = trainer.iteration();
    let existing = run_dir::checkpoints(run).map_err(read_err(run))?;
    let seq = existing
        .iter()
        .filter(|c| c.iteration == iteration)
        .map(|c| c.seq + 1)
        .max()
        .unwrap_or(0);
    let name = CheckpointDir::name(iteration, seq);
    let tmp = run.join(format!("{name}{TMP_SUFFIX}"));
    let done = CheckpointDir {
        path: run.join(&name),
        iteration,
        seq,
    };
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).map_err(write_err(&tmp))?;
    }
    std::fs::create_dir(&tmp).map_err(write_err(&tmp))?;
    if let Err(e) = fill(&tmp, trainer, log) {
        let _ = std::fs::remove_dir_all(&tmp);
        return Err(e);
    }
    let commit = pma_data::fsio::sync_dir(&tmp)
        .and_then(|()| std::fs::rename(&tmp, &done.path))
        .and_then(|()| pma_data::fsio::sync_dir(run));
    if let Err(e) = commit {
        let _ = std::fs::remove_dir_all(&tmp);
        return Err(write_err(&done.path)(e));
    }
    publish_model(run, &done)?;
    prune(run, &done)?;
    Ok(done)
}

/// The checkpoint's files, each written atomically into the temporary directory.
fn fill(dir: &Path, trainer: &Trainer, log: Option<&TrainLog>) -> Result<(), TrainError> {
    let model = dir.join(MODEL_FILE);
    // The run's model: the averaged weights where the run averages them.
    trainer.with_model(|a| a.save(&model).map_err(TrainError::from))?;
    let bytes = read_back(&model)?;
    trainer
        .train_state(fingerprint(&bytes))?
        .save(&dir.join(STATE_FILE))?;
    write_config(trainer.run_config(), &dir.join(CONFIG_FILE))?;
    if let Some(log) = log {
        log.write(&dir.join(LOG_FILE))?;
    }
    Ok(())
}

fn read_back(path: &Path) -> Result<Vec<u8>, TrainError> {
    pma_data::fsio::read_input(path, MAX_CHECKPOINT_BYTES).map_err(read_err(path))
}

/// Replace `RUN/model.safetensors` with the checkpoint's model: a hard link (a copy where
/// the filesystem has none) under a temporary name, renamed into place.
fn publish_model(run: &Path, ckpt: &CheckpointDir) -> Result<(), TrainError> {
    let target = run.join(MODEL_FILE);
    let tmp = run.join(format!(".pma-publish-{}{TMP_SUFFIX}", std::process::id()));
    let _ = std::fs::remove_file(&tmp);
    let linked = std::fs::hard_link(ckpt.model(), &tmp);
    let result = match linked {
        Ok(()) => std::fs::rename(&tmp, &target).and_then(|()| pma_data::fsio::sync_dir(run)),
        Err(_) => {
            let bytes = read_back(&ckpt.model())?;
            pma_data::fsio::write_atomic(&target, &bytes)
        }
    };
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result.map_err(write_err(&target))
}

/// Remove the complete checkpoints older than the newest [`KEEP`], and a top-level train
/// state of an older layout (it belongs to a model no longer published).
fn prune(run: &Path, newest: &CheckpointDir) -> Result<(), TrainError> {
    let all = run_dir::checkpoints(run).map_err(read_err(run))?;
    let keep_from = all.len().saturating_sub(KEEP);
    for c in &all[..keep_from] {
        if c.path != newest.path {
            std::fs::remove_dir_all(&c.path).map_err(write_err(&c.path))?;
        }
    }
    let flat_state = run.join(STATE_FILE);
    if flat_state.is_file() {
        std::fs::remove_file(&flat_state).map_err(write_err(&flat_state))?;
    }
    pma_data::fsio::sync_dir(run).map_err(write_err(run))
}

/// The resolved run configuration as `config.toml`.
pub(crate) fn write_config(run: &RunConfig, path: &Path) -> Result<(), TrainError> {
    let text = format!(
        "# Resolved run configuration, written by `pma train`; `--resume` reads it back.\n{}",
        run.to_toml_string()?
    );
    write_atomic(path, text.as_bytes())
}

/// Remove every checkpoint of `run` (a fresh run replacing an old one).
pub fn remove_all(run: &Path) -> Result<(), TrainError> {
    for c in run_dir::checkpoints(run).map_err(read_err(run))? {
        std::fs::remove_dir_all(&c.path).map_err(write_err(&c.path))?;
    }
    for f in [STATE_FILE, MODEL_FILE] {
        let p = run.join(f);
        if p.is_file() {
            std::fs::remove_file(&p).map_err(write_err(&p))?;
        }
    }
    Ok(())
}

impl Trainer {
    /// Write a checkpoint of this trainer into the run directory `dir` (see [`save`]);
    /// the run's log is not part of it.
    pub fn save_checkpoint(&self, dir: &Path) -> Result<(), TrainError> {
        save(dir, self, None).map(|_| ())
    }

    /// Continue the run saved in `dir` (its newest complete checkpoint that verifies,
    /// [`verified_resume_point`]) with batches from `source` (built exactly as for the
    /// original run; its position is restored from the state). `run` may differ from the
    /// saved configuration only as [`RunConfig::check_resume`] allows.
    pub fn resume_with_source(
        dir: &Path,
        run: RunConfig,
        source: Box<dyn BatchSource>,
        device: &Device,
    ) -> Result<Self, TrainError> {
        let point = verified_resume_point(dir)?;
        Self::resume_from(dir, &point, run, source, device)
    }

    /// Continue the run in `dir` on the same `data` (see [`Self::resume_with_source`]).
    pub fn resume(
        dir: &Path,
        run: RunConfig,
        data: Arc<Dataset>,
        device: &Device,
    ) -> Result<Self, TrainError> {
        Self::resume_at(dir, &verified_resume_point(dir)?, run, data, device)
    }

    /// Continue the run in `dir` from `point` (see [`verified_resume_point`]) on the same
    /// `data` it was trained on.
    pub fn resume_at(
        dir: &Path,
        point: &ResumePoint,
        mut run: RunConfig,
        data: Arc<Dataset>,
        device: &Device,
    ) -> Result<Self, TrainError> {
        run.model.n_framecodes = data.n_images();
        let source = Self::dataset_source(&run, data, device)?;
        Self::resume_from(dir, point, run, source, device)
    }

    /// [`Self::resume_with_source`] from a given [`ResumePoint`] of the run in `dir`.
    pub fn resume_from(
        dir: &Path,
        point: &ResumePoint,
        run: RunConfig,
        source: Box<dyn BatchSource>,
        device: &Device,
    ) -> Result<Self, TrainError> {
        let fail = |reason: String| TrainError::Resume {
            dir: dir.to_path_buf(),
            reason,
        };
        let state = TrainState::load(&point.state, device)?;
        if let Some(saved) = &state.run_config {
            let saved: RunConfig = serde_json::from_value(saved.clone())
                .map_err(|e| fail(format!("the saved run config is unreadable: {e}")))?;
            saved.check_resume(&run).map_err(fail)?;
        }
        check_model(point, &state, &read_back(&point.model)?).map_err(fail)?;
        let avatar = Avatar::load(&point.model, device)?.with_numerics(run.numerics);
        let mut trainer = Self::with_source(run, avatar, source)?;
        trainer.restore(state)?;
        Ok(trainer)
    }
}
