//! The row ops on a device: `rows.cu`'s kernels, launched on a GPU or on the emulated grid
//! (where the atomic adds run in thread order: the CPU's index order).

use super::MODULE;
use crate::compute::kernel::launch::launch;
use crate::compute::kernel::mem::{Arg, Buf, Src};
use crate::compute::kernel::storage::u32_of;
use crate::compute::kernel::Exec;

fn dim_args([b, n, m, c]: [usize; 4]) -> candle_core::Result<[Arg<'static>; 4]> {
    Ok([
        Arg::U32(u32_of(b, "B")?),
        Arg::U32(u32_of(n, "N")?),
        Arg::U32(u32_of(m, "M")?),
        Arg::U32(u32_of(c, "C")?),
    ])
}

/// Run `kernel` with `vals` and `ids` into a zeroed [`out_len`] buffer over `threads`
/// elements (the memset and one launch).
fn run(
    exec: &Exec,
    kernel: &'static str,
    vals: Src,
    ids: Src,
    dims: [usize; 4],
    threads: usize,
    out_len: usize,
) -> candle_core::Result<Buf> {
    let mut out = exec.zeros(out_len)?;
    let mut args = vec![Arg::Src(vals), Arg::Src(ids), Arg::Dst(&mut out)];
    args.extend(dim_args(dims)?);
    launch(exec, &MODULE, kernel, threads, &mut args)?;
    drop(args);
    Ok(out)
}

/// out [B,M,C] = x [B,N,C] rows picked by ids [B,M] (an index out of range reads 0; the
/// caller's ids come checked).
pub(super) fn gather(
    exec: &Exec,
    x: Src,
    ids: Src,
    [b, n, m, c]: [usize; 4],
) -> candle_core::Result<Buf> {
    run(
        exec,
        "pma_gather_rows_f32",
        x,
        ids,
        [b, n, m, c],
        b * m * c,
        b * m * c,
    )
}

/// grad_x [B,N,C] from grad [B,M,C] scattered by ids [B,M]: atomic adds, or (`ordered`)
/// a thread per output element summing in index order.
pub(super) fn scatter_add(
    exec: &Exec,
    grad: Src,
    ids: Src,
    [b, n, m, c]: [usize; 4],
    ordered: bool,
) -> candle_core::Result<Buf> {
    let (kernel, threads) = match ordered {
        true => ("pma_scatter_add_rows_ordered_f32", b * n * c),
        false => ("pma_scatter_add_rows_f32", b * m * c),
    };
    run(exec, kernel, grad, ids, [b, n, m, c], threads, b * n * c)
}
