//! Every kernel module compiled and checked on the device: NVRTC on a GPU (on the CPU, the
//! host build `build.rs` made), then the module's full check against candle's ops on its
//! executor (a GPU, or the CPU's emulated grid).

use candle_core::Device;

use super::Check;
use crate::compute::account::{Account, Route};
use crate::compute::kernel::health::{self, State};
use crate::compute::kernel::{launch, Module, Size};
use crate::compute::ops::MODULES;

/// A row per module and step.
pub fn check(device: &Device) -> Vec<Check> {
    let mut rows = Vec::new();
    for &module in MODULES.iter() {
        rows.push(compile(module));
        rows.push(run_check(module, device));
    }
    rows
}

fn compile(module: &'static Module) -> Check {
    let (passed, note) = match launch::compile(module) {
        Some(Ok(bytes)) => (true, format!("NVRTC: {bytes} bytes of PTX")),
        Some(Err(e)) => {
            health::switch_off(module, &e);
            (false, e)
        }
        None => match health::injected(module) {
            Some(health::Fault::Compile) => {
                (false, "injected compile fault (PMA_KERNEL_FAULT)".into())
            }
            _ => (true, "host build (no CUDA here)".into()),
        },
    };
    Check {
        section: "kernels",
        what: format!("{} compiles ({})", module.name, module.file),
        max_err: None,
        tol: None,
        passed,
        note,
    }
}

/// The module's full check. On the CPU it runs inside a run that takes the CUDA route, so
/// the kernels run on the emulated grid. It passes when every case is within tolerance and
/// the module is still on afterwards (a failed launch or first-use check switches it off,
/// and its ops then compare the generic ops with themselves).
fn run_check(module: &'static Module, device: &Device) -> Check {
    let what = format!("{} against candle's ops", module.name);
    let result = match device.is_cpu() {
        true => Account::start(device, Route::Cuda)
            .map_err(|e| e.to_string())
            .and_then(|account| {
                let r = (module.check)(device, Size::Full).map_err(|e| e.to_string());
                account.finish();
                r
            }),
        false => (module.check)(device, Size::Full).map_err(|e| e.to_string()),
    };
    let state = health::state(module);
    let mut check = Check {
        section: "kernels",
        what,
        max_err: None,
        tol: Some(crate::compute::kernel::check::TOL as f64),
        passed: false,
        note: String::new(),
    };
    match result {
        Err(e) => check.note = e,
        Ok(cases) => {
            let worst = cases.iter().max_by(|a, b| a.max_err.total_cmp(&b.max_err));
            // Switched off, the check compared the generic ops with themselves.
            check.max_err = worst
                .filter(|_| state == State::On)
                .map(|c| c.max_err as f64);
            let failed = cases.iter().filter(|c| !c.passed()).count();
            check.passed = failed == 0 && state == State::On;
            check.note = match (&state, worst) {
                (State::Off(why), _) => format!("switched off: {why}"),
                (_, Some(w)) if failed > 0 => {
                    format!("{failed} of {} cases fail; worst: {}", cases.len(), w.what)
                }
                (_, Some(w)) => format!("{} cases; worst: {}", cases.len(), w.what),
                (_, None) => "no cases".into(),
            };
        }
    }
    check
}
