//! Retargeting real motion onto a trained avatar (docs/conventions.md, "Motion files" and
//! "Units and up axis").
//!
//! A motion (e.g. from `pma convert motion`: AIST++ dance, CMU walk) gives per-frame joint
//! rotations and a root trajectory recorded on *another* body. To drive the avatar:
//!
//! 1. **Up axis.** The avatar was trained with the head toward −y. A y-up motion (AIST++) is
//!    turned by `F = diag(1,−1,−1)` (180° about x): `R₀ ← F·R₀`, `t ← F·t`. Joint rotations
//!    below the root are relative and stay as they are.
//! 2. **Bone lengths** come from the avatar's rest pose: `kp3d` and `skts` are recomputed by
//!    forward kinematics with it, never taken from the motion file (whose `kp3d` were made
//!    with the source skeleton).
//! 3. **Root trajectory.** The rotations transfer as they are, but the root's translation is
//!    in the source body's proportions: a shorter avatar replaying a tall dancer's trajectory
//!    would skate and float. The translation is scaled by the ratio of **leg lengths**
//!    (hip→knee→ankle, mean of both sides) of the avatar's rest pose over the motion's. Leg
//!    length, not body height, because the legs alone set pelvis height and stride; the head
//!    and torso do not move the root. The scale is about the world origin, which keeps a
//!    floor through the origin (AIST++, CMU BVH) a floor.
//!
//! When the motion file holds no rest pose of its own, its source skeleton is unknown and the
//! trajectory is kept (scale 1) unless a factor is given.

use std::path::Path;

use candle_core::Tensor;
use pma_data::cylinder::HeadDir;
use pma_data::dataset::{Dataset, Profile, ReadOptions};
use pma_data::motion::Motion;
use pma_data::skeleton::{forward_kinematics, Joints, Transforms, N_JOINTS};

use crate::error::{ModelError, Result};
use crate::render::avatar::Avatar;
use crate::render::batch::Poses;

/// How the root trajectory is rescaled.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RootScale {
    /// Avatar leg length / motion leg length (1 when the motion has no rest pose).
    LegRatio,
    /// A fixed factor (1 keeps the trajectory).
    Factor(f64),
}

impl std::str::FromStr for RootScale {
    type Err = ModelError;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "legs" => Ok(RootScale::LegRatio),
            "none" => Ok(RootScale::Factor(1.0)),
            other => match other.parse::<f64>() {
                Ok(f) if f.is_finite() && f > 0.0 => Ok(RootScale::Factor(f)),
                _ => Err(ModelError::Input(format!(
                    "root scale {other:?}: expected `legs`, `none` or a positive factor"
                ))),
            },
        }
    }
}

/// A motion to retarget: per-frame rotations and root translations in the motion's world.
#[derive(Debug, Clone, PartialEq)]
pub struct MotionClip {
    /// Axis-angle per frame `[24][3]`; joint 0 is the global orientation.
    pub bones: Vec<Joints>,
    /// Root translation per frame (`kp3d[0] − rest[0]`).
    pub roots: Vec<[f32; 3]>,
    /// Where the head points in the motion's world.
    pub head: HeadDir,
    /// The skeleton the motion was recorded (or converted) on, if known.
    pub rest: Option<Joints>,
}

impl MotionClip {
    /// The pose rows of a dataset (any profile). `root_locs` must be present (it is derived
    /// on import from `kp3d` when absent). The dataset's `rest_pose` counts as the source
    /// skeleton only when it was read from the file, not filled in from the model.
    pub fn from_dataset(ds: &Dataset) -> Result<MotionClip> {
        let roots = ds.root_locs.as_ref().ok_or_else(|| {
            ModelError::Input(format!(
                "{}: no root_locs (and no kp3d to derive them from)",
                ds.source
            ))
        })?;
        let head = ds.head()?;
        let p = ds.n_poses();
        let own_rest = !ds.derived.iter().any(|d| d.starts_with("rest_pose"));
        Ok(MotionClip {
            bones: (0..p).map(|i| ds.pose_bones(i)).collect(),
            roots: (0..p)
                .map(|i| [roots[[i, 0]], roots[[i, 1]], roots[[i, 2]]])
                .collect(),
            head,
            rest: if own_rest { ds.rest_pose } else { None },
        })
    }

    pub fn len(&self) -> usize {
        self.bones.len()
    }

    pub fn is_empty(&self) -> bool {
        self.bones.is_empty()
    }

    fn validate(&self) -> Result<()> {
        if self.bones.is_empty() {
            return Err(ModelError::Input("motion has no frames".into()));
        }
        if self.bones.len() != self.roots.len() {
            return Err(ModelError::Input(format!(
                "motion has {} rotation frames but {} root locations",
                self.bones.len(),
                self.roots.len()
            )));
        }
        for (f, (b, r)) in self.bones.iter().zip(&self.roots).enumerate() {
            if !b.iter().flatten().chain(r).all(|v| v.is_finite()) {
                return Err(ModelError::Input(format!(
                    "motion frame {f} has a non-finite rotation or root location"
                )));
            }
        }
        Ok(())
    }
}

