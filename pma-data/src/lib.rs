//! pma data layer: the SMPL skeleton and its kinematics, cameras and rays,
//! `pma-npz v1` datasets (read, validate, write), the training ray sampler,
//! image metrics, real motion readers and the synthetic multi-view scene.

// Index loops over the 24 joints mirror the written formulas; nested result tuples are
// local plumbing.
#![allow(clippy::needless_range_loop, clippy::type_complexity)]

pub mod camera;
pub mod cylinder;
pub mod dataset;
pub mod error;
pub mod error_map;
pub mod fsio;
pub mod interrupt;
pub mod metrics;
pub mod motion;
pub mod sampler;
pub mod skeleton;
pub mod synth;

pub use error::{DataError, ErrorKind, ExitKind, FileError};
