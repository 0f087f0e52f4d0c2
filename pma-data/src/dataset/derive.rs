//! Import-time derivations (docs/conventions.md, "pma-npz v1"). Stored values always win;
//! only absent keys are filled, and each one filled is listed in
//! `Dataset::derived`.

use ndarray::{s, Array1, Array2};

use super::Dataset;
use crate::cylinder::{cylinder_from_joints, CylinderParams, HeadDir};
use crate::error::Result;
use crate::skeleton::{forward_kinematics_batch, joints_from_view, Joints};

pub(crate) fn derive(ds: &mut Dataset, rest: Option<&Joints>) -> Result<()> {
    if ds.rest_pose.is_none() {
        if let Some(r) = rest {
            ds.rest_pose = Some(*r);
            ds.derived.push("rest_pose (the model's)".into());
        }
    }
    let p = ds.n_poses();

    // root_locs = kp3d[:,0] − rest[0]
    if ds.root_locs.is_none() {
        if let (Some(kp), Some(r)) = (&ds.kp3d, &ds.rest_pose) {
            if kp.shape()[0] == p {
                let mut roots = Array2::<f32>::zeros((p, 3));
                for i in 0..p {
                    for k in 0..3 {
                        roots[[i, k]] = kp[[i, 0, k]] - r[0][k];
                    }
                }
                ds.root_locs = Some(roots);
                ds.derived
                    .push("root_locs (kp3d[:,0] - rest_pose[0])".into());
            }
        }
    }

    // kp3d / skts by FK (f64, stored f32)
    if ds.kp3d.is_none() || ds.skts.is_none() {
        if let (Some(roots), Some(r)) = (&ds.root_locs, &ds.rest_pose) {
            if roots.shape()[0] == p {
                let (kp, skts) = forward_kinematics_batch(r, ds.bones.view(), roots.view())?;
                if ds.kp3d.is_none() {
                    ds.kp3d = Some(kp);
                    ds.derived.push("kp3d (forward kinematics)".into());
                }
                if ds.skts.is_none() {
                    ds.skts = Some(skts);
                    ds.derived
                        .push("skts (inverse of forward kinematics)".into());
                }
            }
        }
    }

    // cyls with the training parameters
    if ds.cyls.is_none() {
        if let (Some(kp), Some(head)) = (&ds.kp3d, HeadDir::from_vector(ds.head_dir)) {
            ds.cyls = Some(cylinders(kp, head));
            ds.derived
                .push("cyls (E 0.25, top 1.0, bottom 0.25)".into());
        }
    }

    if let Some(shape) = ds.img_shape {
        let n = shape[0];
        let c = ds.n_cameras();
        if ds.centers.is_none() && ds.c2ws.is_some() {
            let (w, h) = (shape[2] as f32, shape[1] as f32);
            let mut ce = Array2::<f32>::zeros((c, 2));
            for mut row in ce.rows_mut() {
                row[0] = w / 2.0;
                row[1] = h / 2.0;
            }
            ds.centers = Some(ce);
            ds.derived.push("centers (W/2, H/2)".into());
        }
        if ds.kp_idxs.is_none() && p == n {
            ds.kp_idxs = Some(Array1::from_iter(0..n as i64));
            ds.derived.push("kp_idxs (identity, P = N)".into());
        }
        if ds.img_pose_indices.is_none() && c == n && ds.c2ws.is_some() {
            ds.img_pose_indices = Some(Array1::from_iter(0..n as i64));
            ds.derived.push("img_pose_indices (identity, C = N)".into());
        }
        if ds.bkgd_idxs.is_none() && ds.bkgds.is_some() {
            ds.bkgd_idxs = Some(Array1::zeros(n));
            ds.derived.push("bkgd_idxs (zeros)".into());
        }
    }
    Ok(())
}

/// Cylinders `[P,5]` with the stored-`cyls` parameters.
pub(crate) fn cylinders(kp3d: &ndarray::Array3<f32>, head: HeadDir) -> Array2<f32> {
    let params = CylinderParams::training(head);
    let p = kp3d.shape()[0];
    let mut out = Array2::<f32>::zeros((p, 5));
    for i in 0..p {
        let c = cylinder_from_joints(&joints_from_view(kp3d.slice(s![i, .., ..])), &params);
        for (k, v) in c.iter().enumerate() {
            out[[i, k]] = *v;
        }
    }
    out
}

pub(crate) fn repose(ds: &mut Dataset, rest: &Joints) -> Result<()> {
    if ds.root_locs.is_none() {
        // Needs the old rest pose (or none: a root-centred rest has r0 = 0).
        if let Some(kp) = &ds.kp3d {
            let r0 = ds.rest_pose.map_or([0.0; 3], |r| r[0]);
            let p = kp.shape()[0];
            let mut roots = Array2::<f32>::zeros((p, 3));
            for i in 0..p {
                for k in 0..3 {
                    roots[[i, k]] = kp[[i, 0, k]] - r0[k];
                }
            }
            ds.root_locs = Some(roots);
        }
    }
    let Some(roots) = &ds.root_locs else {
        return Err(crate::error::DataError::MissingKey {
            file: ds.source.clone(),
            key: "root_locs".into(),
            profile: super::Profile::Motion.name().into(),
            hint: " (or kp3d); re-posing needs the root translation".into(),
        });
    };
    let (kp, skts) = forward_kinematics_batch(rest, ds.bones.view(), roots.view())?;
    ds.rest_pose = Some(*rest);
    if let Ok(head) = ds.head() {
        ds.cyls = Some(cylinders(&kp, head));
    }
    ds.kp3d = Some(kp);
    ds.skts = Some(skts);
    ds.derived
        .push("kp3d, skts, cyls (re-posed with another rest pose)".into());
    Ok(())
}
