//! Named configurations.
//!
//! * `default` ([`Config::paper`] + `TrainConfig::paper`): the reference's sizes, 3072 rays
//!   from 16 images per step, 48 + 24 samples per ray. Meant for a GPU workstation.
//! * `cpu-small` ([`Config::cpu_small`] + `TrainConfig::cpu_small`): the same architecture
//!   with narrow widths, fewer rays and fewer samples, sized so that a 2-core CPU does a few
//!   iterations per second and the synthetic figure becomes recognisable within ~10 minutes.
//! * `tiny` ([`Config::tiny`] + `TrainConfig::tiny`): smaller still; for tests and CI only.
//!
//! Training runs can also read a TOML file that names a preset and overrides single fields
//! (`pma_model::train::RunConfig::from_toml_str`, `train` feature):
//!
//! ```toml
//! preset = "cpu-small"
//! [model]
//! trunk_width = 96
//! [train]
//! rays_per_step = 1024
//! ```

use super::config::Config;

impl Config {
    /// Narrow widths for CPU training (see the module docs). Every module of the paper's
    /// architecture is kept; widths and sample counts shrink. The per-joint tensors
    /// ([points, 24, width]: point encoders, window) dominate the cost on a CPU, so those
    /// widths shrink most.
    pub fn cpu_small() -> Self {
        Self {
            trunk_depth: 6,
            trunk_width: 64,
            skips: vec![3],
            view_width: 32,
            gnn_width: 16,
            point_enc_dim: 8,
            win_hidden: 16,
            pose_extractor_hidden: 16,
            pose_extractor_depth: 2,
            freq_dim: 64,
            n_pm: 2,
            framecode_ch: 16,
            // 16 + 8 samples instead of 48 + 24: the ray bounds come from the bone boxes, so
            // the samples already concentrate on the body; halving them halves the step time.
            n_samples: 16,
            n_importance: 8,
            ..Self::paper()
        }
    }

    /// Smallest useful network: for tests (overfit, resume, NaN skip) that must run in seconds.
    pub fn tiny() -> Self {
        Self {
            trunk_depth: 3,
            trunk_width: 32,
            skips: vec![0],
            view_width: 16,
            gnn_width: 8,
            point_enc_dim: 4,
            win_hidden: 8,
            pose_extractor_hidden: 8,
            pose_extractor_depth: 1,
            freq_dim: 32,
            n_pm: 2,
            framecode_ch: 8,
            n_samples: 8,
            n_importance: 4,
            ..Self::paper()
        }
    }
}
