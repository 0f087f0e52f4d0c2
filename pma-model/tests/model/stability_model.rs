//! Stability of the whole avatar on extreme inputs: extreme poses (AIST++ frames, rotations up
//! to and exactly π, near 0 and 2π, the head backwards, tangled limbs), huge and negative
//! modulation frequencies, box sizes at their floor, and degenerate rest poses. Outputs and
//! gradients must be finite; broken rest poses must fail at construction.

use candle_core::{DType, Device, Tensor};
use pma_data::skeleton::{self, Joints};
use pma_data::synth;
use pma_model::render::avatar::Avatar;
use pma_model::tools::stability::{self, ProbeRow};
use pma_model::Config;
use proptest::prelude::*;

fn tiny(quirks: bool) -> Avatar {
    let mut cfg = Config::tiny();
    cfg.n_framecodes = 4;
    cfg.quirks.per_ray_cylinder_fallback = quirks;
    cfg.quirks.robust_ray_bounds = quirks;
    Avatar::new(cfg, &synth::rest_pose(), 3, &Device::Cpu).unwrap()
}

fn assert_finite(row: &ProbeRow) {
    assert_eq!(row.non_finite, 0, "{row:?}");
    let g = row.grad_norm.expect("gradient taken");
    assert!(g.is_finite() && g > 0.0, "{row:?}");
}

#[test]
fn extreme_poses_give_finite_outputs_and_gradients() {
    let fixed = tiny(true);
    let reference = tiny(false);
    let poses = stability::extreme_poses().unwrap();
    assert!(poses.iter().any(|(n, _)| n.starts_with("AIST++")));
    let mut reference_violations = 0;
    for (name, bones) in &poses {
        let row = stability::probe_pose(&fixed, name, bones).unwrap();
        println!(
            "{}",
            stability::Report {
                rows: vec![row.clone()]
            }
            .table()
        );
        assert_finite(&row);
        assert_eq!(row.violations, 0, "robust bounds: {row:?}");
        let row = stability::probe_pose(&reference, name, bones).unwrap();
        assert_finite(&row);
        reference_violations += row.violations;
    }
    // The probe set includes a ray facing away from the cylinder: with the reference's bounds
    // its far < near (docs/numerics.md, "Cameras and rays"), which the robust bounds remove.
    assert!(reference_violations > 0);
}

#[test]
fn kinematics_round_trip_on_extreme_poses() {
    let rest = synth::rest_pose();
    for (name, bones) in stability::extreme_poses().unwrap() {
        let err = stability::kinematics_error(&rest, &bones);
        assert!(err < 1e-5, "{name}: round-trip error {err:e}");
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 6, ..ProptestConfig::default() })]

    /// Random axes, angles anywhere in [0, π] (the end points included), any root position.
    #[test]
    fn random_poses_up_to_pi_are_finite(
        axes in prop::collection::vec((-1f32..1.0, -1f32..1.0, -1f32..1.0), 24),
        angles in prop::collection::vec(prop_oneof![Just(0f32), Just(std::f32::consts::PI), 0f32..=std::f32::consts::PI], 24),
    ) {
        let avatar = tiny(true);
        let mut bones: Joints = [[0.0; 3]; 24];
        for (b, ((x, y, z), a)) in bones.iter_mut().zip(axes.iter().zip(&angles)) {
            let n = (x * x + y * y + z * z).sqrt().max(1e-3);
            *b = [x / n * a, y / n * a, z / n * a];
        }
        let row = stability::probe_pose(&avatar, "random", &bones).unwrap();
        prop_assert_eq!(row.non_finite, 0, "{:?}", row);
        prop_assert_eq!(row.violations, 0, "{:?}", row);
        prop_assert!(stability::kinematics_error(&synth::rest_pose(), &bones) < 1e-5);
    }
}

