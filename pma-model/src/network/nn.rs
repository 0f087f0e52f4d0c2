//! Small building blocks shared by the network modules: a plain linear layer with
//! the PyTorch weight layout, the SIREN variant, and per-joint ("parallel") linears.

use candle_core::{Tensor, D};

use crate::compute::numerics::Numerics;
use crate::error::Result;
use crate::network::params::{Init, Params};

/// `y = x Wᵀ + b` with PyTorch's layout: weight [out,in], bias [out]. Works on any
/// leading batch shape (`x: [..., in]`).
#[derive(Debug, Clone)]
pub struct Linear {
    pub weight: Tensor,
    pub bias: Tensor,
}

impl Linear {
    /// `{prefix}.weight` [out,in] starting from `weight_init`, and `{prefix}.bias` [out]
    /// with torch's default U(±1/√in).
    pub fn new(p: Params, in_dim: usize, out_dim: usize, weight_init: Init) -> Result<Self> {
        Ok(Self {
            weight: p.param([out_dim, in_dim], "weight", weight_init)?,
            bias: p.param([out_dim], "bias", Init::torch_default(in_dim))?,
        })
    }

    /// x: [..., in] -> [..., out]
    pub fn forward(&self, x: &Tensor, k: Numerics) -> Result<Tensor> {
        let dims = x.dims().to_vec();
        let in_dim = *dims.last().unwrap_or(&0);
        let rows = x.elem_count() / in_dim.max(1);
        let y = crate::compute::ops::linear::linear(
            &x.reshape((rows, in_dim))?,
            &self.weight,
            &self.bias,
            k,
        )?;
        let mut out_dims = dims;
        *out_dims
            .last_mut()
            .expect("linear input has at least one dim") = self.weight.dim(0)?;
        Ok(y.reshape(out_dims)?)
    }
}

impl Linear {
    /// `max(x Wᵀ + b, 0)`: x: [rows, in] -> [rows, out] ([`crate::compute::ops::linear`]).
    pub fn forward_relu(&self, x: &Tensor, k: Numerics) -> Result<Tensor> {
        crate::compute::ops::linear::linear_relu(x, &self.weight, &self.bias, k)
    }

    /// [`Self::forward`] as a bf16 tensor-core product computes it: input, weight and output
    /// rounded to bf16 ([`crate::compute::numerics::bf16`]), the sum in f32, the bias added
    /// in f32 before the output is rounded.
    pub fn forward_bf16(&self, x: &Tensor, k: Numerics) -> Result<Tensor> {
        use crate::compute::numerics::bf16;
        let rounded = Self {
            weight: bf16(&self.weight)?,
            bias: self.bias.clone(),
        };
        bf16(&rounded.forward(&bf16(x)?, k)?)
    }
}

/// SIREN layer `sin(ω (W x + b))`: the reference multiplies the bias by ω as well.
#[derive(Debug, Clone)]
pub struct SineLayer {
    pub linear: Linear,
    pub w0: f64,
}

impl SineLayer {
    /// `{prefix}.layer.weight` / `{prefix}.layer.bias` (the reference's key layout).
    pub fn new(
        p: Params,
        in_dim: usize,
        out_dim: usize,
        w0: f64,
        weight_init: Init,
    ) -> Result<Self> {
        Ok(Self {
            linear: Linear::new(p.pp("layer"), in_dim, out_dim, weight_init)?,
            w0,
        })
    }

    /// Pre-activation `W x + b`: x: [..., in] -> [..., out]
    pub fn pre(&self, x: &Tensor, k: Numerics) -> Result<Tensor> {
        self.linear.forward(x, k)
    }

    /// x: [..., in] -> [..., out]
    pub fn forward(&self, x: &Tensor, k: Numerics) -> Result<Tensor> {
        self.forward_scaled(x, None, k)
    }

    /// `scale ⊙ forward(x)`, each output row times its scale: x: [..., in], scale: [...]
    /// -> [..., out]. One op on a GPU's route for a narrow x
    /// ([`crate::compute::ops::sine_linear`]).
    pub fn forward_scaled(
        &self,
        x: &Tensor,
        scale: Option<&Tensor>,
        k: Numerics,
    ) -> Result<Tensor> {
        // ω scales W and b ([out,in] work) rather than every output row: one pass over the
        // activations fewer, forward and backward. For ω a power of two (the reference's 8
        // and 16) the scaling is exact, so the result is bit-identical either way.
        let (w, b) = (
            (&self.linear.weight * self.w0)?,
            (&self.linear.bias * self.w0)?,
        );
        let dims = x.dims().to_vec();
        let in_dim = *dims.last().unwrap_or(&0);
        let rows = x.elem_count() / in_dim.max(1);
        let scale = scale.map(|s| s.reshape(rows)).transpose()?;
        let x2 = x.reshape((rows, in_dim))?;
        let y = match (scale, in_dim > crate::compute::ops::sine_linear::MAX_IN) {
            // A wide input (the pose extractor): cuBLAS's product, then bias and sine.
            (None, true) => crate::compute::ops::linear::linear_sine(&x2, &w, &b, k)?,
            (scale, _) => {
                crate::compute::ops::sine_linear::sine_linear(&x2, &w, &b, scale.as_ref(), k)?
            }
        };
        let mut out_dims = dims;
        *out_dims
            .last_mut()
            .expect("sine layer input has at least one dim") = w.dim(0)?;
        Ok(y.reshape(out_dims)?)
    }
}

pub fn per_joint_matmul(x: &Tensor, w: &Tensor) -> Result<Tensor> {
    // [J,P,in] @ [J,in,out] batches over joints; transposing back keeps [P,J,out].
    let xt = x.transpose(0, 1)?.contiguous()?;
    Ok(xt.matmul(w)?.transpose(0, 1)?.contiguous()?)
}

/// Sum over the last dim without keeping it.
pub fn sum_last(x: &Tensor) -> Result<Tensor> {
    Ok(x.sum(D::Minus1)?)
}
