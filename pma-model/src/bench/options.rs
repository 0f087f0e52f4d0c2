//! The configurations `pma bench` compares with parity.
//!
//! A new kind of option is one more field of [`BenchOption`] (it then appears in every row
//! of `bench.json`), set in [`BenchOption::apply`] and [`BenchOption::configure`], and the
//! rows that use it in [`options`].

use serde::{Deserialize, Serialize};

use crate::network::config::{Culling, SampleFill};
use crate::render::Avatar;
use crate::train::RunConfig;

/// One configuration: how rays and samples are culled, and which sine runs.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct BenchOption {
    pub name: String,
    pub culling: Culling,
    /// The vectorised sine (`--fast-sine`) instead of libm's.
    #[serde(default)]
    pub fast_sine: bool,
}

impl BenchOption {
    /// No culling, libm's sine: what the reference computes.
    pub fn parity() -> Self {
        Self {
            name: "parity".into(),
            ..Default::default()
        }
    }

    /// Render with this option: `avatar`'s culling and sine (its other numerics kept).
    pub fn apply(&self, avatar: &mut Avatar) -> crate::error::Result<()> {
        avatar.set_numerics(crate::compute::numerics::Numerics {
            fast_sine: self.fast_sine,
            ..avatar.numerics()
        });
        avatar.set_culling(self.culling.clone())
    }

    /// Train with this option: `run`'s culling and sine (its other numerics kept).
    pub fn configure(&self, run: &mut RunConfig) {
        run.numerics.fast_sine = self.fast_sine;
        run.model.culling = self.culling.clone();
    }
}

/// Parity, ray culling, ray and sample culling at each of `thresholds`, then the vectorised
/// sine alone and with the last (most aggressive) culling option.
pub fn options(thresholds: &[f64]) -> Vec<BenchOption> {
    let mut v = vec![
        BenchOption::parity(),
        BenchOption {
            name: "rays".into(),
            culling: Culling {
                rays: true,
                ..Default::default()
            },
            fast_sine: false,
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
            fast_sine: false,
        });
    }
    let last = v.last().cloned().expect("parity is always there");
    v.push(BenchOption {
        name: "fast-sine".into(),
        fast_sine: true,
        ..BenchOption::parity()
    });
    if last.name != "rays" {
        v.push(BenchOption {
            name: format!("{}+fast-sine", last.name),
            fast_sine: true,
            ..last
        });
    }
    v
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parity_first_then_culling_then_the_sine() {
        let names: Vec<String> = options(&[0.0, 1e-2]).into_iter().map(|o| o.name).collect();
        assert_eq!(
            names,
            [
                "parity",
                "rays",
                "rays+samples@0e0",
                "rays+samples@1e-2",
                "fast-sine",
                "rays+samples@1e-2+fast-sine"
            ]
        );
        // Without thresholds the last culling option is "rays", which gets no sine twin.
        let names: Vec<String> = options(&[]).into_iter().map(|o| o.name).collect();
        assert_eq!(names, ["parity", "rays", "fast-sine"]);
        let o = options(&[1e-4]);
        assert_eq!(o[2].culling.sample_threshold, Some(1e-4));
        assert_eq!(o[4].culling, o[2].culling);
        assert!(o[4].fast_sine && !o[2].fast_sine);
    }
}
