//! A SIREN layer on a narrow input with each row scaled, `s_r · sin(x Wᵀ + b)` with
//! x [rows, ≤ 4], as one op on a device: the two point encoders, which map x̄ (3
//! coordinates per joint and point) to [N·24, 64] each, the second one scaled by the
//! window weight w of the row's joint (x̃ = w ⊙ z, the modulator's input).
//!
//! With three inputs per output the product does no work worth the name; what costs is
//! memory traffic over the [N·24, 64] output. candle's ops write it from the product, read
//! and write it in the bias add and in the sine, and backward run a cosine, a product, a
//! column sum and the weight's product over it, about a dozen passes in all, and the window
//! weight's product and its gradient another eight. Here the forward writes the output
//! once; the backward reads the upstream gradient once, recomputing the argument from x
//! (three products per element) and its cosine, and sums the weight and bias gradients per
//! block of [`ROWS_PER_BLOCK`] rows, then over the blocks in block order, in two launches
//! without atomics (a run repeats bit for bit); when x or the scale needs a gradient (x̄
//! does: it is divided by the learned box scales; w does: it holds the learned feature
//! window), a third launch reads it again for both, row by row.
//!
//! On the CPU's route the layer is candle's ops, whose CPU bits are pma's parity reference.

mod check;
mod device;

use candle_core::Tensor;

use crate::compute::kernel::op::Op;
use crate::compute::kernel::{self, Route};
use crate::compute::numerics::Numerics;
use crate::error::Result;

pub use device::{MAX_IN, ROWS_PER_BLOCK};

crate::kernel_module!(
    "sine_linear",
    "sine_linear.cu",
    pma_emu_sine_linear,
    check::check
);

/// `scale_r · sin(x Wᵀ + b)`: x [rows,in], W [out,in], b [out], scale [rows] (none: 1) ->
/// [rows,out]; the sine is [`crate::compute::fast_sine::sin`] under `k` on candle's route.
pub fn sine_linear(
    x: &Tensor,
    w: &Tensor,
    b: &Tensor,
    scale: Option<&Tensor>,
    k: Numerics,
) -> Result<Tensor> {
    let rows = x.dim(0)?;
    let fits = x.rank() == 2
        && w.rank() == 2
        && b.rank() == 1
        && x.dim(1)? == w.dim(1)?
        && b.dim(0)? == w.dim(0)?
        && (1..=MAX_IN).contains(&x.dim(1)?)
        && scale.is_none_or(|s| s.dims() == [rows]);
    let generic = || -> Result<Tensor> {
        let pre = crate::compute::ops::linear::linear(x, w, b, k)?;
        let y = crate::compute::fast_sine::sin(&pre, k.fast_sine)?;
        Ok(match scale {
            Some(s) => y.broadcast_mul(&s.unsqueeze(1)?)?,
            None => y,
        })
    };
    let mut on = vec![x, w, b];
    on.extend(scale);
    if !matches!(
        kernel::route(k.fused && fits, &MODULE, &on),
        Route::Device(_)
    ) {
        return generic();
    }
    kernel::or_generic(
        &MODULE,
        || {
            // [W | b]: the op's second input, so that one backward output is its gradient.
            let wb = Tensor::cat(&[w, &b.unsqueeze(1)?], 1)?;
            let scale = match scale {
                Some(s) => s.contiguous()?,
                None => Tensor::ones(rows, x.dtype(), x.device())?,
            };
            Ok(x.contiguous()?
                .apply_op3(&wb, &scale, Op(device::SineLinear))?)
        },
        generic,
    )
}

#[cfg(test)]
mod tests;
