//! The feature window's max-pool `m = max_j (q_j + g_j) · w^p_j` as one op.
//!
//! In candle's ops the pool builds two [N,24,128] tensors forward and about ten passes over
//! that size backward (an equality mask, casts, products, candle's zero-then-add
//! accumulation). Here the forward reads q once and keeps the arg-max joint of every output
//! when the graph tracks gradients; the backward scatters the gradient to it. The same f32
//! operations in the same order, so the values and gradients are candle's bits, except on
//! exact ties of the max, where the gradient goes to the first maximal joint (PyTorch's
//! rule, the reference's) instead of to every tied joint (candle's). Ties only occur where
//! w^p = 0, so both give 0 there. A second backward over the same graph pools again.
//!
//! [`window_pool_of`] also computes q = e · Wᵀ inside the op and frees it at once: the
//! pool's backward needs only the arg-max, and a [N,J,H] product kept alive until the
//! backward was the largest single tensor of a training step.
//!
//! Routes ([`crate::compute::kernel`]): the CPU code of [`cpu`]; the kernels of
//! `window_pool.cu` ([`device`]); candle's ops.

mod check;
mod cpu;
mod device;

use candle_core::{CpuStorage, Layout, Shape, Storage, Tensor};

use crate::compute::kernel::mem::{Buf, Src};
use crate::compute::kernel::op::{product_grads, CpuForward, Forward, Inputs, Kernel, Op, Product};
use crate::compute::kernel::storage::{f32_slice, Kept};
use crate::compute::kernel::{self, Exec};
use crate::compute::numerics::Numerics;
use crate::error::Result;

crate::kernel_module!(
    "window_pool",
    "window_pool.cu",
    pma_emu_window_pool,
    check::check
);

/// `max_j (q[n,j,:] + g[p(n),j,:]) · w_p[n,j]`: q: [N,J,H], g: [P,J,H], w_p: [N,J] -> [N,H],
/// the N points grouped by pose in P equal blocks (point n belongs to pose `n / (N/P)`).
/// No gradient flows to `w_p` (the reference detaches the spatial window).
pub fn window_pool(q: &Tensor, g: &Tensor, w_p: &Tensor, k: Numerics) -> Result<Tensor> {
    let (n, j, h) = q.dims3()?;
    let p = g.dim(0)?;
    if g.dims() != [p, j, h] || p == 0 || n % p != 0 {
        return Err(crate::error::ModelError::shape(
            "window pool: g",
            format!("[P,{j},{h}] with P dividing {n}"),
            g.dims(),
        ));
    }
    let generic = || generic(q, g, w_p);
    let Some(exec) = kernel::fused_route(k.fused, &MODULE, &[q, g, w_p]) else {
        return generic();
    };
    kernel::or_generic(
        &MODULE,
        || {
            let (q, g) = (q.contiguous()?, g.contiguous()?);
            let op = WindowPool::new(q.track_op() || g.track_op(), exec.clone());
            let out = q.apply_op3(&g, &w_p.detach().contiguous()?, Op(op))?;
            if let Some(exec) = &exec {
                device::record_arg(exec, out.elem_count());
            }
            Ok(out)
        },
        generic,
    )
}

/// candle's ops for [`window_pool`].
fn generic(q: &Tensor, g: &Tensor, w_p: &Tensor) -> Result<Tensor> {
    let (n, j, h) = q.dims3()?;
    let p = g.dim(0)?;
    let part = q
        .reshape((p, n / p, j, h))?
        .broadcast_add(&g.unsqueeze(1)?)?
        .reshape((n, j, h))?;
    Ok(part
        .broadcast_mul(&w_p.unsqueeze(candle_core::D::Minus1)?)?
        .max(1)?)
}

/// [`window_pool`] of `q = e · Wᵀ` (e: [N·J,Ce], W: [H,Ce] in PyTorch's layout, viewed as
/// [N,J,H]) as one op that computes the product and pools it without keeping q (see the
/// module docs). The same product and pool as the two ops, so the same values and gradients.
pub fn window_pool_of(
    e: &Tensor,
    w: &Tensor,
    g: &Tensor,
    w_p: &Tensor,
    k: Numerics,
) -> Result<Tensor> {
    let (nj, ce) = e.dims2()?;
    let (h, ce2) = w.dims2()?;
    let (p, j, h2) = g.dims3()?;
    if ce2 != ce || h2 != h || j == 0 || nj % j != 0 {
        return Err(crate::error::ModelError::shape(
            "window pool: e, W and g",
            format!("e [N·{j},Ce], W [{h2},Ce]"),
            e.dims(),
        ));
    }
    let n = nj / j;
    let two_ops = || {
        let q = crate::compute::numerics::matmul(e, &w.t()?, k)?.reshape((n, j, h))?;
        window_pool(&q, g, w_p, k)
    };
    let route = kernel::fused_route(k.fused, &MODULE, &[e, w, g, w_p]);
    let Some(exec) = route.filter(|_| p > 0 && n % p == 0) else {
        return two_ops();
    };
    kernel::or_generic(
        &MODULE,
        || {
            let (e, w, g) = (e.contiguous()?, w.contiguous()?, g.contiguous()?);
            let op = WindowPoolOf {
                inner: WindowPool::new(e.track_op() || w.track_op() || g.track_op(), exec.clone()),
                w_p: w_p.detach().contiguous()?,
                j,
            };
            Ok(candle_core::cuda::with_gemm_reduced_precision_f32(
                k.tf32,
                || e.apply_op3(&w, &g, Op(op)),
            )?)
        },
        two_ops,
    )
}

