//! Validation of a [`Dataset`] for one use profile (docs/conventions.md,
//! "Validation" and "pma-npz v1"). Runs after reading and derivation, and on datasets built in code
//! (the converters and `pma synth` validate before they write).
//!
//! The order matters for the messages: structure (missing keys, shapes,
//! counts) comes first so that later checks can index freely, then numerics,
//! then geometry, then pixels. Kinematics are compared with forward
//! kinematics before the cylinders, so a moved joint is reported as a `kp3d`
//! problem rather than as a cylinder that no longer encloses it.
//!
//! Checks that the reader already enforces by construction (dtypes, pickles,
//! byte order, 6D degeneracy, truncated members) are not repeated here.

use glam::{DMat3, DVec3};

use super::{Dataset, Profile, ReadOptions, Warning};
use crate::camera::check_rigid;
use crate::cylinder::HeadDir;
use crate::error::{DataError, Result};
use crate::skeleton::{
    bone_align, check_rest_pose, joints_from_view, local_to_world, mat4_from_rows, rest_pose_scale,
    Joints, JOINT_NAMES, N_JOINTS, PARENTS,
};

/// |ω| above this is garbage rather than an unwrapped angle.
const MAX_AXIS_ANGLE: f64 = 1e3;
/// `max|skts·L − I|` tolerance.
const SKTS_TOL: f64 = 1e-4;
/// kp3d-vs-FK error and warning thresholds, relative to the rest-pose size S.
const FK_ERROR_REL: f64 = 1e-3;
const FK_WARN_REL: f64 = 1e-5;
/// Root offset tolerance, relative to S.
const ROOT_OFFSET_REL: f64 = 1e-4;
/// Plausible mean rest bone length, scene units.
const BONE_LEN_RANGE: (f64, f64) = (0.02, 2.0);
/// Plausible camera-to-root distance over rest height.
const CAMERA_DIST_RANGE: (f64, f64) = (0.3, 100.0);

struct Checker {
    file: String,
    warnings: Vec<Warning>,
}

impl Checker {
    fn shape(&self, key: &str, expected: impl Into<String>, found: &[usize]) -> DataError {
        DataError::Shape {
            file: self.file.clone(),
            key: key.into(),
            expected: expected.into(),
            found: found.to_vec(),
        }
    }

    fn value(
        &self,
        key: &str,
        problem: impl Into<String>,
        expected: impl Into<String>,
        found: impl Into<String>,
    ) -> DataError {
        DataError::Value {
            file: self.file.clone(),
            key: key.into(),
            problem: problem.into(),
            expected: expected.into(),
            found: found.into(),
        }
    }

    fn missing(&self, key: &str, profile: Profile, hint: &str) -> DataError {
        DataError::MissingKey {
            file: self.file.clone(),
            key: key.into(),
            profile: profile.name().into(),
            hint: hint.into(),
        }
    }

    fn warn(&mut self, key: &str, message: impl Into<String>) {
        self.warnings.push(Warning {
            key: key.into(),
            message: message.into(),
        });
    }

    /// `count` (P, C, N, H·W) of `key` must equal the one of `other_key`.
    fn count(
        &self,
        count: &str,
        key: &str,
        found: usize,
        other_key: &str,
        expected: usize,
    ) -> Result<()> {
        if found == expected {
            return Ok(());
        }
        Err(DataError::Count {
            file: self.file.clone(),
            count: count.into(),
            key: key.into(),
            found,
            other_key: other_key.into(),
            expected,
        })
    }

    fn finite<'a>(&self, key: &str, values: impl IntoIterator<Item = &'a f32>) -> Result<()> {
        match values.into_iter().enumerate().find(|(_, v)| !v.is_finite()) {
            None => Ok(()),
            Some((position, v)) => Err(DataError::NonFinite {
                file: self.file.clone(),
                key: key.into(),
                position,
                value: *v as f64,
            }),
        }
    }

    fn index(&self, key: &str, values: &ndarray::Array1<i64>, bound: usize) -> Result<()> {
        match values
            .iter()
            .enumerate()
            .find(|(_, &v)| v < 0 || v as u64 >= bound as u64)
        {
            None => Ok(()),
            Some((position, v)) => Err(DataError::Index {
                file: self.file.clone(),
                key: key.into(),
                position,
                value: v.to_string(),
                bound,
            }),
        }
    }
}

