//! What one pass may leave out, chosen per pass (all off = parity), and what it did.
//!
//! [`PassOptions`] is an argument of every forward pass and image render; the avatar holds no
//! switch. [`PassStats`] comes back with each pass's outputs.

use serde::{Deserialize, Serialize};

use crate::error::{ModelError, Result};
use crate::network::config::Config;

/// What culled samples are given (see [`Culling`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
pub enum SampleFill {
    /// The network's own output there: where w^p = 0 for every joint, every windowed feature
    /// is 0 and the network reduces to a global constant density and a colour that depends
    /// only on the view. It is evaluated once per ray at a far-away point (or, in inference
    /// when that density is 0, once per pass), so culling at threshold 0 is exact.
    #[default]
    Network,
    /// Density 0 and black: cheapest, exact only where the network learned empty space.
    Zero,
}

/// Leaving work out by the bone boxes and the spatial window (docs/numerics.md, "Empty rays
/// and culling"). Everything is off by default, which is parity with the reference. With the
/// `cli` feature it is also the `--cull-rays`, `--cull-samples T` and `--cull-fill` flags.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::Args))]
#[serde(default, deny_unknown_fields)]
pub struct Culling {
    /// Rays that cross no (enlarged) bone box skip the network: raw outputs 0, so the
    /// render is exactly the background with zero weights, acc, depth and disparity.
    #[cfg_attr(
        feature = "cli",
        arg(
            long = "cull-rays",
            help = "Rays that cross no bone box get the background without running the network"
        )
    )]
    pub rays: bool,
    /// Samples whose spatial window w^p is <= this for every joint skip the network and get
    /// `sample_fill`. `Some(0.0)` culls only exact zeros (exact with `SampleFill::Network`);
    /// `None` is off.
    #[cfg_attr(
        feature = "cli",
        arg(
            long = "cull-samples",
            value_name = "T",
            help = "Samples whose spatial window is <= T for every joint skip the network \
                    (0 = only exact zeros, which leaves the image unchanged)"
        )
    )]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sample_threshold: Option<f64>,
    #[cfg_attr(
        feature = "cli",
        arg(
            long = "cull-fill",
            value_enum,
            default_value = "network",
            help = "What culled samples get: `network` (the network's far-away constant) or `zero`"
        )
    )]
    pub sample_fill: SampleFill,
}

impl Culling {
    pub fn is_off(&self) -> bool {
        !self.rays && self.sample_threshold.is_none()
    }

    /// What is wrong with these settings for a model of `cfg`: a threshold outside [0, 1),
    /// or one for a variant without the spatial window.
    pub fn problem(&self, cfg: &Config) -> Option<String> {
        let t = self.sample_threshold?;
        if !(t.is_finite() && (0.0..1.0).contains(&t)) {
            return Some(format!(
                "culling: the sample threshold must be in [0, 1), found {t}"
            ));
        }
        if !cfg.variant.spatial_window() {
            return Some(format!(
                "culling: the sample threshold needs the spatial window, which variant `{}` \
                 does not use",
                cfg.variant
            ));
        }
        None
    }
}

