//! Skeleton kinematics against the reference's golden outputs and the
//! spec's test vectors (docs/conventions.md, "Skeleton"; docs/reference.md,
//! "Initialisation"), plus rotation round trips.

use std::path::PathBuf;

use glam::{DMat3, DVec3};
use pma_data::skeleton::{
    axis_angle_to_matrix, bone_align, forward_kinematics, init_half_extents, matrix_from_rot6d,
    matrix_to_axis_angle, rot6d_from_matrix, skeleton_profile, Joints, N_JOINTS,
};
use pma_data::DataError;
use proptest::prelude::*;
use safetensors::SafeTensors;

use crate::support::max_abs_diff;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn f32s(st: &SafeTensors, key: &str) -> (Vec<usize>, Vec<f32>) {
    let t = st.tensor(key).unwrap_or_else(|e| panic!("{key}: {e}"));
    assert_eq!(t.dtype(), safetensors::Dtype::F32, "{key}");
    let v = t
        .data()
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect();
    (t.shape().to_vec(), v)
}

fn joints(v: &[f32]) -> Joints {
    let mut j = [[0.0f32; 3]; N_JOINTS];
    for (i, r) in j.iter_mut().enumerate() {
        r.copy_from_slice(&v[3 * i..3 * i + 3]);
    }
    j
}

/// The A-NeRF canonical rest pose (fixtures/data, copied from shared/data).
fn fixture_rest_pose() -> Joints {
    let text =
        std::fs::read_to_string(root().join("fixtures/data/smpl_rest_pose_anerf.csv")).unwrap();
    let mut out = [[0.0f32; 3]; N_JOINTS];
    for (i, line) in text.lines().skip(1).enumerate() {
        let f: Vec<&str> = line.split(',').collect();
        assert_eq!(f[0].parse::<usize>().unwrap(), i);
        for k in 0..3 {
            out[i][k] = f[3 + k].parse().unwrap();
        }
    }
    out
}

/// FK from `input/bones`, `input/rest_pose` and root = kp3d[0] − rest[0]
/// reproduces the dataloader's `kp3d` and `skts` (metres) to 1e-5.
#[test]
fn golden_fk_reproduces_kp3d_and_skts() {
    let bytes = std::fs::read(root().join("fixtures/golden/golden.safetensors")).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let (_, rest) = f32s(&st, "input/rest_pose");
    let (bs, bones) = f32s(&st, "input/bones");
    let (_, kp3d) = f32s(&st, "input/kp3d");
    let (_, skts) = f32s(&st, "input/skts");
    let rest = joints(&rest);
    let rays = bs[0];
    for r in [0, rays / 2, rays - 1] {
        let b = joints(&bones[r * 72..(r + 1) * 72]);
        let kp = &kp3d[r * 72..(r + 1) * 72];
        let root = [kp[0] - rest[0][0], kp[1] - rest[0][1], kp[2] - rest[0][2]];
        let posed = forward_kinematics(&rest, &b, root);
        let got_kp: Vec<f32> = posed.kp3d.iter().flatten().copied().collect();
        let d = max_abs_diff(&got_kp, kp);
        assert!(d < 1e-5, "ray {r}: kp3d max diff {d}");
        let got_skts: Vec<f32> = posed.skts.iter().flatten().flatten().copied().collect();
        let d = max_abs_diff(&got_skts, &skts[r * 384..(r + 1) * 384]);
        assert!(d < 1e-5, "ray {r}: skts max diff {d}");
    }
}

#[test]
fn bone_align_matches_spec_vectors() {
    let ba = bone_align(&fixture_rest_pose()).unwrap();
    let cases: [(usize, [[f32; 3]; 3], f32); 3] = [
        (
            1,
            [
                [-0.032958, 0.0, -0.999457],
                [0.995449, 0.089467, -0.032826],
                [0.089418, -0.995990, -0.002949],
            ],
            -0.437208,
        ),
        (
            16,
            [
                [-0.100038, 0.0, -0.994984],
                [0.044662, 0.998992, -0.004490],
                [0.993981, -0.044887, -0.099938],
            ],
            -0.302010,
        ),
        (
            12,
            [
                [0.994388, 0.0, -0.105794],
                [-0.084084, 0.606879, -0.790334],
                [0.064204, 0.794794, 0.603474],
            ],
            -0.101321,
        ),
    ];
    for (j, r, tz) in cases {
        let m = ba.transforms[j];
        for i in 0..3 {
            for k in 0..3 {
                assert!(
                    (m[i][k] - r[i][k]).abs() < 2e-6,
                    "joint {j} R[{i}][{k}] = {} vs {}",
                    m[i][k],
                    r[i][k]
                );
            }
        }
        assert!(
            m[0][3].abs() < 1e-7 && m[1][3].abs() < 1e-7,
            "joint {j} translation x/y"
        );
        assert!(
            (m[2][3] - tz).abs() < 2e-6,
            "joint {j} t_z = {} vs {tz}",
            m[2][3]
        );
        assert_eq!(m[3], [0.0, 0.0, 0.0, 1.0]);
    }
    assert_eq!(ba.child[1], 4);
    // Joints with 0 or >= 2 children keep the identity.
    for j in [0usize, 9, 10, 11, 15, 22, 23] {
        assert_eq!(ba.child[j], j);
        for i in 0..4 {
            for k in 0..4 {
                assert_eq!(
                    ba.transforms[j][i][k],
                    if i == k { 1.0 } else { 0.0 },
                    "joint {j}"
                );
            }
        }
    }
}

