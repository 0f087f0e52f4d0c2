//! The one-op linear layer and the bias add (the CPU's code, and the linear layer's cuBLAS
//! route), and what the layers' ops share.

use candle_core::{CpuStorage, CustomOp2, Layout, Shape, Tensor};

use crate::compute::kernel::op::{product_grads, Forward, Inputs, Product};

use crate::compute::kernel::storage::{f32_slice, with_f32};

/// Column sums of `grad` ([rows,out]) in row order from zero: the sums candle's reduction
/// forms, in one contiguous pass (the bias gradient).
fn row_sums(grad: &Tensor, out: usize) -> candle_core::Result<Tensor> {
    let sums = with_f32([grad], "bias gradient", |[g]| {
        let mut sums = vec![0f32; out];
        for row in g.chunks_exact(out.max(1)) {
            for (a, v) in sums.iter_mut().zip(row) {
                *a += v;
            }
        }
        sums
    })?;
    Tensor::from_vec(sums, out, grad.device())
}

/// A linear layer's (rows, in, out) from the layouts of x [rows,in], W [out,in], b [out],
/// checked.
pub(super) fn linear_dims(
    l1: &Layout,
    l2: &Layout,
    l3: &Layout,
) -> candle_core::Result<(usize, usize, usize)> {
    let (rows, inn) = l1.shape().dims2()?;
    let (out, inn2) = l2.shape().dims2()?;
    if inn2 != inn || l3.shape().dims1()? != out {
        candle_core::bail!(
            "linear: x {:?}, W {:?} and b {:?} do not agree",
            l1.shape(),
            l2.shape(),
            l3.shape()
        )
    }
    Ok((rows, inn, out))
}

/// Count a linear layer's op as its two kernels: the op is the product (its launch, bytes
/// and FLOPs), its epilogue `name` (reading the product and the bias, writing the output,
/// with `params` dims uploads) is recorded beside it.
pub(super) fn report_linear(
    host: bool,
    (rows, inn, out): (usize, usize, usize),
    name: &'static str,
    params: u32,
) {
    let (rows, inn, out) = (rows as u64, inn as u64, out as u64);
    candle_core::account::report_launches(1, 0);
    candle_core::account::report_bytes(4 * (rows * inn + out * inn), 4 * rows * out);
    candle_core::account::report_flops(2 * rows * out * inn);
    candle_core::account::record(
        host,
        candle_core::account::Op {
            name,
            launches: 1,
            param_uploads: params,
            bytes_read: 4 * (rows * out + out),
            bytes_written: 4 * rows * out,
            flops: 0,
        },
    );
}

/// [`super::linear`]'s op on (x, W, b).
pub(super) struct Linear {
    /// The CPU's route: the bias gradient as [`BiasAdd`] sums it. Elsewhere (CUDA, the
    /// emulated CUDA route) it is candle's reduction, as after a `broadcast_add`.
    pub cpu_route: bool,
}

impl Product for Linear {
    /// The product (candle's CPU product, or cuBLAS) and the bias add (the host's loop, or
    /// candle's kernel); the product is freed on return.
    fn forward(&self, inputs: Inputs<'_, 3>, [l1, l2, l3]: [&Layout; 3]) -> Forward {
        if self.cpu_route {
            crate::compute::kernel::health::cpu_launch(&super::MODULE)?;
        }
        let d = linear_dims(l1, l2, l3)?;
        let (rows, out) = (d.0, d.2);
        report_linear(inputs.exec().is_host(), d, "add", 1);
        let y = inputs.product((0, l1), (1, l2), d)?;
        Ok((
            inputs.bias_add(y, (2, l3), (rows, out))?,
            Shape::from((rows, out)),
        ))
    }

    fn backward(
        &self,
        [x, w, _b]: [&Tensor; 3],
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<[Option<Tensor>; 3]> {
        let (gx, gw) = product_grads(x, w, grad)?;
        let out = w.dim(0)?;
        let gb = match self.cpu_route {
            true => row_sums(grad, out)?,
            false => grad.sum(0)?,
        };
        Ok([gx, Some(gw), Some(gb)])
    }
}

/// [`super::add_bias`]'s op on (y, b), the CPU's route.
pub(super) struct BiasAdd;

impl CustomOp2 for BiasAdd {
    fn name(&self) -> &'static str {
        "pma-bias-add"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        crate::compute::kernel::health::cpu_launch(&super::MODULE)?;
        let (y, b) = (
            f32_slice(s1, l1, "bias add: y")?,
            f32_slice(s2, l2, "bias add: b")?,
        );
        let out = b.len();
        if out == 0 || y.len() % out != 0 {
            candle_core::bail!(
                "bias add: {} values do not split into rows of {out}",
                y.len()
            )
        }
        let mut dst = Vec::with_capacity(y.len());
        for row in y.chunks_exact(out) {
            dst.extend(row.iter().zip(b).map(|(a, c)| a + c));
        }
        Ok((CpuStorage::F32(dst), l1.shape().clone()))
    }

    fn bwd(
        &self,
        _y: &Tensor,
        b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        // Row order, from zero: the same summation candle's reduction does.
        let gb = row_sums(grad, b.elem_count())?;
        Ok((Some(grad.clone()), Some(gb)))
    }
}
