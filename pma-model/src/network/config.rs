//! Hyper-parameters of the PM-Avatar network (docs/reference.md; presets in `presets.rs`).
//!
//! The config is stored as JSON in every checkpoint's metadata, so a checkpoint
//! always carries the shapes it was built with. Field names are snake_case
//! versions of the reference's yaml keys; the reference name is given in each
//! doc comment.

use serde::{Deserialize, Serialize};

/// What the model does where the reference has a quirk that looks like a bug.
/// Every switch defaults to the reference's behaviour (parity first).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Quirks {
    /// Reference: render-time ray directions are not normalised before the SH
    /// view encoding (training directions are). `true` normalises them.
    pub normalize_view_dirs: bool,
    /// Reference: rays that miss the bounding cylinder get the batch mean of the
    /// other rays' near/far, so a ray depends on its batch. `true` uses the
    /// ray's own fallback (`near`/`far` of the config) instead.
    pub per_ray_cylinder_fallback: bool,
    /// Reference: frame-code indices are clamped only when `idx > n` (so `idx == n`
    /// is out of range). `true` clamps `idx >= n`.
    pub fix_framecode_clamp: bool,
    /// Reference: box crossings are unsigned distances, rays through a box edge or corner
    /// ignore that box, and a cylinder behind the camera yields far < near. `true` uses
    /// signed crossings clipped at the camera, keeps edge/corner hits, and treats a cylinder
    /// behind the camera as a miss (changes only such rays; docs/numerics.md).
    pub robust_ray_bounds: bool,
}

/// Limit of every layer count of a [`Config`] (the paper's deepest, the trunk, has 8).
pub const MAX_DEPTH: usize = 32;
/// Limit of every width of a [`Config`] (the paper's widest have 256).
pub const MAX_WIDTH: usize = 2048;
/// Limit of the frame-code count (the paper's run has 780; one per training image).
pub const MAX_FRAMECODES: usize = 1_000_000;
/// Limit of the coarse and the importance samples per ray (the paper's: 48 and 24).
pub const MAX_SAMPLES: usize = 1024;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Config {
    /// Number of skeleton joints (SMPL: 24; the reference hard-codes it).
    pub n_joints: usize,
    /// Density trunk depth (`D`).
    pub trunk_depth: usize,
    /// Density trunk width (`W`).
    pub trunk_width: usize,
    /// Trunk layers after which the modulator output is concatenated again (`skips`).
    pub skips: Vec<usize>,
    /// Colour head hidden width (`view_W`).
    pub view_width: usize,
    /// GNN feature width per joint (`voxel_feat` = `graph_net.W`).
    pub gnn_width: usize,
    /// Graph-convolution layers of the GNN (`graph_net.D - graph_net.fc_D`).
    pub gnn_graph_layers: usize,
    /// Per-node linear layers of the GNN (`graph_net.fc_D`).
    pub gnn_fc_layers: usize,
    /// Output width of both point encoders (`PointEnc.dim_out`).
    pub point_enc_dim: usize,
    /// Hidden width of the feature window `WinFun`.
    pub win_hidden: usize,
    /// Hidden width of the `PoseExtractor` (`dim_hidden`).
    pub pose_extractor_hidden: usize,
    /// Number of sine layers in the `PoseExtractor` before its linear head.
    pub pose_extractor_depth: usize,
    /// Width of each modulated layer (`freq_dim`).
    pub freq_dim: usize,
    /// Number of modulated layers (`N_pm`).
    pub n_pm: usize,
    /// Sine frequency of the point branch and modulator (`sin_w0_point`).
    pub sin_w0_point: f64,
    /// Sine frequency of the pose branch, GNN and window (`sin_w0_pose`).
    pub sin_w0_pose: f64,
    /// Per-training-image latent codes in the colour head (`use_framecodes`).
    pub use_framecodes: bool,
    /// Frame-code width (`framecode_ch`).
    pub framecode_ch: usize,
    /// Number of frame codes = number of training images (`n_framecodes`).
    pub n_framecodes: usize,
    /// Degree of the spherical-harmonics view encoding (`SHEncoder`, degree² outputs).
    pub sh_degree: usize,
    /// Std of the Gaussian density noise in training mode (`density_noise_std`).
    pub density_noise_std: f64,
    /// `graph_net.base_scale` constructor argument (default half-extent).
    pub base_scale: f64,
    /// Spatial window `w^p = exp(-alpha * sum_k x_k^beta)`: alpha.
    pub window_alpha: f64,
    /// Spatial window exponent beta (6 in the reference; must be even).
    pub window_beta: u32,
    /// Zero the root joint's 6D input to the GNN (`mask_root`).
    pub mask_root: bool,
    /// Straight-through floor of the axis scales, as a fraction of the initial scale.
    pub scale_floor: f64,
    /// Coarse samples per ray (`N_samples`).
    pub n_samples: usize,
    /// Importance samples per ray (`N_importance`).
    pub n_importance: usize,
    /// Default near bound of the ray caster.
    pub near: f64,
    /// Default far bound of the ray caster.
    pub far: f64,
    /// Bone boxes are enlarged to `[-bound, bound]^3` in normalised coordinates for ray casting.
    pub box_bound: f64,
    /// Reference quirks that can be switched off.
    pub quirks: Quirks,
    /// Which parts of the model exist (the paper's ablations); omitted from checkpoint JSON
    /// for the full model.
    #[serde(skip_serializing_if = "Variant::is_full")]
    pub variant: Variant,
}

