//! The window pool on a device: `window_pool.cu`'s kernels, launched on a GPU or on the
//! emulated grid.

use std::sync::Arc;

use candle_core::{Layout, Shape, Tensor};

use super::{QSource, MODULE};
use crate::compute::kernel::launch::launch;
use crate::compute::kernel::mem::{Arg, Buf, Src};
use crate::compute::kernel::op::{Kernel, Op};
use crate::compute::kernel::storage::u32_of;
use crate::compute::kernel::Exec;

/// The pool's kernel: (the max [N,H], the arg-max joint [N,H]) of q [N,J,H], g [P,J,H] and
/// w [N,J] (contiguous f32). One launch.
pub(super) fn forward(
    exec: &Exec,
    [q, g, w]: [Src; 3],
    [n, j, h, per_pose]: [usize; 4],
) -> candle_core::Result<(Buf, Buf)> {
    let mut out = exec.output(n * h)?;
    let mut arg = exec.output_u32(n * h)?;
    launch(
        exec,
        &MODULE,
        "pma_window_pool_f32",
        n * h,
        &mut [
            Arg::Src(q),
            Arg::Src(g),
            Arg::Src(w),
            Arg::Dst(&mut out),
            Arg::Dst(&mut arg),
            Arg::U32(u32_of(n, "N")?),
            Arg::U32(u32_of(j, "J")?),
            Arg::U32(u32_of(h, "H")?),
            Arg::U32(u32_of(per_pose, "points per pose")?),
        ],
    )?;
    Ok((out, arg))
}

/// Count the arg-max the pool's kernel writes beside its output (`n_out` u32s).
pub(super) fn record_arg(exec: &Exec, n_out: usize) {
    candle_core::account::record(
        exec.is_host(),
        candle_core::account::Op {
            name: "pma-window-pool",
            launches: 0,
            param_uploads: 0,
            bytes_read: 0,
            bytes_written: (n_out * 4) as u64,
            flops: 0,
        },
    );
}

/// Count one launch of the pool's kernel on q [N,J,H] (reading q, g and the window; writing
/// the max, and the arg-max when `kept`).
pub(super) fn record_pool(host: bool, [n, j, h]: [usize; 3], g_len: usize, kept: bool) {
    let nh = (n * h) as u64;
    candle_core::account::record(
        host,
        candle_core::account::Op {
            name: "pma-window-pool",
            launches: 1,
            param_uploads: 0,
            bytes_read: 4 * ((n * j * h + g_len + n * j) as u64),
            bytes_written: 4 * nh * (1 + u64::from(kept)),
            flops: 0,
        },
    );
}

/// The gradients of q [N,J,H] and g [P,J,H]: from the forward's kept arg-max, or (a
/// second backward) the forward's kernel once more; then one kernel per gradient.
pub(super) fn backward(
    exec: &Exec,
    kept: Option<(Buf, candle_core::account::Held)>,
    q: &QSource,
    g: &Tensor,
    w_p: &Tensor,
    grad: &Tensor,
) -> candle_core::Result<(Tensor, Tensor)> {
    let (n, j, h) = q.dims()?;
    let p = g.dim(0)?;
    let w = w_p.contiguous()?;
    let (arg, held) = match kept {
        Some(k) => k,
        None => {
            let (qt, gt) = (q.get()?.contiguous()?, g.contiguous()?);
            let guards = [&qt, &gt, &w].map(|t| t.storage_and_layout());
            let src = |i: usize| Src::of(&guards[i].0, guards[i].1, "window pool");
            let (_, arg) = forward(exec, [src(0)?, src(1)?, src(2)?], [n, j, h, n / p])?;
            record_pool(exec.is_host(), [n, j, h], g.elem_count(), true);
            let held = candle_core::account::hold(exec.is_host(), arg.bytes());
            (arg, held)
        }
    };
    let arg = Arc::new(arg);
    let grad = grad.contiguous()?;
    let op = |of_g| PoolGrad {
        arg: arg.clone(),
        dims: [n, p, j, h],
        of_g,
    };
    let gq = grad.apply_op2_no_bwd(&w, &Op(op(false)))?;
    let gg = grad.apply_op2_no_bwd(&w, &Op(op(true)))?;
    drop(held);
    Ok((gq, gg))
}

/// One gradient of the pool (of q, or of g when `of_g`) on (upstream gradient [N,H],
/// window [N,J]) from the arg-max: a kernel of `window_pool.cu`.
struct PoolGrad {
    arg: Arc<Buf>,
    /// N, P, J, H.
    dims: [usize; 4],
    of_g: bool,
}

impl Kernel<2> for PoolGrad {
    fn name(&self) -> &'static str {
        "pma-window-pool-grad"
    }

    fn device(
        &self,
        exec: &Exec,
        [grad, w]: [Src; 2],
        l: [&Layout; 2],
    ) -> candle_core::Result<(Buf, Shape)> {
        let [n, p, j, h] = self.dims;
        if l[0].shape().dims2()? != (n, h) || l[1].shape().dims2()? != (n, j) {
            candle_core::bail!("window pool gradient: shapes do not agree with [{n},{j},{h}]")
        }
        candle_core::account::report_launches(1, 0);
        let (len, shape) = match self.of_g {
            true => (p * j * h, Shape::from((p, j, h))),
            false => (n * j * h, Shape::from((n, j, h))),
        };
        candle_core::account::report_bytes(4 * (2 * n * h + n * j) as u64, 4 * len as u64);
        let mut out = exec.output(len)?;
        let dims = [u32_of(n, "N")?, u32_of(j, "J")?, u32_of(h, "H")?];
        let mut args = vec![
            Arg::Src(grad),
            Arg::Src(w),
            Arg::Src(self.arg.src()),
            Arg::Dst(&mut out),
        ];
        let kernel = match self.of_g {
            true => {
                args.push(Arg::U32(u32_of(p, "P")?));
                args.extend(dims[1..].iter().map(|&d| Arg::U32(d)));
                args.push(Arg::U32(u32_of(n / p, "points per pose")?));
                "pma_window_pool_grad_g_f32"
            }
            false => {
                args.extend(dims.iter().map(|&d| Arg::U32(d)));
                "pma_window_pool_grad_q_f32"
            }
        };
        launch(exec, &MODULE, kernel, len, &mut args)?;
        drop(args);
        Ok((out, shape))
    }
}
