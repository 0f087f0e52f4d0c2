//! The page's per-pass switches: what each one does to a frame's render, as the page lists
//! them (`GET /api/info`) and as a render request carries them.

use pma_model::render::{Culling, SampleFill};
use serde::Serialize;

/// The per-pass switches of the page (docs/numerics.md, "Empty rays and culling").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PassOptions {
    /// Rays that cross no enlarged bone box get the background without running the network
    /// (approximate: their samples have a small window, not zero).
    pub cull_rays: bool,
    /// Samples outside every joint's window (w^p = 0 exactly) get the network's far-away
    /// output instead of running it (exact: the image does not change).
    pub cull_samples: bool,
    /// Samples in cells the model's occupancy grid marks empty get the far-away output too
    /// (approximate; needs a model with a grid).
    pub occupancy: bool,
    /// A ray's samples behind the depth where its transmittance falls below
    /// [`EARLY_STOP`] skip the network (approximate).
    pub early_stop: bool,
    /// Network calls carry only the joints whose window is non-zero at their samples
    /// (exact up to float summation order).
    pub cull_joints: bool,
}

/// The transmittance at which the page's early-stop switch stops a ray.
pub const EARLY_STOP: f64 = 1e-2;

/// A switch as the page lists it (`GET /api/info`); its `id` is the render request's
/// parameter. A new per-pass option is one more entry here, one more field of
/// [`PassOptions`] and its parameter in [`crate::query::render_request`].
#[derive(Debug, Clone, Serialize)]
pub struct Switch {
    pub id: &'static str,
    pub label: &'static str,
    pub help: &'static str,
    pub on: bool,
}

pub const SWITCHES: &[Switch] = &[
    Switch {
        id: "cull_rays",
        label: "cull empty rays",
        help: "rays that cross no bone box get the background without the network \
               (approximate)",
        on: true,
    },
    Switch {
        id: "cull_samples",
        label: "cull empty samples",
        help: "samples outside every joint's window skip the network (exact: the image \
               does not change)",
        on: true,
    },
    Switch {
        id: "occupancy",
        label: "skip empty cells",
        help: "samples in cells the model's occupancy grid marks empty skip the network \
               (approximate; the model needs a grid: pma train --occupancy or \
               pma occupancy build)",
        on: false,
    },
    Switch {
        id: "early_stop",
        label: "stop behind the surface",
        help: "a ray's samples behind the depth where its transmittance falls below 0.01 \
               skip the network (approximate)",
        on: false,
    },
    Switch {
        id: "cull_joints",
        label: "group by joints",
        help: "network calls carry only the joints whose window is non-zero at their \
               samples (exact up to float rounding; with a culling switch on)",
        on: true,
    },
];

impl PassOptions {
    /// The avatar's pass options for these switches.
    pub fn model_options(&self) -> pma_model::render::PassOptions {
        pma_model::render::PassOptions {
            culling: Culling {
                rays: self.cull_rays,
                sample_threshold: self.cull_samples.then_some(0.0),
                sample_fill: SampleFill::Network,
            },
            occupancy: self.occupancy,
            early_stop: self.early_stop.then_some(EARLY_STOP),
            // Grouping alone would switch the culled route on: only with another switch.
            cull_joints: self.cull_joints
                && (self.cull_rays || self.cull_samples || self.occupancy || self.early_stop),
            ..Default::default()
        }
    }
}
