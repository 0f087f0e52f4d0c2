//! Tools on a trained avatar: meshes, numerical-stability probes, motion retargeting, and
//! the planning of rendered sequences.
//!
//! | module | what |
//! | --- | --- |
//! | [`mesh`] | density field on a grid, marching cubes, PLY, a preview picture |
//! | [`occupancy`] | an occupancy grid for a model trained without one |
//! | [`stability`] | the extreme-case probes of `pma check-stability` |
//! | [`retarget`] | real motion (AIST++, CMU) onto the avatar's skeleton |
//! | [`video`] | `pma render`'s poses, camera per frame, PNG frames, GIF and strip |

pub mod mesh;
pub mod occupancy;
pub mod retarget;
pub mod stability;
pub mod video;
