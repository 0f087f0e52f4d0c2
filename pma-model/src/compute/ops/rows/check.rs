//! The row kernels against candle's ops ([`crate::compute::kernel::check`]).

use candle_core::{Device, Tensor};

use super::{gather_rows, select_rows, MODULE};
use crate::compute::kernel::check::{cases, compare_in, random, Case, Size};
use crate::compute::numerics::Numerics;

/// Gathers of (B, N, C) with M picks per row and a grid cap, with repeated indices (many
/// rays share a frame code), by the atomic and the ordered scatter: small, a frame-code
/// lookup's size, a grid of 2 blocks, no picks.
pub(super) fn check(device: &Device, size: Size) -> crate::error::Result<Vec<Case>> {
    let all = [
        ([3, 11, 300, 5], 0),
        ([1, 780, 3072, 128], 0),
        ([6, 72, 72, 4], 2),
        ([2, 5, 0, 3], 0),
    ];
    let mut out = Vec::new();
    for &([b, n, m, c], blocks) in cases(size, &all) {
        let seed = (n * 3 + m) as u64;
        let x = random(&[b, n, c], seed, (-1.0, 1.0), device)?;
        let ids: Vec<u32> = (0..b * m).map(|i| ((i * 7 + i / 5) % n) as u32).collect();
        let ids = Tensor::from_vec(ids, (b, m), device)?;
        let up = random(&[b, m, c], seed + 1, (-1.0, 1.0), device)?;
        for deterministic in [false, true] {
            let k = Numerics {
                deterministic,
                ..Numerics::PARITY
            };
            let label = format!(
                "gather [{b},{n},{c}] by [{b},{m}]{}",
                if deterministic { ", ordered" } else { "" }
            );
            out.extend(compare_in(
                blocks,
                &MODULE,
                &label,
                std::slice::from_ref(&x),
                &["x"],
                &up,
                |v| gather_rows(&v[0], &ids, k),
            )?);
        }
        if b == 1 {
            let (x, ids, up) = (x.squeeze(0)?, ids.squeeze(0)?, up.squeeze(0)?);
            let label = format!("select [{n},{c}] by [{m}]");
            out.extend(compare_in(
                blocks,
                &MODULE,
                &label,
                &[x],
                &["x"],
                &up,
                |v| select_rows(&v[0], &ids, Numerics::PARITY),
            )?);
        }
    }
    Ok(out)
}
