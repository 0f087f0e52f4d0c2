//! The bias-and-activation kernels against candle's ops ([`crate::compute::kernel::check`]).

use candle_core::Device;

use super::{linear_relu, linear_sine, MODULE};
use crate::compute::kernel::check::{compare, random, Case, Size};
use crate::compute::kernel::launch::with_block_limit;
use crate::compute::numerics::Numerics;

/// Sizes (rows, in, out): rows that leave a partial block of 256, one row, a wide layer; in
/// the full check also a grid of 3 blocks.
pub(super) fn check(device: &Device, size: Size) -> crate::error::Result<Vec<Case>> {
    let k = Numerics::PARITY;
    let cases: &[([usize; 3], u32)] = match size {
        Size::Quick => &[([300, 5, 9], 0)],
        Size::Full => &[
            ([1000, 7, 33], 0),
            ([1, 5, 2], 0),
            ([513, 128, 64], 3),
            ([0, 4, 3], 0),
        ],
    };
    let mut out = Vec::new();
    for &([rows, inn, outs], blocks) in cases {
        let seed = (rows * 7 + outs) as u64;
        let x = random(&[rows, inn], seed, (-1.0, 1.0), device)?;
        // The pose extractor's sine layers have W and b scaled by ω (up to ~30).
        let w = random(&[outs, inn], seed + 1, (-8.0, 8.0), device)?;
        let b = random(&[outs], seed + 2, (-4.0, 4.0), device)?;
        let up = random(&[rows, outs], seed + 3, (-1.0, 1.0), device)?;
        for (name, relu) in [("relu", true), ("sine", false)] {
            let label = format!(
                "{name} [{rows},{inn}]x[{outs},{inn}]{}",
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
                    &[x.clone(), w.clone(), b.clone()],
                    &["x", "W", "b"],
                    &up,
                    |v| {
                        let f = if relu { linear_relu } else { linear_sine };
                        f(&v[0], &v[1], &v[2], k)
                    },
                )
            };
            out.extend(if blocks > 0 {
                with_block_limit(blocks, run)?
            } else {
                run()?
            });
        }
    }
    Ok(out)
}
