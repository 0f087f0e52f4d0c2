//! A training run's directory as a reader sees it, and the newest complete model in it.
//!
//! `pma train --out RUN` keeps RUN a transaction: a checkpoint (model, train state, config
//! and log up to its iteration) appears all at once or not at all, and the previous complete
//! one stays until the new one is complete.
//!
//! ```text
//! RUN/
//!   ckpt-00000250/           a complete checkpoint (the newest two are kept):
//!     model.safetensors        the model
//!     train_state.safetensors  optimizer moments, RNG and sampler positions, iteration
//!     config.toml              the resolved run configuration
//!     log.csv                  the log up to this iteration
//!   ckpt-00000500.tmp/       a checkpoint being written (or left by a crash): never read
//!   model.safetensors        the newest complete checkpoint's model, published after it
//!   config.toml  log.csv     the run's configuration and its log as training goes
//!   .lock                    held by the `pma train` writing the run (with its PID)
//! ```
//!
//! A checkpoint is written into `ckpt-<iteration>.tmp/` (every file synced), renamed to
//! `ckpt-<iteration>/` (the directory synced): the rename is the commit. Only then is
//! `model.safetensors` replaced (a hard link to the checkpoint's model, renamed into place)
//! and older checkpoints removed. A second checkpoint of the same iteration (a session that
//! ended where the last one did) is `ckpt-<iteration>-<k>/`, ordered after it.
//!
//! A reader that wants the newest model, also while a run is writing it, calls
//! [`newest_model`] (or [`load_newest`], which also loads it); tools accept a run directory
//! wherever they take a model ([`resolve_model`]).

use std::path::{Path, PathBuf};

use candle_core::Device;

use super::checkpoint::{self, Checkpoint, LoadOptions};
use crate::error::{ModelError, Result};
use pma_data::FileError;

/// The model file of a checkpoint, and the run's published model.
pub const MODEL_FILE: &str = "model.safetensors";
/// The train-state file of a checkpoint.
pub const STATE_FILE: &str = "train_state.safetensors";
/// The resolved run configuration (in each checkpoint and at the top of the run).
pub const CONFIG_FILE: &str = "config.toml";
/// The training log (in each checkpoint, up to its iteration, and at the top of the run).
pub const LOG_FILE: &str = "log.csv";
/// The lock file of the writing `pma train`.
pub const LOCK_FILE: &str = ".lock";
/// Name prefix of checkpoint directories.
pub const CKPT_PREFIX: &str = "ckpt-";
/// Name suffix of a checkpoint directory being written.
pub const TMP_SUFFIX: &str = ".tmp";

/// A complete checkpoint directory of a run.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CheckpointDir {
    pub path: PathBuf,
    /// Completed training iterations.
    pub iteration: u64,
    /// 0 for the first checkpoint of an iteration, k for `ckpt-<iteration>-<k>`.
    pub seq: u32,
}

impl CheckpointDir {
    pub fn model(&self) -> PathBuf {
        self.path.join(MODEL_FILE)
    }

    pub fn state(&self) -> PathBuf {
        self.path.join(STATE_FILE)
    }

    pub fn config(&self) -> PathBuf {
        self.path.join(CONFIG_FILE)
    }

    pub fn log(&self) -> PathBuf {
        self.path.join(LOG_FILE)
    }

    /// The directory name for `iteration` and `seq`.
    pub fn name(iteration: u64, seq: u32) -> String {
        match seq {
            0 => format!("{CKPT_PREFIX}{iteration:08}"),
            k => format!("{CKPT_PREFIX}{iteration:08}-{k}"),
        }
    }

    /// (iteration, seq) of a complete checkpoint's directory name; `None` for anything else
    /// (a `.tmp` directory included).
    pub fn parse_name(name: &str) -> Option<(u64, u32)> {
        let rest = name.strip_prefix(CKPT_PREFIX)?;
        let (it, seq) = match rest.split_once('-') {
            Some((it, k)) => (it, k.parse().ok().filter(|&k| k > 0)?),
            None => (rest, 0),
        };
        if it.is_empty() || !it.bytes().all(|b| b.is_ascii_digit()) {
            return None;
        }
        Some((it.parse().ok()?, seq))
    }
}

/// The complete checkpoints of `run`, oldest first. A directory counts when its name is a
/// checkpoint's (not `.tmp`) and it holds both the model and the train state.
pub fn checkpoints(run: &Path) -> std::io::Result<Vec<CheckpointDir>> {
    let mut out = Vec::new();
    let entries = match std::fs::read_dir(run) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(out),
        Err(e) => return Err(e),
    };
    for entry in entries {
        let entry = entry?;
        let name = entry.file_name();
        let Some((iteration, seq)) = name.to_str().and_then(CheckpointDir::parse_name) else {
            continue;
        };
        let c = CheckpointDir {
            path: entry.path(),
            iteration,
            seq,
        };
        if c.model().is_file() && c.state().is_file() {
            out.push(c);
        }
    }
    out.sort_by_key(|c| (c.iteration, c.seq));
    Ok(out)
}

