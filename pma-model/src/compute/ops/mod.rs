//! pma's custom ops, one folder each: the op's API and routes (`mod.rs`), its CPU code
//! (`cpu.rs`, where the CPU has one), its device code (`device.rs`: the launches, shared by
//! a GPU and the emulated grid), its CUDA source (`*.cu`), the host build of that source
//! (`emu.c`), and its check against candle's ops (`check.rs`). They stand on
//! [`crate::compute::kernel`], which imports none of them.
//!
//! | op | what |
//! | --- | --- |
//! | [`linear`] | a linear layer as one op; with its ReLU or sine on a device (`bias_act.cu`) |
//! | [`window_pool`] | the feature window's max-pool, of a product computed inside it |
//! | [`film_sine`] | the modulator's FiLM-sine layers, sharing one head gradient |
//! | [`sine_linear`] | the point encoders' SIREN layer on x̄, scaled by the window |
//! | [`rows`] | row gathers whose backward is parallel on a GPU |
//! | [`adam`] | one Adam update over every parameter at once |
//!
//! A new op is a new folder like these, and a line in [`MODULES`].

pub mod adam;
pub mod film_sine;
pub mod linear;
pub mod rows;
pub mod sine_linear;
pub mod window_pool;

#[cfg(test)]
pub(crate) mod testing;

use crate::compute::kernel::Module;

/// Every op's kernel module (`pma doctor` checks them all).
pub static MODULES: [&Module; 6] = [
    &linear::MODULE,
    &window_pool::MODULE,
    &film_sine::MODULE,
    &sine_linear::MODULE,
    &rows::MODULE,
    &adam::MODULE,
];
