//! The linear layer with its activation on a device: the product (cuBLAS on a GPU, candle's
//! CPU product on the emulated grid), then `bias_act.cu`'s kernels.

use std::sync::{Arc, Mutex};

use candle_core::{Layout, Shape, Tensor};

use super::cpu::{linear_dims, report_linear};
use super::{Act, MODULE};
use crate::compute::kernel::launch::launch;
use crate::compute::kernel::mem::{Arg, Buf, Src};
use crate::compute::kernel::op::{product_grads, Forward, Inputs, Kernel, Op, Product};
use crate::compute::kernel::storage::u32_of;
use crate::compute::kernel::Exec;

/// Rows per partial sum of the bias gradient (`PMA_BIAS_ACT_ROWS` in the kernel).
pub const ROWS_PER_BLOCK: usize = 256;

/// `act(x Wᵀ + b)` on (x, W, b).
pub(super) struct LinearAct {
    exec: Exec,
    act: Act,
    /// Keep the product z for the backward (a sine whose graph tracks gradients).
    keep: bool,
    z: Mutex<Option<(Buf, candle_core::account::Held)>>,
}

impl LinearAct {
    pub(super) fn new(exec: Exec, act: Act, keep: bool) -> Self {
        Self {
            exec,
            act,
            keep,
            z: Mutex::new(None),
        }
    }

    /// The name the bias-and-activation kernel is counted under.
    fn epilogue(&self) -> &'static str {
        match self.act {
            Act::Relu => "pma-bias-relu",
            Act::Sine => "pma-bias-sine",
        }
    }

    /// The kernel after the product `z` [rows,out]: `act(z + b)`; keeps z when asked.
    fn epilogue_of(&self, z: Buf, b: Src, [rows, out]: [usize; 2]) -> candle_core::Result<Buf> {
        let kernel = match self.act {
            Act::Relu => "pma_bias_relu_f32",
            Act::Sine => "pma_bias_sine_f32",
        };
        let mut y = self.exec.output(rows * out)?;
        launch(
            &self.exec,
            &MODULE,
            kernel,
            rows * out,
            &mut [
                Arg::Src(z.src()),
                Arg::Src(b),
                Arg::Dst(&mut y),
                Arg::U32(u32_of(rows, "rows")?),
                Arg::U32(u32_of(out, "OUT")?),
            ],
        )?;
        if self.keep {
            let held = candle_core::account::hold(self.exec.is_host(), z.bytes());
            *self.z.lock().unwrap_or_else(|e| e.into_inner()) = Some((z, held));
        }
        Ok(y)
    }
}

impl Product for LinearAct {
    /// The product (candle's CPU product, or cuBLAS), then the bias and activation kernel; the
    /// product is freed on return unless the sine's backward needs it.
    fn forward(&self, inputs: Inputs<'_, 3>, [l1, l2, l3]: [&Layout; 3]) -> Forward {
        let d = linear_dims(l1, l2, l3)?;
        report_linear(self.exec.is_host(), d, self.epilogue(), 0);
        let z = inputs.product((0, l1), (1, l2), d)?;
        let y = self.epilogue_of(z, inputs.src(2, l3, "b")?, [d.0, d.2])?;
        Ok((y, Shape::from((d.0, d.2))))
    }

    fn backward(
        &self,
        [x, w, b]: [&Tensor; 3],
        y: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<[Option<Tensor>; 3]> {
        let z = match self.act {
            Act::Relu => None,
            Act::Sine => Some(
                self.z
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .take()
                    .ok_or_else(|| candle_core::Error::Msg("linear sine: z was not kept".into()))?,
            ),
        };
        let stash = Arc::new(Mutex::new(None));
        let op = Op(ActGrad {
            act: self.act,
            y,
            z,
            stash: stash.clone(),
        });
        let gz = grad.contiguous()?.apply_op2_no_bwd(b, &op)?;
        drop(op);
        let gb = b.apply_op1_no_bwd(&Op(BiasSum { stash }))?;
        let (gx, gw) = product_grads(x, w, &gz)?;
        Ok([gx, Some(gw), Some(gb)])
    }
}

/// The bias gradient's partial sums [blocks, out] from [`ActGrad`] to [`BiasSum`], and the
/// number of blocks.
type Stash = Arc<Mutex<Option<(Buf, usize)>>>;

/// The product's gradient on (grad, b), from the ReLU's output `y` or the sine's kept
/// product `z`, leaving the bias gradient's partial sums in the stash. One kernel.
struct ActGrad<'a> {
    act: Act,
    y: &'a Tensor,
    z: Option<(Buf, candle_core::account::Held)>,
    stash: Stash,
}

