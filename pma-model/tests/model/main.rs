//! pma-model integration tests, linked as one test binary: each binary links candle, and one per file
//! filled a CI disk. Files stay one module per concern; filter with `cargo test -p pma-model --test model golden::`.

#[path = "../common/mod.rs"]
mod common;
#[cfg(feature = "train")]
#[path = "../train_support/mod.rs"]
mod train_support;

mod account;
mod camera_path;
mod checkpoint;
mod cuda_coverage;
mod cuda_route;
mod culling;
mod early_stop;
mod golden;
mod grad;
mod image_render;
mod layers;
mod lpips;
mod mesh;
mod numerics;
mod occupancy;
mod overfit_tiny;
mod raycast_device;
mod raycast_golden;
mod raycast_props;
mod render_golden;
mod render_props;
mod resume_exact;
mod retarget;
mod spectrum;
mod stability_gradcheck;
mod stability_model;
mod stability_precision;
mod stability_raycast;
mod stability_render;
mod stability_train;
mod train_chunked;
mod train_culling;
mod train_data_parallel;
mod train_nan_skip;
mod train_parity;
mod variants;
