//! Compute machinery under the network: what makes it fast on each backend, and what it costs.
//!
//! Nothing here knows the paper. Every kernel is exact unless its name says otherwise: the
//! fused CPU kernels and the vectorised libm sine return the plain ops' bits, the row ops
//! candle's gathers' bits on the CPU.
//!
//! | module | what |
//! | --- | --- |
//! | [`numerics`] | a network's numeric choices: fused kernels, fast sine, row ops, TF32 |
//! | [`ops`] | pma's custom ops, one folder each: linear layers, window pool, FiLM-sine, point encoder, row gathers, Adam |
//! | [`kernel`] | what the ops stand on: routes, device memory, launches (CUDA and the emulated grid), kernel health, checks |
//! | [`libm_sine`] | glibc's sinf/cosf recipe, lane-wise (bit-identical, vectorised) |
//! | [`fast_sine`] | the sine op; the optional polynomial sine (`--fast-sine`, not parity) |
//! | [`parallel`] | data-parallel CPU workers |
//! | [`host`] | the one device → host copy |
//! | [`device`] | `--device` strings to candle devices, CUDA memory-pool settings |
//! | [`profile`] | per-stage step timing (`PMA_PROFILE=1`) |
//! | [`flops`] | matmul FLOPs per point and the CPU's estimated fp32 peak |
//! | [`account`] | what a step launches and waits for on a GPU, counted on any device; a cost model |

pub mod account;
pub mod device;
pub mod fast_sine;
pub mod flops;
pub mod host;
pub mod kernel;
pub mod libm_sine;
pub mod numerics;
pub mod ops;
pub mod parallel;
pub mod profile;
