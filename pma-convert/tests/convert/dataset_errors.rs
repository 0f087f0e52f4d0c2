//! Bad datasets (docs/conventions.md, "Validation") are refused with the file and key named.
//! Each case starts from the converted h36m_zju fixture, breaks one thing,
//! and converts the broken pma-npz again.

use crate::support::fixture;

use pma_convert::dataset::{convert_dataset, DatasetOptions};
use pma_data::dataset::{Dataset, Profile, ReadOptions, WriteOptions};

/// Converts a copy of h36m_zju broken by `breaks` and returns the error message.
fn error_after(breaks: impl FnOnce(&mut Dataset), profile: Profile) -> String {
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("good.npz");
    let opts = DatasetOptions::new(Profile::Render);
    convert_dataset(&fixture("h36m_zju.h5"), &good, &opts, &mut |_, _| {}).unwrap();
    let mut ds = Dataset::read(&good, &ReadOptions::new(Profile::Render)).unwrap();
    breaks(&mut ds);
    let bad = dir.path().join("bad.npz");
    ds.write(&bad, &WriteOptions::default()).unwrap();
    let out = dir.path().join("out.npz");
    let err = convert_dataset(&bad, &out, &DatasetOptions::new(profile), &mut |_, _| {})
        .expect_err("broken dataset was accepted");
    assert!(!out.exists());
    let msg = err.to_string();
    assert!(msg.contains("bad.npz"), "{msg}");
    msg
}

#[test]
fn nan_pose_is_rejected() {
    let msg = error_after(|ds| ds.bones[[1, 5, 2]] = f32::NAN, Profile::Motion);
    assert!(msg.contains("bones"), "{msg}");
}

#[test]
fn non_orthonormal_camera_rotation_is_rejected() {
    let msg = error_after(
        |ds| {
            let c2ws = ds.c2ws.as_mut().unwrap();
            for r in 0..3 {
                for c in 0..3 {
                    c2ws[[2, r, c]] *= 1.1;
                }
            }
        },
        Profile::Render,
    );
    assert!(msg.contains("c2ws"), "{msg}");
}

#[test]
fn non_positive_focal_is_rejected() {
    let msg = error_after(
        |ds| ds.focals.as_mut().unwrap()[[1, 0]] = 0.0,
        Profile::Render,
    );
    assert!(msg.contains("focals"), "{msg}");
}

#[test]
fn missing_key_for_the_profile_is_named_with_the_profile() {
    let msg = error_after(|ds| ds.c2ws = None, Profile::Render);
    assert!(msg.contains("c2ws") && msg.contains("render"), "{msg}");
}

#[test]
fn wrong_joint_count_is_rejected() {
    let msg = error_after(
        |ds| {
            let kp = ds.kp3d.take().unwrap();
            ds.kp3d = Some(kp.slice(ndarray::s![.., ..23, ..]).to_owned());
        },
        Profile::Motion,
    );
    assert!(msg.contains("kp3d") && msg.contains("24"), "{msg}");
}

#[test]
fn kp3d_that_disagrees_with_the_bones_is_rejected() {
    let msg = error_after(
        |ds| ds.kp3d.as_mut().unwrap()[[0, 7, 1]] += 0.2,
        Profile::Motion,
    );
    assert!(msg.contains("kp3d"), "{msg}");
}
