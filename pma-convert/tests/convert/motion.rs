//! `pma convert motion` on the real AIST++ and CMU files in ../shared/data.

use std::path::{Path, PathBuf};

use pma_convert::{
    dataset::Layout,
    motion::{convert_motion, MotionOptions},
};
use pma_data::{
    dataset::{Dataset, Profile, ReadOptions},
    skeleton::forward_kinematics,
};

fn shared(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data")
        .join(rel)
}

fn csv(rel: &str) -> Vec<Vec<f32>> {
    std::fs::read_to_string(shared(rel))
        .unwrap()
        .lines()
        .map(|l| l.split(',').map(|x| x.parse().unwrap()).collect())
        .collect()
}

fn convert(input: &Path, opts: &MotionOptions) -> (Dataset, pma_convert::motion::MotionReport) {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("motion.npz");
    let rep = convert_motion(input, &out, opts).unwrap();
    let ds = Dataset::read(&out, &ReadOptions::new(Profile::Motion)).unwrap();
    (ds, rep)
}

fn assert_close(a: f32, b: f32, tol: f32, what: &str) {
    assert!((a - b).abs() <= tol, "{what}: {a} vs {b}");
}

/// kp3d of pose row p equals forward kinematics of the stored bones and root.
fn assert_fk_consistent(ds: &Dataset, p: usize) {
    let rest = ds.rest_pose.unwrap();
    let roots = ds.root_locs.as_ref().unwrap();
    let posed = forward_kinematics(
        &rest,
        &ds.pose_bones(p),
        [roots[[p, 0]], roots[[p, 1]], roots[[p, 2]]],
    );
    let kp = ds.pose_kp3d(p).unwrap();
    for (j, (a, b)) in kp.iter().zip(posed.kp3d.iter()).enumerate() {
        for k in 0..3 {
            assert_close(a[k], b[k], 1e-5, &format!("kp3d[{p}][{j}][{k}]"));
        }
    }
}

#[test]
fn aist_npz_keeps_every_frame_in_the_training_convention() {
    let (ds, rep) = convert(
        &shared("aistpp_smpl_demo/aist_demo.npz"),
        &MotionOptions::default(),
    );
    assert_eq!((rep.source_frames, rep.frames), (320, 320));
    assert_eq!(rep.fps, 60.0);
    assert_eq!(ds.n_poses(), 320);
    assert_eq!(ds.head_dir, [0.0, -1.0, 0.0]);
    assert!(ds.kp3d.as_ref().unwrap().iter().all(|v| v.is_finite()));
    assert!(ds.skts.as_ref().unwrap().iter().all(|v| v.is_finite()));
    // The capture is already head -y: poses and translation pass through.
    let poses = csv("aistpp_smpl_demo/poses_axis_angle_320x72.csv");
    let trans = csv("aistpp_smpl_demo/trans_320x3.csv");
    for f in [0, 157, 319] {
        for (k, t) in trans[f].iter().enumerate() {
            assert_close(ds.root_locs.as_ref().unwrap()[[f, k]], *t, 1e-5, "root");
        }
        for j in 0..24 {
            for k in 0..3 {
                assert_close(ds.bones[[f, j, k]], poses[f][3 * j + k], 1e-5, "bones");
            }
        }
        assert_fk_consistent(&ds, f);
    }
    assert_eq!(ds.frame_ids.as_ref().unwrap()[319], 319);
}

