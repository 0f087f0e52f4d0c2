//! The row ops on the CPU: candle's `index_select`/`gather` and `index_add`/`scatter_add`
//! additions, in their order.

use candle_core::{CpuStorage, Layout};

use crate::compute::kernel::storage::slice;

/// A row op's values and ids (named by `[values, ids]` in errors), once the module may run
/// on the CPU (the fault switch).
fn inputs<'a>(
    [s1, s2]: [&'a CpuStorage; 2],
    [l1, l2]: [&Layout; 2],
    [values, ids]: [&str; 2],
) -> candle_core::Result<(&'a [f32], &'a [u32])> {
    crate::compute::kernel::health::cpu_launch(&super::MODULE)?;
    Ok((slice(s1, l1, values)?, slice(s2, l2, ids)?))
}

/// For each entry of ids [B,M] in order: its row of [B,M,C] and the start of the row of
/// [B,N,C] it names, checked against N.
fn rows<'a>(
    ids: &'a [u32],
    [n, m, c]: [usize; 3],
    what: &'a str,
) -> impl Iterator<Item = candle_core::Result<(usize, usize)>> + 'a {
    ids.iter().enumerate().map(move |(row, &i)| {
        let i = i as usize;
        if i >= n {
            candle_core::bail!("{what}: index {i} out of range for {n} rows")
        }
        Ok((row, ((row / m) * n + i) * c))
    })
}

/// out [B,M,C] = x [B,N,C] rows picked by ids [B,M].
pub(super) fn gather(
    s: [&CpuStorage; 2],
    l: [&Layout; 2],
    [b, n, m, c]: [usize; 4],
) -> candle_core::Result<CpuStorage> {
    let (x, ids) = inputs(s, l, ["gather rows: values", "gather rows: ids"])?;
    let mut out = Vec::with_capacity(b * m * c);
    for r in rows(ids, [n, m, c], "gather rows") {
        let (_, start) = r?;
        out.extend_from_slice(&x[start..start + c]);
    }
    Ok(CpuStorage::F32(out))
}

/// grad_x [B,N,C] from grad [B,M,C] scattered by ids [B,M]: index order, each slot from +0
/// (the additions candle's index_add/scatter_add make).
pub(super) fn scatter_add(
    s: [&CpuStorage; 2],
    l: [&Layout; 2],
    [b, n, m, c]: [usize; 4],
) -> candle_core::Result<CpuStorage> {
    let (g, ids) = inputs(s, l, ["scatter-add rows: values", "scatter-add rows: ids"])?;
    let mut dst = vec![0f32; b * n * c];
    for r in rows(ids, [n, m, c], "scatter-add rows") {
        let (row, d) = r?;
        for (a, v) in dst[d..d + c].iter_mut().zip(&g[row * c..(row + 1) * c]) {
            *a += v;
        }
    }
    Ok(CpuStorage::F32(dst))
}
