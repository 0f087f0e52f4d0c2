//! Input encoders (paper Sec. 3; docs/reference.md): the 6D pose embedding fed to the
//! GNN, the two SIREN point encoders applied to bone-normalised points x̄, and the
//! spherical-harmonics view encoding in the root joint's frame.

use candle_core::{Device, Tensor};
use pma_data::skeleton::{pose_to_rot6d, Joints, N_JOINTS};

use crate::compute::numerics::Numerics;
use crate::error::{ModelError, Result};
use crate::network::nn::SineLayer;
use crate::network::params::{Init, Params};

/// 6D rotation features of every joint of every pose: bones (axis-angle) -> [P,J,6].
/// No gradient flows here (poses are data).
pub fn pose6d(bones: &[Joints], device: &Device) -> Result<Tensor> {
    let mut flat = Vec::with_capacity(bones.len() * N_JOINTS * 6);
    for pose in bones {
        for w in pose {
            if !w.iter().all(|v| v.is_finite()) {
                return Err(ModelError::Input(format!(
                    "non-finite axis-angle in bones: {w:?}"
                )));
            }
        }
        for row in pose_to_rot6d(pose) {
            flat.extend_from_slice(&row);
        }
    }
    Ok(Tensor::from_vec(flat, (bones.len(), N_JOINTS, 6), device)?)
}

/// One SIREN layer `sin(ω (W x̄ + b))` shared by all joints (`PointEnc`).
#[derive(Debug, Clone)]
pub struct PointEnc {
    layer: SineLayer,
}

impl PointEnc {
    /// `{pts_enc_pose|pts_enc_point}.sin_lin0.layer.*`, with SIREN's first-layer init
    /// U(±1/fan_in).
    pub fn new<'a>(p: impl Into<Params<'a>>, out_dim: usize, w0: f64) -> Result<Self> {
        Ok(Self {
            layer: SineLayer::new(
                p.into().pp("sin_lin0"),
                3,
                out_dim,
                w0,
                Init::Uniform(1.0 / 3.0),
            )?,
        })
    }

    /// x_bar: [N,J,3] -> [N,J,C]
    pub fn forward(&self, x_bar: &Tensor, k: Numerics) -> Result<Tensor> {
        self.layer.forward(x_bar, k)
    }

    /// `w ⊙ forward(x̄)`: x̄ [N,J,3], w [N,J] -> [N,J,out], each joint's features times its
    /// window weight (one op on a GPU's route).
    pub fn forward_weighted(&self, x_bar: &Tensor, w: &Tensor, k: Numerics) -> Result<Tensor> {
        self.layer.forward_scaled(x_bar, Some(w), k)
    }
}

/// Real spherical harmonics up to `degree` (≤ 4) of directions d: [R,3] -> [R,degree²].
///
/// The polynomial forms are the reference's (e.g. `2z²−x²−y²`, not `3z²−1`): they differ
/// for non-unit inputs, which the reference feeds at render time.
pub fn spherical_harmonics(d: &Tensor, degree: usize) -> Result<Tensor> {
    if !(1..=4).contains(&degree) {
        return Err(ModelError::Config(format!(
            "sh_degree must be in 1..=4, found {degree}"
        )));
    }
    let x = d.narrow(1, 0, 1)?;
    let y = d.narrow(1, 1, 1)?;
    let z = d.narrow(1, 2, 1)?;
    let (xx, yy, zz) = (x.sqr()?, y.sqr()?, z.sqr()?);
    let (xy, yz, xz) = ((&x * &y)?, (&y * &z)?, (&x * &z)?);
    let mut out = vec![(x.ones_like()? * 0.282_094_791_773_878_14)?];
    if degree > 1 {
        out.push((&y * -0.488_602_511_902_919_9)?);
        out.push((&z * 0.488_602_511_902_919_9)?);
        out.push((&x * -0.488_602_511_902_919_9)?);
    }
    if degree > 2 {
        out.push((&xy * 1.092_548_430_592_079_2)?);
        out.push((&yz * -1.092_548_430_592_079_2)?);
        out.push((((&zz * 2.0)? - &xx)? - &yy)?.affine(0.315_391_565_252_520_05, 0.0)?);
        out.push((&xz * -1.092_548_430_592_079_2)?);
        out.push(((&xx - &yy)? * 0.546_274_215_296_039_6)?);
    }
    if degree > 3 {
        // y(3x² − y²), xyz, y(4z² − x² − y²), z(2z² − 3x² − 3y²), x(4z² − x² − y²), z(x² − y²), x(x² − 3y²)
        let four_z2_m = (((&zz * 4.0)? - &xx)? - &yy)?;
        out.push(((&y * ((&xx * 3.0)? - &yy)?)? * -0.590_043_589_926_643_5)?);
        out.push(((&xy * &z)? * 2.890_611_442_640_554)?);
        out.push(((&y * &four_z2_m)? * -0.457_045_799_464_465_8)?);
        out.push(
            ((&z * (((&zz * 2.0)? - (&xx * 3.0)?)? - (&yy * 3.0)?)?)? * 0.373_176_332_590_115_4)?,
        );
        out.push(((&x * &four_z2_m)? * -0.457_045_799_464_465_8)?);
        out.push(((&z * (&xx - &yy)?)? * 1.445_305_721_320_277)?);
        out.push(((&x * (&xx - (&yy * 3.0)?)?)? * -0.590_043_589_926_643_5)?);
    }
    Ok(Tensor::cat(&out, 1)?)
}
