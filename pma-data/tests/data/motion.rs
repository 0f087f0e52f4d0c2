//! Motion readers: BVH parsing and kinematics, CMU → SMPL retargeting,
//! SMPL-parameter npz reading, frame-rate and up-axis edits.

use std::path::{Path, PathBuf};

use glam::DVec3;
use pma_data::motion::bvh::Bvh;
use pma_data::motion::retarget::{retarget_bvh, RetargetOptions, Source, CMU_TO_SMPL};
use pma_data::motion::{read_smpl_npz, HeadDir, Motion, MotionError};
use pma_data::skeleton::{axis_angle_to_matrix, forward_kinematics, PARENTS};
use pma_data::synth::ANERF_REST_POSE;

/// `bvh` (read from `file`) retargeted by the CMU map onto the A-NeRF rest pose, with the
/// default options.
fn retarget_cmu(bvh: &Bvh, file: &str) -> Result<Motion, MotionError> {
    retarget_bvh(
        bvh,
        file,
        &CMU_TO_SMPL,
        &ANERF_REST_POSE,
        &Default::default(),
    )
}

fn asset(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("assets/motion")
        .join(name)
}

fn cmu() -> Bvh {
    Bvh::read(&asset("cmu_131_01_30fps.bvh")).unwrap()
}

fn v(a: [f32; 3]) -> DVec3 {
    DVec3::new(a[0] as f64, a[1] as f64, a[2] as f64)
}

fn angle(a: DVec3, b: DVec3) -> f64 {
    a.normalize().dot(b.normalize()).clamp(-1.0, 1.0).acos()
}

/// A root with position channels and ZYX rotation, a child with ZXY order
/// and an end site; every expected position below is worked out by hand.
const TINY: &str = "HIERARCHY
ROOT Base
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT Arm
  {
    OFFSET 1 0 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 1 0
    }
  }
}
MOTION
Frames: 2
Frame Time: .5
0 0 0 0 0 0 0 0 0
1 2 3 90 0 0 0 90 90
";

#[test]
fn bvh_kinematics_follow_channel_order() {
    let bvh = Bvh::parse(TINY, "tiny.bvh").unwrap();
    assert_eq!(bvh.n_frames(), 2);
    assert_eq!(bvh.n_channels(), 9);
    assert_eq!(bvh.fps(), 2.0);
    let arm = bvh.joint("Arm").unwrap();

    let rest = bvh.pose(0);
    assert!((rest.position[arm] - DVec3::new(1.0, 0.0, 0.0)).length() < 1e-12);
    let end = rest.end_site(&bvh, arm).unwrap();
    assert!((end - DVec3::new(1.0, 1.0, 0.0)).length() < 1e-12);

    // Root: translate (1,2,3), Rz(90°) sends the arm offset (1,0,0) to (0,1,0).
    // Arm: Rx(90°)·Ry(90°) sends the end offset (0,1,0) to (0,0,1), and the
    // root's Rz(90°) keeps it there. The opposite order Ry·Rx would give
    // (1,0,0) → (0,1,0) and an end site at (1,4,3).
    let p = bvh.pose(1);
    assert!((p.position[arm] - DVec3::new(1.0, 3.0, 3.0)).length() < 1e-12);
    let end = p.end_site(&bvh, arm).unwrap();
    assert!(
        (end - DVec3::new(1.0, 3.0, 4.0)).length() < 1e-12,
        "end site {end}"
    );
}

#[test]
fn bvh_errors_name_the_line() {
    let cases = [
        (
            TINY.replace("Xrotation Yrotation\n", "Wrotation Yrotation\n"),
            9,
            "Wrotation",
        ),
        (
            TINY.replace("0 90 90\n", "0 90\n"),
            20,
            "ends inside frame 1",
        ),
        (TINY.replace("1 2 3 90", "1 2 x 90"), 20, "`x`"),
        (TINY.replace("Frames: 2", "Frames: 0"), 17, "frame count"),
        (format!("{TINY}5\n"), 21, "after the 2 announced frames"),
    ];
    for (text, line, needle) in cases {
        let err = Bvh::parse(&text, "tiny.bvh").unwrap_err();
        let msg = err.to_string();
        match err {
            MotionError::Bvh { line: l, .. } => assert_eq!(l, line, "{msg}"),
            other => panic!("expected a Bvh error, got {other:?}"),
        }
        assert!(msg.starts_with("tiny.bvh:"), "{msg}");
        assert!(msg.contains(needle), "{msg} lacks {needle}");
    }
}

#[test]
fn cmu_asset_has_the_documented_layout() {
    let bvh = cmu();
    assert_eq!(bvh.joints.len(), 31);
    assert_eq!(bvh.n_frames(), 249);
    assert_eq!(bvh.n_channels(), 6 + 30 * 3);
    assert!((bvh.fps() - 30.0).abs() < 1e-3);
    // The first kept frame is the original's frame 0.
    assert_eq!(&bvh.frame(0)[..3], &[5.23, 16.9002, -33.8986]);
}

