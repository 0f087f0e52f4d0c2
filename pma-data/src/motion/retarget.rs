//! Retargeting CMU BVH motion capture onto the SMPL 24-joint skeleton.
//!
//! # Why a plain channel copy does not work
//! The CMU skeleton (31 joints) and SMPL (24) differ in joint count, in
//! where the joints sit, and in their rest poses: the "cmuconvert" BVH rest
//! pose has the arms hanging down, SMPL's is a T-pose, and the spine
//! segments lean differently. A BVH joint rotation is relative to *its*
//! rest pose, so copying it onto SMPL would put the arms 90° off.
//!
//! # Method: match world bone directions
//! For every SMPL joint `j` we build its world orientation `Q_j` from the
//! posed BVH, then take local rotations `R_j = Q_parent(j)ᵀ·Q_j` (and
//! `R_0 = Q_0`). Every SMPL joint has one [`Source`]:
//!
//! * **Bone** (joints with one SMPL child `c`): the SMPL bone `j → c` must
//!   point where the BVH segment `from → to` points. In the rest poses (all
//!   BVH channels zero, all SMPL rotations identity) the two directions are
//!   `s` (SMPL) and `u` (BVH); `A_j` is the shortest-arc rotation taking
//!   `s` onto `u`. The BVH joint that carries `to` (its parent, the
//!   "owner") has world rotation `G`; then
//!   `Q_j = Δ·G·A_j`, where `Δ` is the shortest arc from `G·u` onto the
//!   posed segment direction. `Δ` is the identity whenever the owner sits
//!   at `from` (true for every entry of [`CMU_TO_SMPL`]); it is kept so a
//!   map whose segment spans several BVH joints still matches directions.
//!   So `Q_j·s` equals the posed BVH direction, and the twist about the bone
//!   is the owner's twist.
//! * **Frame** (pelvis and spine3, which have several children): no single
//!   direction fixes them, so `A_j` aligns two rest-pose reference
//!   directions at once (an "up" segment and a left–right segment, turned
//!   into orthonormal frames by Gram–Schmidt in both skeletons), and
//!   `Q_j = G_owner·A_j`.
//! * **Leaf** (feet, head, hands, which have no SMPL child): they turn with
//!   the BVH's own relative rotation between their owner and their
//!   parent's owner, `Q_j = (G_owner(j)·G_owner(parent)ᵀ)·Q_parent`; in the
//!   rest pose that is the identity local rotation.
//!
//! Bone lengths are SMPL's (only directions are transferred). The root
//! location is the BVH `Hips` position in metres.

use glam::{DMat3, DQuat, DVec3};

use super::bvh::{Bvh, BvhPose};
use super::{rotvec_from_mat, HeadDir, Motion, MotionError};
use crate::skeleton::{Joints, JOINT_NAMES, N_JOINTS, PARENTS};

/// CMU "cmuconvert" BVH length unit in metres: `(1/0.45)·2.54/100`.
pub const CMU_UNIT_METRES: f64 = 0.056444;

