//! One Adam update over every parameter at once: flat gradients, moments and parameters,
//! each parameter (slot) with its own step size and bias correction, the global-norm clip
//! factor and the skip flag read on the device, and the step applied only where its slot
//! has a gradient and the flag is set (elsewhere the old values are kept).
//!
//! The update follows torch's single-tensor `Adam` in f32:
//!
//! ```text
//! m <- m + (g - m)(1 - b1)
//! v <- v b2 + g² (1 - b2)
//! p <- p - step_size · m / (sqrt(v) · (1 / sqrt(1 - b2^t)) + eps)
//! ```
//!
//! Routes ([`crate::compute::kernel`]): on the CPU one pass over the elements ([`cpu`]); on
//! a device one kernel (`adam.cu`); candle's ops otherwise (Metal, `--generic-kernels`). All
//! three give the same bits: every operation is the tensor ops', rounded separately in the
//! same order (candle's `x * c` by an f64 scalar is its affine `x * (c as f32) + 0`, kept
//! for its sign of zero).

mod check;
mod cpu;
mod device;

use candle_core::{DType, Device, Tensor};

use crate::compute::kernel::{self, Route};
use crate::error::Result;

crate::kernel_module!("adam", "adam.cu", pma_emu_adam, check::check);

/// One update's inputs: N flat elements in S slots.
pub struct Update<'a> {
    /// The flat gradient [N] (f32).
    pub g: &'a Tensor,
    /// Every slot's parameter (any shape), in slot order: their elements are the flat
    /// buffers' in that order.
    pub params: &'a [Tensor],
    /// The flat moments [N] (f32).
    pub m: &'a Tensor,
    pub v: &'a Tensor,
    /// The slot of every element [N] (u32).
    pub slot_of: &'a Tensor,
    /// Which slots have a gradient.
    pub has: &'a [bool],
    /// A device scalar: the update applies only where it is non-zero (the skip flag).
    pub apply: Option<&'a Tensor>,
    /// A device scalar the gradient is scaled by first (the clip factor).
    pub coef: Option<&'a Tensor>,
    /// Per slot: `lr / (1 − b1^t)` and `sqrt(1 − b2^t)` [S] (f64).
    pub step_size: &'a Tensor,
    pub bias2_sqrt: &'a Tensor,
    pub b1: f64,
    pub b2: f64,
    pub eps: f64,
}

/// [`Update::slot_of`] for slots of `lens` elements, in slot order.
pub fn slot_index(lens: &[usize], device: &Device) -> Result<Tensor> {
    let slot_of: Vec<u32> = lens
        .iter()
        .enumerate()
        .flat_map(|(i, &len)| std::iter::repeat_n(i as u32, len))
        .collect();
    let n = slot_of.len();
    Ok(Tensor::from_vec(slot_of, n, device)?)
}

/// The new (parameters, first moments, second moments), flat [N].
pub fn update(u: &Update) -> Result<(Tensor, Tensor, Tensor)> {
    match kernel::route(true, &MODULE, &[u.g]) {
        Route::Cpu => kernel::or_generic(&MODULE, || cpu::update(u), || generic(u)),
        Route::Device(_) => kernel::or_generic(&MODULE, || device::update(u), || generic(u)),
        Route::Generic => generic(u),
    }
}

/// Every parameter, flat in slot order.
fn flat_params(u: &Update) -> candle_core::Result<Tensor> {
    let params: Vec<Tensor> = u
        .params
        .iter()
        .map(|p| p.detach().flatten_all())
        .collect::<candle_core::Result<_>>()?;
    Tensor::cat(&params, 0)
}

/// The update in candle's ops (the bits the CPU's and the kernel's match).
fn generic(u: &Update) -> Result<(Tensor, Tensor, Tensor)> {
    let (b1, b2, eps) = (u.b1, u.b2, u.eps);
    let g = match u.coef {
        Some(c) => u.g.broadcast_mul(c)?,
        None => u.g.clone(),
    };
    // Per element: the f32 factors a per-parameter update would multiply by.
    let per_elem = |v: Tensor| -> candle_core::Result<Tensor> {
        v.to_dtype(DType::F32)?.index_select(u.slot_of, 0)
    };
    let step_size = per_elem(u.step_size.clone())?;
    let inv_bias2 = per_elem(u.bias2_sqrt.recip()?)?;
    let g = g.detach();
    let m = (u.m + ((&g - u.m)? * (1.0 - b1))?)?;
    let v = ((u.v * b2)? + (g.sqr()? * (1.0 - b2))?)?;
    let denom = (v.sqrt()?.mul(&inv_bias2)? + eps)?;
    let step = (m.mul(&step_size)? / denom)?;
    let p_old = flat_params(u)?;
    let mut p = (&p_old - step)?;
    let (mut m, mut v) = (m, v);
    // Where the update does not apply, everything keeps its old value.
    let all = u.has.iter().all(|&h| h);
    let mask = match (u.apply, all) {
        (None, true) => None,
        (Some(a), true) => Some(a.broadcast_as(p.shape())?),
        (a, false) => {
            let has_u8: Vec<u8> = u.has.iter().map(|&h| h as u8).collect();
            let slot_has = Tensor::from_vec(has_u8, u.has.len(), u.g.device())?;
            let mut mask = slot_has.index_select(u.slot_of, 0)?;
            if let Some(a) = a {
                mask = mask.broadcast_mul(&a.to_dtype(DType::U8)?)?;
            }
            Some(mask)
        }
    };
    if let Some(mask) = &mask {
        p = mask.where_cond(&p, &p_old)?;
        m = mask.where_cond(&m, u.m)?;
        v = mask.where_cond(&v, u.v)?;
    }
    Ok((p, m, v))
}

#[cfg(test)]
mod tests;
