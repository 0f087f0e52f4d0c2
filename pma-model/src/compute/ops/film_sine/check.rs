//! The FiLM-sine kernels against candle's ops ([`crate::compute::kernel::check`]).

use candle_core::Device;

use super::{FilmHead, MODULE};
use crate::compute::kernel::check::{cases, compare_in, random, Case, Size};
use crate::compute::numerics::Numerics;

/// A whole stack (its shared head gradient) of (N, F, K) and a grid cap, frequencies up to
/// ~30 as the modulator's: a small one, a wide one, a grid of 2 blocks, no rows.
pub(super) fn check(device: &Device, size: Size) -> crate::error::Result<Vec<Case>> {
    let all = [
        ([29, 8, 3], 0),
        ([1000, 128, 4], 0),
        ([300, 16, 2], 2),
        ([0, 8, 2], 0),
    ];
    let mut out = Vec::new();
    for &([n, f, kk], blocks) in cases(size, &all) {
        let seed = (n * 13 + f) as u64;
        let x = random(&[n, f], seed, (-1.0, 1.0), device)?;
        let o = random(&[n, 2 * kk * f], seed + 1, (-4.0, 4.0), device)?;
        let up = random(&[n, kk * f], seed + 2, (-1.0, 1.0), device)?;
        let label = format!("stack of {kk} [{n},{f}]");
        out.extend(compare_in(
            blocks,
            &MODULE,
            &label,
            &[x, o],
            &["x", "head"],
            &up,
            |v| {
                let head = FilmHead::new(&v[1], kk, (15.0, 30.0), Numerics::PARITY);
                let outs = head.stack(&v[0], |_, h| Ok((h * 0.5)?))?;
                Ok(candle_core::Tensor::cat(&outs, 1)?)
            },
        )?);
    }
    Ok(out)
}
