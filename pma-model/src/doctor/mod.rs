//! `pma doctor`: a self-test of a device, to run before a long run on it.
//!
//! * the device: name, memory, the CUDA driver's and NVRTC's versions;
//! * every kernel module: compiled (NVRTC on a GPU), then checked against candle's ops on
//!   random inputs of awkward sizes ([`crate::compute::kernel::check`]) on the device; on
//!   the CPU the kernels run on the emulated grid, so the command and its checks are the
//!   same everywhere;
//! * the official code's golden case, when its fixtures are found: the forward stage by
//!   stage, the gradients and one Adam step on the device (on the CPU both on the CPU's route
//!   and on the CUDA route emulated there);
//! * a short training burst: steps per second and peak memory.
//!
//! A kernel that fails here is switched off for the process, as it would be in a run: the
//! report then says which, and a run on this device goes on with candle's generic ops for
//! that op (docs/gpu.md, "When the doctor fails").

mod burst;
pub mod golden;
mod kernels;

use std::path::PathBuf;

use candle_core::Device;
use serde::Serialize;

pub use burst::Burst;

use crate::compute::account::{Account, Route};
use crate::compute::device::DeviceInfo;
use crate::train::Preset;

/// What to run.
#[derive(Debug, Clone)]
pub struct DoctorOptions {
    /// The golden case's directory (a copy of `fixtures/golden`); none: skip it.
    pub golden: Option<PathBuf>,
    /// Steps of the training burst (0: none).
    pub burst_steps: usize,
    /// The burst's preset (default: the device's, [`Preset::for_device`]).
    pub burst_preset: Option<Preset>,
}

/// One line of the report.
#[derive(Debug, Clone, Serialize)]
pub struct Check {
    pub section: &'static str,
    pub what: String,
    pub max_err: Option<f64>,
    pub tol: Option<f64>,
    pub passed: bool,
    /// What else a reader needs: an error, the worst case, why it was skipped.
    pub note: String,
}

/// `doctor.json`.
#[derive(Debug, Serialize)]
pub struct DoctorReport {
    pub device: DeviceInfo,
    pub checks: Vec<Check>,
    pub burst: Option<Burst>,
    /// The golden case's directory, or why there is none.
    pub golden: String,
    /// Every kernel module's state at the end (`on`, or `off: why`).
    pub kernel_states: Vec<(String, String)>,
    pub passed: bool,
}

/// Run every check on `device`; `progress` hears each section as it starts.
pub fn run(device: &Device, opts: &DoctorOptions, progress: &mut dyn FnMut(&str)) -> DoctorReport {
    let info = crate::compute::device::describe(device);
    progress("kernels");
    let mut checks = kernels::check(device);
    let golden = match &opts.golden {
        None => "not run (none found, or --no-golden; --golden DIR: a copy of the repository's fixtures/golden)".to_string(),
        Some(dir) => {
            progress("golden case");
            checks.extend(golden_checks(dir, device));
            dir.display().to_string()
        }
    };
    let burst = (opts.burst_steps > 0).then(|| {
        let preset = opts
            .burst_preset
            .unwrap_or_else(|| Preset::for_device(device));
        progress(&format!(
            "training burst ({} steps of {})",
            opts.burst_steps,
            preset.name()
        ));
        match burst::run(device, preset, opts.burst_steps) {
            Ok(b) => Some(b),
            Err(e) => {
                checks.push(Check {
                    section: "burst",
                    what: format!("{} steps of {}", opts.burst_steps, preset.name()),
                    max_err: None,
                    tol: None,
                    passed: false,
                    note: e,
                });
                None
            }
        }
    });
    let kernel_states = crate::compute::ops::MODULES
        .iter()
        .map(|m| {
            let state = match crate::compute::kernel::health::state(m) {
                crate::compute::kernel::health::State::Off(why) => format!("off: {why}"),
                s => format!("{s:?}").to_lowercase(),
            };
            (m.name.to_string(), state)
        })
        .collect();
    let passed = checks.iter().all(|c| c.passed);
    DoctorReport {
        device: info,
        checks,
        burst: burst.flatten(),
        golden,
        kernel_states,
        passed,
    }
}

/// The golden case on `device`'s own route; on the CPU also on the CUDA route, emulated.
fn golden_checks(dir: &std::path::Path, device: &Device) -> Vec<Check> {
    let mut rows = Vec::new();
    let mut section = |name: &'static str, emulated: bool| {
        let run = || -> crate::error::Result<Vec<Check>> {
            let g = golden::Golden::load(dir, device)?;
            let mut r = golden::forward(&g, device, name)?;
            r.extend(golden::gradients(&g, device, name)?);
            r.extend(golden::adam_step(&g, device, name)?);
            Ok(r)
        };
        let result = match emulated {
            true => Account::start(device, Route::Cuda).and_then(|account| {
                let r = run();
                account.finish();
                r
            }),
            false => run(),
        };
        match result {
            Ok(r) => rows.extend(r),
            Err(e) => rows.push(Check {
                section: name,
                what: "the golden case".into(),
                max_err: None,
                tol: None,
                passed: false,
                note: e.to_string(),
            }),
        }
    };
    if device.is_cpu() {
        section("golden, cpu route", false);
        section("golden, cuda route (emulated)", true);
    } else {
        section("golden", false);
    }
    rows
}