#[test]
fn init_half_extents_match_spec_table() {
    let rest = fixture_rest_pose();
    let prof = skeleton_profile(&rest).unwrap();
    assert!((prof.shoulder_width - 0.801207).abs() < 1e-6);
    assert!((prof.knee_width - 0.489591).abs() < 1e-6);
    let l = [
        0.2650, 0.8744, 0.8969, 0.3446, 0.9113, 0.9105, 0.1386, 0.3087, 0.3066, 0.4053, -1.0, -1.0,
        0.2026, 0.2242, 0.2366, -1.0, 0.6040, 0.5901, 0.5644, 0.5831, 0.1903, 0.1904, -1.0, -1.0,
    ];
    for (j, &want) in l.iter().enumerate() {
        assert!((prof.bone_lens_to_child[j] - want).abs() < 6e-5, "L[{j}]");
    }
    #[rustfmt::skip]
    let table: [[f32; 3]; 24] = [
        [0.4006,0.4006,0.2120], [0.2448,0.2448,0.6995], [0.2448,0.2448,0.7175], [0.4006,0.4006,0.2757],
        [0.2448,0.2448,0.7290], [0.2448,0.2448,0.7284], [0.4006,0.4006,0.1109], [0.2448,0.2448,0.2470],
        [0.2448,0.2448,0.2453], [0.4006,0.4006,0.3242], [0.2448,0.2448,0.3087], [0.2448,0.2448,0.3066],
        [0.2404,0.2804,0.2187], [0.1958,0.1958,0.1794], [0.1958,0.1958,0.1893], [0.2404,0.4807,0.2187],
        [0.1958,0.1958,0.4832], [0.1958,0.1958,0.4721], [0.1958,0.1958,0.4515], [0.1958,0.1958,0.4665],
        [0.1958,0.1958,0.1522], [0.1958,0.1958,0.1523], [0.1958,0.1958,0.1903], [0.1958,0.1958,0.1904],
    ];
    let got = init_half_extents(&rest).unwrap();
    for j in 0..24 {
        for k in 0..3 {
            assert!(
                (got[j][k] - table[j][k]).abs() < 6e-5,
                "joint {j} axis {k}: {} vs {}",
                got[j][k],
                table[j][k]
            );
        }
    }
}

/// The golden model's buffers were computed by the reference from its rest
/// pose: `graph_net.base_scale` = initial half-extents, and
/// `pts_embedder.transforms` = bone-align transforms.
#[test]
fn golden_model_buffers_match_rest_pose() {
    let bytes = std::fs::read(root().join("fixtures/golden/model.safetensors")).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let (_, rest) = f32s(&st, "rest_pose");
    let rest = joints(&rest);
    let (_, base) = f32s(&st, "graph_net.base_scale");
    let got: Vec<f32> = init_half_extents(&rest)
        .unwrap()
        .iter()
        .flatten()
        .copied()
        .collect();
    let d = max_abs_diff(&got, &base);
    assert!(d < 1e-6, "base_scale max diff {d}");
    let (_, tr) = f32s(&st, "pts_embedder.transforms");
    let got: Vec<f32> = bone_align(&rest)
        .unwrap()
        .transforms
        .iter()
        .flatten()
        .flatten()
        .copied()
        .collect();
    let d = max_abs_diff(&got, &tr);
    // The reference builds A_j in float32 (arccos, sin, cos of float32 angles); ours is f64
    // rounded once, so they differ by a few dozen float32 ulps of values ~1.
    assert!(d < 5e-6, "transforms max diff {d}");
}