/// Retargets `bvh` and checks that every Bone-sourced SMPL bone points
/// along its BVH segment in every frame.
fn check_bone_directions(bvh: &Bvh) -> f64 {
    let m = retarget_cmu(bvh, "cmu").unwrap();
    assert_eq!(m.up, HeadDir::PosY);
    let mut worst = 0.0f64;
    let mut checked = 0;
    for f in 0..bvh.n_frames() {
        let smpl = forward_kinematics(&ANERF_REST_POSE, &m.bones[f], m.root[f]);
        let pose = bvh.pose(f);
        for (j, entry) in CMU_TO_SMPL.iter().enumerate() {
            let Source::Bone { from, to } = entry.source else {
                continue;
            };
            let c = (1..24).find(|&c| PARENTS[c] == j).unwrap();
            let smpl_dir = v(smpl.kp3d[c]) - v(smpl.kp3d[j]);
            let bvh_dir =
                pose.position[bvh.joint(to).unwrap()] - pose.position[bvh.joint(from).unwrap()];
            worst = worst.max(angle(smpl_dir, bvh_dir));
            checked += 1;
        }
    }
    // Every bone-sourced SMPL joint with a child is checked in every frame.
    let per_frame = CMU_TO_SMPL
        .iter()
        .enumerate()
        .filter(|(j, e)| {
            matches!(e.source, Source::Bone { .. }) && (1..24).any(|c| PARENTS[c] == *j)
        })
        .count();
    assert!(
        per_frame >= 15,
        "only {per_frame} bones are retargeted by direction"
    );
    assert_eq!(checked, per_frame * bvh.n_frames());
    worst
}

#[test]
fn retargeted_bones_follow_bvh_directions() {
    let worst = check_bone_directions(&cmu());
    // f32 axis-angle storage and a 24-joint f64 chain: far below 0.1°.
    assert!(worst < 1e-3, "worst bone direction error {worst} rad");
}

#[test]
fn retargeted_torso_and_root_follow_the_bvh() {
    let bvh = cmu();
    let opts = RetargetOptions::default();
    let m = retarget_bvh(&bvh, "cmu", &CMU_TO_SMPL, &ANERF_REST_POSE, &opts).unwrap();
    let hips = bvh.joint("Hips").unwrap();
    let (chest2, neck) = (bvh.joint("Chest2").unwrap(), bvh.joint("Neck").unwrap());
    let (lhip, rhip) = (
        bvh.joint("LeftHip").unwrap(),
        bvh.joint("RightHip").unwrap(),
    );
    for f in (0..bvh.n_frames()).step_by(7) {
        let pose = bvh.pose(f);
        let smpl = forward_kinematics(&ANERF_REST_POSE, &m.bones[f], m.root[f]);
        // Root location: the Hips in metres.
        let hip_m = pose.position[hips] * opts.unit_metres;
        assert!((v(smpl.kp3d[0]) - hip_m).length() < 1e-5);
        // The multi-child joints only follow frames, so compare loosely:
        // upper back and the hip line.
        let up = angle(
            v(smpl.kp3d[12]) - v(smpl.kp3d[9]),
            pose.position[neck] - pose.position[chest2],
        );
        assert!(up < 0.35, "frame {f}: spine3→neck off by {up} rad");
        let side = angle(
            v(smpl.kp3d[1]) - v(smpl.kp3d[2]),
            pose.position[lhip] - pose.position[rhip],
        );
        assert!(side < 0.2, "frame {f}: hip line off by {side} rad");
    }
}

/// The asset's hierarchy with a single all-zero frame: the BVH rest pose.
fn cmu_rest_bvh() -> Bvh {
    let text = std::fs::read_to_string(asset("cmu_131_01_30fps.bvh")).unwrap();
    let head = &text[..text.find("MOTION").unwrap()];
    let zeros = vec!["0"; 96].join(" ");
    Bvh::parse(
        &format!("{head}MOTION\nFrames: 1\nFrame Time: .1\n{zeros}\n"),
        "rest.bvh",
    )
    .unwrap()
}

