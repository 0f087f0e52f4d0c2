//! The point-encoder layer on a device: `sine_linear.cu`'s kernels, launched on a GPU or on
//! the emulated grid.

use candle_core::{Layout, Shape, Tensor};

use super::MODULE;
use crate::compute::kernel::launch::launch;
use crate::compute::kernel::mem::{Arg, Buf, Src};
use crate::compute::kernel::op::{Kernel, Op};
use crate::compute::kernel::storage::u32_of;
use crate::compute::kernel::Exec;

/// The widest input the kernels take (their per-thread sums are an array this long + 1).
pub const MAX_IN: usize = 4;

/// Rows per partial sum of the backward (`PMA_SINE_LINEAR_ROWS` in the kernel).
pub const ROWS_PER_BLOCK: usize = 1024;

/// (rows, in, out) of x [rows,in], [W|b] [out,in+1] and s [rows], checked.
fn dims(l1: &Layout, l2: &Layout, l3: &Layout) -> candle_core::Result<(usize, usize, usize)> {
    let (rows, inp) = l1.shape().dims2()?;
    let (out, inp1) = l2.shape().dims2()?;
    if inp1 != inp + 1 || l3.shape().dims1()? != rows || !(1..=MAX_IN).contains(&inp) {
        candle_core::bail!(
            "sine linear: x {:?}, [W|b] {:?}, s {:?} do not agree (at most {MAX_IN} inputs)",
            l1.shape(),
            l2.shape(),
            l3.shape()
        )
    }
    Ok((rows, inp, out))
}

fn dim_args((rows, inp, out): (usize, usize, usize)) -> candle_core::Result<[Arg<'static>; 3]> {
    Ok([
        Arg::U32(u32_of(rows, "rows")?),
        Arg::U32(u32_of(inp, "IN")?),
        Arg::U32(u32_of(out, "OUT")?),
    ])
}

/// The layer on (x, [W|b], s).
pub(super) struct SineLinear;

impl Kernel<3> for SineLinear {
    fn name(&self) -> &'static str {
        "pma-sine-linear"
    }

    /// `s_r sin(x Wᵀ + b)` [rows,out]. One launch.
    fn device(
        &self,
        exec: &Exec,
        [x, wb, sc]: [Src; 3],
        l: [&Layout; 3],
    ) -> candle_core::Result<(Buf, Shape)> {
        let d = dims(l[0], l[1], l[2])?;
        let (rows, inp, out) = d;
        let f = |v: usize| 4 * v as u64;
        candle_core::account::report_bytes(f(rows * inp + out * (inp + 1) + rows), f(rows * out));
        let mut y = exec.output(rows * out)?;
        let mut args = vec![Arg::Src(x), Arg::Src(wb), Arg::Src(sc), Arg::Dst(&mut y)];
        args.extend(dim_args(d)?);
        launch(exec, &MODULE, "pma_sine_linear_f32", rows * out, &mut args)?;
        drop(args);
        Ok((y, Shape::from((rows, out))))
    }

    fn backward(
        &self,
        [x, wb, sc]: [&Tensor; 3],
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<[Option<Tensor>; 3]> {
        let grad = grad.contiguous()?;
        let op = |of_rows| {
            Op(SineLinearGrad {
                x: x.clone(),
                of_rows,
            })
        };
        let gwb = grad.apply_op3_no_bwd(wb, sc, &op(false))?;
        let (gx, gs) = match x.track_op() || sc.track_op() {
            // Narrowed views of an empty tensor would point past its storage.
            true if x.dim(0)? == 0 => (
                x.track_op().then(|| x.zeros_like()).transpose()?,
                sc.track_op().then(|| sc.zeros_like()).transpose()?,
            ),
            true => {
                let g = grad.apply_op3_no_bwd(wb, sc, &op(true))?;
                let inp = x.dim(1)?;
                (
                    x.track_op().then(|| g.narrow(1, 0, inp)).transpose()?,
                    sc.track_op()
                        .then(|| g.narrow(1, inp, 1)?.squeeze(1))
                        .transpose()?,
                )
            }
            false => (None, None),
        };
        Ok([gx, Some(gwb), gs])
    }
}

/// The backward as ops on (grad, [W|b], s) with x held: the gradient of [W|b] (two
/// kernels: partial sums per block of rows, then their sum in block order), or, `of_rows`,
/// [rows, in+1]: x's gradient and s's (one kernel).
struct SineLinearGrad {
    x: Tensor,
    of_rows: bool,
}

impl Kernel<3> for SineLinearGrad {
    fn name(&self) -> &'static str {
        match self.of_rows {
            true => "pma-sine-linear-grad-rows",
            false => "pma-sine-linear-grad",
        }
    }

    fn device(
        &self,
        exec: &Exec,
        [grad, wb, sc]: [Src; 3],
        l: [&Layout; 3],
    ) -> candle_core::Result<(Buf, Shape)> {
        let d = dims(self.x.layout(), l[1], l[2])?;
        let (rows, inp, out) = d;
        if l[0].shape().dims2()? != (rows, out) {
            candle_core::bail!("sine linear: grad {:?} is not [{rows},{out}]", l[0].shape())
        }
        let width = inp + 1;
        let blocks = rows.div_ceil(ROWS_PER_BLOCK);
        let f = |v: usize| 4 * v as u64;
        let inputs = f(rows * out + rows * inp + out * width + rows);
        let (launches, read, written) = match self.of_rows {
            true => (1, inputs, f(rows * width)),
            false => (
                2,
                inputs + f(blocks * out * width),
                f(blocks * out * width + out * width),
            ),
        };
        candle_core::account::report_launches(launches, 0);
        candle_core::account::report_bytes(read, written);
        let (xs, lx) = self.x.storage_and_layout();
        let x = Src::of(&xs, lx, "sine linear: x")?;
        let (len, kernel, threads, shape) = match self.of_rows {
            true => (
                rows * width,
                "pma_sine_linear_grad_rows_f32",
                rows,
                Shape::from((rows, width)),
            ),
            false => (
                blocks * out * width,
                "pma_sine_linear_grad_part_f32",
                blocks * out,
                Shape::from((out, width)),
            ),
        };
        if len == 0 {
            // No rows or no outputs: nothing to sum, the gradients are zero.
            return Ok((exec.zeros(shape.elem_count())?, shape));
        }
        let mut first = exec.output(len)?;
        let mut args = vec![
            Arg::Src(grad),
            Arg::Src(x),
            Arg::Src(wb),
            Arg::Src(sc),
            Arg::Dst(&mut first),
        ];
        args.extend(dim_args(d)?);
        launch(exec, &MODULE, kernel, threads, &mut args)?;
        drop(args);
        if self.of_rows {
            return Ok((first, shape));
        }
        let mut g = exec.output(out * width)?;
        launch(
            exec,
            &MODULE,
            "pma_sine_linear_grad_sum_f32",
            out * width,
            &mut [
                Arg::Src(first.src()),
                Arg::Dst(&mut g),
                Arg::U32(u32_of(blocks, "blocks")?),
                Arg::U32(u32_of(inp, "IN")?),
                Arg::U32(u32_of(out, "OUT")?),
            ],
        )?;
        Ok((g, shape))
    }
}
