//! Training (feature `train`): the reference's optimisation (see `docs/reference.md`,
//! "Training schedule and Adam") and the files a run writes.
//!
//! * [`account`]: one training step under step accounting (launches, syncs, uploads, bytes).
//! * [`adam`]: Adam with parameter groups, the lr schedule, global-norm clipping.
//! * [`average`]: averaged weights, the model a run with `[train.average]` saves and scores.
//! * [`batch`]: what a step consumes ([`TrainBatch`]) and where it comes from ([`BatchSource`]).
//! * [`state`]: the train-state file (optimizer moments, RNG, sampler, iteration).
//! * `log`: `log.csv`.
//! * [`source`]: training batches from a dataset (see `docs/conventions.md`, "Ray sampler").
//! * [`trainer`]: one training step (forward, loss, backward, clip, Adam, schedule), run in
//!   chunks of rays with gradient accumulation when the batch is large, non-finite steps
//!   skipped on the device, numbers read back every few steps.
//! * [`checkpoint`]: checkpoints written as transactions into a run directory, `--resume`'s
//!   starting point, the one rule of what a resumed run may change
//!   ([`RunConfig::check_resume`]).
//! * [`lock`]: one writer per run directory.
//! * [`parallel`]: data-parallel training on a group of devices (NCCL on GPUs, threads on
//!   the CPU as its test double).
//! * [`recipe`]: the fast recipe, the options that reach a held-out quality sooner, in one
//!   switch.
//! * [`run`]: a whole training run (run directory, loop, held-out evaluation schedule,
//!   checkpoints, interruption), reporting to a [`TrainObserver`].
//!
//! The inference path of the crate does not depend on anything here.

pub mod account;
pub mod adam;
pub mod average;
pub mod batch;
pub mod checkpoint;
mod error;
pub mod lock;
pub mod log;
pub mod loss;
pub mod parallel;
pub mod presets;
pub mod recipe;
pub mod run;
pub mod source;
pub mod state;
pub mod trainer;

pub use adam::{decayed_lr, Adam, ParamGroup, ParamState};
pub use batch::{BatchSource, FixedBatch, TrainBatch};
pub use log::{LogRow, TrainLog};
pub use pma_data::metrics::psnr_from_mse;
pub use run::{
    train_run, Silent, StepReport, TrainObserver, TrainOutcome, TrainRequest, CONFIG_FILE,
    LOG_FILE, MAX_MINUTES,
};
pub use source::DatasetSource;
pub use state::{Progress, RngState, TrainState};
pub use trainer::*;

pub use error::{write_atomic, ObserverError, TrainError};
pub use presets::{Preset, RunConfig, TrainConfig};