/// How one SMPL joint gets its world orientation (see the module docs).
#[derive(Clone, Copy, Debug)]
pub enum Source {
    /// The SMPL bone to the single child follows BVH segment `from → to`.
    Bone {
        from: &'static str,
        to: &'static str,
    },
    /// Orientation of BVH joint `owner`, aligned in the rest pose by an up
    /// segment and a side segment given for both skeletons.
    Frame {
        owner: &'static str,
        bvh_up: (&'static str, &'static str),
        bvh_side: (&'static str, &'static str),
        smpl_up: (usize, usize),
        smpl_side: (usize, usize),
    },
    /// An end effector turning with BVH joint `owner` relative to the
    /// parent's owner.
    Leaf { owner: &'static str },
}

/// One row of a joint map: the BVH joint at the SMPL joint's location and
/// where its orientation comes from.
#[derive(Clone, Copy, Debug)]
pub struct MapEntry {
    /// BVH joint (or, for spine3, the nearest one) at this SMPL joint.
    pub at: &'static str,
    pub source: Source,
}

const fn bone(at: &'static str, from: &'static str, to: &'static str) -> MapEntry {
    MapEntry {
        at,
        source: Source::Bone { from, to },
    }
}

const fn leaf(at: &'static str) -> MapEntry {
    MapEntry {
        at,
        source: Source::Leaf { owner: at },
    }
}

/// The CMU 31-joint skeleton (cmuconvert release) onto SMPL, in SMPL joint
/// order. The CMU spine is shorter than SMPL's and branches the collars
/// at `Chest2`, so spine2 follows the upper back `Chest2 → Neck` and spine3
/// takes the `Chest2` frame.
pub const CMU_TO_SMPL: [MapEntry; N_JOINTS] = [
    MapEntry {
        at: "Hips",
        source: Source::Frame {
            owner: "Hips",
            bvh_up: ("Hips", "Chest"),
            bvh_side: ("RightHip", "LeftHip"),
            smpl_up: (0, 3),
            smpl_side: (2, 1),
        },
    },
    bone("LeftHip", "LeftHip", "LeftKnee"),
    bone("RightHip", "RightHip", "RightKnee"),
    bone("Chest", "Chest", "Chest2"),
    bone("LeftKnee", "LeftKnee", "LeftAnkle"),
    bone("RightKnee", "RightKnee", "RightAnkle"),
    bone("Chest2", "Chest2", "Neck"),
    bone("LeftAnkle", "LeftAnkle", "LeftToe"),
    bone("RightAnkle", "RightAnkle", "RightToe"),
    MapEntry {
        at: "lowerneck",
        source: Source::Frame {
            owner: "Chest2",
            bvh_up: ("Chest2", "Neck"),
            bvh_side: ("RightShoulder", "LeftShoulder"),
            smpl_up: (9, 12),
            smpl_side: (17, 16),
        },
    },
    leaf("LeftToe"),
    leaf("RightToe"),
    bone("Neck", "Neck", "Head"),
    bone("LeftCollar", "LeftCollar", "LeftShoulder"),
    bone("RightCollar", "RightCollar", "RightShoulder"),
    leaf("Head"),
    bone("LeftShoulder", "LeftShoulder", "LeftElbow"),
    bone("RightShoulder", "RightShoulder", "RightElbow"),
    bone("LeftElbow", "LeftElbow", "LeftWrist"),
    bone("RightElbow", "RightElbow", "RightWrist"),
    bone("LeftWrist", "LeftWrist", "LFingers"),
    bone("RightWrist", "RightWrist", "RFingers"),
    leaf("LFingers"),
    leaf("RFingers"),
];

/// Options for [`retarget_bvh`].
#[derive(Clone, Copy, Debug)]
pub struct RetargetOptions {
    /// Metres per BVH length unit.
    pub unit_metres: f64,
}

impl Default for RetargetOptions {
    fn default() -> Self {
        RetargetOptions {
            unit_metres: CMU_UNIT_METRES,
        }
    }
}

/// A joint map resolved against one BVH hierarchy and one SMPL rest pose.
struct Resolved {
    /// Per SMPL joint: the owner BVH joint whose rotation drives it.
    owner: [usize; N_JOINTS],
    /// Per SMPL joint: the rest alignment `A_j`.
    align: [DMat3; N_JOINTS],
    /// Per Bone joint: BVH segment (from, to) indices.
    segment: [Option<(usize, usize)>; N_JOINTS],
    /// Per Bone joint: the BVH rest direction `u` of its segment.
    rest_dir: [DVec3; N_JOINTS],
    /// Per Leaf joint: true.
    leaf: [bool; N_JOINTS],
}

fn direction(a: DVec3, b: DVec3) -> DVec3 {
    (b - a).normalize_or_zero()
}

/// Right-handed orthonormal frame with `y` along `up` and `x` along the
/// part of `side` orthogonal to it (columns x, y, z).
fn frame(up: DVec3, side: DVec3) -> Option<DMat3> {
    let y = up.try_normalize()?;
    let x = (side - y * side.dot(y)).try_normalize()?;
    Some(DMat3::from_cols(x, y, x.cross(y)))
}

fn arc(from: DVec3, to: DVec3) -> DMat3 {
    DMat3::from_quat(DQuat::from_rotation_arc(from, to))
}

fn resolve(
    bvh: &Bvh,
    file: &str,
    map: &[MapEntry; N_JOINTS],
    rest: &Joints,
) -> Result<Resolved, MotionError> {
    let find = |name: &'static str, j: usize| {
        bvh.joint(name).ok_or(MotionError::MissingJoint {
            file: file.to_string(),
            joint: name.to_string(),
            smpl_joint: j,
            smpl_name: JOINT_NAMES[j],
        })
    };
    let degenerate = |j: usize, what: &str| MotionError::Argument {
        name: "joint map",
        expected: format!(
            "non-degenerate rest directions for SMPL joint {j} `{}`",
            JOINT_NAMES[j]
        ),
        found: what.to_string(),
    };
    let r = |j: usize| DVec3::new(rest[j][0] as f64, rest[j][1] as f64, rest[j][2] as f64);
    let bvh_rest: BvhPose = bvh.rest();
    let p = |b: usize| bvh_rest.position[b];

