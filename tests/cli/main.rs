//! End-to-end tests of the `pma` binary, linked as one test binary: each binary links candle, and one per file
//! filled a CI disk. Files stay one module per concern; filter with `cargo test --test cli train::`.

mod cdp;
mod run;

mod ablate;
mod bench;
mod check_stability;
mod convert;
mod data_parallel;
mod demo;
mod devices;
mod doctor;
mod eval;
mod exit_codes;
mod faults;
mod forward;
mod inspect;
mod mesh;
mod metrics;
mod occupancy;
mod render;
mod synth;
mod train;
mod view;
