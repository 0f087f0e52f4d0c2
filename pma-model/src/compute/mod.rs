//! Compute machinery under the network: what makes it fast on each backend, and what it costs.
//!
//! Nothing here knows the paper. Every kernel is exact unless its name says otherwise: the
//! fused CPU kernels and the vectorised libm sine return the plain ops' bits, the row ops
//! candle's gathers' bits on the CPU.
//!
//! | module | what |
//! | --- | --- |
//! | [`numerics`] | a network's numeric choices: fused kernels, fast sine, row ops, TF32 |
//! | [`fused`] | fused kernels: the window max-pool, the FiLM-sine stack, bias adds |
//! | [`linear_act`] | a linear layer and its ReLU or sine as one op on a GPU's route |
//! | [`sine_linear`] | the point encoders' SIREN layer as one op on a GPU's route |
//! | [`cuda`] | the fused ops' CUDA kernels (`cuda/kernels/*.cu`, NVRTC at run time) |
//! | [`libm_sine`] | glibc's sinf/cosf recipe, lane-wise (bit-identical, vectorised) |
//! | [`fast_sine`] | the sine op; the optional polynomial sine (`--fast-sine`, not parity) |
//! | [`ops`] | row gathers with a parallel backward on CUDA (`ops/kernels/*.cu`) |
//! | [`parallel`] | data-parallel CPU workers |
//! | [`host`] | the one device → host copy |
//! | [`device`] | `--device` strings to candle devices, CUDA memory-pool settings |
//! | [`profile`] | per-stage step timing (`PMA_PROFILE=1`) |
//! | [`flops`] | matmul FLOPs per point and the CPU's estimated fp32 peak |
//! | [`account`] | what a step launches and waits for on a GPU, counted on any device; a cost model |

pub mod account;
pub mod cuda;
pub mod device;
pub mod fast_sine;
pub mod flops;
pub mod fused;
pub mod host;
pub mod libm_sine;
pub mod linear_act;
pub mod numerics;
pub mod ops;
pub mod parallel;
pub mod profile;
pub mod sine_linear;
