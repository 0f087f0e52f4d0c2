//! The fast recipe (`pma train --fast`, `pma demo`): the training options that reach a
//! held-out quality sooner on a CPU, switched on together over any preset; parity is the
//! preset without them.
//!
//! It is ray and sample culling at w^p ≤ 0.6 with the occupancy grid (fewer network points
//! per step, so about twice the steps per minute), averaged weights (the model is the
//! moving average of the weights over the last ninth of the steps, at most about 500, which
//! scatter less than the weights of one step; the steps do not change) and, in a run with a
//! wall-clock budget (`--minutes`), the pose side's rate starting at 4x and coming down to
//! its own over that budget (`pose_boost`: the reference's pose-side rate is made for 300,000 steps, and
//! in a run of minutes that side lags). A run by iterations gets no boost: the presets'
//! iteration counts are not budgets, and over a span far longer than the run the boost is a
//! constant 4x, which was behind by five minutes. The other time-to-quality options (coarse
//! samples from the grid, the error map, rates annealed over the budget) stay options of
//! their own: each alone, and all together, reached parity's held-out PSNR later than
//! culling with the grid did (`pma bench --time-to-quality`, docs/performance.md "Time to
//! quality"); rates that cool down at the end of the budget gained nothing over the longer
//! average at five minutes and lost at one.

use crate::network::occupancy::OccupancyConfig;
use crate::render::options::{Culling, SampleFill};
use crate::train::average::AverageConfig;
use crate::train::presets::RunConfig;

/// The w^p threshold of the recipe's sample culling.
pub const FAST_CULL_THRESHOLD: f64 = 0.6;

/// One option the recipe switched on, and why (for the user).
#[derive(Debug, Clone, PartialEq)]
pub struct Choice {
    pub option: &'static str,
    pub why: &'static str,
}

/// Switch the recipe's options on in `run`, a run of `budget_s` seconds of wall clock
/// (`--minutes`), or `None` for a run by iterations. Returns what it switched on, in order.
pub fn fast(run: &mut RunConfig, budget_s: Option<f64>) -> Vec<Choice> {
    let mut choices = cull_with_grid(run);
    run.train.average.get_or_insert_with(AverageConfig::default);
    choices.push(Choice {
        option: "--average",
        why: "the model is the moving average of the weights, which scatter from step to step",
    });
    if let Some(seconds) = budget_s.filter(|&s| s > 0.0) {
        run.train.boost_pose_over(Some(seconds));
        choices.push(Choice {
            option: "--pose-boost",
            why: "the pose side's rate starts at 4x and comes down to its own over the \
                  --minutes budget (that side lags in a run of minutes)",
        });
    }
    choices
}

/// The recipe's part that leaves work out: culling at w^p ≤ 0.6 and the occupancy grid.
pub fn cull_with_grid(run: &mut RunConfig) -> Vec<Choice> {
    let t = &mut run.train;
    t.culling = Culling {
        rays: true,
        sample_threshold: Some(FAST_CULL_THRESHOLD),
        sample_fill: SampleFill::Network,
    };
    t.occupancy.get_or_insert_with(OccupancyConfig::default);
    vec![
        Choice {
            option: "--cull-rays --cull-samples 0.6",
            why: "rays that miss every bone box and samples outside the windows skip the network",
        },
        Choice {
            option: "--occupancy",
            why: "samples in cells the grid marks empty skip the network",
        },
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::train::presets::{PoseBoost, Preset};

    #[test]
    fn the_recipe_validates_on_every_preset_and_keeps_the_other_options_off() {
        for p in Preset::ALL {
            // With a budget the pose side's boost spans it.
            let mut budgeted = RunConfig::from_preset(p);
            assert_eq!(fast(&mut budgeted, Some(90.0)).len(), 4);
            let boost = budgeted.train.pose_boost.take().expect("a boost");
            assert_eq!(boost.seconds, 90.0, "{p}");
            assert_eq!(boost.factor, PoseBoost::default().factor, "{p}");
            let mut run = RunConfig::from_preset(p);
            let preset_rates = (run.train.lr, run.train.lr_freq);
            let choices = fast(&mut run, None);
            assert_eq!(choices.len(), 3);
            assert_eq!(budgeted, run, "{p}: the budget changes only the boost");
            assert_eq!((run.train.lr, run.train.lr_freq), preset_rates, "{p}");
            run.validate().unwrap_or_else(|e| panic!("{p}: {e}"));
            assert!(
                run.train.culling.rays
                    && run.train.occupancy.is_some()
                    && run.train.average.is_some(),
                "{p}"
            );
            assert!(!run.train.coarse_from_grid, "{p}");
            assert!(
                run.train.error_map.is_none()
                    && run.train.anneal.is_none()
                    && run.train.pose_boost.is_none(),
                "{p}"
            );
            // The run's TOML keeps every option.
            let back = RunConfig::from_toml_str(&run.to_toml_string().unwrap()).unwrap();
            assert_eq!(back, run, "{p}");
        }
    }
}