#[test]
fn bvh_rest_pose_lowers_the_smpl_t_pose_arms() {
    let bvh = cmu_rest_bvh();
    let m = retarget_cmu(&bvh, "rest").unwrap();
    let smpl = forward_kinematics(&ANERF_REST_POSE, &m.bones[0], [0.0; 3]);
    for (shoulder, elbow, wrist) in [(16, 18, 20), (17, 19, 21)] {
        let upper = v(smpl.kp3d[elbow]) - v(smpl.kp3d[shoulder]);
        let lower = v(smpl.kp3d[wrist]) - v(smpl.kp3d[elbow]);
        // The cmuconvert rest pose hangs the arms straight down (−y).
        assert!(angle(upper, DVec3::NEG_Y) < 1e-3, "upper arm {upper}");
        assert!(angle(lower, DVec3::NEG_Y) < 1e-3, "forearm {lower}");
    }
    // Legs stay down and the head stays up.
    assert!(smpl.kp3d[7][1] < smpl.kp3d[4][1] && smpl.kp3d[4][1] < smpl.kp3d[1][1]);
    assert!(smpl.kp3d[15][1] > smpl.kp3d[12][1]);
}

#[test]
fn retarget_names_a_missing_joint() {
    let text = TINY.replace("Base", "Hips");
    let bvh = Bvh::parse(&text, "tiny.bvh").unwrap();
    let err = retarget_cmu(&bvh, "tiny.bvh").unwrap_err();
    assert!(
        matches!(&err, MotionError::MissingJoint { joint, smpl_joint: 0, .. } if joint == "Chest"),
        "{err}"
    );
    assert!(err.to_string().contains("tiny.bvh"));
}

#[test]
fn aist_npz_matches_the_csv_export() {
    let m = read_smpl_npz(&asset("aist_demo.npz"), 60.0).unwrap();
    assert_eq!(m.len(), 320);
    assert_eq!(m.fps, 60.0);
    // Values from the upstream CSV export (numpy savetxt, %.7g).
    let first = [3.070928f32, -0.1080172, -0.6153619];
    let last_left_hip = [-0.5238505f32, -0.06122155, 0.2166345];
    for c in 0..3 {
        assert!((m.bones[0][0][c] - first[c]).abs() < 1e-6);
        assert!((m.bones[319][1][c] - last_left_hip[c]).abs() < 1e-6);
    }
    // The CSV keeps 7 significant digits.
    assert!((m.bones[0][2][0] - -0.1137236).abs() < 1e-7);
    let t0 = [0.07914753f32, 1.977826, -0.8184864];
    let t_last = [0.007994803f32, 1.944203, -0.8973989];
    for c in 0..3 {
        assert!((m.root[0][c] - t0[c]).abs() < 1e-6);
        assert!((m.root[319][c] - t_last[c]).abs() < 1e-6);
    }
    // The root is ~180° about x: a y-down capture frame.
    assert_eq!(m.up, HeadDir::NegY);
}

fn write_npz(path: &Path, arrays: &[(&str, Vec<u64>, Vec<f32>)]) {
    use npyz::WriterBuilder;
    let mut npz = npyz::npz::NpzWriter::create(path).unwrap();
    for (name, shape, data) in arrays {
        let mut w = npz
            .array::<f32>(name, Default::default())
            .unwrap()
            .default_dtype()
            .shape(shape)
            .begin_nd()
            .unwrap();
        w.extend(data.iter().copied()).unwrap();
        w.finish().unwrap();
    }
}

#[test]
fn smpl_npz_rejects_bad_members() {
    let dir = tempfile::tempdir().unwrap();
    let upright = |t: usize| {
        let mut p = vec![0.0f32; t * 72];
        for f in 0..t {
            p[f * 72] = 0.01 * f as f32;
        }
        p
    };
    #[allow(clippy::type_complexity)]
    let cases: Vec<(&str, Vec<(&str, Vec<u64>, Vec<f32>)>, &str)> = vec![
        (
            "short_poses.npz",
            vec![
                ("poses", vec![2, 71], vec![0.0; 142]),
                ("trans", vec![2, 3], vec![0.0; 6]),
            ],
            "key `poses` has shape [2, 71], expected (T,72) or (T,24,3)",
        ),
        (
            "trans_mismatch.npz",
            vec![
                ("poses", vec![2, 72], upright(2)),
                ("trans", vec![3, 3], vec![0.0; 9]),
            ],
            "key `trans` has shape [3, 3], expected (2,3)",
        ),
        (
            "no_trans.npz",
            vec![("poses", vec![2, 72], upright(2))],
            "key `trans`: missing",
        ),
        (
            "nan.npz",
            vec![
                ("poses", vec![2, 72], {
                    let mut p = upright(2);
                    p[72 + 5] = f32::NAN;
                    p
                }),
                ("trans", vec![2, 3], vec![0.0; 6]),
            ],
            "key `poses` holds a non-finite value at frame 1",
        ),
        (
            "lying.npz",
            vec![
                ("poses", vec![1, 72], {
                    let mut p = vec![0.0f32; 72];
                    p[0] = std::f32::consts::FRAC_PI_2;
                    p
                }),
                ("trans", vec![1, 3], vec![0.0; 3]),
            ],
            "cannot tell which way is up",
        ),
    ];
    for (name, arrays, needle) in cases {
        let path = dir.path().join(name);
        write_npz(&path, &arrays);
        let msg = read_smpl_npz(&path, 30.0).unwrap_err().to_string();
        assert!(msg.contains(needle), "{name}: {msg}");
        assert!(msg.contains(name), "{name}: {msg}");
    }
    // The upright file itself reads, with the y-up convention.
    let path = dir.path().join("ok.npz");
    write_npz(
        &path,
        &[
            ("poses", vec![2, 72], upright(2)),
            ("trans", vec![2, 3], vec![0.5; 6]),
        ],
    );
    assert_eq!(read_smpl_npz(&path, 30.0).unwrap().up, HeadDir::PosY);
}

