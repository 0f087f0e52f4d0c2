//! From rays to pixels: the bone boxes, ray casting and importance sampling, how samples
//! reach the network (densely, in chunks, or culled), volume rendering, and the [`Avatar`]
//! that wires them to the network top-down.
//!
//! | module | what |
//! | --- | --- |
//! | [`batch`] | what a pass takes and returns: rays, poses, mode, outputs |
//! | [`batch_file`] | the ray-batch npz of `pma forward` and its outputs npz |
//! | [`bones`] | world → bone-aligned box frames of a batch of poses |
//! | [`raycast`] | near/far from the bounding cylinder and the boxes; 48 + 24 samples |
//! | [`options`] | what one pass may leave out ([`PassOptions`]), and what it did |
//! | [`cull`] | which rays and samples may skip the network |
//! | [`placement`] | coarse samples in the intervals the occupancy grid marks occupied |
//! | [`points`] | the routes of a pass's samples through the network |
//! | [`volume`] | volume rendering (differentiable) |
//! | [`occupancy`] | refreshing an avatar's occupancy grid from the network's density |
//! | [`avatar`] | the forward pass, top-down |
//! | [`image`] | whole images in bounded memory |
//! | [`camera_path`] | orbit, bullet-time and framing cameras |

/// The most rays one chunk of a render or a training step may have (a flag such as
/// `--chunk` above it is refused; the paper's training step has 3,072 rays).
pub const MAX_CHUNK_RAYS: usize = 1 << 20;

pub mod avatar;
pub mod batch;
pub mod batch_file;
pub mod bones;
pub mod camera_path;
pub mod cull;
pub mod image;
pub mod occupancy;
pub mod options;
pub mod placement;
pub mod points;
pub mod raycast;
pub mod volume;

pub use avatar::Avatar;
pub use options::{Culling, PassOptions, PassStats, SampleFill};
