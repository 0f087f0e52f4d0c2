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
    /// Fused kernels (on the CPU: [`crate::compute::fused`], bit-identical to the plain ops; on
    /// CUDA: [`crate::compute::cuda`]'s kernels). Off: candle's plain ops everywhere.
    pub fused: bool,
    /// pma's row gathers ([`crate::compute::ops`]), whose backward is parallel on CUDA. Off:
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
    };

    /// Whether every choice reproduces the plain f32 ops (bit for bit on the CPU).
    pub fn is_parity(&self) -> bool {
        !self.fast_sine && !self.tf32
    }
}

/// `a · b` with the network's precision choice: TF32 on CUDA when [`Numerics::tf32`], f32
/// otherwise (a scope of this thread's launches, so other avatars are unaffected).
pub fn matmul(a: &Tensor, b: &Tensor, k: Numerics) -> Result<Tensor> {
    Ok(candle_core::cuda::with_gemm_reduced_precision_f32(
        k.tf32,
        || a.matmul(b),
    )?)
}
