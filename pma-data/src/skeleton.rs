//! The SMPL 24-joint skeleton: joint table, rotations (axis-angle, 6D),
//! forward kinematics, the bone-align transforms and the per-part volume
//! initialisation (docs/conventions.md, "Skeleton").
//!
//! Everything is computed in f64 and stored as f32, as the reference's
//! preprocessing does; 4×4 transforms are stored row-major (`m[row][col]`).

use glam::{DMat3, DMat4, DQuat, DVec3, DVec4};
use ndarray::{Array3, Array4, ArrayView2, ArrayView3};

use crate::error::{DataError, Result};

/// Number of SMPL joints (the only skeleton supported).
pub const N_JOINTS: usize = 24;

/// Index of the root (pelvis).
pub const ROOT: usize = 0;

/// SMPL joint names; "left" is the subject's left (+x in the rest frame).
pub const JOINT_NAMES: [&str; N_JOINTS] = [
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hand",
    "right_hand",
];

/// Parent of each joint. The root lists itself (0), as the reference does;
/// every other parent has a smaller index, so index order is a valid
/// kinematic traversal.
pub const PARENTS: [usize; N_JOINTS] = [
    0, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21,
];

/// Joints with no child.
pub const END_EFFECTORS: [usize; 5] = [10, 11, 15, 22, 23];

/// One pose's joint positions or rotation vectors, `[24][3]`.
pub type Joints = [[f32; 3]; N_JOINTS];

/// One 4×4 transform per joint, row-major: `[24][4][4]`.
pub type Transforms = [[[f32; 4]; 4]; N_JOINTS];

/// True children of `j` (the root is not its own child).
pub fn children(j: usize) -> Vec<usize> {
    (1..N_JOINTS).filter(|&c| PARENTS[c] == j).collect()
}

/// Children as the reference derives them from [`PARENTS`]: the root appears
/// among its own children, so it has 4 and is never treated as a
/// single-child joint.
pub fn reference_children(j: usize) -> Vec<usize> {
    (0..N_JOINTS).filter(|&c| PARENTS[c] == j).collect()
}

// ---------------------------------------------------------------------------
// Rotations

fn skew(w: DVec3) -> DMat3 {
    // glam matrices are built from columns.
    DMat3::from_cols(
        DVec3::new(0.0, w.z, -w.y),
        DVec3::new(-w.z, 0.0, w.x),
        DVec3::new(w.y, -w.x, 0.0),
    )
}

/// Rodrigues' formula, `R = I + A·[w]× + B·[w]×²` with `A = sinθ/θ` and
/// `B = (1−cosθ)/θ²`. Below θ = 1e-4 the Taylor series of A and B is exact to
/// f64 precision and avoids the 0/0; |w| > π is legal and not canonicalised.
pub fn axis_angle_to_matrix(w: DVec3) -> DMat3 {
    let t2 = w.length_squared();
    let t = t2.sqrt();
    let (a, b) = if t < 1e-4 {
        (
            1.0 - t2 / 6.0 + t2 * t2 / 120.0,
            0.5 - t2 / 24.0 + t2 * t2 / 720.0,
        )
    } else {
        (t.sin() / t, (1.0 - t.cos()) / t2)
    };
    let k = skew(w);
    DMat3::IDENTITY + k * a + (k * k) * b
}

/// Inverse of [`axis_angle_to_matrix`] for a proper rotation, with the angle
/// in [0, π]. Goes through a unit quaternion (robust near 0 and near π); at
/// exactly π either of the two equivalent axes may be returned.
pub fn matrix_to_axis_angle(m: DMat3) -> DVec3 {
    let mut q = DQuat::from_mat3(&m).normalize();
    if q.w < 0.0 {
        q = -q;
    }
    let v = DVec3::new(q.x, q.y, q.z);
    let s = v.length();
    if s < 1e-12 {
        // θ ≈ 2s/w; the first-order term is exact to f64 here.
        return v * (2.0 / q.w);
    }
    let angle = 2.0 * s.atan2(q.w);
    v * (angle / s)
}