pub(crate) fn validate(ds: &mut Dataset, opts: &ReadOptions) -> Result<()> {
    let mut ck = Checker {
        file: ds.source.clone(),
        warnings: Vec::new(),
    };
    let result = (|| {
        required_keys(&ck, ds, opts.profile)?;
        shapes_and_counts(&ck, ds, opts.profile)?;
        numerics(&mut ck, ds)?;
        indices(&ck, ds)?;
        geometry(&mut ck, ds, opts)?;
        pixels(&mut ck, ds, opts)
    })();
    ds.warnings.append(&mut ck.warnings);
    result
}

// ---------------------------------------------------------------------------
// Structure: required keys and shapes

fn required_keys(ck: &Checker, ds: &Dataset, profile: Profile) -> Result<()> {
    if ds.kp3d.is_none() && ds.root_locs.is_none() {
        return Err(ck.missing(
            "kp3d",
            profile,
            "; give kp3d or root_locs (the root translation of every pose)",
        ));
    }
    if profile >= Profile::Render {
        if ds.c2ws.is_none() {
            return Err(ck.missing("c2ws", profile, ""));
        }
        if ds.focals.is_none() {
            return Err(ck.missing("focals", profile, ""));
        }
        let Some(shape) = ds.img_shape else {
            return Err(ck.missing("img_shape", profile, "; (N,H,W,3)"));
        };
        let (n, p, c) = (shape[0], ds.n_poses(), ds.n_cameras());
        // Derivation fills identity maps only where the counts allow them.
        if ds.kp_idxs.is_none() {
            return Err(ck.missing(
                "kp_idxs",
                profile,
                &format!("; the identity default needs P = N, but P = {p} and N = {n}"),
            ));
        }
        if ds.img_pose_indices.is_none() {
            return Err(ck.missing(
                "img_pose_indices",
                profile,
                &format!("; the identity default needs C = N, but C = {c} and N = {n}"),
            ));
        }
    }
    if profile >= Profile::Eval {
        if ds.rest_pose.is_none() {
            return Err(ck.missing("rest_pose", profile, ""));
        }
        if ds.imgs.is_none() {
            return Err(ck.missing("imgs", profile, ""));
        }
        if ds.masks.is_none() {
            return Err(ck.missing("masks", profile, ""));
        }
    }
    if profile >= Profile::Train && ds.sampling_masks.is_none() {
        return Err(ck.missing("sampling_masks", profile, ""));
    }
    Ok(())
}