/// Two joints turning about z by `angles`, root moving along x.
fn ramp(angles: &[f32], fps: f64) -> Motion {
    Motion {
        fps,
        bones: angles
            .iter()
            .map(|&a| {
                let mut b = [[0.0f32; 3]; 24];
                b[0] = [0.0, 0.0, a];
                b[5] = [0.0, 0.0, -2.0 * a];
                b
            })
            .collect(),
        root: angles.iter().map(|&a| [a, 1.0, 0.0]).collect(),
        up: HeadDir::PosY,
    }
}

#[test]
fn resample_slerps_between_frames_and_copies_on_frames() {
    let m = ramp(&[0.0, 0.4, 0.8], 2.0);
    let r = m.resample(4.0).unwrap();
    assert_eq!(r.len(), 5);
    assert_eq!(r.fps, 4.0);
    let expect = [0.0f32, 0.2, 0.4, 0.6, 0.8];
    for (k, e) in expect.iter().enumerate() {
        assert!((r.bones[k][0][2] - e).abs() < 1e-6, "frame {k}");
        assert!((r.bones[k][5][2] + 2.0 * e).abs() < 1e-6, "frame {k}");
        assert!((r.root[k][0] - e).abs() < 1e-6, "frame {k}");
    }
    assert_eq!(r.bones[2], m.bones[1]);
    // Downsampling by an integral factor keeps the original frames.
    let d = ramp(&[0.0, 0.1, 0.2, 0.3, 0.4], 8.0).resample(4.0).unwrap();
    assert_eq!(d.len(), 3);
    assert_eq!(d.bones, ramp(&[0.0, 0.2, 0.4], 4.0).bones);
    let e = ramp(&[0.0, 0.1, 0.2, 0.3, 0.4], 8.0).every(2).unwrap();
    assert_eq!(e, ramp(&[0.0, 0.2, 0.4], 4.0));
    assert!(m.resample(0.0).is_err());
}

#[test]
fn frames_and_every_reject_bad_ranges() {
    let m = ramp(&[0.0, 0.1, 0.2], 2.0);
    assert_eq!(m.frames(1..3).unwrap().bones, m.bones[1..3].to_vec());
    for r in [0..4, 2..2] {
        let msg = m.frames(r).unwrap_err().to_string();
        assert!(msg.contains("within 0..3"), "{msg}");
    }
    assert!(m.every(0).is_err());
}

#[test]
fn to_up_flips_the_root_only_and_is_its_own_inverse() {
    let mut m = ramp(&[0.3], 30.0);
    m.root[0] = [1.0, 2.0, 3.0];
    let down = m.to_up(HeadDir::NegY);
    assert_eq!(down.up, HeadDir::NegY);
    assert_eq!(down.root[0], [1.0, -2.0, -3.0]);
    // The head (SMPL +y in the rest frame) now points to −y.
    let r0 = axis_angle_to_matrix(v(down.bones[0][0]));
    let head = r0 * DVec3::Y;
    assert!(head.y < -0.9, "{head}");
    // F·Rz(0.3): the x axis stays in the x–y plane, mirrored in y.
    let x = r0 * DVec3::X;
    assert!((x - DVec3::new(0.3f64.cos(), -(0.3f64.sin()), 0.0)).length() < 1e-6);
    assert_eq!(down.bones[0][5], m.bones[0][5]);
    let back = down.to_up(HeadDir::PosY);
    for c in 0..3 {
        assert!((back.bones[0][0][c] - m.bones[0][0][c]).abs() < 1e-6);
    }
    assert_eq!(back.root, m.root);
    assert_eq!(m.to_up(HeadDir::PosY), m);
}

#[test]
fn centre_root_removes_the_mean_on_chosen_axes() {
    let m = ramp(&[0.0, 0.2, 0.4], 2.0).centre_root([false, true, false]);
    let xs: Vec<f32> = m.root.iter().map(|r| r[0]).collect();
    assert!((xs[0] + 0.2).abs() < 1e-6 && xs[1].abs() < 1e-6 && (xs[2] - 0.2).abs() < 1e-6);
    assert!(m.root.iter().all(|r| r[1] == 1.0));
}