/// 6D representation (Zhou et al.): the first two **columns** of `m`,
/// flattened row-major: `(R00, R01, R10, R11, R20, R21)`.
pub fn rot6d_from_matrix(m: DMat3) -> [f64; 6] {
    let (c0, c1) = (m.x_axis, m.y_axis);
    [c0.x, c1.x, c0.y, c1.y, c0.z, c1.z]
}

/// Gram–Schmidt decode of a 6D rotation. Columns shorter than 1e-6 (first
/// column, or the second after removing its component along the first) have
/// no reliable direction and are an error.
pub fn matrix_from_rot6d(x: [f64; 6]) -> Result<DMat3> {
    const EPS: f64 = 1e-6;
    let a1 = DVec3::new(x[0], x[2], x[4]);
    let a2 = DVec3::new(x[1], x[3], x[5]);
    if !(a1.is_finite() && a2.is_finite()) {
        return Err(DataError::DegenerateRotation {
            reason: format!("non-finite components {x:?}"),
        });
    }
    let n1 = a1.length();
    if n1 < EPS {
        return Err(DataError::DegenerateRotation {
            reason: format!("first column has length {n1:e} < {EPS:e}"),
        });
    }
    let b1 = a1 / n1;
    let u = a2 - b1 * b1.dot(a2);
    let nu = u.length();
    if nu < EPS {
        return Err(DataError::DegenerateRotation {
            reason: format!("second column is (anti)parallel to the first: |u| = {nu:e} < {EPS:e}"),
        });
    }
    let b2 = u / nu;
    Ok(DMat3::from_cols(b1, b2, b1.cross(b2)))
}

/// 6D features of a whole pose (f32 in and out), `[24][6]`: the pose input
/// of the graph network.
pub fn pose_to_rot6d(bones: &Joints) -> [[f32; 6]; N_JOINTS] {
    let mut out = [[0.0f32; 6]; N_JOINTS];
    for (o, w) in out.iter_mut().zip(bones) {
        let r = rot6d_from_matrix(axis_angle_to_matrix(vec3(w)));
        for (d, s) in o.iter_mut().zip(r) {
            *d = s as f32;
        }
    }
    out
}

/// Standard rotation about x, `[[1,0,0],[0,c,−s],[0,s,c]]`.
pub fn rot_x(phi: f64) -> DMat3 {
    let (s, c) = phi.sin_cos();
    DMat3::from_cols(
        DVec3::new(1.0, 0.0, 0.0),
        DVec3::new(0.0, c, s),
        DVec3::new(0.0, -s, c),
    )
}

/// The reference's y rotation `[[c,0,−s],[0,1,0],[s,0,c]]`: the transpose of
/// the textbook one (a rotation by −θ). Bone-align and the camera
/// trajectories depend on this exact sign.
pub fn rot_y_ref(theta: f64) -> DMat3 {
    let (s, c) = theta.sin_cos();
    DMat3::from_cols(
        DVec3::new(c, 0.0, s),
        DVec3::new(0.0, 1.0, 0.0),
        DVec3::new(-s, 0.0, c),
    )
}

// ---------------------------------------------------------------------------
// Conversions between f32 storage and f64 glam types

pub(crate) fn vec3(v: &[f32; 3]) -> DVec3 {
    DVec3::new(v[0] as f64, v[1] as f64, v[2] as f64)
}

/// Row-major f32 4×4 → glam (column-major) f64.
pub fn mat4_from_rows(m: &[[f32; 4]; 4]) -> DMat4 {
    DMat4::from_cols_array_2d(&[
        [
            m[0][0] as f64,
            m[1][0] as f64,
            m[2][0] as f64,
            m[3][0] as f64,
        ],
        [
            m[0][1] as f64,
            m[1][1] as f64,
            m[2][1] as f64,
            m[3][1] as f64,
        ],
        [
            m[0][2] as f64,
            m[1][2] as f64,
            m[2][2] as f64,
            m[3][2] as f64,
        ],
        [
            m[0][3] as f64,
            m[1][3] as f64,
            m[2][3] as f64,
            m[3][3] as f64,
        ],
    ])
}