fn shapes_and_counts(ck: &Checker, ds: &Dataset, profile: Profile) -> Result<()> {
    let joints = |key: &str, s: &[usize], tail: &[usize], want: &str| -> Result<()> {
        if s.len() != 2 + tail.len() || s[1] != N_JOINTS || &s[2..] != tail {
            let note = if s.len() > 1 && s[1] != N_JOINTS {
                " - only the 24-joint SMPL skeleton is supported"
            } else {
                ""
            };
            return Err(ck.shape(key, format!("{want}{note}"), s));
        }
        Ok(())
    };
    let b = ds.bones.shape();
    joints("bones", b, &[3], "(P,24,3)")?;
    let p = b[0];
    if p == 0 {
        return Err(DataError::Empty {
            file: ck.file.clone(),
            what: "`bones` has no pose rows (P = 0)".into(),
        });
    }
    if let Some(a) = &ds.kp3d {
        joints("kp3d", a.shape(), &[3], "(P,24,3)")?;
        ck.count("P (pose rows)", "kp3d", a.shape()[0], "bones", p)?;
    }
    if let Some(a) = &ds.skts {
        joints("skts", a.shape(), &[4, 4], "(P,24,4,4)")?;
        ck.count("P (pose rows)", "skts", a.shape()[0], "bones", p)?;
    }
    if let Some(a) = &ds.root_locs {
        if a.shape()[1] != 3 {
            return Err(ck.shape("root_locs", "(P,3)", a.shape()));
        }
        ck.count("P (pose rows)", "root_locs", a.shape()[0], "bones", p)?;
    }
    if let Some(a) = &ds.cyls {
        if a.shape()[1] != 5 {
            return Err(ck.shape("cyls", "(P,5)", a.shape()));
        }
        ck.count("P (pose rows)", "cyls", a.shape()[0], "bones", p)?;
    }
    if let Some(a) = &ds.betas {
        if a.shape()[1] != 10 {
            return Err(ck.shape("betas", "(P,10) or (1,10)", a.shape()));
        }
        if a.shape()[0] != 1 {
            ck.count("P (pose rows)", "betas", a.shape()[0], "bones", p)?;
        }
    }
    if let Some(a) = &ds.gt_kp3d {
        ck.count("P (pose rows)", "gt_kp3d", a.shape()[0], "bones", p)?;
    }
    if let Some(a) = &ds.frame_ids {
        ck.count("P (pose rows)", "frame_ids", a.len(), "bones", p)?;
    }

    if let Some(a) = &ds.c2ws {
        if a.shape()[1..] != [4, 4] {
            return Err(ck.shape("c2ws", "(C,4,4)", a.shape()));
        }
        let c = a.shape()[0];
        if let Some(f) = &ds.focals {
            if f.shape()[1] != 2 {
                return Err(ck.shape("focals", "(C,2) or (C,)", f.shape()));
            }
            ck.count("C (camera rows)", "focals", f.shape()[0], "c2ws", c)?;
        }
        if let Some(ce) = &ds.centers {
            if ce.shape()[1] != 2 {
                return Err(ck.shape("centers", "(C,2)", ce.shape()));
            }
            ck.count("C (camera rows)", "centers", ce.shape()[0], "c2ws", c)?;
        }
        if c == 0 && profile >= Profile::Render {
            return Err(DataError::Empty {
                file: ck.file.clone(),
                what: "`c2ws` has no camera rows (C = 0)".into(),
            });
        }
    }

    let Some(shape) = ds.img_shape else {
        return Ok(());
    };
    if shape[3] != 3 {
        return Err(ck.value(
            "img_shape",
            "image shape",
            "4 entries (N,H,W,3)",
            format!("{shape:?}"),
        ));
    }
    let (n, hw) = (shape[0], shape[1] * shape[2]);
    if profile >= Profile::Render && (n == 0 || hw == 0) {
        return Err(DataError::Empty {
            file: ck.file.clone(),
            what: format!("`img_shape` = {shape:?} holds no images or no pixels"),
        });
    }
    for (key, a) in [
        ("kp_idxs", &ds.kp_idxs),
        ("img_pose_indices", &ds.img_pose_indices),
        ("bkgd_idxs", &ds.bkgd_idxs),
    ] {
        if let Some(a) = a {
            ck.count("N (images)", key, a.len(), "img_shape[0]", n)?;
        }
    }
    if let Some(a) = &ds.eval_tag {
        ck.count("N (images)", "eval_tag", a.len(), "img_shape[0]", n)?;
    }
    for (key, a, ch) in [
        ("imgs", &ds.imgs, 3),
        ("masks", &ds.masks, 1),
        ("sampling_masks", &ds.sampling_masks, 1),
        ("bkgds", &ds.bkgds, 3),
    ] {
        let Some(a) = a else { continue };
        let s = a.shape();
        if s[2] != ch {
            return Err(ck.shape(key, format!("(n,H*W,{ch})"), s));
        }
        if key != "bkgds" {
            ck.count("N (images)", key, s[0], "img_shape[0]", n)?;
        } else if s[0] == 0 {
            return Err(DataError::Empty {
                file: ck.file.clone(),
                what: "`bkgds` has no plates (B = 0)".into(),
            });
        }
        ck.count("H*W (pixels per image)", key, s[1], "img_shape H*W", hw)?;
    }
    Ok(())
}

// ---------------------------------------------------------------------------
// Numerics