/// The pool's op on (q, g, w_p). When the graph tracks gradients the forward keeps the
/// arg-max of every output for the backward.
struct WindowPool {
    /// The device kernels' executor, or `None` on the CPU's route.
    exec: Option<Exec>,
    /// The CPU route's arg-max.
    arg: Kept<Vec<u32>>,
    /// The device route's arg-max, with its bytes held live in an accounted run.
    arg_dev: Kept<(Buf, candle_core::account::Held)>,
}

impl WindowPool {
    fn new(tracked: bool, exec: Option<Exec>) -> Self {
        Self {
            exec,
            arg: Kept::new(tracked),
            arg_dev: Kept::new(tracked),
        }
    }

    /// The device forward on storages of `exec`; keeps the arg-max when wanted.
    fn device_fwd(
        &self,
        exec: &Exec,
        [q, g, w]: [Src; 3],
        dims: [usize; 4],
    ) -> candle_core::Result<Buf> {
        let (out, arg) = device::forward(exec, [q, g, w], dims)?;
        if self.arg_dev.wanted() {
            let held = candle_core::account::hold(exec.is_host(), arg.bytes());
            self.arg_dev.put((arg, held));
        }
        Ok(out)
    }

    /// The gradients of q and g: from the forward's kept arg-max, or (a second backward)
    /// from pooling q again.
    fn grads(
        &self,
        q: &QSource,
        g: &Tensor,
        w_p: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Tensor, Tensor)> {
        match &self.exec {
            Some(exec) => device::backward(exec, self.arg_dev.take(), q, g, w_p, grad),
            None => cpu::backward(self.arg.take(), q, g, w_p, grad),
        }
    }
}

/// (N, J, H, points per pose) of q [N,J,H], g [P,J,H], w [N,J], checked.
fn dims(lq: &Layout, lg: &Layout, lw: &Layout) -> candle_core::Result<[usize; 4]> {
    let (n, j, h) = lq.shape().dims3()?;
    let (p, j2, h2) = lg.shape().dims3()?;
    if j2 != j || h2 != h || p == 0 || n % p != 0 || lw.shape().dims2()? != (n, j) {
        candle_core::bail!("window pool: shapes do not agree with q [{n},{j},{h}]")
    }
    Ok([n, j, h, n / p])
}

impl Kernel<3> for WindowPool {
    fn name(&self) -> &'static str {
        "pma-window-pool"
    }

    fn device(
        &self,
        exec: &Exec,
        srcs: [Src; 3],
        l: [&Layout; 3],
    ) -> candle_core::Result<(Buf, Shape)> {
        let d = dims(l[0], l[1], l[2])?;
        candle_core::account::report_launches(1, 0);
        Ok((self.device_fwd(exec, srcs, d)?, Shape::from((d[0], d[2]))))
    }

    fn cpu(&self, s: [&CpuStorage; 3], l: [&Layout; 3]) -> Option<CpuForward> {
        self.exec.is_none().then(|| {
            let d = dims(l[0], l[1], l[2])?;
            let f = |i: usize, what| f32_slice(s[i], l[i], what);
            let out = cpu::forward([f(0, "q")?, f(1, "g")?, f(2, "w_p")?], d, &self.arg)?;
            Ok((CpuStorage::F32(out), Shape::from((d[0], d[2]))))
        })
    }

    fn backward(
        &self,
        [q, g, w_p]: [&Tensor; 3],
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<[Option<Tensor>; 3]> {
        let (gq, gg) = self.grads(&QSource::Tensor(q), g, w_p, grad)?;
        Ok([Some(gq), Some(gg), None])
    }
}

/// [`window_pool_of`]'s op on (e, W, g), the spatial window held (no gradient flows to it).
struct WindowPoolOf {
    inner: WindowPool,
    w_p: Tensor,
    j: usize,
}

