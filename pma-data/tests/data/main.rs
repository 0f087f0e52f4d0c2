//! pma-data integration tests, linked as one test binary: each binary links candle, and one per file
//! filled a CI disk. Files stay one module per concern; filter with `cargo test -p pma-data --test data sampler::`.

mod dataset;
mod golden_rays;
mod metrics;
mod motion;
mod sampler;
mod skeleton;
mod support;
mod synth;
