//! One module per subcommand: clap `Args` plus `run`.

pub mod bench;
pub mod check_stability;
pub mod convert;
pub mod demo;
pub mod eval;
pub mod forward;
pub mod inspect;
pub mod mesh;
pub mod render;
pub mod synth;
pub mod train;

/// Open the compute device named by a `--device` flag: cpu, cuda, cuda:N, metal or metal:N.
/// A backend missing from this build is reported with the cargo feature that brings it.
pub fn device(spec: &str) -> anyhow::Result<candle_core::Device> {
    Ok(pma_model::device::parse_device(spec)?)
}
