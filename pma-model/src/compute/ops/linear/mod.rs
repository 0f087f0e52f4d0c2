//! Linear layers as single ops: `x Wᵀ + b`, and `act(x Wᵀ + b)` for a ReLU or a sine.
//!
//! * [`linear`]: candle keeps each op's inputs alive until the graph is dropped, so a product
//!   followed by a bias add kept the product, a second [rows,out] tensor per layer that no
//!   backward reads. One op keeps only its output: the largest cut of a training step's peak
//!   memory, on every device. Its CPU backward sums the bias gradient in one contiguous
//!   pass ([`add_bias`] likewise), where candle's reduction over rows runs element by
//!   element; the same sums in the same order.
//! * [`linear_relu`], [`linear_sine`] on a device: cuBLAS's product, then the bias add and
//!   the activation in one kernel (`bias_act.cu`), and backward one kernel writing the
//!   product's gradient and, per block of [`ROWS_PER_BLOCK`] rows, its column sums, then a
//!   small one adding those in block order (the bias gradient: no atomics, a run repeats bit
//!   for bit). What the backward needs is one [rows,out] tensor: the ReLU's output (its
//!   gradient passes where it is positive, PyTorch's rule; candle's passes where the input
//!   is ≥ 0, which differs at an input of exactly 0), or the sine's product before the bias.
//!   On the CPU's route these layers are [`linear`] and candle's activation, whose bits are
//!   pma's parity reference.

mod check;
mod cpu;
mod device;

use candle_core::{DType, Tensor};

use crate::compute::kernel::op::Op;
use crate::compute::kernel::{self, Route};
use crate::compute::numerics::Numerics;
use crate::error::Result;

pub use device::ROWS_PER_BLOCK;

crate::kernel_module!("linear", "bias_act.cu", pma_emu_linear, check::check);

/// The activation after the linear layer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Act {
    Relu,
    Sine,
}

/// Whether the CPU's route (`Some(true)`), CUDA's or the emulated CUDA route
/// (`Some(false)`) takes `ts`: f32 tensors all on the CPU or all on CUDA.
fn f32_route(ts: &[&Tensor]) -> Option<bool> {
    if ts.iter().any(|t| t.dtype() != DType::F32) {
        return None;
    }
    if ts.iter().all(|t| t.device().is_cpu()) {
        return Some(!crate::compute::account::emulates_cuda());
    }
    (cfg!(feature = "cuda") && ts.iter().all(|t| t.device().is_cuda())).then_some(false)
}

/// `x Wᵀ + b`: x: [rows,in], W: [out,in] (PyTorch's layout), b: [out] -> [rows,out], as one
/// op that keeps only its output for the backward (see the module docs): the same product
/// (candle's, under the network's TF32 choice) and the same bias add, so the values and
/// gradients of [`add_bias`] after the product. Counted as what it launches: the product,
/// then the bias add.
pub fn linear(x: &Tensor, w: &Tensor, b: &Tensor, k: Numerics) -> Result<Tensor> {
    let fits = x.rank() == 2
        && w.rank() == 2
        && b.rank() == 1
        && x.dim(1)? == w.dim(1)?
        && b.dim(0)? == w.dim(0)?;
    let generic = || add_bias(&crate::compute::numerics::matmul(x, &w.t()?, k)?, b, k);
    let route = f32_route(&[x, w, b])
        .filter(|_| k.fused && fits && !kernel::health::forced_generic(&MODULE));
    let Some(cpu_route) = route else {
        return generic();
    };
    kernel::or_generic(
        &MODULE,
        || {
            let (x, w, b) = (x.contiguous()?, w.contiguous()?, b.contiguous()?);
            Ok(candle_core::cuda::with_gemm_reduced_precision_f32(
                k.tf32,
                || x.apply_op3(&w, &b, Op(cpu::Linear { cpu_route })),
            )?)
        },
        generic,
    )
}

/// `y + b` broadcast over rows: y: [rows,out], b: [out] -> [rows,out].
pub fn add_bias(y: &Tensor, b: &Tensor, k: Numerics) -> Result<Tensor> {
    let generic = || Ok(y.broadcast_add(b)?);
    let cpu_route = f32_route(&[y, b]) == Some(true) && !kernel::health::forced_generic(&MODULE);
    if !(k.fused && cpu_route) || y.rank() != 2 || b.rank() != 1 {
        return generic();
    }
    kernel::or_generic(
        &MODULE,
        || Ok(y.contiguous()?.apply_op2(&b.contiguous()?, cpu::BiasAdd)?),
        generic,
    )
}

/// `max(x Wᵀ + b, 0)`: x [rows,in], W [out,in] (PyTorch's layout), b [out] -> [rows,out].
pub fn linear_relu(x: &Tensor, w: &Tensor, b: &Tensor, k: Numerics) -> Result<Tensor> {
    linear_act(x, w, b, Act::Relu, k)
}

/// `sin(x Wᵀ + b)` (the sine [`crate::compute::fast_sine::sin`] under `k` on candle's route).
pub fn linear_sine(x: &Tensor, w: &Tensor, b: &Tensor, k: Numerics) -> Result<Tensor> {
    linear_act(x, w, b, Act::Sine, k)
}

fn linear_act(x: &Tensor, w: &Tensor, b: &Tensor, act: Act, k: Numerics) -> Result<Tensor> {
    let fits = x.rank() == 2
        && w.rank() == 2
        && b.rank() == 1
        && x.dim(1)? == w.dim(1)?
        && b.dim(0)? == w.dim(0)?;
    let generic = || -> Result<Tensor> {
        let pre = linear(x, w, b, k)?;
        match act {
            Act::Relu => Ok(pre.relu()?),
            Act::Sine => crate::compute::fast_sine::sin(&pre, k.fast_sine),
        }
    };
    let exec = match kernel::route(k.fused && fits, &MODULE, &[x, w, b]) {
        Route::Device(e) => e,
        Route::Cpu | Route::Generic => return generic(),
    };
    kernel::or_generic(
        &MODULE,
        || {
            let (x, w, b) = (x.contiguous()?, w.contiguous()?, b.contiguous()?);
            let keep = act == Act::Sine && (x.track_op() || w.track_op() || b.track_op());
            let op = device::LinearAct::new(exec.clone(), act, keep);
            Ok(candle_core::cuda::with_gemm_reduced_precision_f32(
                k.tf32,
                || x.apply_op3(&w, &b, Op(op)),
            )?)
        },
        generic,
    )
}

#[cfg(test)]
mod tests;
