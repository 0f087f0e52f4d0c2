//! Real motion for driving the SMPL skeleton: SMPL-parameter npz files
//! (AIST++, AMASS-style `poses` + `trans`) and CMU BVH motion capture
//! retargeted onto the SMPL 24 joints.
//!
//! Every reader produces a [`Motion`]: per-frame SMPL axis-angle rotations
//! (joint 0 = global orientation) and root locations in metres, plus the
//! direction the subject's head points in the motion's world frame. Models
//! trained on H36M-ZJU expect the head toward −y; [`Motion::to_up`] applies
//! the flip `F = diag(1,−1,−1)` to the root rotation and translation
//! (docs/conventions.md, "Units and up axis").

pub mod bvh;
pub mod retarget;
mod smpl_npz;

use std::ops::Range;
use std::path::PathBuf;

use glam::{DMat3, DQuat, DVec3};

pub use crate::cylinder::HeadDir;
use crate::skeleton::{axis_angle_to_matrix, matrix_to_axis_angle, Joints, N_JOINTS};

pub use smpl_npz::{parse_smpl_npz, read_smpl_npz};

/// Errors from reading, retargeting or editing motion.
#[derive(Debug, thiserror::Error)]
pub enum MotionError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The npz container or one of its members cannot be read.
    #[error("{file}: key `{key}`: {msg}")]
    Npz {
        file: String,
        key: String,
        msg: String,
    },
    #[error("{file}: key `{key}` has shape {found:?}, expected {expected}")]
    Shape {
        file: String,
        key: String,
        expected: String,
        found: Vec<u64>,
    },
    #[error("{file}: key `{key}` holds a non-finite value at frame {frame}")]
    NonFinite {
        file: String,
        key: String,
        frame: usize,
    },
    #[error("{file}:{line}: {msg}")]
    Bvh {
        file: String,
        line: usize,
        msg: String,
    },
    /// A joint the retargeting map needs is absent from the BVH hierarchy.
    #[error(
        "{file}: the BVH has no joint `{joint}` (needed for SMPL joint {smpl_joint} `{smpl_name}`)"
    )]
    MissingJoint {
        file: String,
        joint: String,
        smpl_joint: usize,
        smpl_name: &'static str,
    },
    #[error("{what}: cannot tell which way is up: the mean head direction has y = {mean_y:.3}, expected |y| > 0.5 (pass the up axis explicitly)")]
    AmbiguousUp { what: String, mean_y: f64 },
    #[error("invalid argument `{name}`: expected {expected}, found {found}")]
    Argument {
        name: &'static str,
        expected: String,
        found: String,
    },
}

impl crate::error::ExitKind for MotionError {
    fn kind(&self) -> crate::error::ErrorKind {
        match self {
            MotionError::Io { source, .. } => crate::error::input_io_kind(source),
            _ => crate::error::ErrorKind::Refused,
        }
    }
}

/// A sequence of SMPL poses.
#[derive(Clone, Debug, PartialEq)]
pub struct Motion {
    /// Frames per second.
    pub fps: f64,
    /// Per frame `[24][3]` axis-angle (radians) relative to the parent;
    /// joint 0 is the global orientation in the motion's world frame.
    pub bones: Vec<Joints>,
    /// Per frame, the root (pelvis) location in metres, world frame.
    pub root: Vec<[f32; 3]>,
    /// Where the head points in this motion's world frame.
    pub up: HeadDir,
}

/// Axis-angle (radians) → rotation matrix, in f64.
pub(crate) fn mat_from_rotvec(v: [f32; 3]) -> DMat3 {
    axis_angle_to_matrix(DVec3::new(v[0] as f64, v[1] as f64, v[2] as f64))
}

/// Rotation matrix → axis-angle (angle in [0, π]), stored as f32.
pub(crate) fn rotvec_from_mat(m: DMat3) -> [f32; 3] {
    let v = matrix_to_axis_angle(m);
    [v.x as f32, v.y as f32, v.z as f32]
}

fn quat_from_rotvec(v: [f32; 3]) -> DQuat {
    DQuat::from_mat3(&mat_from_rotvec(v))
}

/// The up-axis flip, a 180° turn about x.
const FLIP: DMat3 = DMat3::from_cols(
    DVec3::new(1.0, 0.0, 0.0),
    DVec3::new(0.0, -1.0, 0.0),
    DVec3::new(0.0, 0.0, -1.0),
);

impl Motion {
    /// Checks that the per-frame arrays agree in length, the frame rate is
    /// positive and every value is finite.
    pub fn validate(&self) -> Result<(), MotionError> {
        if !(self.fps.is_finite() && self.fps > 0.0) {
            return Err(MotionError::Argument {
                name: "fps",
                expected: "a positive frame rate".into(),
                found: self.fps.to_string(),
            });
        }
        if self.bones.len() != self.root.len() {
            return Err(MotionError::Argument {
                name: "root",
                expected: format!("one root per pose ({} frames)", self.bones.len()),
                found: format!("{} roots", self.root.len()),
            });
        }
        if self.bones.is_empty() {
            return Err(MotionError::Argument {
                name: "bones",
                expected: "at least one frame".into(),
                found: "0 frames".into(),
            });
        }
        let bad = |key: &str, frame| MotionError::NonFinite {
            file: "<motion>".into(),
            key: key.into(),
            frame,
        };
        for (f, (b, r)) in self.bones.iter().zip(&self.root).enumerate() {
            if !b.iter().flatten().all(|v| v.is_finite()) {
                return Err(bad("bones", f));
            }
            if !r.iter().all(|v| v.is_finite()) {
                return Err(bad("root", f));
            }
        }
        Ok(())
    }