impl Kernel<2> for ActGrad<'_> {
    fn name(&self) -> &'static str {
        match self.act {
            Act::Relu => "pma-relu-grad",
            Act::Sine => "pma-sine-grad",
        }
    }

    fn device(
        &self,
        exec: &Exec,
        [grad, b]: [Src; 2],
        [lg, lb]: [&Layout; 2],
    ) -> candle_core::Result<(Buf, Shape)> {
        let (rows, out) = lg.shape().dims2()?;
        if lb.shape().dims1()? != out || self.y.dims() != [rows, out] {
            candle_core::bail!(
                "linear act: grad {:?}, b {:?} and the output {:?} do not agree",
                lg.shape(),
                lb.shape(),
                self.y.shape()
            )
        }
        let blocks = rows.div_ceil(ROWS_PER_BLOCK);
        let (ro, bo) = ((rows * out * 4) as u64, (blocks * out * 4) as u64);
        candle_core::account::report_bytes(2 * ro + (out * 4) as u64, ro + bo);
        let (ys, yl) = self.y.storage_and_layout();
        let kept = match &self.z {
            Some((z, _)) => z.src(),
            None => Src::of(&ys, yl, "linear act: y")?,
        };
        let mut gz = exec.output(rows * out)?;
        let mut part = exec.output(blocks * out)?;
        launch(
            exec,
            &MODULE,
            "pma_act_grad_f32",
            blocks * out,
            &mut [
                Arg::Src(grad),
                Arg::Src(kept),
                Arg::Src(b),
                Arg::Dst(&mut gz),
                Arg::Dst(&mut part),
                Arg::U32(u32_of(rows, "rows")?),
                Arg::U32(u32_of(out, "OUT")?),
                Arg::I32(i32::from(self.act == Act::Sine)),
            ],
        )?;
        *self.stash.lock().unwrap_or_else(|e| e.into_inner()) = Some((part, blocks));
        Ok((gz, Shape::from((rows, out))))
    }
}

/// The bias gradient [out] from the stash (applied to b, for its device and shape): the
/// partial sums added in block order. One kernel.
struct BiasSum {
    stash: Stash,
}

impl Kernel<1> for BiasSum {
    fn name(&self) -> &'static str {
        "pma-bias-grad"
    }

    fn device(
        &self,
        exec: &Exec,
        _: [Src; 1],
        [l]: [&Layout; 1],
    ) -> candle_core::Result<(Buf, Shape)> {
        let out = l.shape().elem_count();
        let got = self.stash.lock().unwrap_or_else(|e| e.into_inner()).take();
        let (part, blocks) =
            got.ok_or_else(|| candle_core::Error::Msg("linear act: no partial sums".into()))?;
        candle_core::account::report_bytes((blocks * out * 4) as u64, (out * 4) as u64);
        if blocks == 0 || out == 0 {
            return Ok((exec.zeros(out)?, Shape::from(out)));
        }
        let mut gb = exec.output(out)?;
        launch(
            exec,
            &MODULE,
            "pma_bias_grad_sum_f32",
            out,
            &mut [
                Arg::Src(part.src()),
                Arg::Dst(&mut gb),
                Arg::U32(u32_of(blocks, "blocks")?),
                Arg::U32(u32_of(out, "OUT")?),
            ],
        )?;
        Ok((gb, Shape::from(out)))
    }
}