/// The per-pass choices of a forward pass or an image render. The default is parity.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::Args))]
#[serde(default, deny_unknown_fields)]
pub struct PassOptions {
    #[cfg_attr(feature = "cli", command(flatten))]
    pub culling: Culling,
    /// Samples whose cell is empty in the occupancy grid of every joint whose window is above
    /// the culling threshold (0 without `--cull-samples`) skip the network, like samples
    /// outside every window ([`crate::network::occupancy`]). Needs a model with a grid.
    #[cfg_attr(
        feature = "cli",
        arg(
            long = "occupancy",
            help = "Samples in empty cells of the model's occupancy grid skip the network \
                    (the model needs a grid: `pma train --occupancy` or `pma occupancy build`)"
        )
    )]
    pub occupancy: bool,
    /// With the grid, in inference: the importance samples are placed from the grid's
    /// densities along the coarse samples instead of from the coarse render, so that the
    /// coarse and fine samples run the network in one round. Approximate: the fine samples
    /// land where the grid (not this pose's network) puts density.
    #[cfg_attr(
        feature = "cli",
        arg(
            long = "occupancy-fine",
            requires = "occupancy",
            help = "Place the importance samples from the occupancy grid instead of the coarse \
                    render: coarse and fine samples run the network in one round (approximate)"
        )
    )]
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub occupancy_fine: bool,
    /// With the grid: each ray's coarse samples are placed in the intervals along it that
    /// the grid marks occupied (each interval's ends just outside it) instead of evenly
    /// over its whole box interval ([`crate::render::placement`]), so that the same samples
    /// fall where the body is. Approximate: where the grid is wrong the body is sampled more
    /// coarsely; a grid that was never refreshed leaves the samples where they were.
    #[cfg_attr(
        feature = "cli",
        arg(
            long = "coarse-from-grid",
            requires = "occupancy",
            help = "Place each ray's coarse samples in the intervals the occupancy grid marks \
                    occupied instead of over its whole box interval (approximate)"
        )
    )]
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub coarse_from_grid: bool,
    /// In inference: the coarse samples run the network front to back in
    /// [`EARLY_STOP_SEGMENT`]-sample segments, and once a ray's transmittance is below this
    /// threshold its later samples, coarse and fine, skip the network and are filled like
    /// culled samples. Approximate: what they would have added is weighted by less than the
    /// threshold in the coarse render (docs/numerics.md, "Empty rays and culling").
    #[cfg_attr(
        feature = "cli",
        arg(
            long = "early-stop",
            value_name = "EPS",
            help = "Samples behind the depth where a ray's transmittance falls below EPS skip \
                    the network (approximate; e.g. 1e-3)"
        )
    )]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub early_stop: Option<f64>,
    /// On the CPU: the samples that run the network are grouped by the joints whose spatial
    /// window is non-zero at them, and each network call carries only the joints non-zero
    /// somewhere in it through the per-joint work (the two point encoders, the window's
    /// part features and max-pool, f^m and the first modulated layer). A left-out joint's
    /// window is exactly 0 at every point of the call, so the outputs are those of the full
    /// call up to float summation order; calls and their sizes change, so the bits may.
    #[cfg_attr(
        feature = "cli",
        arg(
            long = "cull-joints",
            help = "Network calls carry only the joints whose spatial window is non-zero at \
                    their points (CPU; the same outputs up to float summation order)"
        )
    )]
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub cull_joints: bool,
    /// Training with the grid: what the pass tells the grid (set per chunk by the trainer,
    /// never by a user or a run file).
    #[cfg_attr(feature = "cli", arg(skip))]
    #[serde(skip)]
    pub grid_feed: Option<GridFeed>,
    /// Training with stratified samples: where in its stratum each sample of the step lies
    /// (set per step by the trainer, never by a user or a run file; `None` is the
    /// reference's evenly spaced samples).
    #[cfg_attr(feature = "cli", arg(skip))]
    #[serde(skip)]
    pub jitter: Option<crate::render::raycast::Jitter>,
}

/// How a training pass feeds the occupancy grid it consults: every sample it evaluates is
/// recorded as an observation of the cells it lies in ([`GridObservation`]), and a share of
/// the samples the grid would leave out run anyway (probes), so that cells the body grows
/// into are found again by the rays that cross them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridFeed {
    /// Share of the samples in empty cells that run anyway, in [0, 1].
    pub probe_share: f64,
    /// Which of them (a hash of the seed and the sample's place in the pass picks them, so a
    /// step repeats bit for bit).
    pub seed: u64,
}

impl GridFeed {
    /// Whether the sample at `index` of the pass's call number `call` is a probe.
    pub fn probes(&self, call: u64, index: u64) -> bool {
        if self.probe_share <= 0.0 {
            return false;
        }
        unit_hash(self.seed, call, index) < self.probe_share
    }
}

