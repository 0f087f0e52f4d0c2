//! The point-encoder kernels against candle's ops ([`crate::compute::kernel::check`]).

use candle_core::Device;

use super::{sine_linear, MODULE};
use crate::compute::kernel::check::{cases, compare_in, random, Case, Size};
use crate::compute::numerics::Numerics;

/// (rows, in, out) and a grid cap: rows that leave a partial block of 1,024, one input, the
/// widest input in a grid of 2 blocks, no rows.
pub(super) fn check(device: &Device, size: Size) -> crate::error::Result<Vec<Case>> {
    let all = [
        ([3000, 3, 64], 0),
        ([1500, 1, 5], 0),
        ([1100, 4, 7], 2),
        ([0, 3, 4], 0),
    ];
    let mut out = Vec::new();
    for &([rows, inp, outs], blocks) in cases(size, &all) {
        let seed = (rows * 5 + outs) as u64;
        let inputs = [
            random(&[rows, inp], seed, (-1.2, 1.2), device)?,
            random(&[outs, inp], seed + 1, (-16.0, 16.0), device)?,
            random(&[outs], seed + 2, (-16.0, 16.0), device)?,
            random(&[rows], seed + 3, (0.0, 1.0), device)?,
        ];
        let up = random(&[rows, outs], seed + 4, (-1.0, 1.0), device)?;
        let label = format!("[{rows},{inp}]x[{outs},{inp}]");
        out.extend(compare_in(
            blocks,
            &MODULE,
            &label,
            &inputs,
            &["x", "W", "b", "s"],
            &up,
            |v| sine_linear(&v[0], &v[1], &v[2], Some(&v[3]), Numerics::PARITY),
        )?);
    }
    Ok(out)
}
