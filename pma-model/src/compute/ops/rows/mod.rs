//! Row gathers whose gradient does not run serially on a GPU.
//!
//! candle's CUDA `index_add` and `scatter_add` (the backward passes of `index_select` and
//! `gather`) give one thread per column and loop over every index in that thread, without
//! atomics: the frame-code lookup's gradient is 128 threads walking all rays of a chunk, the
//! merge of coarse and fine samples 4 threads per ray walking its 72 samples (see
//! docs/gpu.md, "Training graph audit"). [`gather_rows`] and [`select_rows`] compute the
//! same values with one op whose backward has one thread per (index, column) and adds with
//! `atomicAdd` on CUDA (`rows.cu`).
//!
//! On the CPU the op runs the same f32 additions in the same order as candle's kernels
//! (rows in index order, each accumulated from zero), so forward values and gradients are
//! bit-identical to candle's ops (`tests`). On CUDA, rows that share an index (all rays of
//! an image share its frame code) are summed in no fixed order: the gradient can differ
//! from run to run by float rounding, unless [`Numerics::deterministic`] asks for the
//! ordered kernel. Other dtypes and devices take candle's ops.

mod check;
mod cpu;
mod device;

use candle_core::{CpuStorage, DType, Layout, Shape, Tensor};

use crate::compute::kernel::mem::{Buf, Src};
use crate::compute::kernel::op::{CpuForward, Kernel, Op};
use crate::compute::kernel::{self, Exec, Route};
use crate::compute::numerics::Numerics;
use crate::error::{ModelError, Result};

crate::kernel_module!("rows", "rows.cu", pma_emu_rows, check::check);

/// `x.index_select(ids, 0)`: x [N,C], ids [M] (u32) -> [M,C].
pub fn select_rows(x: &Tensor, ids: &Tensor, k: Numerics) -> Result<Tensor> {
    let (n, c) = x.dims2()?;
    let m = ids.dims1()?;
    if matches!(kernel::route(k.row_ops, &MODULE, &[x]), Route::Generic) {
        return Ok(x.index_select(&ids.to_dtype(DType::U32)?, 0)?);
    }
    let out = gather_rows(&x.reshape((1, n, c))?, &ids.reshape((1, m))?, k)?;
    Ok(out.reshape((m, c))?)
}

/// Rows of x picked along dim 1, the same index for every column: x [B,N,C], ids [B,M]
/// (u32, < N) -> out [B,M,C] with `out[b,m,:] = x[b, ids[b,m], :]` (candle's
/// `x.gather(ids broadcast to [B,M,C], 1)`).
pub fn gather_rows(x: &Tensor, ids: &Tensor, k: Numerics) -> Result<Tensor> {
    let (b, _n, c) = x.dims3()?;
    let (bi, m) = ids.dims2()?;
    if bi != b {
        return Err(ModelError::shape("row ids", format!("[{b},M]"), ids.dims()));
    }
    let ids = ids.to_dtype(DType::U32)?;
    let generic = || -> Result<Tensor> {
        let idx = ids.unsqueeze(2)?.broadcast_as((b, m, c))?.contiguous()?;
        Ok(x.gather(&idx, 1)?)
    };
    let Some(exec) = kernel::fused_route(k.row_ops, &MODULE, &[x]) else {
        return generic();
    };
    kernel::or_generic(
        &MODULE,
        || {
            let op = RowOp {
                way: Way::Gather,
                exec: exec.clone(),
                deterministic: k.deterministic,
            };
            Ok(x.contiguous()?
                .apply_op2(&ids.detach().contiguous()?, Op(op))?)
        },
        generic,
    )
}

/// For step accounting: on a device each row op is a memset of its zeroed output and one
/// kernel; the CPU forward reports the same.
fn report_launches() {
    candle_core::account::report_launches(2, 0);
}

/// (B, N, M, C) of values [B,N,C] (a gather's input) or [B,M,C] (a scatter's gradient)
/// against ids [B,M], checked; N or M is the values' middle dimension.
fn dims_bmc(l_vals: &Layout, l_ids: &Layout, what: &str) -> candle_core::Result<[usize; 4]> {
    let (b, n, c) = l_vals.shape().dims3()?;
    let (bi, m) = l_ids.shape().dims2()?;
    if bi != b {
        candle_core::bail!("{what}: values [{b},{n},{c}] but ids [{bi},{m}]")
    }
    Ok([b, n, m, c])
}

/// Which way an op moves rows.
#[derive(Clone, Copy)]
enum Way {
    /// Forward: x [B,N,C], ids [B,M] -> [B,M,C].
    Gather,
    /// Backward: grad [B,M,C], ids [B,M] -> grad_x [B,N,C], rows summed from zero.
    ScatterAdd { n: usize },
}

struct RowOp {
    way: Way,
    /// The device kernels' executor, or `None` on the CPU's route.
    exec: Option<Exec>,
    /// The device scatter sums in index order, without atomics (the CPU always does;
    /// [`Numerics::deterministic`]).
    deterministic: bool,
}

impl RowOp {
    /// (B, N, M, C) and the output's shape, checked.
    fn dims(&self, l_vals: &Layout, l_ids: &Layout) -> candle_core::Result<([usize; 4], Shape)> {
        Ok(match self.way {
            Way::Gather => {
                let [b, n, m, c] = dims_bmc(l_vals, l_ids, "gather rows")?;
                ([b, n, m, c], Shape::from((b, m, c)))
            }
            Way::ScatterAdd { n } => {
                let [b, m, _, c] = dims_bmc(l_vals, l_ids, "scatter-add rows")?;
                ([b, n, m, c], Shape::from((b, n, c)))
            }
        })
    }
}

impl Kernel<2> for RowOp {
    fn name(&self) -> &'static str {
        match self.way {
            Way::Gather => "pma-gather-rows",
            Way::ScatterAdd { .. } => "pma-scatter-add-rows",
        }
    }

    fn device(
        &self,
        exec: &Exec,
        [vals, ids]: [Src; 2],
        [l1, l2]: [&Layout; 2],
    ) -> candle_core::Result<(Buf, Shape)> {
        let (d, shape) = self.dims(l1, l2)?;
        report_launches();
        let out = match self.way {
            Way::Gather => device::gather(exec, vals, ids, d)?,
            Way::ScatterAdd { .. } => device::scatter_add(exec, vals, ids, d, self.deterministic)?,
        };
        Ok((out, shape))
    }

    fn cpu(&self, s: [&CpuStorage; 2], l: [&Layout; 2]) -> Option<CpuForward> {
        self.exec.is_none().then(|| {
            let (d, shape) = self.dims(l[0], l[1])?;
            report_launches();
            let out = match self.way {
                Way::Gather => cpu::gather(s, l, d)?,
                Way::ScatterAdd { .. } => cpu::scatter_add(s, l, d)?,
            };
            Ok((out, shape))
        })
    }

    fn backward(
        &self,
        [x, ids]: [&Tensor; 2],
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<[Option<Tensor>; 2]> {
        if let Way::ScatterAdd { .. } = self.way {
            candle_core::bail!("{} has no backward", self.name())
        }
        let op = RowOp {
            way: Way::ScatterAdd { n: x.dim(1)? },
            exec: self.exec.clone(),
            deterministic: self.deterministic,
        };
        Ok([
            Some(grad.contiguous()?.apply_op2_no_bwd(ids, &Op(op))?),
            None,
        ])
    }
}

#[cfg(test)]
mod tests;