/// A uniform number in [0, 1) that depends only on a seed and two places (splitmix64 of
/// them): draws that repeat bit for bit whatever the thread or chunk that makes them.
pub fn unit_hash(seed: u64, a: u64, b: u64) -> f64 {
    let mut z = seed
        .wrapping_add(a.wrapping_mul(0xd1b5_4a32_d192_ed03))
        .wrapping_add(b.wrapping_mul(0x9e37_79b9_7f4a_7c15));
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^= z >> 31;
    ((z >> 11) as f64) * (1.0 / (1u64 << 53) as f64)
}

/// One cell a training pass saw: relu(σ) of the network (no noise) at a sample that lies in
/// cell `cell` of joint `joint`'s grid, whose window is above the pass's threshold there.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridObservation {
    pub joint: u16,
    pub cell: u32,
    pub sigma: f32,
}

/// Coarse samples per segment of the early-stop march: a ray stops at a segment's end, so
/// shorter segments stop closer to the surface but split the pass into more network calls.
pub const EARLY_STOP_SEGMENT: usize = 8;

impl PassOptions {
    /// Parity: every sample of every ray runs the network.
    pub fn parity() -> Self {
        Self::default()
    }

    /// Culling only.
    pub fn culled(culling: Culling) -> Self {
        Self {
            culling,
            ..Self::default()
        }
    }

    /// Whether the pass leaves nothing out.
    pub fn is_parity(&self) -> bool {
        self.culling.is_off()
            && !self.occupancy
            && !self.occupancy_fine
            && !self.coarse_from_grid
            && self.early_stop.is_none()
            && !self.cull_joints
    }

    /// Whether some samples may skip the network (the culled route of
    /// [`crate::render::points`]).
    pub fn leaves_out_work(&self) -> bool {
        !self.is_parity()
    }

    /// The w^p threshold the window test uses: the culling threshold, or exact zeros when
    /// only the occupancy grid, the early stop (whose skipped samples take the far-away
    /// constant) or the joint grouping asks for the test.
    pub fn window_threshold(&self) -> Option<f64> {
        match (
            self.culling.sample_threshold,
            self.occupancy || self.early_stop.is_some() || self.cull_joints,
        ) {
            (Some(t), _) => Some(t),
            (None, true) => Some(0.0),
            (None, false) => None,
        }
    }

    /// What is wrong with these options for a model of `cfg`, if anything.
    pub fn problem(&self, cfg: &Config) -> Option<String> {
        if let Some(p) = self.culling.problem(cfg) {
            return Some(p);
        }
        if self.occupancy_fine && !self.occupancy {
            return Some(
                "occupancy: placing the fine samples from the grid (occupancy_fine) needs the \
                 grid option (occupancy)"
                    .into(),
            );
        }
        if self.coarse_from_grid && !self.occupancy {
            return Some(
                "occupancy: placing the coarse samples from the grid (coarse_from_grid) needs \
                 the grid option (occupancy)"
                    .into(),
            );
        }
        if let Some(eps) = self.early_stop {
            if !(eps.is_finite() && eps > 0.0 && eps < 1.0) {
                return Some(format!(
                    "early_stop: the transmittance threshold must be in (0, 1), found {eps}"
                ));
            }
            if self.occupancy_fine {
                return Some(
                    "early_stop: the early stop marches the coarse samples before placing the \
                     fine ones, which occupancy_fine places without them; choose one"
                        .into(),
                );
            }
            if !cfg.variant.spatial_window() {
                return Some(format!(
                    "early_stop: skipped samples take the far-away constant of the spatial \
                     window, which variant `{}` does not use",
                    cfg.variant
                ));
            }
        }
        if self.cull_joints && !cfg.variant.spatial_window() {
            return Some(format!(
                "cull_joints: joints are left out where their spatial window is 0, which \
                 variant `{}` does not use",
                cfg.variant
            ));
        }
        if let Some(feed) = &self.grid_feed {
            if !self.occupancy {
                return Some(
                    "grid_feed: a pass feeds only the grid it consults (occupancy)".into(),
                );
            }
            if !(0.0..=1.0).contains(&feed.probe_share) {
                return Some(format!(
                    "grid_feed: the probe share must be in [0, 1], found {}",
                    feed.probe_share
                ));
            }
        }
        if self.occupancy && !cfg.variant.spatial_window() {
            return Some(format!(
                "occupancy: the grid is consulted for joints whose spatial window is above the \
                 threshold, which variant `{}` does not use",
                cfg.variant
            ));
        }
        None
    }

