//! The pool's kernels against candle's ops ([`crate::compute::kernel::check`]).

use candle_core::{Device, Tensor};

use super::{window_pool, window_pool_of, MODULE};
use crate::compute::kernel::check::{cases, compare_in, random, Case, Size};
use crate::compute::numerics::Numerics;

/// (N, J, H, P) and a grid cap: blocks that do not divide evenly, several poses, a grid of
/// 2 blocks, one point (no points: the generic max-pool refuses an empty reduction).
pub(super) fn check(device: &Device, size: Size) -> crate::error::Result<Vec<Case>> {
    let k = Numerics::PARITY;
    let all = [
        ([37, 5, 7, 1], 0),
        ([1030, 24, 16, 2], 0),
        ([12, 24, 128, 3], 2),
        ([1, 24, 16, 1], 0),
    ];
    let mut out = Vec::new();
    for &([n, j, h, p], blocks) in cases(size, &all) {
        let seed = (n * 31 + h) as u64;
        let q = random(&[n, j, h], seed, (-1.0, 1.0), device)?;
        let g = random(&[p, j, h], seed + 1, (-1.0, 1.0), device)?;
        // A third of the rows far from every bone (w_p = 0: all joints tie).
        let w = random(&[n, j], seed + 2, (0.0, 1.0), device)?;
        let far = Tensor::zeros((n / 3, j), candle_core::DType::F32, device)?;
        let w = Tensor::cat(&[&far, &w.narrow(0, n / 3, n - n / 3)?], 0)?;
        let up = random(&[n, h], seed + 3, (-1.0, 1.0), device)?;
        let label = format!("[{n},{j},{h}] P={p}");
        out.extend(compare_in(
            blocks,
            &MODULE,
            &label,
            &[q, g.clone()],
            &["q", "g"],
            &up,
            |v| window_pool(&v[0], &v[1], &w, k),
        )?);
        let e = random(&[n * j, 9], seed + 4, (-1.0, 1.0), device)?;
        let wm = random(&[h, 9], seed + 5, (-1.0, 1.0), device)?;
        let label = format!("of a product, {label}");
        out.extend(compare_in(
            blocks,
            &MODULE,
            &label,
            &[e, wm, g],
            &["e", "W", "g"],
            &up,
            |v| window_pool_of(&v[0], &v[1], &v[2], &w, k),
        )?);
    }
    Ok(out)
}
