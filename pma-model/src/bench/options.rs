//! The configurations `pma bench` compares with parity.
//!
//! A new kind of option is one more field of [`BenchOption`] (it then appears in every row
//! of `bench.json`), set in [`BenchOption::apply`] and [`BenchOption::configure`], and the
//! rows that use it in [`options`].

use serde::{Deserialize, Serialize};

use crate::network::occupancy::OccupancyConfig;
use crate::render::{Avatar, Culling, PassOptions, SampleFill};
use crate::train::RunConfig;

/// One configuration: how rays and samples are culled, whether the occupancy grid skips
/// samples, and which sine runs.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct BenchOption {
    pub name: String,
    pub culling: Culling,
    /// The occupancy grid (rendering: the bench model's; training: one built and refreshed
    /// during the run).
    #[serde(default)]
    pub occupancy: bool,
    /// The vectorised sine (`--fast-sine`) instead of libm's.
    #[serde(default)]
    pub fast_sine: bool,
    /// Rendering places the fine samples from the grid (`PassOptions::occupancy_fine`);
    /// training is that of the same option without it.
    #[serde(default)]
    pub occupancy_fine: bool,
    /// Rendering stops rays early at this transmittance (`PassOptions::early_stop`);
    /// training is that of the same option without it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub early_stop: Option<f64>,
    /// Rendering groups the network calls by the joints their samples need
    /// (`PassOptions::cull_joints`); training is that of the same option without it.
    #[serde(default)]
    pub cull_joints: bool,
}

/// The default transmittance at which the bench's early-stop rows stop a ray: what it leaves
/// out is weighted by less than 1 % in the coarse render.
pub const BENCH_EARLY_STOP: f64 = 1e-2;

impl BenchOption {
    /// No culling, libm's sine: what the reference computes.
    pub fn parity() -> Self {
        Self {
            name: "parity".into(),
            ..Default::default()
        }
    }

    /// The pass options of this option's renders.
    pub fn pass(&self) -> PassOptions {
        PassOptions {
            culling: self.culling.clone(),
            occupancy: self.occupancy,
            occupancy_fine: self.occupancy_fine,
            coarse_from_grid: false,
            early_stop: self.early_stop,
            cull_joints: self.cull_joints,
            grid_feed: None,
            jitter: None,
        }
    }

    /// Render with this option: sets `avatar`'s sine (its other numerics kept) and returns
    /// the pass options.
    pub fn apply(&self, avatar: &mut Avatar) -> PassOptions {
        avatar.set_numerics(crate::compute::numerics::Numerics {
            fast_sine: self.fast_sine,
            ..avatar.numerics()
        });
        self.pass()
    }

    /// Train with this option: `run`'s culling and sine (its other numerics kept), and a
    /// grid of `grid`'s settings when the option uses one.
    pub fn configure(&self, run: &mut RunConfig, grid: &OccupancyConfig) {
        run.numerics.fast_sine = self.fast_sine;
        run.train.culling = self.culling.clone();
        run.train.occupancy = self.occupancy.then(|| grid.clone());
    }
}