    /// Refuse options a model of `cfg` cannot run with ([`Self::problem`]).
    pub fn validate(&self, cfg: &Config) -> Result<()> {
        match self.problem(cfg) {
            Some(p) => Err(ModelError::Input(p)),
            None => Ok(()),
        }
    }
}

/// What one pass did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct PassStats {
    /// Samples of the pass (rays × (coarse + importance samples)).
    pub samples: u64,
    /// Points that went through the network (far-away constants included).
    pub points_evaluated: u64,
    /// Samples of the coarse pass that ran the network.
    pub coarse_evaluated: u64,
    /// Samples of the fine (importance) pass that ran the network.
    pub fine_evaluated: u64,
    /// Samples skipped because every active joint marked their cell empty.
    pub skipped_empty: u64,
    /// Samples skipped because they lie behind the early stop of their ray.
    #[serde(default)]
    pub stopped_early: u64,
    /// Σ over the network calls of points × joints carried through the per-joint work (24
    /// per point unless calls are grouped by joints, [`PassOptions::cull_joints`]).
    #[serde(default)]
    pub joint_rows: u64,
    /// Rays that cross no bone box (ray culling): every sample of theirs is culled.
    #[serde(default)]
    pub rays_culled: u64,
}

impl PassStats {
    /// Add another pass's counts (a render's chunks).
    pub fn add(&mut self, o: &PassStats) {
        self.samples += o.samples;
        self.points_evaluated += o.points_evaluated;
        self.coarse_evaluated += o.coarse_evaluated;
        self.fine_evaluated += o.fine_evaluated;
        self.skipped_empty += o.skipped_empty;
        self.stopped_early += o.stopped_early;
        self.joint_rows += o.joint_rows;
        self.rays_culled += o.rays_culled;
    }

    /// Share of the samples that ran the network (far-away constants not counted).
    pub fn evaluated_fraction(&self) -> f64 {
        (self.coarse_evaluated + self.fine_evaluated) as f64 / self.samples.max(1) as f64
    }
}

#[cfg(test)]
mod tests {
    use super::GridFeed;

    /// The probes are the share asked for, the same ones for the same seed, other ones for
    /// another seed or call, none at 0 and all at 1.
    #[test]
    fn probes_take_their_share_and_repeat() {
        let n = 100_000u64;
        let count = |f: &GridFeed, call: u64| (0..n).filter(|&i| f.probes(call, i)).count();
        let f = GridFeed {
            probe_share: 0.05,
            seed: 3,
        };
        let c = count(&f, 0) as f64 / n as f64;
        assert!((c - 0.05).abs() < 0.004, "share {c}");
        let same: Vec<bool> = (0..1000).map(|i| f.probes(1, i)).collect();
        assert_eq!(same, (0..1000).map(|i| f.probes(1, i)).collect::<Vec<_>>());
        let other_call: Vec<bool> = (0..1000).map(|i| f.probes(2, i)).collect();
        assert_ne!(same, other_call);
        let other_seed = GridFeed { seed: 4, ..f };
        assert_ne!(
            same,
            (0..1000)
                .map(|i| other_seed.probes(1, i))
                .collect::<Vec<_>>()
        );
        assert_eq!(
            count(
                &GridFeed {
                    probe_share: 0.0,
                    ..f
                },
                0
            ),
            0
        );
        assert_eq!(
            count(
                &GridFeed {
                    probe_share: 1.0,
                    ..f
                },
                0
            ),
            n as usize
        );
    }
}
