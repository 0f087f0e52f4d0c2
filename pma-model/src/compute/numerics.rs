//! The numeric choices of a network: which kernels compute it and in what precision.
//!
//! A [`Numerics`] belongs to a network (`Network::with_numerics`, `Avatar::with_numerics`)
//! and reaches every layer through its forward call, so two avatars with different choices
//! can run side by side in one process. A custom op captures the choice when it is built,
//! so its backward pass computes what its forward did.
//!
//! The default is parity: the plain or bit-identical kernels, f32 matrix products.

use candle_core::Tensor;
use serde::{Deserialize, Serialize};

use crate::error::Result;

/// How a network computes (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default)]
pub struct Numerics {
    /// The vectorised polynomial sine on the CPU (`--fast-sine`): last-bit differences from
    /// libm, so not parity. CUDA always takes its own `sinf`.
    pub fast_sine: bool,
    /// pma's fused ops ([`crate::compute::ops`]: on the CPU bit-identical to candle's ops, on
    /// CUDA their kernels). Off: candle's ops everywhere.
    pub fused: bool,
    /// pma's row gathers ([`crate::compute::ops::rows`]), whose backward is parallel on CUDA. Off:
    /// candle's `index_select` and `gather`.
    pub row_ops: bool,
    /// TF32 tensor cores for the forward matrix products of the network's layers ([`matmul`];
    /// CUDA only; never for geometry or compositing). The backward's products stay f32: candle
    /// runs them outside the forward's scope.
    pub tf32: bool,
    /// On CUDA, sum every gradient in a fixed order (no atomics), so a run repeats and
    /// resumes bit for bit; costs the row ops' backward a scan over the indices per output
    /// element. Nothing changes on the CPU, which is deterministic anyway.
    pub deterministic: bool,
    /// The density trunk's products in bf16 (`--bf16-trunk`): inputs, weights and outputs
    /// rounded to bf16, accumulation in f32, as bf16 tensor cores compute them ([`bf16`]);
    /// on the CPU this emulates the GPU's numbers (it is not faster). Not parity: its PSNR
    /// cost is measured in docs/numerics.md.
    pub bf16_trunk: bool,
}

impl Default for Numerics {
    fn default() -> Self {
        Self::PARITY
    }
}

impl Numerics {
    /// The parity choices (the default).
    pub const PARITY: Self = Self {
        fast_sine: false,
        fused: true,
        row_ops: true,
        tf32: false,
        deterministic: false,
        bf16_trunk: false,
    };

    /// Whether every choice reproduces the plain f32 ops (bit for bit on the CPU).
    pub fn is_parity(&self) -> bool {
        !self.fast_sine && !self.tf32 && !self.bf16_trunk
    }
}

/// `x` rounded to the nearest bf16 (round to nearest even), kept as f32; the gradient
/// passes through unchanged (candle's cast backward).
pub fn bf16(x: &Tensor) -> Result<Tensor> {
    Ok(x.to_dtype(candle_core::DType::BF16)?
        .to_dtype(candle_core::DType::F32)?)
}

/// `a · b` with the network's precision choice: TF32 on CUDA when [`Numerics::tf32`], f32
/// otherwise (a scope of this thread's launches, so other avatars are unaffected).
pub fn matmul(a: &Tensor, b: &Tensor, k: Numerics) -> Result<Tensor> {
    Ok(candle_core::cuda::with_gemm_reduced_precision_f32(
        k.tf32,
        || a.matmul(b),
    )?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::network::nn::Linear;
    use candle_core::Device;

    #[test]
    fn bf16_rounds_to_the_nearest_even_bf16() {
        let ulp = 2f32.powi(-7); // bf16 keeps 8 significant bits: 1 + 2^-7 is next after 1
        let x = Tensor::new(
            &[
                1.0 + ulp / 2.0,
                1.0 + 1.5 * ulp,
                1.0 + 0.75 * ulp,
                -3.0,
                0.0,
            ],
            &Device::Cpu,
        )
        .unwrap();
        let r: Vec<f32> = bf16(&x).unwrap().to_vec1().unwrap();
        assert_eq!(r, [1.0, 1.0 + 2.0 * ulp, 1.0 + ulp, -3.0, 0.0]);
    }

    /// `--bf16-trunk`'s layer is the f32 layer within bf16's rounding (inputs, weights and
    /// output each rounded once: a relative error of a few 2^-9 on well-conditioned sums),
    /// and not the same values (it is not parity).
    #[test]
    fn a_bf16_layer_is_the_f32_layer_within_bf16_rounding() {
        let dev = Device::Cpu;
        let vals = |n: usize, s: f32| -> Vec<f32> {
            (0..n)
                .map(|i| ((i * 37 % 101) as f32 / 101.0 + 0.5) * s)
                .collect()
        };
        let layer = Linear {
            weight: Tensor::from_vec(vals(16 * 8, 0.3), (16, 8), &dev).unwrap(),
            bias: Tensor::from_vec(vals(16, 0.1), 16, &dev).unwrap(),
        };
        let x = Tensor::from_vec(vals(5 * 8, 1.0), (5, 8), &dev).unwrap();
        let k = Numerics::PARITY;
        let f32s: Vec<f32> = layer
            .forward(&x, k)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let bf: Vec<f32> = layer
            .forward_bf16(&x, k)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let worst = f32s
            .iter()
            .zip(&bf)
            .map(|(a, b)| ((a - b) / a).abs())
            .fold(0f32, f32::max);
        assert!(worst > 0.0, "bf16 rounding changed nothing");
        assert!(worst < 4.0 * 2f32.powi(-9), "relative error {worst}");
    }
}