/// Parity, ray culling, ray and sample culling at each of `thresholds`, the last (most
/// aggressive) culling option with the early stop, with the joint grouping and with both,
/// then the vectorised sine alone and with that culling option; with `occupancy` the grid
/// alone, with that culling option, with the fine samples placed from the grid, with the
/// early stop (at transmittance `early_stop`) and with the early stop and the joint grouping.
pub fn options(thresholds: &[f64], occupancy: bool, early_stop: f64) -> Vec<BenchOption> {
    let mut v = vec![
        BenchOption::parity(),
        BenchOption {
            name: "rays".into(),
            culling: Culling {
                rays: true,
                ..Default::default()
            },
            ..BenchOption::parity()
        },
    ];
    for &t in thresholds {
        v.push(BenchOption {
            name: format!("rays+samples@{t:e}"),
            culling: Culling {
                rays: true,
                sample_threshold: Some(t),
                sample_fill: SampleFill::Network,
            },
            ..BenchOption::parity()
        });
    }
    let last = v.last().cloned().expect("parity is always there");
    let early_stop = |o: &BenchOption| BenchOption {
        name: format!("{}+early-stop@{early_stop:e}", o.name),
        early_stop: Some(early_stop),
        ..o.clone()
    };
    let joints = |o: &BenchOption| BenchOption {
        name: format!("{}+joints", o.name),
        cull_joints: true,
        ..o.clone()
    };
    v.push(early_stop(&last));
    v.push(joints(&last));
    v.push(joints(&early_stop(&last)));
    v.push(BenchOption {
        name: "fast-sine".into(),
        fast_sine: true,
        ..BenchOption::parity()
    });
    if last.name != "rays" {
        v.push(BenchOption {
            name: format!("{}+fast-sine", last.name),
            fast_sine: true,
            ..last.clone()
        });
    }
    if occupancy {
        v.push(BenchOption {
            name: "occupancy".into(),
            occupancy: true,
            ..BenchOption::parity()
        });
        let with_grid = BenchOption {
            name: format!("{}+occupancy", last.name),
            occupancy: true,
            ..last
        };
        v.push(with_grid.clone());
        v.push(BenchOption {
            name: format!("{}+grid-fine", with_grid.name),
            occupancy_fine: true,
            ..with_grid.clone()
        });
        v.push(early_stop(&with_grid));
        v.push(joints(&early_stop(&with_grid)));
    }
    v
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The names of the bench's options for these sample thresholds.
    fn names(thresholds: &[f64]) -> Vec<String> {
        options(thresholds, false, BENCH_EARLY_STOP)
            .into_iter()
            .map(|o| o.name)
            .collect()
    }

    #[test]
    fn parity_first_then_culling_then_the_sine() {
        assert_eq!(
            names(&[0.0, 1e-2]),
            [
                "parity",
                "rays",
                "rays+samples@0e0",
                "rays+samples@1e-2",
                "rays+samples@1e-2+early-stop@1e-2",
                "rays+samples@1e-2+joints",
                "rays+samples@1e-2+early-stop@1e-2+joints",
                "fast-sine",
                "rays+samples@1e-2+fast-sine"
            ]
        );
        // Without thresholds the last culling option is "rays", which gets no sine twin.
        assert_eq!(
            names(&[]),
            [
                "parity",
                "rays",
                "rays+early-stop@1e-2",
                "rays+joints",
                "rays+early-stop@1e-2+joints",
                "fast-sine"
            ]
        );
        let o = options(&[1e-4], false, BENCH_EARLY_STOP);
        assert_eq!(o[2].culling.sample_threshold, Some(1e-4));
        assert_eq!(o[3].culling, o[2].culling);
        assert_eq!(o[3].pass().early_stop, Some(BENCH_EARLY_STOP));
        // The joint grouping: alone on the last culling option, then with the early stop.
        assert!(o[4].pass().cull_joints && o[4].culling == o[2].culling);
        assert!(o[4].pass().early_stop.is_none());
        assert!(o[5].pass().cull_joints && o[5].pass().early_stop == Some(BENCH_EARLY_STOP));
        assert!(o[..4].iter().chain(&o[6..]).all(|o| !o.pass().cull_joints));
        assert_eq!(o[7].culling, o[2].culling);
        assert!(o[7].fast_sine && !o[2].fast_sine);
        assert!(o.iter().all(|o| !o.occupancy));
        // Each early-stop row follows the row it differs from only in the early stop (the
        // bench trains them once).
        assert!(o.iter().filter(|o| o.early_stop.is_some()).count() == 2);
        // The grid alone, then with the last culling option (without the sine).
        let o = options(&[1e-4], true, BENCH_EARLY_STOP);
        let names: Vec<&str> = o[8..].iter().map(|o| o.name.as_str()).collect();
        assert_eq!(
            names,
            [
                "occupancy",
                "rays+samples@1e-4+occupancy",
                "rays+samples@1e-4+occupancy+grid-fine",
                "rays+samples@1e-4+occupancy+early-stop@1e-2",
                "rays+samples@1e-4+occupancy+early-stop@1e-2+joints"
            ]
        );
        assert!(o[10].occupancy_fine && o[10].pass().occupancy_fine && o[10].pass().occupancy);
        assert!(o[..10].iter().all(|o| !o.pass().occupancy_fine));
        assert!(o[8].occupancy && o[8].culling == Culling::default() && !o[8].fast_sine);
        assert!(o[9].occupancy && o[9].culling == o[2].culling && !o[9].fast_sine);
        assert!(o[9].pass().occupancy && o[9].pass().culling == o[2].culling);
        assert!(o[11].pass().occupancy && !o[11].occupancy_fine);
        assert_eq!(o[11].pass().early_stop, Some(BENCH_EARLY_STOP));
        assert!(o[12].pass().cull_joints && o[12].pass().occupancy);
        for o in &o {
            assert!(o
                .pass()
                .validate(&crate::network::config::Config::default())
                .is_ok());
        }
    }
}