/// glam f64 4×4 → row-major f32.
pub fn mat4_to_rows(m: &DMat4) -> [[f32; 4]; 4] {
    let mut out = [[0.0f32; 4]; 4];
    for (c, col) in m.to_cols_array_2d().iter().enumerate() {
        for (r, v) in col.iter().enumerate() {
            out[r][c] = *v as f32;
        }
    }
    out
}

/// `[R | t]` with last row (0,0,0,1).
pub fn rigid(r: DMat3, t: DVec3) -> DMat4 {
    DMat4::from_cols(
        r.x_axis.extend(0.0),
        r.y_axis.extend(0.0),
        r.z_axis.extend(0.0),
        t.extend(1.0),
    )
}

/// Closed-form inverse of a rigid transform: `[Rᵀ | −Rᵀ·t]`.
pub fn rigid_inverse(m: &DMat4) -> DMat4 {
    let r = DMat3::from_mat4(*m);
    let t = m.w_axis.truncate();
    let rt = r.transpose();
    rigid(rt, -(rt * t))
}

// ---------------------------------------------------------------------------
// Forward kinematics

/// Local-to-world transforms `L_j`, f64.
/// rest: rest pose `[24][3]`; bones: axis-angle `[24][3]`; root: root
/// translation `t`, added to every `L_j` (so `kp3d[0] = rest[0] + t`).
pub fn local_to_world(rest: &Joints, bones: &Joints, root: DVec3) -> [DMat4; N_JOINTS] {
    let mut l = [DMat4::IDENTITY; N_JOINTS];
    l[ROOT] = rigid(axis_angle_to_matrix(vec3(&bones[ROOT])), vec3(&rest[ROOT]));
    for j in 1..N_JOINTS {
        let p = PARENTS[j];
        let local = rigid(
            axis_angle_to_matrix(vec3(&bones[j])),
            vec3(&rest[j]) - vec3(&rest[p]),
        );
        l[j] = l[p] * local;
    }
    for m in l.iter_mut() {
        m.w_axis += DVec4::new(root.x, root.y, root.z, 0.0);
    }
    l
}

/// One posed skeleton, stored as f32.
#[derive(Debug, Clone, PartialEq)]
pub struct Posed {
    /// Joint world positions `[24][3]`.
    pub kp3d: Joints,
    /// Local-to-world transforms `[24][4][4]`.
    pub l2ws: Transforms,
    /// World-to-joint transforms (inverse of `l2ws`) `[24][4][4]`.
    pub skts: Transforms,
}

/// FK for one frame (computed in f64, stored as f32).
pub fn forward_kinematics(rest: &Joints, bones: &Joints, root: [f32; 3]) -> Posed {
    let l = local_to_world(rest, bones, vec3(&root));
    let mut out = Posed {
        kp3d: [[0.0; 3]; N_JOINTS],
        l2ws: [[[0.0; 4]; 4]; N_JOINTS],
        skts: [[[0.0; 4]; 4]; N_JOINTS],
    };
    for j in 0..N_JOINTS {
        let t = l[j].w_axis;
        out.kp3d[j] = [t.x as f32, t.y as f32, t.z as f32];
        out.l2ws[j] = mat4_to_rows(&l[j]);
        out.skts[j] = mat4_to_rows(&rigid_inverse(&l[j]));
    }
    out
}

/// FK for many frames.
/// bones: `[P,24,3]`, roots: `[P,3]` → (kp3d `[P,24,3]`, skts `[P,24,4,4]`).
pub fn forward_kinematics_batch(
    rest: &Joints,
    bones: ArrayView3<f32>,
    roots: ArrayView2<f32>,
) -> Result<(Array3<f32>, Array4<f32>)> {
    let p = bones.shape()[0];
    if bones.shape() != [p, N_JOINTS, 3] {
        return Err(DataError::arg(
            "bones",
            "shape [P,24,3]",
            format!("{:?}", bones.shape()),
        ));
    }
    if roots.shape() != [p, 3] {
        return Err(DataError::arg(
            "roots",
            format!("shape [{p},3]"),
            format!("{:?}", roots.shape()),
        ));
    }
    let mut kp3d = Array3::<f32>::zeros((p, N_JOINTS, 3));
    let mut skts = Array4::<f32>::zeros((p, N_JOINTS, 4, 4));
    for i in 0..p {
        let b = joints_from_view(bones.index_axis(ndarray::Axis(0), i));
        let r = roots.row(i);
        let posed = forward_kinematics(rest, &b, [r[0], r[1], r[2]]);
        for j in 0..N_JOINTS {
            for k in 0..3 {
                kp3d[[i, j, k]] = posed.kp3d[j][k];
            }
            for r in 0..4 {
                for c in 0..4 {
                    skts[[i, j, r, c]] = posed.skts[j][r][c];
                }
            }
        }
    }
    Ok((kp3d, skts))
}

