//! The PM-Avatar network in candle.
//!
//! Modules follow the paper's concepts; `avatar.rs` wires them together top-down.

pub mod avatar;
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
pub mod fused;
pub mod gnn;
pub mod image;
pub mod loss;
pub mod mesh;
pub mod modulator;
pub mod nn;
pub mod parallel;
pub mod presets;
pub mod raycast;
pub mod render;
pub mod retarget;
pub mod stability;
pub mod window;

#[cfg(feature = "train")]
pub mod train;

pub use config::Config;
