//! pma-convert integration tests (the peak-RSS tests keep their own process), linked as one test binary: each binary links candle, and one per file
//! filled a CI disk. Files stay one module per concern; filter with `cargo test -p pma-convert --test convert motion::`.

mod support;

mod capture;
mod checkpoint;
mod dataset_errors;
mod dataset_h5;
mod fuzz_readers;
mod motion;
mod resume_reference;
mod torch_reader;