/// Copy a `[24,3]` view into a fixed array (the caller checked the shape).
pub fn joints_from_view(v: ArrayView2<f32>) -> Joints {
    let mut out = [[0.0f32; 3]; N_JOINTS];
    for (j, o) in out.iter_mut().enumerate() {
        for (k, x) in o.iter_mut().enumerate() {
            *x = v[[j, k]];
        }
    }
    out
}

// ---------------------------------------------------------------------------
// Rest-pose checks, bone-align, profile, volume initialisation

/// Diagonal of the rest pose's bounding box: the length scale `S` that the
/// degeneracy tolerances are relative to.
pub fn rest_pose_scale(rest: &Joints) -> f64 {
    let mut lo = DVec3::splat(f64::INFINITY);
    let mut hi = DVec3::splat(f64::NEG_INFINITY);
    for r in rest {
        let v = vec3(r);
        lo = lo.min(v);
        hi = hi.max(v);
    }
    (hi - lo).length()
}

/// Reject rest poses that the kinematics cannot use: non-finite values and
/// parent–child distances below 1e-6·S (S: the rest pose's size).
pub fn check_rest_pose(rest: &Joints) -> Result<()> {
    for (j, r) in rest.iter().enumerate() {
        if !r.iter().all(|v| v.is_finite()) {
            return Err(DataError::DegenerateRestPose {
                joint: j,
                name: JOINT_NAMES[j],
                reason: format!("non-finite position {r:?}"),
            });
        }
    }
    let s = rest_pose_scale(rest);
    if s <= 0.0 {
        return Err(DataError::DegenerateRestPose {
            joint: 0,
            name: JOINT_NAMES[0],
            reason: "all joints coincide (bounding-box diagonal 0)".into(),
        });
    }
    for j in 1..N_JOINTS {
        let p = PARENTS[j];
        let d = (vec3(&rest[j]) - vec3(&rest[p])).length();
        if d < 1e-6 * s {
            return Err(DataError::DegenerateRestPose {
                joint: j,
                name: JOINT_NAMES[j],
                reason: format!(
                    "bone from parent {p} ({}) has length {d:e}, expected at least 1e-6 x {s:.6} (rest-pose size)",
                    JOINT_NAMES[p]
                ),
            });
        }
    }
    Ok(())
}

/// Bone-align transforms `A_j` and the joint each box is aligned to.
#[derive(Debug, Clone, PartialEq)]
pub struct BoneAlign {
    /// `[24][4][4]` row-major; identity for joints with 0 or ≥ 2 children.
    pub transforms: Transforms,
    /// The single child the bone points to, or the joint itself.
    pub child: [usize; N_JOINTS],
}

/// The sign used by the construction: like numpy's `sign`, except that 0
/// counts as +1 so that a bone exactly along −z gets θ = π (the reference
/// gets 0 there and maps the bone to −z).
fn sign_pos(x: f64) -> f64 {
    if x < 0.0 {
        -1.0
    } else {
        1.0
    }
}

/// Arccos of the cosine of a 2-D direction `(a, c)` (normalised here). The
/// reference clips to ±(1−1e-8) in float32, where that bound rounds to 1, so
/// clipping to [−1, 1] is what it effectively does.
fn signed_angle(a: f64, c: f64) -> f64 {
    let n = (a * a + c * c).sqrt();
    if n == 0.0 {
        // Perfectly aligned with the rotation axis: no rotation needed.
        return 0.0;
    }
    (c / n).clamp(-1.0, 1.0).acos() * sign_pos(a / n)
}

