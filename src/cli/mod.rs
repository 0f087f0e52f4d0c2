//! One module per subcommand: clap `Args` plus `run`.

pub mod convert;
pub mod demo;
pub mod eval;
pub mod forward;
pub mod inspect;
pub mod mesh;
pub mod render;
pub mod synth;
pub mod train;
