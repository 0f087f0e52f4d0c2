//! Ray bounds on hard geometry (docs/numerics.md, "Cameras and rays"): random rays around an
//! extreme pose, cameras inside the body, boxes behind the camera, vertical rays. With
//! `quirks.robust_ray_bounds` and `quirks.per_ray_cylinder_fallback` every ray gets finite,
//! ordered bounds whose ends lie on a box, independent of the other rays in its batch; the
//! reference settings are checked to show the hazards these switches remove.

use candle_core::Device;
use pma_data::synth;
use pma_model::render::avatar::Avatar;
use pma_model::tools::stability;
use pma_model::Config;
use proptest::prelude::*;

fn avatar(robust: bool, per_ray: bool) -> Avatar {
    let mut cfg = Config::tiny();
    cfg.quirks.robust_ray_bounds = robust;
    cfg.quirks.per_ray_cylinder_fallback = per_ray;
    Avatar::new(cfg, &synth::rest_pose(), 0, &Device::Cpu).unwrap()
}

struct Scene {
    skts: Vec<f32>,
    cyls: Vec<f32>,
    scales: Vec<f32>,
    kp3d: pma_data::skeleton::Joints,
}

fn scene(a: &Avatar, bones: &pma_data::skeleton::Joints) -> Scene {
    let (poses, kp3d) = a.pose_from_bones(bones, [0.0; 3]).unwrap();
    let host = |t: &candle_core::Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    Scene {
        skts: host(&poses.skts),
        cyls: host(&poses.cyls),
        scales: host(&a.axis_scale().unwrap()),
        kp3d,
    }
}

fn bounds(a: &Avatar, s: &Scene, o: &[f32], d: &[f32]) -> pma_model::render::raycast::RayBounds {
    a.ray_caster()
        .near_far(o, d, &s.cyls, &s.skts, &s.scales)
        .unwrap()
}

#[test]
fn camera_inside_a_box_samples_from_its_origin() {
    let bones = [[0.0; 3]; 24];
    let (fixed, reference) = (avatar(true, true), avatar(false, false));
    let s = scene(&fixed, &bones);
    // From the pelvis straight forward: the camera sits inside the pelvis box.
    let o = s.kp3d[0].to_vec();
    let d = [0.0f32, 0.0, 1.0];
    let b = bounds(&fixed, &s, &o, &d);
    assert!(b.ray_hits_body[0]);
    assert_eq!(b.near[0], 0.0, "robust bounds start at the camera");
    assert!(b.far[0] > 0.0);
    // The reference measures unsigned distances: it starts at the box face behind the camera
    // mirrored to the front, skipping the body right in front of the lens.
    let b = bounds(&reference, &s, &o, &d);
    assert!(b.near[0] > 0.0, "{:?}", b.near);
}

#[test]
fn boxes_behind_the_camera_are_not_hits() {
    let bones = [[0.0; 3]; 24];
    let (fixed, reference) = (avatar(true, true), avatar(false, false));
    let s = scene(&fixed, &bones);
    let c = s.kp3d[0];
    // Three metres in front of the pelvis, looking away from the body.
    let o = [c[0], c[1], c[2] + 3.0];
    let d = [0.0f32, 0.0, 1.0];
    let b = bounds(&reference, &s, &o, &d);
    assert!(
        b.ray_hits_body[0],
        "reference counts the body behind the camera"
    );
    let b = bounds(&fixed, &s, &o, &d);
    assert!(!b.ray_hits_body[0]);
    assert!(b.near[0] <= b.far[0] && b.near[0] >= 0.0, "{b:?}");
}

#[test]
fn cylinder_misses_depend_on_the_batch_only_in_the_reference() {
    let bones = [[0.0; 3]; 24];
    let c = synth::rest_pose()[0];
    // Ray 0 misses everything; ray 1 crosses the body.
    let o = [c[0] + 30.0, c[1], c[2], c[0], c[1], c[2] - 3.0];
    let d = [1.0f32, 0.0, 0.0, 0.0, 0.0, 1.0];
    for (per_ray, independent) in [(false, false), (true, true)] {
        let a = avatar(true, per_ray);
        let s = scene(&a, &bones);
        let alone = bounds(&a, &s, &o[..3], &d[..3]);
        let both = bounds(&a, &s, &o, &d);
        let same = alone.near[0] == both.near[0] && alone.far[0] == both.far[0];
        assert_eq!(
            same, independent,
            "per_ray {per_ray}: {alone:?} vs {both:?}"
        );
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]

    /// Random rays through a random region around an extreme pose: finite, ordered bounds on
    /// a box, and the same bounds for each ray alone as in the batch.
    #[test]
    fn random_rays_get_valid_batch_independent_bounds(
        pose in 0usize..6,
        rays in prop::collection::vec(
            ((-3f32..3.0, -3f32..3.0, -3f32..3.0), (-1f32..1.0, -1f32..1.0, -1f32..1.0), 0usize..4),
            1..24,
        ),
    ) {
        let a = avatar(true, true);
        let bones = stability::extreme_poses().unwrap()[pose].1;
        let s = scene(&a, &bones);
        let mut o = Vec::new();
        let mut d = Vec::new();
        for (p, q, kind) in &rays {
            let mut dir = [q.0, q.1, q.2];
            match kind {
                0 => dir = [0.0, dir[1].signum(), 0.0], // vertical
                1 => dir[1] = 0.0,                       // horizontal
                _ => {}
            }
            if dir.iter().all(|&x| x == 0.0) {
                dir = [1.0, 0.0, 0.0];
            }
            let origin = if *kind == 3 { s.kp3d[(p.0.abs() * 7.0) as usize % 24] } else { [p.0, p.1, p.2] };
            o.extend_from_slice(&origin);
            d.extend_from_slice(&dir);
        }
        let b = bounds(&a, &s, &o, &d);
        let bad = stability::bound_violations(&a, &o, &d, &b, &s.skts, &s.scales);
        prop_assert_eq!(bad, 0, "{:?}", b);
        for r in 0..rays.len() {
            let alone = bounds(&a, &s, &o[3 * r..3 * r + 3], &d[3 * r..3 * r + 3]);
            prop_assert_eq!(alone.near[0].to_bits(), b.near[r].to_bits());
            prop_assert_eq!(alone.far[0].to_bits(), b.far[r].to_bits());
        }
    }
}