    pub fn len(&self) -> usize {
        self.bones.len()
    }

    pub fn is_empty(&self) -> bool {
        self.bones.is_empty()
    }

    /// Frames `range` of this motion.
    pub fn frames(&self, range: Range<usize>) -> Result<Motion, MotionError> {
        if range.start >= range.end || range.end > self.len() {
            return Err(MotionError::Argument {
                name: "frame range",
                expected: format!("a non-empty range within 0..{}", self.len()),
                found: format!("{}..{}", range.start, range.end),
            });
        }
        Ok(Motion {
            fps: self.fps,
            bones: self.bones[range.clone()].to_vec(),
            root: self.root[range].to_vec(),
            up: self.up,
        })
    }

    /// Every `step`-th frame starting at frame 0; the frame rate drops by
    /// the same factor.
    pub fn every(&self, step: usize) -> Result<Motion, MotionError> {
        if step == 0 {
            return Err(MotionError::Argument {
                name: "step",
                expected: "at least 1".into(),
                found: "0".into(),
            });
        }
        Ok(Motion {
            fps: self.fps / step as f64,
            bones: self.bones.iter().step_by(step).copied().collect(),
            root: self.root.iter().step_by(step).copied().collect(),
            up: self.up,
        })
    }

    /// Resamples to `fps`, covering the same time span from the first
    /// frame. Joint rotations are interpolated by quaternion slerp and the
    /// root linearly; a sample time that falls on a source frame copies it.
    pub fn resample(&self, fps: f64) -> Result<Motion, MotionError> {
        if !(fps.is_finite() && fps > 0.0) {
            return Err(MotionError::Argument {
                name: "fps",
                expected: "a positive frame rate".into(),
                found: fps.to_string(),
            });
        }
        self.validate()?;
        let last = (self.len() - 1) as f64;
        // Sample k sits at source position k·ratio; the small slack keeps a
        // span that divides evenly from losing its last frame to rounding.
        let ratio = self.fps / fps;
        let n = (last / ratio + 1e-9).floor() as usize + 1;
        let mut bones = Vec::with_capacity(n);
        let mut root = Vec::with_capacity(n);
        for k in 0..n {
            let pos = (k as f64 * ratio).min(last);
            let i = pos.floor() as usize;
            let s = pos - i as f64;
            if s < 1e-9 || i + 1 >= self.len() {
                bones.push(self.bones[i]);
                root.push(self.root[i]);
                continue;
            }
            let (a, b) = (&self.bones[i], &self.bones[i + 1]);
            let mut frame = [[0.0f32; 3]; N_JOINTS];
            for j in 0..N_JOINTS {
                let q = quat_from_rotvec(a[j]).slerp(quat_from_rotvec(b[j]), s);
                frame[j] = rotvec_from_mat(DMat3::from_quat(q));
            }
            bones.push(frame);
            let (ra, rb) = (self.root[i], self.root[i + 1]);
            root.push(std::array::from_fn(|c| {
                (ra[c] as f64 + s * (rb[c] as f64 - ra[c] as f64)) as f32
            }));
        }
        Ok(Motion {
            fps,
            bones,
            root,
            up: self.up,
        })
    }

    /// Re-expresses the motion so the head points along `up`: `R₀ ← F·R₀`
    /// and `t ← F·t` with `F = diag(1,−1,−1)`. Joint rotations below the
    /// root are relative and stay as they are. A camera
    /// rig seen with this motion needs `c2w ← diag(1,−1,−1,1)·c2w`.
    pub fn to_up(&self, up: HeadDir) -> Motion {
        if up == self.up {
            return self.clone();
        }
        let mut out = self.clone();
        for (b, r) in out.bones.iter_mut().zip(out.root.iter_mut()) {
            b[0] = rotvec_from_mat(FLIP * mat_from_rotvec(b[0]));
            *r = [r[0], -r[1], -r[2]];
        }
        out.up = up;
        out
    }

    /// Replaces the root locations by `root − mean(root)` on the axes where
    /// `keep` is false, removing global drift (a treadmill for walks).
    pub fn centre_root(&self, keep: [bool; 3]) -> Motion {
        let n = self.len().max(1) as f64;
        let mean: [f64; 3] =
            std::array::from_fn(|c| self.root.iter().map(|r| r[c] as f64).sum::<f64>() / n);
        let mut out = self.clone();
        for r in &mut out.root {
            for c in 0..3 {
                if !keep[c] {
                    r[c] = (r[c] as f64 - mean[c]) as f32;
                }
            }
        }
        out
    }
}

/// Guesses the up axis from the root orientations: SMPL's canonical head
/// direction is +y, so the head points along `R₀·ŷ`. Returns `None` when
/// the mean of its y component is within ±0.5 (lying or tumbling motion).
pub fn detect_up(bones: &[Joints]) -> Option<HeadDir> {
    let mean_y = mean_head_y(bones);
    if mean_y > 0.5 {
        Some(HeadDir::PosY)
    } else if mean_y < -0.5 {
        Some(HeadDir::NegY)
    } else {
        None
    }
}

fn mean_head_y(bones: &[Joints]) -> f64 {
    let sum: f64 = bones
        .iter()
        .map(|b| (mat_from_rotvec(b[0]) * DVec3::Y).y)
        .sum();
    sum / bones.len().max(1) as f64
}

pub(crate) fn ambiguous_up(what: &str, bones: &[Joints]) -> MotionError {
    MotionError::AmbiguousUp {
        what: what.to_string(),
        mean_y: mean_head_y(bones),
    }
}
