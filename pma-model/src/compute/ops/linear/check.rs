//! The bias-and-activation kernels against candle's ops ([`crate::compute::kernel::check`]).

use candle_core::Device;

use super::MODULE;
use crate::compute::kernel::check::{cases, compare_in, random, Case, Size};
use crate::compute::numerics::Numerics;

/// (rows, in, out) and a grid cap: rows that leave a partial block of 256, one row, a wide
/// layer in a grid of 3 blocks, no rows.
pub(super) fn check(device: &Device, size: Size) -> crate::error::Result<Vec<Case>> {
    let all = [
        ([1000, 7, 33], 0),
        ([1, 5, 2], 0),
        ([513, 128, 64], 3),
        ([0, 4, 3], 0),
    ];
    let mut out = Vec::new();
    for &([rows, inn, outs], blocks) in cases(size, &all) {
        let seed = (rows * 7 + outs) as u64;
        let x = random(&[rows, inn], seed, (-1.0, 1.0), device)?;
        // The pose extractor's sine layers have W and b scaled by ω (up to ~30).
        let w = random(&[outs, inn], seed + 1, (-8.0, 8.0), device)?;
        let b = random(&[outs], seed + 2, (-4.0, 4.0), device)?;
        let up = random(&[rows, outs], seed + 3, (-1.0, 1.0), device)?;
        for (name, act) in [("relu", super::Act::Relu), ("sine", super::Act::Sine)] {
            let label = format!("{name} [{rows},{inn}]x[{outs},{inn}]");
            let inputs = [x.clone(), w.clone(), b.clone()];
            out.extend(compare_in(
                blocks,
                &MODULE,
                &label,
                &inputs,
                &["x", "W", "b"],
                &up,
                |v| super::linear_act(&v[0], &v[1], &v[2], act, Numerics::PARITY),
            )?);
        }
    }
    Ok(out)
}
