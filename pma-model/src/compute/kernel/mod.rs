//! The layer every custom op of [`crate::compute::ops`] stands on; it imports no op.
//!
//! An op call takes one of three routes ([`Route`]):
//!
//! * **CPU**: f32 tensors on the CPU, the op's own CPU code (bit-identical to candle's ops);
//! * **device**: the op's CUDA kernels, launched on a GPU, or, in a CPU run that takes the
//!   CUDA route ([`crate::compute::account::emulates_cuda`]), launched over an emulated
//!   grid on the host: the same `.cu` source compiled as C (`build.rs`), the same launch
//!   code and arguments ([`launch`]), so that everything of the CUDA route but candle's CUDA
//!   backend and the driver runs, and is tested, without a GPU;
//! * **generic**: candle's ops, on any device and dtype. A kernel that fails to compile or
//!   launch, or disagrees with the generic ops in its first-use check, is switched off for
//!   the process and its ops take this route ([`health`]); `--generic-kernels` sends every
//!   op here.
//!
//! | module | what |
//! | --- | --- |
//! | [`storage`] | a storage's values under a layout; what a forward keeps for its backward |
//! | [`mem`] | the memory a device kernel reads and writes: a GPU's, or host memory standing in for it |
//! | [`launch`] | one launch: the grid, NVRTC and its PTX cache on CUDA, the emulated grid on the host |
//! | [`op`] | an op's forward and backward as candle's custom op, for the CPU and CUDA alike |
//! | [`health`] | which kernels are on: failures, the first-use check, injected faults, `--generic-kernels` |
//! | [`check`] | an op's kernels against its generic ops on random inputs (first use, `pma doctor`) |

pub mod check;
pub mod health;
pub mod launch;
pub mod mem;
pub mod op;
pub mod storage;

use candle_core::{DType, Tensor};

pub use check::{Case, Size};
pub use mem::Exec;

/// One `.cu` file of an op: its kernels, how the host runs them, and how they are checked.
pub struct Module {
    /// The op's name, as warnings, `PMA_KERNEL_FAULT` and `pma doctor` spell it.
    pub name: &'static str,
    /// The source's path below `pma-model/src` (errors name it).
    pub file: &'static str,
    /// The CUDA source after `kernel/prelude.cuh`, compiled with NVRTC at run time.
    pub source: &'static str,
    /// The same source compiled for the host (`emu.c` in the op's folder): runs kernel `name`
    /// over an emulated grid with CUDA's `kernelParams` convention.
    pub emulate: launch::EmuFn,
    /// The op's kernels against its generic ops (first use, `pma doctor`).
    pub check: check::CheckFn,
}

impl std::fmt::Debug for Module {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name)
    }
}

/// Where one call of an op runs (see the module docs).
#[derive(Clone)]
pub enum Route {
    Cpu,
    Device(Exec),
    Generic,
}

/// The route of a call of `module`'s op on tensors `ts` when the network asks for its
/// kernels (`on`): the CPU's when they are f32 on the CPU's route, the device's when they are
/// f32 on CUDA (a `cuda` build) or on the CPU of a run that takes the CUDA route and the
/// kernel is on (its first use on a device checks it), otherwise the generic one.
pub fn route(on: bool, module: &'static Module, ts: &[&Tensor]) -> Route {
    if !on || ts.iter().any(|t| t.dtype() != DType::F32) || health::forced_generic(module) {
        return Route::Generic;
    }
    let exec = if ts.iter().all(|t| t.device().is_cpu()) {
        if !crate::compute::account::emulates_cuda() {
            return Route::Cpu;
        }
        Exec::Emulated
    } else {
        match Exec::of_device(ts[0].device()) {
            Some(e) if ts.iter().all(|t| t.device().same_device(ts[0].device())) => e,
            _ => return Route::Generic,
        }
    };
    match ready(module, &exec) {
        true => Route::Device(exec),
        false => Route::Generic,
    }
}

/// [`route`] for an op with a CPU route of its own: `None` for candle's generic ops, else
/// the kernels' executor (`None` on the CPU's route, `Some` on a device).
pub fn fused_route(on: bool, module: &'static Module, ts: &[&Tensor]) -> Option<Option<Exec>> {
    match route(on, module, ts) {
        Route::Generic => None,
        Route::Cpu => Some(None),
        Route::Device(e) => Some(Some(e)),
    }
}

/// Whether `module`'s kernels may run on `exec` now: before their first use on a device,
/// their quick check runs (once per process; a failing or erroring check switches the
/// module off).
fn ready(module: &'static Module, exec: &Exec) -> bool {
    if health::begin_check(module) {
        let device = exec.device();
        // The check's own ops are not part of any accounted run.
        let result = candle_core::account::uncounted(|| (module.check)(&device, Size::Quick));
        match result {
            Ok(cases) => match cases.iter().find(|c| !c.passed()) {
                None => health::checked(module),
                Some(c) => health::switch_off(
                    module,
                    &format!(
                        "its first-use check found {} off by {:e} (tolerance {:e})",
                        c.what, c.max_err, c.tol
                    ),
                ),
            },
            Err(e) => health::switch_off(module, &format!("its first-use check failed: {e}")),
        }
    }
    health::usable(module)
}

/// `fused()` on `module`'s kernels, or `generic()` when a kernel failed while it ran (the
/// failure switched `module` off, with its one warning line): the op's result either way.
/// Failures of anything else are returned as they are.
pub fn or_generic<T>(
    module: &'static Module,
    fused: impl FnOnce() -> crate::error::Result<T>,
    generic: impl FnOnce() -> crate::error::Result<T>,
) -> crate::error::Result<T> {
    match fused() {
        Err(_) if !health::usable(module) => generic(),
        r => r,
    }
}