fn numerics(ck: &mut Checker, ds: &Dataset) -> Result<()> {
    if let Some(r) = &ds.rest_pose {
        ck.finite("rest_pose", r.iter().flatten())?;
    }
    ck.finite("bones", ds.bones.iter())?;
    macro_rules! finite_opt {
        ($($key:literal => $field:expr),* $(,)?) => {$(
            if let Some(a) = &$field {
                ck.finite($key, a.iter())?;
            }
        )*};
    }
    finite_opt!(
        "kp3d" => ds.kp3d,
        "root_locs" => ds.root_locs,
        "skts" => ds.skts,
        "cyls" => ds.cyls,
        "betas" => ds.betas,
        "gt_kp3d" => ds.gt_kp3d,
        "c2ws" => ds.c2ws,
        "focals" => ds.focals,
        "centers" => ds.centers,
    );
    ck.finite("head_dir", ds.head_dir.iter())?;
    ck.finite("pose_scale", [ds.pose_scale].iter())?;
    if let Some(e) = ds.ext_scale {
        if !e.is_finite() {
            return Err(DataError::NonFinite {
                file: ck.file.clone(),
                key: "ext_scale".into(),
                position: 0,
                value: e,
            });
        }
    }
    if ds.pose_scale <= 0.0 {
        return Err(ck.value(
            "pose_scale",
            "non-positive scale",
            "> 0",
            ds.pose_scale.to_string(),
        ));
    }
    if HeadDir::from_vector(ds.head_dir).is_none() {
        return Err(ck.value(
            "head_dir",
            "unsupported head direction (the cylinder, box and near/far code assume a y height axis; convert the motion first; docs/conventions.md, \"Units and up axis\")",
            "(0,-1,0) or (0,1,0)",
            format!("{:?}", ds.head_dir),
        ));
    }

    // Axis-angle magnitudes: garbage above 1e3, legal but unusual above π.
    let mut beyond_pi = 0usize;
    for (i, w) in ds.bones.rows().into_iter().enumerate() {
        let norm = (w[0] as f64).hypot(w[1] as f64).hypot(w[2] as f64);
        if norm > MAX_AXIS_ANGLE {
            return Err(ck.value(
                "bones",
                format!(
                    "axis-angle of pose {} joint {} ({})",
                    i / N_JOINTS,
                    i % N_JOINTS,
                    JOINT_NAMES[i % N_JOINTS]
                ),
                format!("|w| <= {MAX_AXIS_ANGLE} radians"),
                format!("|w| = {norm:e}"),
            ));
        }
        if norm > std::f64::consts::PI {
            beyond_pi += 1;
        }
    }
    if beyond_pi > 0 {
        ck.warn(
            "bones",
            format!("{beyond_pi} joint rotation(s) with |w| > pi (legal, not canonicalised)"),
        );
    }

    if let Some(f) = &ds.focals {
        for (c, row) in f.outer_iter().enumerate() {
            for (k, name) in ["fx", "fy"].iter().enumerate() {
                if row[k] <= 0.0 {
                    return Err(ck.value(
                        "focals",
                        format!("{name} of camera row {c}"),
                        "a focal length > 0 pixels",
                        row[k].to_string(),
                    ));
                }
            }
        }
    }
    if let (Some(ce), Some(shape)) = (&ds.centers, ds.img_shape) {
        let (w, h) = (shape[2] as f32, shape[1] as f32);
        for (c, row) in ce.outer_iter().enumerate() {
            if !(-w..=2.0 * w).contains(&row[0]) || !(-h..=2.0 * h).contains(&row[1]) {
                ck.warn(
                    "centers",
                    format!(
                        "principal point ({}, {}) of camera row {c} lies outside [-W,2W]x[-H,2H] for a {}x{} image",
                        row[0], row[1], shape[2], shape[1]
                    ),
                );
            }
        }
    }
    if let Some(c2ws) = &ds.c2ws {
        for (c, m) in c2ws.outer_iter().enumerate() {
            let rows = rows4(m.iter().copied());
            if let Err(d) = check_rigid(&rows) {
                return Err(ck.value(
                    "c2ws",
                    format!("camera row {c}: {}", d.problem),
                    d.expected,
                    d.found,
                ));
            }
        }
    }
    if let Some(skts) = &ds.skts {
        for (p, pose) in skts.outer_iter().enumerate() {
            for (j, m) in pose.outer_iter().enumerate() {
                if let Err(d) = check_rigid(&rows4(m.iter().copied())) {
                    return Err(ck.value(
                        "skts",
                        format!("pose {p} joint {j} ({}): {}", JOINT_NAMES[j], d.problem),
                        d.expected,
                        d.found,
                    ));
                }
            }
        }
    }
    Ok(())
}

fn rows4(mut it: impl Iterator<Item = f32>) -> [[f32; 4]; 4] {
    let mut m = [[0.0f32; 4]; 4];
    for row in m.iter_mut() {
        for v in row.iter_mut() {
            *v = it.next().unwrap_or(f32::NAN);
        }
    }
    m
}

// ---------------------------------------------------------------------------
// Index maps