#[test]
fn huge_and_negative_frequencies_stay_finite() {
    let avatar = tiny(true);
    let bones = [[std::f32::consts::PI, 0.0, 0.0]; 24];
    let mut norms = Vec::new();
    for gamma in [-1e4, -30.0, 0.0, 30.0, 1e3, 1e4] {
        let a = stability::with_constant_gamma(&avatar, gamma).unwrap();
        let row = stability::probe_pose(&a, &format!("gamma {gamma}"), &bones).unwrap();
        assert_finite(&row);
        norms.push((gamma, row.grad_norm.unwrap()));
    }
    for (g, n) in &norms {
        println!("gamma {g:>8}: gradient norm {n:.3e}");
    }
    // Gradients of the modulator grow with γ: the probe really moved the frequencies.
    let at = |g: f64| norms.iter().find(|x| x.0 == g).unwrap().1;
    assert!(at(1e4) > at(30.0), "{norms:?}");
}

#[test]
fn axis_scales_at_the_floor_stay_finite() {
    let avatar = tiny(true);
    let floor = (avatar.tensors()["graph_net.base_scale"].clone() * 0.95).unwrap();
    let bones = stability::extreme_poses().unwrap()[1].1;
    for factor in [0.0, -1e-3, 1e-30] {
        let a = stability::with_axis_scale(&avatar, factor).unwrap();
        let s = a.axis_scale().unwrap();
        let diff = (s - &floor)
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert!(
            diff < 1e-6,
            "factor {factor}: scales not at the floor ({diff})"
        );
        assert_finite(&stability::probe_pose(&a, "floor", &bones).unwrap());
    }
}

#[test]
fn degenerate_rest_poses_fail_at_construction() {
    let cfg = Config::tiny();
    let dev = Device::Cpu;
    let rest = synth::rest_pose();

    // A bone of length 0 (left knee on the left hip).
    let mut coincident = rest;
    coincident[4] = coincident[1];
    let err = Avatar::new(cfg.clone(), &coincident, 0, &dev).unwrap_err();
    assert!(err.to_string().contains("joint 4"), "{err}");

    // Two knees in the same place: every bone is fine, but the leg boxes would be 0 wide.
    let mut knees = rest;
    knees[5] = knees[4];
    knees[8] = [knees[4][0], knees[7][1], knees[7][2]];
    knees[11] = [knees[4][0], knees[10][1], knees[10][2]];
    let err = Avatar::new(cfg.clone(), &knees, 0, &dev).unwrap_err();
    assert!(err.to_string().contains("half-extent"), "{err}");

    // A vertical bone is legal: its bone-align transform is finite and maps it onto +z.
    let mut vertical = rest;
    vertical[6] = [rest[3][0], rest[3][1] + 0.1, rest[3][2]];
    let a = Avatar::new(cfg.clone(), &vertical, 0, &dev).unwrap();
    let align = skeleton::bone_align(&vertical).unwrap();
    assert_eq!(align.child[3], 6);
    let m = skeleton::mat4_from_rows(&align.transforms[3]);
    let bone = glam::DVec3::new(0.0, 0.1, 0.0);
    let mapped = m.transform_vector3(bone);
    assert!(
        (mapped - glam::DVec3::new(0.0, 0.0, 0.1)).length() < 1e-6,
        "{mapped:?}"
    );
    assert_finite(&stability::probe_pose(&a, "vertical bone", &[[0.0; 3]; 24]).unwrap());

    // A checkpoint whose box sizes are 0 is refused when loaded, naming the tensor.
    let mut t = a.tensors();
    let zero = Tensor::zeros((24, 3), DType::F32, &dev).unwrap();
    t.insert("graph_net.base_scale".into(), zero);
    let err = Avatar::from_tensors(cfg, t, &dev).unwrap_err();
    assert!(err.to_string().contains("graph_net.base_scale"), "{err}");
}

#[test]
fn geometry_bounds_are_ordered_and_batch_independent_with_the_fixes() {
    let fixed = tiny(true);
    let reference = tiny(false);
    for (name, bones) in stability::extreme_poses().unwrap().iter().take(4) {
        let row = stability::probe_geometry(&fixed, bones).unwrap();
        assert_eq!(row.non_finite, 0, "{name}: {row:?}");
        assert_eq!(row.violations, 0, "{name}: {row:?}");
        // The reference breaks batch independence (cylinder misses take the batch mean) and
        // near <= far (a cylinder behind the camera).
        let row = stability::probe_geometry(&reference, bones).unwrap();
        assert_eq!(row.non_finite, 0, "{name}: {row:?}");
        assert!(row.violations > 0, "{name}: {row:?}");
    }
}