#[test]
fn aist_npz_flipped_for_a_y_up_target_then_cut_and_resampled() {
    let opts = MotionOptions {
        frames: Some(10..51),
        fps: Some(30.0),
        target: Layout::Aist,
        ..Default::default()
    };
    let (ds, rep) = convert(&shared("aistpp_smpl_demo/aist_demo.npz"), &opts);
    // Frames 10..51 at 60 fps span 40 source intervals: 21 frames at 30 fps.
    assert_eq!(rep.frames, 21);
    assert_eq!(ds.n_poses(), 21);
    assert_eq!(ds.head_dir, [0.0, 1.0, 0.0]);
    assert!(ds.frame_ids.is_none());
    let trans = csv("aistpp_smpl_demo/trans_320x3.csv");
    let poses = csv("aistpp_smpl_demo/poses_axis_angle_320x72.csv");
    // Output frame k is source frame 10 + 2k; the flip F = diag(1,-1,-1) turns the root.
    for k in [0, 7, 20] {
        let t = &trans[10 + 2 * k];
        let r = ds.root_locs.as_ref().unwrap();
        assert_close(r[[k, 0]], t[0], 1e-5, "x");
        assert_close(r[[k, 1]], -t[1], 1e-5, "y");
        assert_close(r[[k, 2]], -t[2], 1e-5, "z");
        for k3 in 0..3 {
            assert_close(
                ds.bones[[k, 5, k3]],
                poses[10 + 2 * k][15 + k3],
                1e-5,
                "right knee",
            );
        }
        // Head above the pelvis now.
        let kp = ds.pose_kp3d(k).unwrap();
        assert!(
            kp[15][1] > kp[0][1] + 0.3,
            "head {:?} pelvis {:?}",
            kp[15],
            kp[0]
        );
        assert_fk_consistent(&ds, k);
    }
}

#[test]
fn cmu_bvh_is_retargeted_resampled_and_upright() {
    let opts = MotionOptions {
        fps: Some(30.0),
        ..Default::default()
    };
    let (ds, rep) = convert(&shared("cmu_mocap_131_bvh/131_01.bvh"), &opts);
    assert_eq!(rep.source_frames, 994);
    assert!((rep.source_fps - 120.0).abs() < 0.01, "{}", rep.source_fps);
    // 993 intervals at 120 fps = 8.275 s → 249 frames at 30 fps.
    assert_eq!(rep.frames, 249);
    assert_eq!(ds.head_dir, [0.0, -1.0, 0.0]);
    let kp = ds.kp3d.as_ref().unwrap();
    assert!(kp.iter().all(|v| v.is_finite()));
    for p in 0..249 {
        let j = ds.pose_kp3d(p).unwrap();
        // Standing: head toward -y above the pelvis, feet below it.
        assert!(
            j[15][1] < j[0][1] - 0.3,
            "frame {p}: head {:?} pelvis {:?}",
            j[15],
            j[0]
        );
        let (l, r) = (j[10][1] - j[0][1], j[11][1] - j[0][1]);
        assert!(l.min(r) > 0.25, "frame {p}: feet {l} {r} below the pelvis");
        assert_fk_consistent(&ds, p);
    }
}

#[test]
fn a_truncated_motion_file_is_a_clear_error() {
    let bytes = std::fs::read(shared("aistpp_smpl_demo/aist_demo.npz")).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let cut = dir.path().join("cut.npz");
    std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
    let err =
        convert_motion(&cut, &dir.path().join("o.npz"), &MotionOptions::default()).unwrap_err();
    assert!(err.to_string().contains("cut.npz"), "{err}");
    assert!(!dir.path().join("o.npz").exists());
}

#[test]
fn nan_poses_are_rejected_with_the_frame_named() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("nan.npz");
    let mut poses = vec![0.1f32; 4 * 72];
    poses[2 * 72 + 7] = f32::NAN;
    let trans = vec![0.0f32; 4 * 3];
    {
        let f = std::fs::File::create(&p).unwrap();
        let mut w = pma_data::dataset::npz::NpzWriter::new(f, false, "nan.npz");
        w.add(
            "poses",
            &[4, 72],
            pma_data::dataset::npz::MemberData::F32(&poses),
        )
        .unwrap();
        w.add(
            "trans",
            &[4, 3],
            pma_data::dataset::npz::MemberData::F32(&trans),
        )
        .unwrap();
        w.finish().unwrap();
    }
    let msg = convert_motion(&p, &dir.path().join("o.npz"), &MotionOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        msg.contains("nan.npz") && msg.contains("poses") && msg.contains("frame 2"),
        "{msg}"
    );
}
