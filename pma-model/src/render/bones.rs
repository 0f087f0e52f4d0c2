//! The bone boxes of a batch of poses.
//!
//! Each joint j of pose p owns a box: world space is mapped into the joint's frame by
//! `skt_j` (world → joint, from forward kinematics), then into the bone-aligned frame by
//! `A_j` (the bone-alignment transform of the rest pose, a buffer of the model). The
//! composite `A_j · skt_j` is what ray casting clips rays against, what culling evaluates the
//! spatial window with, and what mesh extraction and the stability probes test points
//! against; it is composed here, once, for all of them. The network itself applies the two
//! steps separately (see `Network::eval_points`), because folding them changes the rounding.

use candle_core::Tensor;
use pma_data::skeleton::N_JOINTS;

use crate::compute::host::host_f32;
use crate::error::{ModelError, Result};

/// Host copies of `A_j` [24,4,4] and `skt_j` [P,24,4,4], row-major.
#[derive(Debug, Clone)]
pub struct BoneFrames {
    align: Vec<f32>,
    skts: Vec<f32>,
}

impl BoneFrames {
    /// align: [24·16] `A_j`; skts: [P·24·16] world → joint transforms.
    pub fn new(align: &[f32], skts: &[f32]) -> Result<Self> {
        if align.len() != N_JOINTS * 16 {
            return Err(ModelError::shape(
                "bone-alignment transforms",
                [N_JOINTS, 4, 4],
                format!("{} values", align.len()),
            ));
        }
        if skts.is_empty() || skts.len() % (N_JOINTS * 16) != 0 {
            return Err(ModelError::shape(
                "skts",
                "[P,24,4,4] with P >= 1",
                format!("{} values", skts.len()),
            ));
        }
        Ok(Self {
            align: align.to_vec(),
            skts: skts.to_vec(),
        })
    }

    /// From tensors on any device: align [24,4,4], skts [P,24,4,4].
    pub fn from_tensors(align: &Tensor, skts: &Tensor) -> Result<Self> {
        Self::new(&host_f32(align)?, &host_f32(skts)?)
    }

    pub fn n_poses(&self) -> usize {
        self.skts.len() / (N_JOINTS * 16)
    }

    /// `A_j`, row-major 4×4.
    pub fn align(&self, j: usize) -> &[f32] {
        &self.align[j * 16..j * 16 + 16]
    }

    /// `skt_j` of pose p, row-major 4×4.
    pub fn skt(&self, p: usize, j: usize) -> &[f32] {
        &self.skts[(p * N_JOINTS + j) * 16..][..16]
    }

    /// `A_j · skt_j` in f32 arithmetic (what the ray caster clips against).
    pub fn world_to_box(&self, p: usize, j: usize) -> [f32; 16] {
        mat4_mul(self.align(j), self.skt(p, j))
    }

    /// The top three rows of `A_j · skt_j`, accumulated in f64 (culling and mesh tests).
    pub fn world_to_box_f64(&self, p: usize, j: usize) -> [[f64; 4]; 3] {
        let (a, t) = (self.align(j), self.skt(p, j));
        let mut m = [[0f64; 4]; 3];
        for (i, row) in m.iter_mut().enumerate() {
            for (k, v) in row.iter_mut().enumerate() {
                *v = (0..4)
                    .map(|l| a[4 * i + l] as f64 * t[4 * l + k] as f64)
                    .sum::<f64>();
            }
        }
        m
    }

    /// World position of pose p's root joint: `−R⁰ᵀ t⁰` of `skt_0`.
    pub fn root_origin(&self, p: usize) -> [f64; 3] {
        let t = self.skt(p, 0);
        let mut root = [0f64; 3];
        for (c, r) in root.iter_mut().enumerate() {
            *r = -(0..3)
                .map(|i| t[4 * i + c] as f64 * t[4 * i + 3] as f64)
                .sum::<f64>();
        }
        root
    }
}

/// 4×4 row-major product a·b in f32.
pub fn mat4_mul(a: &[f32], b: &[f32]) -> [f32; 16] {
    let mut m = [0f32; 16];
    for i in 0..4 {
        for k in 0..4 {
            m[4 * i + k] = (0..4).fold(0f32, |s, l| s + a[4 * i + l] * b[4 * l + k]);
        }
    }
    m
}