fn indices(ck: &Checker, ds: &Dataset) -> Result<()> {
    if let Some(a) = &ds.kp_idxs {
        ck.index("kp_idxs", a, ds.n_poses())?;
    }
    if let Some(a) = &ds.img_pose_indices {
        ck.index("img_pose_indices", a, ds.n_cameras())?;
    }
    if let Some(a) = &ds.bkgd_idxs {
        // Without plates every image uses the one default black plate.
        let b = ds.bkgds.as_ref().map_or(1, |b| b.shape()[0]);
        ck.index("bkgd_idxs", a, b)?;
    }
    Ok(())
}

// ---------------------------------------------------------------------------
// Geometry and consistency

fn geometry(ck: &mut Checker, ds: &Dataset, opts: &ReadOptions) -> Result<()> {
    let head = ds.head()?;
    if let Some(rest) = &ds.rest_pose {
        rest_pose_checks(ck, rest, opts)?;
    }
    if let (Some(rest), Some(kp3d)) = (&ds.rest_pose, &ds.kp3d) {
        kinematics(ck, ds, rest, kp3d)?;
    }
    if let (Some(cyls), Some(kp3d)) = (&ds.cyls, &ds.kp3d) {
        let derived = ds.derived.iter().any(|d| d.starts_with("cyls"));
        if !derived {
            for (p, cyl) in cyls.outer_iter().enumerate() {
                let kp = joints_from_view(kp3d.index_axis(ndarray::Axis(0), p));
                cylinder_encloses(ck, p, [cyl[0], cyl[1], cyl[2], cyl[3], cyl[4]], &kp, head)?;
            }
        }
    }
    if opts.profile >= Profile::Render {
        cameras_see_the_person(ck, ds, opts.profile)?;
    }
    Ok(())
}

fn rest_pose_checks(ck: &Checker, rest: &Joints, opts: &ReadOptions) -> Result<()> {
    let degenerate = |e: DataError| match e {
        DataError::DegenerateRestPose {
            joint,
            name,
            reason,
        } => ck.value(
            "rest_pose",
            format!("degenerate rest pose at joint {joint} ({name})"),
            "distinct joints (every bone longer than 1e-6 x the rest-pose size)",
            reason,
        ),
        other => other,
    };
    check_rest_pose(rest).map_err(degenerate)?;
    bone_align(rest).map_err(degenerate)?;
    let s = rest_pose_scale(rest);
    let r0 = vec3(&rest[0]);
    if !opts.allow_offset_root && r0.length() > ROOT_OFFSET_REL * s {
        return Err(ck.value(
            "rest_pose",
            "root joint is not at the origin (pass --allow-offset-root to accept it)",
            format!(
                "|rest_pose[0]| <= {:.3e} (1e-4 x rest-pose size)",
                ROOT_OFFSET_REL * s
            ),
            format!("{:?} (|r0| = {:.3e})", rest[0], r0.length()),
        ));
    }
    let mean_bone = (1..N_JOINTS)
        .map(|j| (vec3(&rest[j]) - vec3(&rest[PARENTS[j]])).length())
        .sum::<f64>()
        / (N_JOINTS - 1) as f64;
    if !(BONE_LEN_RANGE.0..=BONE_LEN_RANGE.1).contains(&mean_bone) {
        return Err(ck.value(
            "rest_pose",
            "implausible units (a mm/m mix-up or a missing pose_scale undo?)",
            format!(
                "a mean bone length in [{}, {}] scene units (0.19 for metres)",
                BONE_LEN_RANGE.0, BONE_LEN_RANGE.1
            ),
            format!("{mean_bone:.4}"),
        ));
    }
    Ok(())
}

fn vec3(v: &[f32; 3]) -> DVec3 {
    DVec3::new(v[0] as f64, v[1] as f64, v[2] as f64)
}

