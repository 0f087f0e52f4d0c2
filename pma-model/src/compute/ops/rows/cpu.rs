//! The row ops on the CPU: candle's `index_select`/`gather` and `index_add`/`scatter_add`
//! additions, in their order.

use candle_core::{CpuStorage, Layout};

use crate::compute::kernel::storage::slice;

/// out [B,M,C] = x [B,N,C] rows picked by ids [B,M].
pub(super) fn gather(
    s1: &CpuStorage,
    l1: &Layout,
    s2: &CpuStorage,
    l2: &Layout,
    [b, n, m, c]: [usize; 4],
) -> candle_core::Result<CpuStorage> {
    crate::compute::kernel::health::cpu_launch(&super::MODULE)?;
    let x: &[f32] = slice(s1, l1, "gather rows: x")?;
    let ids: &[u32] = slice(s2, l2, "gather rows: ids")?;
    let mut out = Vec::with_capacity(b * m * c);
    for (row, &i) in ids.iter().enumerate() {
        let i = i as usize;
        if i >= n {
            candle_core::bail!("gather rows: index {i} out of range for {n} rows")
        }
        let start = ((row / m) * n + i) * c;
        out.extend_from_slice(&x[start..start + c]);
    }
    Ok(CpuStorage::F32(out))
}

/// grad_x [B,N,C] from grad [B,M,C] scattered by ids [B,M]: index order, each slot from +0
/// (the additions candle's index_add/scatter_add make).
pub(super) fn scatter_add(
    s1: &CpuStorage,
    l1: &Layout,
    s2: &CpuStorage,
    l2: &Layout,
    [b, n, m, c]: [usize; 4],
) -> candle_core::Result<CpuStorage> {
    crate::compute::kernel::health::cpu_launch(&super::MODULE)?;
    let g: &[f32] = slice(s1, l1, "scatter-add rows: grad")?;
    let ids: &[u32] = slice(s2, l2, "scatter-add rows: ids")?;
    let mut dst = vec![0f32; b * n * c];
    for (row, &i) in ids.iter().enumerate() {
        let i = i as usize;
        if i >= n {
            candle_core::bail!("scatter-add rows: index {i} out of range for {n} rows")
        }
        let d = ((row / m) * n + i) * c;
        for (a, v) in dst[d..d + c].iter_mut().zip(&g[row * c..(row + 1) * c]) {
            *a += v;
        }
    }
    Ok(CpuStorage::F32(dst))
}