/// The paper's ablations (Sec. 5, "Ablation Study"): which branches the model keeps. A
/// variant leaves out what it does not use: those layers are neither built, computed nor
/// saved, so a checkpoint's tensors say which variant it is (and its config names it).
///
/// | variant | window w | point features into the NeRF trunk |
/// | --- | --- | --- |
/// | `full` | w^p · w^f | sine layers modulated by (γ, Φ) predicted from f^m |
/// | `only-gnn` | w^p · w^f | f^m itself (upper branch only, no sine layers) |
/// | `only-syn` | w^p | the same sine layers at a fixed frequency γ(0), no GNN features |
/// | `only-wp` | w^p | modulated sine layers |
/// | `only-wf` | w^f (max-pool without w^p) | modulated sine layers |
/// | `no-window` | 1 for every joint | modulated sine layers |
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum Variant {
    #[default]
    Full,
    OnlyGnn,
    OnlySyn,
    OnlyWp,
    OnlyWf,
    NoWindow,
}

impl Variant {
    pub const ALL: [Variant; 6] = [
        Variant::Full,
        Variant::OnlyGnn,
        Variant::OnlySyn,
        Variant::OnlyWp,
        Variant::OnlyWf,
        Variant::NoWindow,
    ];

    pub fn is_full(&self) -> bool {
        *self == Variant::Full
    }

    /// The name used in configs and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Variant::Full => "full",
            Variant::OnlyGnn => "only-gnn",
            Variant::OnlySyn => "only-syn",
            Variant::OnlyWp => "only-wp",
            Variant::OnlyWf => "only-wf",
            Variant::NoWindow => "no-window",
        }
    }

    /// Per-joint GNN features (the upper branch) exist.
    pub fn gnn_features(self) -> bool {
        self != Variant::OnlySyn
    }

    /// The spatial window w^p weighs the joints (and sample culling can use it).
    pub fn spatial_window(self) -> bool {
        !matches!(self, Variant::OnlyWf | Variant::NoWindow)
    }

    /// The learned feature window w^f weighs the joints.
    pub fn feature_window(self) -> bool {
        matches!(self, Variant::Full | Variant::OnlyGnn | Variant::OnlyWf)
    }

    /// The sine-layer synthesis branch exists (modulated or not).
    pub fn synthesis(self) -> bool {
        self != Variant::OnlyGnn
    }

    /// The synthesis branch is modulated by frequencies and phases predicted from f^m.
    pub fn modulation(self) -> bool {
        !matches!(self, Variant::OnlyGnn | Variant::OnlySyn)
    }
}

impl std::fmt::Display for Variant {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl Default for Config {
    fn default() -> Self {
        Self::paper()
    }
}

impl Config {
    /// The reference's default configuration (`configs/pm_avatar.yaml`), as used by the golden case.
    pub fn paper() -> Self {
        Self {
            n_joints: 24,
            trunk_depth: 8,
            trunk_width: 256,
            skips: vec![4],
            view_width: 128,
            gnn_width: 128,
            gnn_graph_layers: 2,
            gnn_fc_layers: 2,
            point_enc_dim: 64,
            win_hidden: 128,
            pose_extractor_hidden: 128,
            pose_extractor_depth: 3,
            freq_dim: 256,
            n_pm: 3,
            sin_w0_point: 16.0,
            sin_w0_pose: 8.0,
            use_framecodes: true,
            framecode_ch: 128,
            n_framecodes: 780,
            sh_degree: 4,
            density_noise_std: 1.0,
            base_scale: 0.5,
            window_alpha: 2.0,
            window_beta: 6,
            mask_root: true,
            scale_floor: 0.95,
            n_samples: 48,
            n_importance: 24,
            near: 0.0,
            far: 100.0,
            box_bound: 1.1,
            quirks: Quirks::default(),
            variant: Variant::Full,
        }
    }