    let mut out = Resolved {
        owner: [0; N_JOINTS],
        align: [DMat3::IDENTITY; N_JOINTS],
        segment: [None; N_JOINTS],
        rest_dir: [DVec3::ZERO; N_JOINTS],
        leaf: [false; N_JOINTS],
    };
    for (j, entry) in map.iter().enumerate() {
        find(entry.at, j)?;
        match entry.source {
            Source::Bone { from, to } => {
                let (f, t) = (find(from, j)?, find(to, j)?);
                let owner = bvh.joints[t]
                    .parent
                    .ok_or_else(|| degenerate(j, &format!("segment end `{to}` is the BVH root")))?;
                let child = crate::skeleton::children(j);
                let [c] = child.as_slice() else {
                    return Err(degenerate(
                        j,
                        &format!("a Bone source on a joint with {} children", child.len()),
                    ));
                };
                let s = direction(r(j), r(*c));
                let u = direction(p(f), p(t));
                if s == DVec3::ZERO || u == DVec3::ZERO {
                    return Err(degenerate(
                        j,
                        &format!("zero-length rest segment `{from}` → `{to}` or SMPL bone"),
                    ));
                }
                out.owner[j] = owner;
                out.align[j] = arc(s, u);
                out.segment[j] = Some((f, t));
                out.rest_dir[j] = u;
            }
            Source::Frame {
                owner,
                bvh_up,
                bvh_side,
                smpl_up,
                smpl_side,
            } => {
                let seg = |(a, b): (&'static str, &'static str)| -> Result<DVec3, MotionError> {
                    Ok(p(find(b, j)?) - p(find(a, j)?))
                };
                let fb = frame(seg(bvh_up)?, seg(bvh_side)?)
                    .ok_or_else(|| degenerate(j, "parallel BVH up/side segments"))?;
                let fs = frame(r(smpl_up.1) - r(smpl_up.0), r(smpl_side.1) - r(smpl_side.0))
                    .ok_or_else(|| degenerate(j, "parallel SMPL up/side segments"))?;
                out.owner[j] = find(owner, j)?;
                out.align[j] = fb * fs.transpose();
            }
            Source::Leaf { owner } => {
                if j == 0 {
                    return Err(degenerate(j, "the root cannot be a leaf"));
                }
                out.owner[j] = find(owner, j)?;
                out.leaf[j] = true;
            }
        }
    }
    Ok(out)
}

/// World orientations `Q_j` of the SMPL joints for one BVH pose.
fn world_orientations(res: &Resolved, pose: &BvhPose) -> [DMat3; N_JOINTS] {
    let mut q = [DMat3::IDENTITY; N_JOINTS];
    for j in 0..N_JOINTS {
        let g = pose.rotation[res.owner[j]];
        q[j] = if res.leaf[j] {
            let parent_owner = pose.rotation[res.owner[PARENTS[j]]];
            g * parent_owner.transpose() * q[PARENTS[j]]
        } else if let Some((f, t)) = res.segment[j] {
            // G·u (u: the rest direction) is where the owner alone would
            // point the bone; Δ takes it onto the posed segment.
            let want = direction(pose.position[f], pose.position[t]);
            arc(g * res.rest_dir[j], want) * g * res.align[j]
        } else {
            g * res.align[j]
        };
    }
    q
}

/// Retargets every frame of a BVH onto SMPL. `rest` is the SMPL rest pose
/// the motion will be played on (only its bone directions matter). The
/// result is y-up like the BVH ([`HeadDir::PosY`]).
pub fn retarget_bvh(
    bvh: &Bvh,
    file: &str,
    map: &[MapEntry; N_JOINTS],
    rest: &Joints,
    opts: &RetargetOptions,
) -> Result<Motion, MotionError> {
    if !(opts.unit_metres.is_finite() && opts.unit_metres > 0.0) {
        return Err(MotionError::Argument {
            name: "unit_metres",
            expected: "a positive scale".into(),
            found: opts.unit_metres.to_string(),
        });
    }
    let res = resolve(bvh, file, map, rest)?;
    let root_joint = bvh.joint(map[0].at).ok_or(MotionError::MissingJoint {
        file: file.to_string(),
        joint: map[0].at.to_string(),
        smpl_joint: 0,
        smpl_name: JOINT_NAMES[0],
    })?;
    let mut bones = Vec::with_capacity(bvh.n_frames());
    let mut root = Vec::with_capacity(bvh.n_frames());
    for f in 0..bvh.n_frames() {
        let pose = bvh.pose(f);
        let q = world_orientations(&res, &pose);
        let mut frame = [[0.0f32; 3]; N_JOINTS];
        frame[0] = rotvec_from_mat(q[0]);
        for j in 1..N_JOINTS {
            frame[j] = rotvec_from_mat(q[PARENTS[j]].transpose() * q[j]);
        }
        bones.push(frame);
        let hip = pose.position[root_joint] * opts.unit_metres;
        root.push([hip.x as f32, hip.y as f32, hip.z as f32]);
    }
    let motion = Motion {
        fps: bvh.fps(),
        bones,
        root,
        up: HeadDir::PosY,
    };
    motion.validate()?;
    Ok(motion)
}
