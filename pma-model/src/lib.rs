//! The PM-Avatar (Song, Wandt, Rhodin, ICLR 2024) in candle.
//!
//! The folders are the layers of the model, each depending only on those below it:
//!
//! ```text
//! bench/  doctor/              what `pma bench` measures, a device's self-test (feature `train`)
//! train/  eval/  tools/        training, scoring, meshes and probes   (use a whole Avatar)
//!        render/               rays → samples → network → pixels      (the Avatar)
//!        network/              the network on points                  (everything with weights)
//!        compute/              kernels, workers, device, accounting   (knows no paper)
//! ```
//!
//! | module | what |
//! | --- | --- |
//! | [`compute`] | fused CPU kernels, the libm sine, row ops, workers, host copies, device, profile, FLOPs |
//! | [`network`] | config, parameters, checkpoints; GNN, windows, modulated sine layers, NeRF heads |
//! | [`render`] | bone boxes, ray casting, culling, sample routes, volume rendering, [`Avatar`], images, camera paths |
//! | [`eval`] | the evaluation protocol: PSNR/SSIM/LPIPS, frequency spectra, splits |
//! | [`tools`] | meshes, stability probes, retargeting, render planning (poses, cameras, frames, GIF) |
//! | [`train`] (feature `train`) | presets, loss, Adam, one step, the training run |
//! | [`bench`] (feature `train`) | speed, memory and quality of each speed option against parity; step accounting |
//! | [`doctor`] (feature `train`) | a device's self-test: kernels, the golden case, a training burst |
//! | [`error`] | the crate's error type |
//!
//! The skeleton (SMPL joints, forward kinematics, bone alignment) lives in `pma_data`.

pub mod compute;
pub mod error;
pub mod eval;
/// The process-wide interrupt flag (see `pma_data::interrupt`).
pub use pma_data::interrupt;
pub mod network;
pub mod render;
pub mod tools;

#[cfg(feature = "train")]
pub mod bench;
#[cfg(feature = "train")]
pub mod doctor;
#[cfg(feature = "train")]
pub mod train;

pub use network::config::Config;
pub use render::Avatar;