/// Stored `kp3d`, `root_locs` and `skts` agree with FK of `bones`.
fn kinematics(
    ck: &mut Checker,
    ds: &Dataset,
    rest: &Joints,
    kp3d: &ndarray::Array3<f32>,
) -> Result<()> {
    let s = rest_pose_scale(rest);
    let (err_tol, warn_tol) = (FK_ERROR_REL * s, FK_WARN_REL * s);
    let mut worst_warn = 0.0f64;
    for p in 0..ds.n_poses() {
        let kp = joints_from_view(kp3d.index_axis(ndarray::Axis(0), p));
        let root = match &ds.root_locs {
            Some(r) => {
                let t = DVec3::new(r[[p, 0]] as f64, r[[p, 1]] as f64, r[[p, 2]] as f64);
                let d = (vec3(&kp[0]) - vec3(&rest[0]) - t).length();
                if d > err_tol {
                    return Err(ck.value(
                        "root_locs",
                        format!("pose {p} disagrees with kp3d[:,0] - rest_pose[0]"),
                        format!("a difference <= {err_tol:.3e}"),
                        format!("{d:.3e}"),
                    ));
                }
                t
            }
            None => vec3(&kp[0]) - vec3(&rest[0]),
        };
        let bones = joints_from_view(ds.bones.index_axis(ndarray::Axis(0), p));
        let l2w = local_to_world(rest, &bones, root);
        let mut worst = (0.0f64, 0usize);
        for j in 0..N_JOINTS {
            let d = (l2w[j].w_axis.truncate() - vec3(&kp[j])).length();
            if d > worst.0 {
                worst = (d, j);
            }
        }
        if worst.0 > err_tol {
            return Err(ck.value(
                "kp3d",
                format!(
                    "pose {p} disagrees with forward kinematics of bones and rest_pose at joint {} ({}) - a mismatched rest pose, joint order or axes?",
                    worst.1, JOINT_NAMES[worst.1]
                ),
                format!("max |kp3d - FK| <= {err_tol:.3e} (1e-3 x rest-pose size)"),
                format!("{:.3e}", worst.0),
            ));
        }
        if worst.0 > warn_tol {
            worst_warn = worst_warn.max(worst.0);
        }
        if let Some(skts) = &ds.skts {
            for j in 0..N_JOINTS {
                let m = mat4_from_rows(&rows4(
                    skts.index_axis(ndarray::Axis(0), p)
                        .index_axis(ndarray::Axis(0), j)
                        .iter()
                        .copied(),
                ));
                let e = (m * l2w[j]).to_cols_array();
                let id = glam::DMat4::IDENTITY.to_cols_array();
                let err = e
                    .iter()
                    .zip(id)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f64::max);
                if err > SKTS_TOL {
                    return Err(ck.value(
                        "skts",
                        format!(
                            "pose {p} joint {j} ({}) is not the inverse of forward kinematics",
                            JOINT_NAMES[j]
                        ),
                        format!("max |skts . L - I| <= {SKTS_TOL:e}"),
                        format!("{err:.3e}"),
                    ));
                }
            }
        }
    }
    if worst_warn > 0.0 {
        ck.warn(
            "kp3d",
            format!(
                "differs from forward kinematics by up to {worst_warn:.3e} (above 1e-5 x rest-pose size)"
            ),
        );
    }
    Ok(())
}

/// A stored cylinder must enclose its joints in x–z and have its caps
/// beyond them along the head direction.
fn cylinder_encloses(
    ck: &Checker,
    p: usize,
    cyl: [f32; 5],
    kp: &Joints,
    head: HeadDir,
) -> Result<()> {
    let [xc, zc, r, top, bot] = cyl.map(f64::from);
    let reach = kp
        .iter()
        .map(|j| (j[0] as f64 - xc).hypot(j[2] as f64 - zc))
        .fold(0.0, f64::max);
    if r <= reach {
        return Err(ck.value(
            "cyls",
            format!("cylinder of pose {p} does not enclose its joints in the x-z plane"),
            format!("radius > {reach:.4} (the farthest joint)"),
            format!("radius {r:.4}"),
        ));
    }
    let (lo, hi) = kp
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), j| {
            (l.min(j[1] as f64), h.max(j[1] as f64))
        });
    let ok = match head {
        HeadDir::NegY => top <= lo && bot >= hi,
        HeadDir::PosY => top >= hi && bot <= lo,
    };
    if !ok {
        return Err(ck.value(
            "cyls",
            format!("caps of the cylinder of pose {p} are on the wrong side of the joints for head_dir {head:?}"),
            match head {
                HeadDir::NegY => format!("y_top <= {lo:.4} and y_bot >= {hi:.4}"),
                HeadDir::PosY => format!("y_top >= {hi:.4} and y_bot <= {lo:.4}"),
            },
            format!("y_top {top:.4}, y_bot {bot:.4}"),
        ));
    }
    Ok(())
}

