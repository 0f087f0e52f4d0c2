//! The PM-Avatar network in candle.
//!
//! Modules follow the paper's concepts; `avatar.rs` wires them together top-down:
//!
//! | module | what |
//! | --- | --- |
//! | `skeleton` (pma-data) | SMPL joints, forward kinematics, bone alignment |
//! | `gnn` | the pose graph network over the 24 joints, box half-extents |
//! | `window` | spatial window w^p, feature window w^f |
//! | `modulator` | pose-predicted frequencies/phases, modulated sine layers |
//! | `field` | NeRF density/colour heads, frame codes |
//! | `raycast`, `bones` | near/far from cylinder and bone boxes, samples |
//! | `render` | volume rendering |
//! | `points`, `cull` | how samples reach the network; leaving work out |
//! | `params`, `checkpoint` | tensor registration and init; the file format |
//! | `eval`, `lpips` | the evaluation protocol; the LPIPS network |
//! | `train` (feature) | optimiser, losses, the training loop |

pub mod avatar;
pub mod batch;
pub mod bones;
pub mod camera_path;
pub mod checkpoint;
pub mod config;
pub mod cull;
pub mod device;
pub mod encoders;
pub mod error;
pub mod eval;
pub mod fast_sine;
pub mod field;
pub mod flops;
pub mod fused;
pub mod gnn;
pub mod host;
pub mod image;
/// The process-wide interrupt flag (see `pma_data::interrupt`).
pub use pma_data::interrupt;
pub mod libm_sine;
pub mod loss;
pub mod lpips;
pub mod mesh;
pub mod modulator;
pub mod nn;
pub mod ops;
pub mod parallel;
pub mod params;
pub mod points;
pub mod presets;
pub mod profile;
pub mod raycast;
pub mod render;
pub mod retarget;
pub mod stability;
pub mod trace;
pub mod window;

#[cfg(feature = "train")]
pub mod train;

pub use config::Config;