#[test]
fn degenerate_rest_pose_is_an_error() {
    let mut rest = fixture_rest_pose();
    rest[4] = rest[1]; // left knee on the left hip: zero-length thigh
    match bone_align(&rest) {
        Err(DataError::DegenerateRestPose { joint, .. }) => assert_eq!(joint, 4),
        other => panic!("expected DegenerateRestPose, got {other:?}"),
    }
    assert!(init_half_extents(&[[0.0; 3]; 24]).is_err());
    let mut nan = fixture_rest_pose();
    nan[7][1] = f32::NAN;
    assert!(skeleton_profile(&nan).is_err());
}

#[test]
fn degenerate_6d_is_an_error() {
    assert!(matrix_from_rot6d([0.0, 1.0, 0.0, 0.0, 0.0, 0.0]).is_err());
    // Parallel columns.
    assert!(matrix_from_rot6d([1.0, 2.0, 0.0, 0.0, 0.0, 0.0]).is_err());
}

fn mat_close(a: DMat3, b: DMat3, tol: f64) -> bool {
    a.to_cols_array()
        .iter()
        .zip(b.to_cols_array())
        .all(|(x, y)| (x - y).abs() < tol)
}

fn unit_axis() -> impl Strategy<Value = DVec3> {
    (-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0)
        .prop_filter("non-zero", |(x, y, z)| x * x + y * y + z * z > 1e-2)
        .prop_map(|(x, y, z)| DVec3::new(x, y, z).normalize())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn axis_angle_round_trip(axis in unit_axis(), angle in 0.0f64..(std::f64::consts::PI - 1e-3)) {
        let w = axis * angle;
        let m = axis_angle_to_matrix(w);
        prop_assert!(mat_close(m.transpose() * m, DMat3::IDENTITY, 1e-12));
        prop_assert!((m.determinant() - 1.0).abs() < 1e-12);
        let back = matrix_to_axis_angle(m);
        prop_assert!((back - w).length() < 1e-9, "{w} -> {back}");
    }

    #[test]
    fn axis_angle_round_trip_near_zero(axis in unit_axis(), e in -12.0f64..-3.0) {
        let w = axis * 10f64.powf(e);
        let m = axis_angle_to_matrix(w);
        // First-order check independent of the implementation: R ≈ I + [w]× up to the
        // second-order term, whose entries are bounded by |w|².
        let tol = 1e-12 + w.length_squared();
        prop_assert!((m.col(0).y - w.z).abs() < tol && (m.col(1).x + w.z).abs() < tol);
        let back = matrix_to_axis_angle(m);
        prop_assert!((back - w).length() < 1e-14 + 1e-9 * w.length(), "{w} -> {back}");
    }

    #[test]
    fn axis_angle_round_trip_near_pi(axis in unit_axis(), e in -9.0f64..-2.0) {
        let angle = std::f64::consts::PI - 10f64.powf(e);
        let m = axis_angle_to_matrix(axis * angle);
        let back = matrix_to_axis_angle(m);
        prop_assert!(back.length() <= std::f64::consts::PI + 1e-12);
        prop_assert!(mat_close(axis_angle_to_matrix(back), m, 1e-9));
        prop_assert!((back.length() - angle).abs() < 1e-7);
    }

    #[test]
    fn angles_beyond_pi_map_to_the_same_rotation(axis in unit_axis(), angle in 3.2f64..12.0) {
        let m = axis_angle_to_matrix(axis * angle);
        let back = matrix_to_axis_angle(m);
        prop_assert!(back.length() <= std::f64::consts::PI + 1e-12);
        prop_assert!(mat_close(axis_angle_to_matrix(back), m, 1e-9));
    }

    #[test]
    fn rot6d_round_trip(axis in unit_axis(), angle in 0.0f64..std::f64::consts::PI) {
        let m = axis_angle_to_matrix(axis * angle);
        let x = rot6d_from_matrix(m);
        // Layout: first two columns, row-major.
        prop_assert_eq!(x[1], m.col(1).x);
        prop_assert_eq!(x[2], m.col(0).y);
        let back = matrix_from_rot6d(x).unwrap();
        prop_assert!(mat_close(back, m, 1e-12));
        // Gram–Schmidt makes a scaled, skewed input orthonormal again.
        let mut y = x;
        for (i, v) in y.iter_mut().enumerate() { *v *= if i % 2 == 0 { 3.0 } else { 0.5 }; }
        y[1] += 0.2 * y[0]; y[3] += 0.2 * y[2]; y[5] += 0.2 * y[4];
        prop_assert!(mat_close(matrix_from_rot6d(y).unwrap(), m, 1e-10));
    }
}