/// A motion (or any pma-npz) file's pose rows for `avatar`, with the file read as a
/// dataset. Kinematics the file leaves out use the avatar's rest pose (see
/// `docs/conventions.md`, "pma-npz v1"); the dataset's `warnings` are for the caller to
/// show. A clip without a `rest` of its own keeps its root trajectory as it is.
pub fn read_motion(avatar: &Avatar, path: &Path) -> Result<(MotionClip, Dataset)> {
    let mut opts = ReadOptions::new(Profile::Motion);
    opts.rest_pose = Some(*avatar.rest_pose());
    let ds = Dataset::read(path, &opts).map_err(|e| ModelError::Motion {
        path: path.to_path_buf(),
        source: Box::new(e),
    })?;
    let clip = MotionClip::from_dataset(&ds)?;
    Ok((clip, ds))
}

/// One retargeted frame, in the training convention (head −y).
#[derive(Debug, Clone, PartialEq)]
pub struct RetargetedFrame {
    pub bones: Joints,
    /// Root translation after the up-axis turn and rescaling.
    pub root: [f32; 3],
    /// Joints by FK with the avatar's rest pose.
    pub kp3d: Joints,
    /// World → joint transforms `[24][4][4]`.
    pub skts: Transforms,
}

#[derive(Debug, Clone, PartialEq)]
pub struct Retargeted {
    pub frames: Vec<RetargetedFrame>,
    /// The factor applied to the root translation.
    pub root_scale: f64,
    /// Whether the motion was turned from y-up to y-down.
    pub flipped: bool,
}

/// Hip→knee→ankle length, mean of both legs.
pub fn leg_length(rest: &Joints) -> f64 {
    let d = |a: usize, b: usize| -> f64 {
        (0..3)
            .map(|k| (rest[a][k] as f64 - rest[b][k] as f64).powi(2))
            .sum::<f64>()
            .sqrt()
    };
    // SMPL: 1/2 hips, 4/5 knees, 7/8 ankles.
    0.5 * (d(1, 4) + d(4, 7) + d(2, 5) + d(5, 8))
}

/// The root scale `scale` resolves to for a motion recorded on `source` played on `target`.
pub fn root_scale(scale: RootScale, source: Option<&Joints>, target: &Joints) -> Result<f64> {
    match (scale, source) {
        (RootScale::Factor(f), _) => {
            if f.is_finite() && f > 0.0 {
                Ok(f)
            } else {
                Err(ModelError::Input(format!(
                    "root scale must be finite and > 0, found {f}"
                )))
            }
        }
        (RootScale::LegRatio, None) => Ok(1.0),
        (RootScale::LegRatio, Some(src)) => {
            let (ls, lt) = (leg_length(src), leg_length(target));
            if !(ls.is_finite() && ls > 0.0 && lt.is_finite() && lt > 0.0) {
                return Err(ModelError::Input(format!(
                    "leg lengths must be finite and > 0 (motion {ls}, avatar {lt})"
                )));
            }
            Ok(lt / ls)
        }
    }
}

/// Retarget `clip` onto a body with rest pose `target` (see the module docs).
pub fn retarget(clip: &MotionClip, target: &Joints, scale: RootScale) -> Result<Retargeted> {
    clip.validate()?;
    pma_data::skeleton::check_rest_pose(target)?;
    let s = root_scale(scale, clip.rest.as_ref(), target)?;
    let motion = Motion {
        // The frame rate plays no part in the up-axis turn.
        fps: 1.0,
        bones: clip.bones.clone(),
        root: clip.roots.clone(),
        up: clip.head,
    }
    .to_up(HeadDir::NegY);
    let frames = motion
        .bones
        .iter()
        .zip(&motion.root)
        .map(|(b, r)| {
            let root = r.map(|v| (v as f64 * s) as f32);
            let posed = forward_kinematics(target, b, root);
            RetargetedFrame {
                bones: *b,
                root,
                kp3d: posed.kp3d,
                skts: posed.skts,
            }
        })
        .collect();
    Ok(Retargeted {
        frames,
        root_scale: s,
        flipped: clip.head != HeadDir::NegY,
    })
}

impl Avatar {
    /// Per-pose data for one pose given only its bones and root location: FK with the
    /// avatar's own rest pose (what retargeting needs).
    pub fn pose_from_bones(&self, bones: &Joints, root: [f32; 3]) -> Result<(Poses, Joints)> {
        let posed = forward_kinematics(self.rest_pose(), bones, root);
        let skts: Vec<f32> = posed.skts.iter().flatten().flatten().copied().collect();
        let cyl = pma_data::cylinder::cylinder_from_joints(
            &posed.kp3d,
            &pma_data::cylinder::CylinderParams::training(pma_data::cylinder::HeadDir::NegY),
        );
        Ok((
            Poses {
                bones: vec![*bones],
                skts: Tensor::from_vec(skts, (1, N_JOINTS, 4, 4), self.device())?,
                cyls: Tensor::from_vec(cyl.to_vec(), (1, 5), self.device())?,
            },
            posed.kp3d,
        ))
    }
}