/// Bone-align rotation for a bone vector `d`: `Rx(ψ)·Ry(θ)` maps `d` onto
/// `(0, 0, |d|)`.
pub fn bone_align_rotation(d: DVec3) -> DMat3 {
    let theta = signed_angle(d.x, d.z);
    let ry = rot_y_ref(theta);
    let v = ry * d;
    let psi = signed_angle(v.y, v.z);
    rot_x(psi) * ry
}

/// Bone-align transforms from the rest pose (docs/conventions.md, "Skeleton").
pub fn bone_align(rest: &Joints) -> Result<BoneAlign> {
    check_rest_pose(rest)?;
    let mut out = BoneAlign {
        transforms: [[[0.0; 4]; 4]; N_JOINTS],
        child: [0; N_JOINTS],
    };
    for j in 0..N_JOINTS {
        let ch = reference_children(j);
        let m = if ch.len() == 1 {
            let c = ch[0];
            out.child[j] = c;
            let d = vec3(&rest[c]) - vec3(&rest[j]);
            rigid(
                bone_align_rotation(d),
                DVec3::new(0.0, 0.0, -0.5 * d.length()),
            )
        } else {
            out.child[j] = j;
            DMat4::IDENTITY
        };
        out.transforms[j] = mat4_to_rows(&m);
    }
    Ok(out)
}

/// Widths and bone lengths of a rest pose, which size the per-part volumes.
#[derive(Debug, Clone, PartialEq)]
pub struct SkeletonProfile {
    /// `|r16 − r17|`
    pub shoulder_width: f64,
    /// `|r1 − r2|`
    pub hip_width: f64,
    /// `|r13 − r14|` (computed but not used by the volume init, see below)
    pub collar_width: f64,
    /// `|r4 − r5|`
    pub knee_width: f64,
    /// `|r_j − r_parent(j)|`, 0 for the root.
    pub bone_lens: [f64; N_JOINTS],
    /// Mean distance to the true children; −1 for end effectors.
    pub bone_lens_to_child: [f64; N_JOINTS],
}

/// Skeleton profile of a rest pose.
pub fn skeleton_profile(rest: &Joints) -> Result<SkeletonProfile> {
    check_rest_pose(rest)?;
    let p = |j: usize| vec3(&rest[j]);
    let mut bone_lens = [0.0; N_JOINTS];
    let mut to_child = [-1.0; N_JOINTS];
    for j in 0..N_JOINTS {
        if j != ROOT {
            bone_lens[j] = (p(j) - p(PARENTS[j])).length();
        }
        let ch = children(j);
        if !ch.is_empty() {
            to_child[j] = ch.iter().map(|&c| (p(c) - p(j)).length()).sum::<f64>() / ch.len() as f64;
        }
    }
    Ok(SkeletonProfile {
        shoulder_width: (p(16) - p(17)).length(),
        hip_width: (p(1) - p(2)).length(),
        collar_width: (p(13) - p(14)).length(),
        knee_width: (p(4) - p(5)).length(),
        bone_lens,
        bone_lens_to_child: to_child,
    })
}