/// The newest complete checkpoint of `run`, if any.
pub fn newest_checkpoint(run: &Path) -> std::io::Result<Option<CheckpointDir>> {
    Ok(checkpoints(run)?.pop())
}

/// The newest complete model of the run directory `run`: the newest complete checkpoint's
/// model, or `RUN/model.safetensors` in a run written before checkpoint directories (or
/// assembled by hand). The file may be removed once two newer checkpoints are complete;
/// a reader that then gets "not found" asks again ([`load_newest`] does).
pub fn newest_model(run: &Path) -> Result<PathBuf> {
    if let Some(c) = newest_checkpoint(run).map_err(FileError::reading(run))? {
        return Ok(c.model());
    }
    let flat = run.join(MODEL_FILE);
    if flat.is_file() {
        return Ok(flat);
    }
    Err(ModelError::Input(format!(
        "{} holds no complete model (no {CKPT_PREFIX}* checkpoint with {MODEL_FILE}, no {MODEL_FILE})",
        run.display()
    )))
}

/// `path` itself if it is a file, the [`newest_model`] of it if it is a directory.
pub fn resolve_model(path: &Path) -> Result<PathBuf> {
    if path.is_dir() {
        newest_model(path)
    } else {
        Ok(path.to_path_buf())
    }
}

/// Load the [`newest_model`] of `run` (or the model file `run` names), asking again when a
/// concurrent `pma train` removed the checkpoint between finding and reading it.
pub fn load_newest(
    run: &Path,
    device: &Device,
    opts: &LoadOptions,
) -> Result<(PathBuf, Checkpoint)> {
    let mut tries = 0;
    loop {
        let path = resolve_model(run)?;
        match checkpoint::load_with(&path, device, opts) {
            Err(ModelError::File(FileError::Read { source, .. }))
                if source.kind() == std::io::ErrorKind::NotFound && tries < 3 && path != run =>
            {
                tries += 1;
            }
            r => return r.map(|c| (path, c)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_temporaries_are_not_checkpoints() {
        assert_eq!(CheckpointDir::name(250, 0), "ckpt-00000250");
        assert_eq!(CheckpointDir::name(250, 2), "ckpt-00000250-2");
        assert_eq!(CheckpointDir::parse_name("ckpt-00000250"), Some((250, 0)));
        assert_eq!(CheckpointDir::parse_name("ckpt-00000250-2"), Some((250, 2)));
        for bad in [
            "ckpt-00000250.tmp",
            "ckpt-00000250-2.tmp",
            "ckpt-",
            "ckpt-12a",
            "ckpt-1-0",
            "model.safetensors",
        ] {
            assert_eq!(CheckpointDir::parse_name(bad), None, "{bad}");
        }
    }

    #[test]
    fn newest_complete_checkpoint_wins() {
        let dir = tempfile::tempdir().unwrap();
        let run = dir.path();
        let make = |name: &str, files: &[&str]| {
            let d = run.join(name);
            std::fs::create_dir_all(&d).unwrap();
            for f in files {
                std::fs::write(d.join(f), b"x").unwrap();
            }
        };
        assert!(newest_model(run).is_err());
        std::fs::write(run.join(MODEL_FILE), b"flat").unwrap();
        assert_eq!(newest_model(run).unwrap(), run.join(MODEL_FILE));
        make("ckpt-00000010", &[MODEL_FILE, STATE_FILE]);
        make("ckpt-00000020", &[MODEL_FILE, STATE_FILE]);
        make("ckpt-00000020-1", &[MODEL_FILE, STATE_FILE]);
        // Newer, but not complete: a temporary, and one without its state.
        make("ckpt-00000030.tmp", &[MODEL_FILE, STATE_FILE]);
        make("ckpt-00000040", &[MODEL_FILE]);
        let newest = newest_checkpoint(run).unwrap().unwrap();
        assert_eq!((newest.iteration, newest.seq), (20, 1));
        assert_eq!(
            newest_model(run).unwrap(),
            run.join("ckpt-00000020-1").join(MODEL_FILE)
        );
        assert_eq!(resolve_model(run).unwrap(), newest.model());
        let file = run.join("x.safetensors");
        assert_eq!(resolve_model(&file).unwrap(), file);
    }
}
