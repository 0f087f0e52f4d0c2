//! What the ops' tests share.

use candle_core::{Device, Tensor};

use crate::compute::account::{Account, Route};
use crate::compute::kernel::{Module, Size};

/// Deterministic values in [-1, 1) of `shape` on the CPU.
pub fn rand(shape: &[usize], seed: u64) -> Tensor {
    crate::compute::kernel::check::random(shape, seed, (-1.0, 1.0), &Device::Cpu).unwrap()
}

/// The bits of every value of `t`.
pub fn bits(t: &Tensor) -> Vec<u32> {
    let v: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
    v.iter().map(|x| x.to_bits()).collect()
}

/// `module`'s full check on the emulated grid (a CPU run that takes the CUDA route): every
/// case passes, and its kernels ran (the account saw their launches).
pub fn full_check_passes(module: &'static Module) {
    let account = Account::start(&Device::Cpu, Route::Cuda).unwrap();
    let cases = (module.check)(&Device::Cpu, Size::Full).unwrap();
    let report = account.finish();
    assert!(cases.len() >= 4, "{}: {} cases", module.name, cases.len());
    for c in &cases {
        eprintln!(
            "{} {}: {:e} (tolerance {:e})",
            module.name, c.what, c.max_err, c.tol
        );
        assert!(
            c.passed(),
            "{} {}: {:e} > {:e}",
            module.name,
            c.what,
            c.max_err,
            c.tol
        );
    }
    let pma_launches: u64 = report
        .ops
        .iter()
        .filter(|(name, _)| name.starts_with("pma-"))
        .map(|(_, c)| c.launches)
        .sum();
    assert!(
        pma_launches > 0,
        "{}: no kernel of pma's ran: {:?}",
        module.name,
        report.ops.keys()
    );
}