    /// Every size of the config with its limit (see [`Config::validate`]).
    pub fn size_fields(&self) -> [(&'static str, usize, usize); 18] {
        [
            ("trunk_depth", self.trunk_depth, MAX_DEPTH),
            ("trunk_width", self.trunk_width, MAX_WIDTH),
            ("view_width", self.view_width, MAX_WIDTH),
            ("gnn_width", self.gnn_width, MAX_WIDTH),
            ("gnn_graph_layers", self.gnn_graph_layers, MAX_DEPTH),
            ("gnn_fc_layers", self.gnn_fc_layers, MAX_DEPTH),
            ("point_enc_dim", self.point_enc_dim, MAX_WIDTH),
            ("win_hidden", self.win_hidden, MAX_WIDTH),
            (
                "pose_extractor_hidden",
                self.pose_extractor_hidden,
                MAX_WIDTH,
            ),
            ("pose_extractor_depth", self.pose_extractor_depth, MAX_DEPTH),
            ("freq_dim", self.freq_dim, MAX_WIDTH),
            ("n_pm", self.n_pm, MAX_DEPTH),
            ("framecode_ch", self.framecode_ch, MAX_WIDTH),
            ("n_framecodes", self.n_framecodes, MAX_FRAMECODES),
            ("n_samples", self.n_samples, MAX_SAMPLES),
            ("n_importance", self.n_importance, MAX_SAMPLES),
            ("n_joints", self.n_joints, 24),
            ("window_beta", self.window_beta as usize, 64),
        ]
    }

    /// Width of what the NeRF trunk reads per point: the synthesis layers' concatenated
    /// outputs, or f^m for `only-gnn`.
    pub fn trunk_input_dim(&self) -> usize {
        match self.variant.synthesis() {
            true => self.n_pm * self.freq_dim,
            false => self.win_hidden,
        }
    }
}

impl Config {
    /// Reject configurations the network cannot be built for.
    pub fn validate(&self) -> Result<(), crate::error::ModelError> {
        let mut bad = Vec::new();
        // Sizes come from files (checkpoint metadata, TOML): each is bounded before anything
        // is allocated from it. The limits cover the paper's config with room.
        for (name, v, max) in self.size_fields() {
            if v > max {
                bad.push(format!("{name} = {v} is over the limit of {max}"));
            }
        }
        if self.skips.len() > self.trunk_depth.min(MAX_DEPTH) {
            bad.push(format!(
                "skips lists {} layers, more than trunk_depth {}",
                self.skips.len(),
                self.trunk_depth
            ));
        }
        if !bad.is_empty() {
            return Err(crate::error::ModelError::Config(bad.join("; ")));
        }
        if self.n_joints != 24 {
            bad.push(format!(
                "n_joints must be 24 (SMPL skeleton), found {}",
                self.n_joints
            ));
        }
        if self.window_beta == 0 || self.window_beta % 2 != 0 {
            bad.push(format!(
                "window_beta must be even and > 0, found {}",
                self.window_beta
            ));
        }
        if !(1..=4).contains(&self.sh_degree) {
            bad.push(format!(
                "sh_degree must be in 1..=4, found {}",
                self.sh_degree
            ));
        }
        if self.trunk_depth == 0 || self.skips.iter().any(|&s| s + 1 >= self.trunk_depth) {
            bad.push(format!(
                "trunk_depth must be > 0 and every skip < trunk_depth - 1, found depth {} skips {:?}",
                self.trunk_depth, self.skips
            ));
        }
        if self.n_pm == 0 {
            bad.push("n_pm must be > 0".to_string());
        }
        if self.use_framecodes && self.n_framecodes == 0 {
            bad.push("n_framecodes must be > 0 when use_framecodes is set".to_string());
        }
        if self.n_samples < 2 || self.n_importance < 2 {
            bad.push(format!(
                "n_samples and n_importance must be >= 2, found {} and {}",
                self.n_samples, self.n_importance
            ));
        }
        for (name, v) in [
            ("sin_w0_point", self.sin_w0_point),
            ("sin_w0_pose", self.sin_w0_pose),
        ] {
            if !(v.is_finite() && v > 0.0) {
                bad.push(format!("{name} must be finite and > 0, found {v}"));
            }
        }
        if bad.is_empty() {
            Ok(())
        } else {
            Err(crate::error::ModelError::Config(bad.join("; ")))
        }
    }
}
