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

/// Mean absolute error: pred, target: [R,3] -> scalar.
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
    let fine = l1(&out.fine.rgb, target)?;
    let coarse = l1(&out.coarse.rgb, target)?;
    let scale = box_volume(&out.vol_scale)?;
    let total = ((&fine * w.fine)? + (&coarse * w.coarse)?)?.add(&(&scale * w.scale)?)?;
    Ok(Loss {
        total,
        fine,
        coarse,
        scale,
    })
}