/// Every image's camera sits at a plausible distance and the person is in
/// front of it.
fn cameras_see_the_person(ck: &Checker, ds: &Dataset, profile: Profile) -> Result<()> {
    let (Some(kp3d), Some(c2ws)) = (&ds.kp3d, &ds.c2ws) else {
        return Ok(());
    };
    let height = ds.rest_pose.map(|r| {
        let ys = r.iter().map(|j| j[1] as f64);
        ys.clone().fold(f64::NEG_INFINITY, f64::max) - ys.fold(f64::INFINITY, f64::min)
    });
    for n in 0..ds.n_images() {
        let (p, c) = (ds.pose_row(n)?, ds.camera_row(n)?);
        let m = rows4(c2ws.index_axis(ndarray::Axis(0), c).iter().copied());
        let centre = DVec3::new(m[0][3] as f64, m[1][3] as f64, m[2][3] as f64);
        let rot = DMat3::from_cols(
            DVec3::new(m[0][0] as f64, m[1][0] as f64, m[2][0] as f64),
            DVec3::new(m[0][1] as f64, m[1][1] as f64, m[2][1] as f64),
            DVec3::new(m[0][2] as f64, m[1][2] as f64, m[2][2] as f64),
        );
        let root = DVec3::new(
            kp3d[[p, 0, 0]] as f64,
            kp3d[[p, 0, 1]] as f64,
            kp3d[[p, 0, 2]] as f64,
        );
        let local = rot.transpose() * (root - centre);
        if profile >= Profile::Eval && local.z >= 0.0 {
            return Err(ck.value(
                "c2ws",
                format!(
                    "image {n}: the root joint of pose {p} is behind camera row {c} (OpenGL cameras look along -z)"
                ),
                "camera-space z < 0",
                format!("z = {:.4}", local.z),
            ));
        }
        if let Some(h) = height.filter(|h| *h > 0.0) {
            let ratio = (root - centre).length() / h;
            if !(CAMERA_DIST_RANGE.0..=CAMERA_DIST_RANGE.1).contains(&ratio) {
                return Err(ck.value(
                    "c2ws",
                    format!(
                        "image {n}: implausible camera distance (a mm/m mix-up or a missing pose_scale undo?) for camera row {c} and pose {p}"
                    ),
                    format!(
                        "camera-to-root distance / rest height in [{}, {}]",
                        CAMERA_DIST_RANGE.0, CAMERA_DIST_RANGE.1
                    ),
                    format!("{ratio:.4}"),
                ));
            }
        }
    }
    Ok(())
}

// ---------------------------------------------------------------------------
// Pixels

fn pixels(ck: &mut Checker, ds: &mut Dataset, opts: &ReadOptions) -> Result<()> {
    if let Some(masks) = &mut ds.masks {
        let hw = masks.shape()[1].max(1);
        let bad = masks.iter().position(|&v| v > 1);
        if let Some(pos) = bad {
            if opts.binarize_masks {
                // The reference's PerfCap rule: values >= 2 become 1 (so 1 stays 1).
                masks.mapv_inplace(|v| v.min(1));
                ck.warn("masks", "binarised (values >= 2 set to 1)");
            } else {
                let v = masks.iter().nth(pos).copied().unwrap_or(0);
                return Err(ck.value(
                    "masks",
                    format!("image {} pixel {} is not binary", pos / hw, pos % hw),
                    "values in {0,1} (0/255 masks are accepted with binarize_masks / --binarize-masks)",
                    v.to_string(),
                ));
            }
        }
        let empty: Vec<usize> = masks
            .outer_iter()
            .enumerate()
            .filter(|(_, m)| m.iter().all(|&v| v == 0))
            .map(|(n, _)| n)
            .collect();
        if !empty.is_empty() && opts.profile >= Profile::Eval {
            ck.warn(
                "masks",
                format!(
                    "{} image(s) have no foreground pixels (first: {}); evaluation skips them",
                    empty.len(),
                    empty[0]
                ),
            );
        }
    }
    if let Some(sm) = &ds.sampling_masks {
        let empty: Vec<usize> = sm
            .outer_iter()
            .enumerate()
            .filter(|(_, m)| m.iter().all(|&v| v == 0))
            .map(|(n, _)| n)
            .collect();
        if !empty.is_empty() {
            ck.warn(
                "sampling_masks",
                format!(
                    "{} image(s) have an all-zero sampling mask (first: {}); training samples all their pixels",
                    empty.len(),
                    empty[0]
                ),
            );
        }
    }
    Ok(())
}