/// Initial per-part half-extents `(x, y, z)` in the bone-aligned frame
/// (`graph_net.base_scale`; docs/reference.md, "Initialisation"), `[24][3]`.
///
/// Reproduces the reference's quirks: collars and arms use the **knee**
/// width, and end effectors get their parent's length to child without the
/// 0.8 factor.
pub fn init_half_extents(rest: &Joints) -> Result<[[f32; 3]; N_JOINTS]> {
    const LEGS: [usize; 8] = [1, 2, 4, 5, 7, 8, 10, 11];
    const TORSO: [usize; 4] = [0, 3, 6, 9];
    const COLLAR: [usize; 2] = [13, 14];
    const ARMS: [usize; 8] = [16, 17, 18, 19, 20, 21, 22, 23];
    const HEAD: [usize; 2] = [12, 15];

    let prof = skeleton_profile(rest)?;
    let mut s = [[0.5f64; 3]; N_JOINTS];
    let mut set_xy = |idx: &[usize], v: f64| {
        for &j in idx {
            s[j][0] = v;
            s[j][1] = v;
        }
    };
    set_xy(&LEGS, 0.5 * prof.knee_width);
    set_xy(&TORSO, 0.5 * prof.shoulder_width);
    set_xy(&COLLAR, 0.4 * prof.knee_width);
    set_xy(&ARMS, 0.4 * prof.knee_width);
    for j in 0..N_JOINTS {
        s[j][2] = 0.8 * prof.bone_lens_to_child[j];
    }
    let z_max = s.iter().map(|v| v[2]).fold(f64::NEG_INFINITY, f64::max);
    for &j in &HEAD {
        s[j][0] = 0.30 * prof.shoulder_width;
        s[j][1] = 0.35 * prof.shoulder_width;
        s[j][2] = 0.3 * z_max;
    }
    s[15][1] = 0.6 * prof.shoulder_width;
    for j in 0..N_JOINTS {
        if s[j][2] < 0.0 && !HEAD.contains(&j) {
            s[j][2] = prof.bone_lens_to_child[PARENTS[j]];
        }
    }
    let mut out = [[0.0f32; 3]; N_JOINTS];
    for (o, v) in out.iter_mut().zip(s) {
        *o = [v[0] as f32, v[1] as f32, v[2] as f32];
    }
    Ok(out)
}

/// Reject box half-extents that would divide by (almost) zero later: `x̄ = x̂ / s` with a
/// floor proportional to `s`, so a zero initial extent (e.g. coincident knees give a zero leg
/// width) turns into inf/NaN points far from where it was caused. `what` names the source
/// (file and key) for the message; extents must be finite and at least `1e-6 x scale`.
pub fn check_half_extents(what: &str, s: &[[f32; 3]; N_JOINTS], scale: f64) -> Result<()> {
    let min = 1e-6 * scale.max(f64::MIN_POSITIVE);
    for (j, v) in s.iter().enumerate() {
        for (k, &x) in v.iter().enumerate() {
            if !(x.is_finite() && f64::from(x) >= min) {
                return Err(DataError::DegenerateRestPose {
                    joint: j,
                    name: JOINT_NAMES[j],
                    reason: format!(
                        "{what}: half-extent axis {k} is {x:e}, expected finite and >= {min:e}"
                    ),
                });
            }
        }
    }
    Ok(())
}

/// Everything the model builds from a rest pose, validated up front: the kinematic checks
/// of [`check_rest_pose`], finite bone-align transforms, and positive initial half-extents.
/// Returns the half-extents.
pub fn check_model_rest_pose(rest: &Joints) -> Result<[[f32; 3]; N_JOINTS]> {
    let align = bone_align(rest)?;
    for (j, m) in align.transforms.iter().enumerate() {
        if !m.iter().flatten().all(|v| v.is_finite()) {
            return Err(DataError::DegenerateRestPose {
                joint: j,
                name: JOINT_NAMES[j],
                reason: "bone-align transform is not finite".into(),
            });
        }
    }
    let s = init_half_extents(rest)?;
    check_half_extents("rest pose", &s, rest_pose_scale(rest))?;
    Ok(s)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn children_follow_parents() {
        assert_eq!(children(0), vec![1, 2, 3]);
        assert_eq!(reference_children(0), vec![0, 1, 2, 3]);
        assert_eq!(children(9), vec![12, 13, 14]);
        for &e in &END_EFFECTORS {
            assert!(children(e).is_empty());
        }
    }

    #[test]
    fn vertical_and_minus_z_bones_align_to_plus_z() {
        for d in [
            DVec3::new(0.0, 0.7, 0.0),
            DVec3::new(0.0, -0.7, 0.0),
            DVec3::new(0.0, 0.0, -0.4),
            DVec3::new(0.0, 0.3, -0.4),
        ] {
            let v = bone_align_rotation(d) * d;
            assert!(
                (v - DVec3::new(0.0, 0.0, d.length())).length() < 1e-12,
                "{d} -> {v}"
            );
        }
    }
}
