//! The fast recipe (`pma train --fast`, `pma demo`): the training options that reach a
//! held-out quality sooner on a CPU, switched on together over any preset. Each is an
//! option of its own with its error against run time measured (docs/performance.md, "Time
//! to quality"); parity is the preset without them.
//!
//! * ray and sample culling at w^p ≤ 0.6 and the occupancy grid: fewer network points per
//!   step, so more steps per minute;
//! * coarse samples placed in the grid's occupied intervals: the same samples where the body
//!   is;
//! * rays drawn where a running map of the training error is high;
//! * learning rates that anneal over the run's budget.

use crate::network::occupancy::OccupancyConfig;
use crate::render::options::{Culling, SampleFill};
use crate::train::presets::{Anneal, RunConfig};
use pma_data::error_map::ErrorMapConfig;

/// The w^p threshold of the recipe's sample culling.
pub const FAST_CULL_THRESHOLD: f64 = 0.6;

/// One option the recipe switched on, and why (for the user).
#[derive(Debug, Clone, PartialEq)]
pub struct Choice {
    pub option: &'static str,
    pub why: &'static str,
}

/// Switch the recipe's options on in `run`; `minutes` is the run's wall-clock budget (the
/// learning rates anneal over it; without one, over `run.train.iters`). Returns what it
/// switched on, in order.
pub fn fast(run: &mut RunConfig, minutes: Option<f64>) -> Vec<Choice> {
    let t = &mut run.train;
    t.culling = Culling {
        rays: true,
        sample_threshold: Some(FAST_CULL_THRESHOLD),
        sample_fill: SampleFill::Network,
    };
    t.occupancy.get_or_insert_with(OccupancyConfig::default);
    t.coarse_from_grid = true;
    t.error_map = Some(ErrorMapConfig::default());
    t.anneal = Some(Anneal {
        seconds: minutes.map_or(0.0, |m| m * 60.0),
        ..Anneal::default()
    });
    vec![
        Choice {
            option: "--cull-rays --cull-samples 0.6",
            why: "rays that miss every bone box and samples outside the windows skip the network",
        },
        Choice {
            option: "--occupancy",
            why: "samples in cells the grid marks empty skip the network",
        },
        Choice {
            option: "--coarse-from-grid",
            why: "the coarse samples go where the grid sees the body",
        },
        Choice {
            option: "--error-map",
            why: "half of each image's rays go where the training error is",
        },
        Choice {
            option: "--anneal",
            why: "the learning rates fall to a tenth by the end of the budget",
        },
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::train::presets::Preset;

    #[test]
    fn the_recipe_validates_on_every_preset_and_anneals_over_the_budget() {
        for p in Preset::ALL {
            let mut run = RunConfig::from_preset(p);
            let choices = fast(&mut run, Some(5.0));
            assert!(!choices.is_empty());
            run.validate().unwrap_or_else(|e| panic!("{p}: {e}"));
            assert_eq!(run.train.anneal.as_ref().unwrap().seconds, 300.0);
            // The run's TOML keeps every option.
            let back = RunConfig::from_toml_str(&run.to_toml_string().unwrap()).unwrap();
            assert_eq!(back, run, "{p}");
        }
        let mut run = RunConfig::from_preset(Preset::Tiny);
        fast(&mut run, None);
        assert_eq!(
            run.train.anneal.unwrap().seconds,
            0.0,
            "over the iterations"
        );
    }
}
