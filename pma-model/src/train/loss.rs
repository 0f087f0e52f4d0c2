//! The reference's training objective: L1 on the fine and the coarse render (means over
//! rays × channels) plus 0.001 × the summed box volumes (docs/reference.md, "Training schedule
//! and Adam").

use candle_core::Tensor;

use crate::error::Result;
use crate::render::avatar::Outputs;

/// Weights of the loss terms (reference: 1, 1, 0.001).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LossWeights {
    pub fine: f64,
    pub coarse: f64,
    pub scale: f64,
}

impl Default for LossWeights {
    fn default() -> Self {
        Self {
            fine: 1.0,
            coarse: 1.0,
            scale: 0.001,
        }
    }
}

/// The terms and their weighted sum (all scalars, differentiable).
#[derive(Debug, Clone)]
pub struct Loss {
    pub total: Tensor,
    pub fine: Tensor,
    pub coarse: Tensor,
    pub scale: Tensor,
}

/// Mean absolute error: pred, target: [R,3] -> scalar (`sum · (1/n)`, like candle's mean).
pub fn l1(pred: &Tensor, target: &Tensor) -> Result<Tensor> {
    Ok((pred - target)?.abs()?.mean_all()?)
}

/// Σ_j s_x s_y s_z of the effective half-extents s: [J,3] -> scalar.
pub fn box_volume(s: &Tensor) -> Result<Tensor> {
    let v = (s.narrow(1, 0, 1)? * s.narrow(1, 1, 1)?)?.mul(&s.narrow(1, 2, 1)?)?;
    Ok(v.sum_all()?)
}

/// The full objective on a forward pass's outputs; target: [R,3].
pub fn training_loss(out: &Outputs, target: &Tensor, w: &LossWeights) -> Result<Loss> {
    loss_share(out, target, w, target.dim(0)?, true)
}

/// The share of the objective of the rays in `out` (target: [R',3]) when they are part of a
/// batch of `batch_rays` rays: the L1 terms are their sums times `1/(3·batch_rays)` (the same
/// two multiplications as a mean over the whole batch), the box-volume term is included when
/// `with_scale` (once per batch) and 0 otherwise. The shares of a batch's chunks add up to
/// [`training_loss`] of the batch.
pub fn loss_share(
    out: &Outputs,
    target: &Tensor,
    w: &LossWeights,
    batch_rays: usize,
    with_scale: bool,
) -> Result<Loss> {
    loss_share_weighted(out, target, None, w, batch_rays, with_scale)
}

/// [`loss_share`] with each ray's L1 terms multiplied by its weight in `ray_weights` ([R']:
/// an error map's unbiased draws, `pma_data::error_map`); `None` is [`loss_share`] itself.
pub fn loss_share_weighted(
    out: &Outputs,
    target: &Tensor,
    ray_weights: Option<&Tensor>,
    w: &LossWeights,
    batch_rays: usize,
    with_scale: bool,
) -> Result<Loss> {
    let inv_n = 1.0 / (3 * batch_rays) as f64;
    let ray_weights = ray_weights
        .map(|rw| rw.to_dtype(target.dtype())?.unsqueeze(1))
        .transpose()?;
    let share = |pred: &Tensor| -> Result<Tensor> {
        let err = (pred - target)?.abs()?;
        let err = match &ray_weights {
            Some(rw) => err.broadcast_mul(rw)?,
            None => err,
        };
        Ok((err.sum_all()? * inv_n)?)
    };
    let fine = share(&out.fine.rgb)?;
    let coarse = share(&out.coarse.rgb)?;
    let l1 = ((&fine * w.fine)? + (&coarse * w.coarse)?)?;
    let (scale, total) = if with_scale {
        let scale = box_volume(&out.vol_scale)?;
        let total = l1.add(&(&scale * w.scale)?)?;
        (scale, total)
    } else {
        (fine.zeros_like()?, l1)
    };
    Ok(Loss {
        total,
        fine,
        coarse,
        scale,
    })
}
