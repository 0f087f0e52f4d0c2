//! Copies of tensors on the host, where the ray caster, culling and mesh extraction work.

use candle_core::{DType, Device, Tensor};

use crate::error::{ModelError, Result};

/// A tensor of any float dtype and device as host f32, row-major. The one host-copy helper
/// of the crate.
pub fn host_f32(t: &Tensor) -> Result<Vec<f32>> {
    Ok(t.flatten_all()?
        .to_dtype(DType::F32)?
        .to_device(&Device::Cpu)?
        .to_vec1::<f32>()?)
}

/// [`host_f32`] after checking the shape; `what` names the tensor in the error.
pub fn host_f32_shaped(what: &str, t: &Tensor, shape: &[usize]) -> Result<Vec<f32>> {
    if t.dims() != shape {
        return Err(ModelError::shape(what, shape, t.dims()));
    }
    host_f32(t)
}
