//! The pool's kernels against candle's ops ([`crate::compute::kernel::check`]).

use candle_core::{Device, Tensor};

use super::{window_pool, window_pool_of, MODULE};
use crate::compute::kernel::check::{compare, random, Case, Size};
use crate::compute::kernel::launch::with_block_limit;
use crate::compute::numerics::Numerics;

/// Sizes (N, J, H, P): blocks that do not divide evenly, several poses, one point; in the
/// full check also a grid of 2 blocks (every thread walks many elements). (No points: the
/// generic max-pool refuses an empty reduction.)
pub(super) fn check(device: &Device, size: Size) -> crate::error::Result<Vec<Case>> {
    let k = Numerics::PARITY;
    let cases: &[([usize; 4], u32)] = match size {
        Size::Quick => &[([37, 5, 7, 1], 0)],
        Size::Full => &[
            ([37, 5, 7, 1], 0),
            ([1030, 24, 16, 2], 0),
            ([12, 24, 128, 3], 2),
            ([1, 24, 16, 1], 0),
        ],
    };
    let mut out = Vec::new();
    for &([n, j, h, p], blocks) in cases {
        let seed = (n * 31 + h) as u64;
        let q = random(&[n, j, h], seed, (-1.0, 1.0), device)?;
        let g = random(&[p, j, h], seed + 1, (-1.0, 1.0), device)?;
        // A third of the rows far from every bone (w_p = 0: all joints tie).
        let w = random(&[n, j], seed + 2, (0.0, 1.0), device)?;
        let far = Tensor::zeros((n / 3, j), candle_core::DType::F32, device)?;
        let w = Tensor::cat(&[&far, &w.narrow(0, n / 3, n - n / 3)?], 0)?;
        let up = random(&[n, h], seed + 3, (-1.0, 1.0), device)?;
        let label = format!(
            "[{n},{j},{h}] P={p}{}",
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
                &[q.clone(), g.clone()],
                &["q", "g"],
                &up,
                |v| window_pool(&v[0], &v[1], &w, k),
            )
        };
        out.extend(if blocks > 0 {
            with_block_limit(blocks, run)?
        } else {
            run()?
        });
        if n > 0 && size == Size::Full {
            let ce = 9;
            let e = random(&[n * j, ce], seed + 4, (-1.0, 1.0), device)?;
            let wm = random(&[h, ce], seed + 5, (-1.0, 1.0), device)?;
            out.extend(compare(
                &MODULE,
                &format!("of a product, {label}"),
                &[e, wm, g.clone()],
                &["e", "W", "g"],
                &up,
                |v| window_pool_of(&v[0], &v[1], &v[2], &w, k),
            )?);
        }
    }
    Ok(out)
}
