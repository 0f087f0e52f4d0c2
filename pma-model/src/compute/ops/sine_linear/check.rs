//! The point-encoder kernels against candle's ops ([`crate::compute::kernel::check`]).

use candle_core::Device;

use super::{sine_linear, MODULE};
use crate::compute::kernel::check::{compare, random, Case, Size};
use crate::compute::kernel::launch::with_block_limit;
use crate::compute::numerics::Numerics;

/// Sizes (rows, in, out): rows that leave a partial block of 1,024, one input, the widest
/// input; in the full check also a grid of 2 blocks and no rows.
pub(super) fn check(device: &Device, size: Size) -> crate::error::Result<Vec<Case>> {
    let cases: &[([usize; 3], u32)] = match size {
        Size::Quick => &[([300, 3, 16], 0)],
        Size::Full => &[
            ([3000, 3, 64], 0),
            ([1500, 1, 5], 0),
            ([1100, 4, 7], 2),
            ([0, 3, 4], 0),
        ],
    };
    let mut out = Vec::new();
    for &([rows, inp, outs], blocks) in cases {
        let seed = (rows * 5 + outs) as u64;
        let x = random(&[rows, inp], seed, (-1.2, 1.2), device)?;
        let w = random(&[outs, inp], seed + 1, (-16.0, 16.0), device)?;
        let b = random(&[outs], seed + 2, (-16.0, 16.0), device)?;
        let sc = random(&[rows], seed + 3, (0.0, 1.0), device)?;
        let up = random(&[rows, outs], seed + 4, (-1.0, 1.0), device)?;
        let label = format!(
            "[{rows},{inp}]x[{outs},{inp}]{}",
            if blocks > 0 {
                format!(" in {blocks} blocks")
            } else {
                String::new()
            }
        );
        let run = || {
            compare(
                &MODULE,
                &label,
                &[x.clone(), w.clone(), b.clone(), sc.clone()],
                &["x", "W", "b", "s"],
                &up,
                |v| sine_linear(&v[0], &v[1], &v[2], Some(&v[3]), Numerics::PARITY),
            )
        };
        out.extend(if blocks > 0 {
            with_block_limit(blocks, run)?
        } else {
            run()?
        });
    }
    Ok(out)
}
