//! The FiLM-sine kernels against candle's ops ([`crate::compute::kernel::check`]).

use candle_core::Device;

use super::{FilmHead, MODULE};
use crate::compute::kernel::check::{compare, random, Case, Size};
use crate::compute::kernel::launch::with_block_limit;
use crate::compute::numerics::Numerics;

/// A whole stack (shared head gradient) of (N, F, K): frequencies up to ~30, as the
/// modulator's; in the full check also a grid of 2 blocks and no rows.
pub(super) fn check(device: &Device, size: Size) -> crate::error::Result<Vec<Case>> {
    let cases: &[([usize; 3], u32)] = match size {
        Size::Quick => &[([29, 8, 3], 0)],
        Size::Full => &[
            ([29, 8, 3], 0),
            ([1000, 128, 4], 0),
            ([300, 16, 2], 2),
            ([0, 8, 2], 0),
        ],
    };
    let mut out = Vec::new();
    for &([n, f, kk], blocks) in cases {
        let seed = (n * 13 + f) as u64;
        let x = random(&[n, f], seed, (-1.0, 1.0), device)?;
        let o = random(&[n, 2 * kk * f], seed + 1, (-4.0, 4.0), device)?;
        let up = random(&[n, kk * f], seed + 2, (-1.0, 1.0), device)?;
        let label = format!(
            "stack of {kk} [{n},{f}]{}",
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
                &[x.clone(), o.clone()],
                &["x", "head"],
                &up,
                |v| {
                    let head = FilmHead::new(&v[1], kk, (15.0, 30.0), Numerics::PARITY);
                    let outs = head.stack(&v[0], |_, h| Ok((h * 0.5)?))?;
                    Ok(candle_core::Tensor::cat(&outs, 1)?)
                },
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
