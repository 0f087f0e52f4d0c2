//! The window pool on the CPU: the same f32 operations as candle's ops, in their order.

use candle_core::Tensor;

use super::QSource;
use crate::compute::kernel::storage::{with_f32, Kept};

/// One point's pooled row: `best[k] = max_j (q[j,k] + g[j,k]) · w[j]` and the first joint
/// reaching it in `arg` (a NaN wins and stays, as PyTorch's max propagates it). Written with
/// selects rather than branches, so it vectorises.
fn pool_row(q: &[f32], g: &[f32], w: &[f32], best: &mut [f32], arg: &mut [u32]) {
    let h = best.len();
    for (k, (b, a)) in best.iter_mut().zip(arg.iter_mut()).enumerate() {
        *b = (q[k] + g[k]) * w[0];
        *a = 0;
    }
    for (jj, &wj) in w.iter().enumerate().skip(1) {
        let (qj, gj) = (&q[jj * h..(jj + 1) * h], &g[jj * h..(jj + 1) * h]);
        let joint = jj as u32;
        for ((b, a), (&qv, &gv)) in best.iter_mut().zip(arg.iter_mut()).zip(qj.iter().zip(gj)) {
            let v = (qv + gv) * wj;
            let take = v > *b || (v.is_nan() & !b.is_nan());
            *b = if take { v } else { *b };
            *a = if take { joint } else { *a };
        }
    }
}

/// The pool of q [N,J,H], g [P,J,H], w [N,J] (`dims`: N, J, H, points per pose); every
/// row's arg-max goes to `arg` when it is wanted (the graph tracks gradients).
pub(super) fn forward(
    [q, g, w]: [&[f32]; 3],
    [n, j, h, per_pose]: [usize; 4],
    arg: &Kept<Vec<u32>>,
) -> candle_core::Result<Vec<f32>> {
    crate::compute::kernel::health::cpu_launch(&super::MODULE)?;
    if j > u32::MAX as usize {
        candle_core::bail!("window pool: {j} joints")
    }
    let mut dst = vec![0f32; n * h];
    // Every row's arg-max when it is kept for the backward, else one row's scratch.
    let mut args = vec![0u32; if arg.wanted() { n * h } else { h }];
    for (i, m) in dst.chunks_exact_mut(h.max(1)).enumerate() {
        let a = if arg.wanted() {
            &mut args[i * h..(i + 1) * h]
        } else {
            &mut args[..]
        };
        let gp = i / per_pose;
        pool_row(
            &q[i * j * h..(i + 1) * j * h],
            &g[gp * j * h..(gp + 1) * j * h],
            &w[i * j..(i + 1) * j],
            m,
            a,
        );
    }
    if arg.wanted() {
        arg.put(args);
    }
    Ok(dst)
}

/// The arg-max joint of every output, pooling q again (a second backward over the same
/// graph, whose forward's arg-max was used by the first).
fn pool_arg(q: &QSource, g: &Tensor, w_p: &Tensor) -> candle_core::Result<Vec<u32>> {
    let (n, j, h) = q.dims()?;
    let per_pose = n / g.dim(0)?.max(1);
    with_f32([&q.get()?, g, w_p], "window pool", |[qs, gs, ws]| {
        let mut arg = vec![0u32; n * h];
        let mut best = vec![0f32; h];
        for i in 0..n {
            let gp = (i / per_pose) * j * h;
            pool_row(
                &qs[i * j * h..(i + 1) * j * h],
                &gs[gp..gp + j * h],
                &ws[i * j..(i + 1) * j],
                &mut best,
                &mut arg[i * h..(i + 1) * h],
            );
        }
        arg
    })
}

/// The gradients of q [N,J,H] and g [P,J,H]: the upstream gradient times the window at the
/// arg-max joint (`kept`, or found again).
pub(super) fn backward(
    kept: Option<Vec<u32>>,
    q: &QSource,
    g: &Tensor,
    w_p: &Tensor,
    grad: &Tensor,
) -> candle_core::Result<(Tensor, Tensor)> {
    crate::compute::kernel::health::cpu_launch(&super::MODULE)?;
    let (n, j, h) = q.dims()?;
    let poses = g.dim(0)?;
    let per_pose = n / poses;
    let arg = match kept.filter(|a| a.len() == n * h) {
        Some(a) => a,
        None => pool_arg(q, g, w_p)?,
    };
    let (gq, gg) = with_f32([w_p, grad], "window pool", |[w, dm]| {
        let mut gq = vec![0f32; n * j * h];
        let mut gg = vec![0f32; poses * j * h];
        for i in 0..n {
            let wn = &w[i * j..(i + 1) * j];
            let gp = (i / per_pose) * j * h;
            let arg_i = &arg[i * h..(i + 1) * h];
            let dmn = &dm[i * h..(i + 1) * h];
            for k in 0..h {
                let jj = arg_i[k] as usize;
                let d = dmn[k] * wn[jj];
                gq[i * j * h + jj * h + k] = d;
                gg[gp + jj * h + k] += d;
            }
        }
        (gq, gg)
    })?;
    Ok((
        Tensor::from_vec(gq, (n, j, h), g.device())?,
        Tensor::from_vec(gg, (poses, j, h), g.device())?,
    ))
}