impl WindowPoolOf {
    /// (N, J, H, Ce) of e [N·J,Ce] and W [H,Ce], checked.
    fn dims(&self, l1: &Layout, l2: &Layout) -> candle_core::Result<(usize, usize, usize, usize)> {
        let (nj, ce) = l1.shape().dims2()?;
        let (h, ce2) = l2.shape().dims2()?;
        if ce2 != ce || nj % self.j != 0 {
            candle_core::bail!(
                "window pool: e {:?} and W {:?} do not agree",
                l1.shape(),
                l2.shape()
            )
        }
        Ok((nj / self.j, self.j, h, ce))
    }

    /// Count the op as its two kernels: this op is the product (its launch, bytes and
    /// FLOPs); the pool is recorded beside it.
    fn report(&self, host: bool, (n, j, h, ce): (usize, usize, usize, usize), g_len: usize) {
        let (nj, h64, ce) = ((n * j) as u64, h as u64, ce as u64);
        candle_core::account::report_launches(1, 0);
        candle_core::account::report_bytes(4 * (nj * ce + h64 * ce), 4 * nj * h64);
        candle_core::account::report_flops(2 * nj * h64 * ce);
        device::record_pool(
            host,
            [n, j, h],
            g_len,
            self.inner.arg.wanted() || self.inner.arg_dev.wanted(),
        );
    }
}

impl Product for WindowPoolOf {
    /// The product exactly as `Tensor::matmul` calls it for e · Wᵀ (freed on return), then
    /// the pool: the CPU's code on the CPU's route, the kernel otherwise.
    fn forward(&self, inputs: Inputs<'_, 3>, [l1, l2, l3]: [&Layout; 3]) -> Forward {
        let (n, j, h, ce) = self.dims(l1, l2)?;
        let exec = inputs.exec();
        self.report(exec.is_host(), (n, j, h, ce), l3.shape().elem_count());
        let q = inputs.product((0, l1), (1, l2), (n * j, ce, h))?;
        let lq = Layout::contiguous((n, j, h));
        let (wp, wl) = self.w_p.storage_and_layout();
        let d = dims(&lq, l3, wl)?;
        let out = match (&self.inner.exec, q) {
            (None, Buf::F32(q)) => match (&inputs, &*wp) {
                (Inputs::Cpu([_, _, g]), Storage::Cpu(wp)) => {
                    let (g, wp) = (f32_slice(g, l3, "g")?, f32_slice(wp, wl, "w_p")?);
                    Buf::F32(cpu::forward([&q, g, wp], d, &self.inner.arg)?)
                }
                _ => candle_core::bail!("window pool: the CPU's route on other storages"),
            },
            (_, q) => {
                let srcs = [q.src(), inputs.src(2, l3, "g")?, Src::of(&wp, wl, "w_p")?];
                self.inner.device_fwd(&exec, srcs, d)?
            }
        };
        Ok((out, Shape::from((n, h))))
    }

    fn backward(
        &self,
        [e, w, g]: [&Tensor; 3],
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<[Option<Tensor>; 3]> {
        let q = QSource::Product { e, w, j: self.j };
        let (gq, gg) = self.inner.grads(&q, g, &self.w_p, grad)?;
        // The product's gradients on the [N·J,H] view.
        let gq = gq.reshape((e.dim(0)?, w.dim(0)?))?;
        let (ge, gw) = product_grads(e, w, &gq)?;
        Ok([ge, Some(gw), Some(gg)])
    }
}

/// Where a window pool's backward gets q when it must pool again (a second backward over
/// the same graph): the forward's input, or the product [`window_pool_of`] computed it from.
enum QSource<'a> {
    Tensor(&'a Tensor),
    /// q = e · Wᵀ, [N·J,Ce] · [H,Ce]ᵀ, viewed as [N,J,H].
    Product {
        e: &'a Tensor,
        w: &'a Tensor,
        j: usize,
    },
}

impl QSource<'_> {
    fn dims(&self) -> candle_core::Result<(usize, usize, usize)> {
        match self {
            Self::Tensor(q) => q.dims3(),
            Self::Product { e, w, j } => Ok((e.dim(0)? / j, *j, w.dim(0)?)),
        }
    }

    fn get(&self) -> candle_core::Result<Tensor> {
        match self {
            Self::Tensor(q) => Ok((*q).clone()),
            Self::Product { e, w, j } => {
                let (n, h) = (e.dim(0)? / j, w.dim(0)?);
                e.matmul(&w.t()?)?.reshape((n, *j, h))
            }
        }
    }
}

#[cfg(test)]
mod tests;
