//! What a forward pass takes and returns: rays, the poses they see, the mode, the outputs.

use candle_core::{DType, Tensor};
use pma_data::skeleton::Joints;

use crate::error::{ModelError, Result};
use crate::render::options::PassStats;
use crate::render::raycast::RayBounds;
use crate::render::volume::RenderOutputs;

/// Per-pose data of a ray batch: P distinct poses. Rays are grouped by pose in P equal,
/// contiguous blocks (rays `[p·R/P, (p+1)·R/P)` belong to pose p).
#[derive(Debug, Clone)]
pub struct Poses {
    /// bones: [P][24][3] axis-angle per joint.
    pub bones: Vec<Joints>,
    /// skts: [P,24,4,4] world→joint transforms.
    pub skts: Tensor,
    /// cyls: [P,5] bounding cylinders (centre_x, centre_z, radius, top, bottom).
    pub cyls: Tensor,
}

/// A batch of rays.
#[derive(Debug, Clone)]
pub struct Rays {
    /// origins: [R,3]
    pub origins: Tensor,
    /// dirs: [R,3] (unit for training rays; any length at render time)
    pub dirs: Tensor,
    /// bgs: [R,3] background colours, or `None` for black.
    pub bgs: Option<Tensor>,
    /// Frame-code index per ray: [R] (training image index; −1 everywhere = mean code).
    pub framecodes: Vec<i64>,
}

/// Standard-normal noise source for the density noise: `n` → [n] tensor. Supplied by the
/// trainer from its own seeded RNG so runs resume bit-exactly.
pub type NoiseFn<'a> = &'a mut dyn FnMut(usize) -> Result<Tensor>;

/// How a forward pass runs.
pub enum Mode<'a> {
    /// Training: gradients flow, frame codes are looked up by image index, and density
    /// noise is drawn from the source when one is given (and `density_noise_std > 0`).
    Train(Option<NoiseFn<'a>>),
    /// Evaluation with the graph kept (the parity hook, gradient checks): no noise, and a
    /// batch whose frame-code indices are all −1 gets the mean code.
    Eval,
    /// Inference: no gradient is needed, so points go through the network in bounded
    /// chunks on the CPU workers and their outputs are detached at once. Memory no longer
    /// grows with the number of rays. Otherwise as [`Mode::Eval`].
    Infer,
}

impl Mode<'_> {
    pub fn is_training(&self) -> bool {
        matches!(self, Mode::Train(_))
    }

    pub fn is_inference(&self) -> bool {
        matches!(self, Mode::Infer)
    }
}

/// Everything a forward pass returns.
#[derive(Debug, Clone)]
pub struct Outputs {
    /// Fine render (coarse + importance samples merged): rgb [R,3], acc [R], disp [R],
    /// weights (T_i) and alpha [R,Sc+Sf].
    pub fine: RenderOutputs,
    /// Coarse render: rgb0, acc0, disp0, weights, alpha [R,Sc].
    pub coarse: RenderOutputs,
    /// z_coarse: [R,Sc]
    pub z_coarse: Tensor,
    /// z_vals: [R,Sc+Sf] merged and sorted.
    pub z_vals: Tensor,
    /// raw_coarse: [R,Sc,4] (rgb, density) of the coarse samples.
    pub raw_coarse: Tensor,
    /// raw: [R,Sc+Sf,4] merged.
    pub raw: Tensor,
    /// vol_scale: [24,3] effective box half-extents (differentiable).
    pub vol_scale: Tensor,
    /// Host-side ray bounds (near/far, box hits); `None` when the rays were cast on the
    /// device ([`crate::render::raycast::device`]).
    pub bounds: Option<RayBounds>,
    /// What the pass evaluated and left out.
    pub stats: PassStats,
    /// Training with the grid: the cells its evaluated samples saw
    /// ([`crate::render::options::GridFeed`]); empty otherwise.
    pub observed: Vec<crate::render::options::GridObservation>,
}

/// Shapes of a batch: R rays in P equal per-pose blocks.
pub(crate) fn check_batch(rays: &Rays, poses: &Poses) -> Result<()> {
    let r = rays.origins.dim(0)?;
    let p = poses.bones.len();
    if p == 0 || r == 0 || r % p != 0 {
        return Err(ModelError::Input(format!(
            "{r} rays cannot be split into {p} equal, contiguous per-pose blocks"
        )));
    }
    if rays.origins.dims() != [r, 3] || rays.dirs.dims() != [r, 3] {
        return Err(ModelError::shape("rays_o/rays_d", [r, 3], rays.dirs.dims()));
    }
    if poses.cyls.dims() != [p, 5] {
        return Err(ModelError::shape("cyls", [p, 5], poses.cyls.dims()));
    }
    if rays.framecodes.len() != r {
        return Err(ModelError::shape(
            "framecodes",
            [r],
            [rays.framecodes.len()],
        ));
    }
    Ok(())
}

/// Rays and poses in `dtype`, or `None` when they already are (the only case training and
/// parity use).
pub(crate) fn cast_batch(
    rays: &Rays,
    poses: &Poses,
    dtype: DType,
) -> Result<Option<(Rays, Poses)>> {
    if rays.dirs.dtype() == dtype && rays.origins.dtype() == dtype && poses.skts.dtype() == dtype {
        return Ok(None);
    }
    let rays = Rays {
        origins: rays.origins.to_dtype(dtype)?,
        dirs: rays.dirs.to_dtype(dtype)?,
        bgs: rays.bgs.as_ref().map(|b| b.to_dtype(dtype)).transpose()?,
        framecodes: rays.framecodes.clone(),
    };
    let poses = Poses {
        bones: poses.bones.clone(),
        skts: poses.skts.to_dtype(dtype)?,
        cyls: poses.cyls.to_dtype(dtype)?,
    };
    Ok(Some((rays, poses)))
}
