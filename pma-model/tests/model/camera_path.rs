//! Camera paths (orbit, bullet time, framing camera) and the render-time ray-direction choice.
// Closures return `pma_model::error::Result`, whose error carries candle's (large) error.
#![allow(clippy::result_large_err)]

use std::f64::consts::TAU;

use candle_core::{Device, Tensor};
use pma_data::camera::Camera;
use pma_data::cylinder::HeadDir;
use pma_data::skeleton::forward_kinematics;
use pma_data::synth;
use pma_model::render::avatar::{Avatar, Rays};
use pma_model::render::camera_path::{
    bullet_time, facing, framing_camera, load_avatar, look_at, Orbit, ViewDirs,
};
use pma_model::render::image::{render_image, ChunkRender, ImageOptions};
use pma_model::Config;

use crate::common::max_abs_diff;

fn dist(a: [f32; 3], b: [f32; 3]) -> f32 {
    (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f32>().sqrt()
}

fn ring_camera() -> Camera {
    synth::ring_cameras(5, 64, 3, &synth::Ring::default()).unwrap()[2].clone()
}

#[test]
fn orbit_keeps_distance_and_height_and_looks_at_the_target() {
    let cam = ring_camera();
    let target = [0.0f32, 0.12, 0.0]; // the ring's look-at point
    let orbit = Orbit::through(&cam, target, HeadDir::NegY).unwrap();
    let cams = orbit.cameras(target, 8).unwrap();
    assert_eq!(cams.len(), 8);
    let d0 = dist(cam.origin(), target);
    assert!((orbit.distance() as f32 - d0).abs() < 1e-4);
    for (k, c) in cams.iter().enumerate() {
        assert!((dist(c.origin(), target) - d0).abs() < 1e-4, "camera {k}");
        assert!(
            (c.origin()[1] - cam.origin()[1]).abs() < 1e-4,
            "height of camera {k}"
        );
        let uv = c.project(target).unwrap();
        assert!((uv[0] - c.cx as f64).abs() < 1e-3 && (uv[1] - c.cy as f64).abs() < 1e-3);
        // The head (−y) is up in the image.
        let above = c.project([target[0], target[1] - 0.5, target[2]]).unwrap();
        assert!(above[1] < uv[1] - 1.0, "camera {k}: {above:?} vs {uv:?}");
        assert_eq!((c.fx, c.width, c.height), (cam.fx, cam.width, cam.height));
    }
    // The first camera is the training camera's position.
    assert!(dist(cams[0].origin(), cam.origin()) < 1e-4);
    // Cameras are evenly spaced: neighbours are all the same chord apart.
    let chord = dist(cams[0].origin(), cams[1].origin());
    for k in 1..8 {
        assert!((dist(cams[k].origin(), cams[(k + 1) % 8].origin()) - chord).abs() < 1e-4);
    }
    // A moved target carries the circle with it.
    let moved = orbit.camera([1.0, 0.12, -2.0], 0.0).unwrap();
    assert!(
        dist(
            moved.origin(),
            [
                cam.origin()[0] + 1.0,
                cam.origin()[1],
                cam.origin()[2] - 2.0
            ]
        ) < 1e-4
    );
    // A closer orbit keeps the elevation angle.
    let near = orbit
        .clone()
        .at_distance(2.0)
        .unwrap()
        .camera(target, 0.0)
        .unwrap();
    assert!((dist(near.origin(), target) - 2.0).abs() < 1e-4);
    assert!(Orbit::through(&cam, target, HeadDir::NegY)
        .unwrap()
        .at_distance(-1.0)
        .is_err());
}

#[test]
fn bullet_time_uses_the_transposed_ry_about_the_pivot() {
    let c2w = look_at([0.0, -0.5, 4.0], [0.0, -0.5, 0.0], [0.0, -1.0, 0.0]).unwrap();
    let cam = Camera::new(32, 32, 40.0, 40.0, 16.0, 16.0, c2w).unwrap();
    let views = bullet_time(&cam, [0.0; 3], 4).unwrap();
    assert_eq!(views.len(), 4);
    assert_eq!(views[0].c2w, cam.c2w, "view 0 is the camera itself");
    // Ry_ref(90°)·(0,0,4) = (−4,0,0): the reference's rotation sense.
    let o = views[1].origin();
    assert!(dist(o, [-4.0, -0.5, 0.0]) < 1e-5, "{o:?}");
    // Every view still looks at the pivot line.
    for v in &views {
        let uv = v.project([0.0, -0.5, 0.0]).unwrap();
        assert!((uv[0] - 16.0).abs() < 1e-3 && (uv[1] - 16.0).abs() < 1e-3);
    }
    // Off-origin pivot: the circle is around the pivot, heights unchanged.
    let pivot = [2.0f32, 0.3, -1.0];
    let views = bullet_time(&cam, pivot, 6).unwrap();
    let r0 = dist(
        [cam.origin()[0], 0.0, cam.origin()[2]],
        [pivot[0], 0.0, pivot[2]],
    );
    for v in &views {
        let o = v.origin();
        assert!((dist([o[0], 0.0, o[2]], [pivot[0], 0.0, pivot[2]]) - r0).abs() < 1e-4);
        assert!((o[1] - cam.origin()[1]).abs() < 1e-5);
    }
    assert!(bullet_time(&cam, [0.0; 3], 0).is_err());
    assert!(bullet_time(&cam, [f32::NAN, 0.0, 0.0], 3).is_err());
}

#[test]
fn orbit_and_bullet_time_agree_for_a_camera_looking_at_the_pivot() {
    let target = [0.2f32, -0.4, 0.1];
    let c2w = look_at([1.5, -1.0, 3.0], target, [0.0, -1.0, 0.0]).unwrap();
    let cam = Camera::new(48, 40, 50.0, 50.0, 24.0, 20.0, c2w).unwrap();
    let orbit = Orbit::through(&cam, target, HeadDir::NegY).unwrap();
    let n = 7;
    for (k, b) in bullet_time(&cam, target, n).unwrap().iter().enumerate() {
        let o = orbit.camera(target, TAU * k as f64 / n as f64).unwrap();
        for r in 0..3 {
            for c in 0..4 {
                assert!((o.c2w[r][c] - b.c2w[r][c]).abs() < 1e-4, "view {k}");
            }
        }
    }
}

#[test]
fn orbit_rejects_a_camera_on_the_axis() {
    let c2w = look_at([0.0, -3.0, 0.0], [0.0, 0.0, 0.001], [0.0, -1.0, 0.0]).unwrap();
    let cam = Camera::new(8, 8, 8.0, 8.0, 4.0, 4.0, c2w).unwrap();
    assert!(Orbit::through(&cam, [0.0; 3], HeadDir::NegY).is_err());
}

#[test]
fn framing_camera_sees_the_whole_body_upright() {
    let rest = synth::rest_pose();
    let walk = synth::walk_motion(&rest).unwrap();
    for f in [0, 30] {
        let kp = forward_kinematics(&rest, &walk.bones[f], walk.root[f]).kp3d;
        let cam = framing_camera(&kp, HeadDir::NegY, facing(&walk.bones[f]), 64, 48).unwrap();
        for (j, p) in kp.iter().enumerate() {
            let uv = cam.project(*p).unwrap();
            assert!(
                (0.0..64.0).contains(&uv[0]) && (0.0..48.0).contains(&uv[1]),
                "frame {f} joint {j} at {uv:?}"
            );
        }
        let head = cam.project(kp[15]).unwrap();
        let foot = cam.project(kp[10]).unwrap();
        assert!(head[1] < foot[1], "head above feet");
        // The body faces the camera: its left hip is on the image's right.
        let l = cam.project(kp[1]).unwrap();
        let r = cam.project(kp[2]).unwrap();
        assert!(l[0] > r[0], "frame {f}: left hip {l:?} right hip {r:?}");
    }
    assert!(framing_camera(&[[f32::NAN; 3]; 24], HeadDir::NegY, [0.0, 0.0, 1.0], 8, 8).is_err());
    assert!(framing_camera(&rest, HeadDir::NegY, [0.0, 0.0, 1.0], 0, 8).is_err());
}

/// Render one pose with either direction handling, feeding the renderer raw or pre-normalised
/// ray directions.
fn render(avatar: &Avatar, cam: &Camera, normalise_input: bool) -> Vec<f32> {
    let rest = *avatar.rest_pose();
    let mut bones = [[0f32; 3]; 24];
    bones[0] = [std::f32::consts::PI, 0.0, 0.0]; // upright, head −y
    let (poses, kp3d) = avatar.pose_from_bones(&bones, [0.0; 3]).unwrap();
    let _ = rest;
    let renderer = |o: &Tensor, d: &Tensor, bg: &Tensor| -> pma_model::error::Result<ChunkRender> {
        let d = if normalise_input {
            d.broadcast_div(&d.sqr()?.sum_keepdim(1)?.sqrt()?)?
        } else {
            d.clone()
        };
        let rays = Rays {
            origins: o.clone(),
            dirs: d,
            bgs: Some(bg.clone()),
            framecodes: vec![-1; o.dim(0)?],
        };
        let out = avatar.render_rays(&rays, &poses, &Default::default())?;
        Ok(ChunkRender {
            rgb: out.fine.rgb,
            acc: out.fine.acc,
            disp: out.fine.disp,
            stats: out.stats,
        })
    };
    let opts = ImageOptions {
        chunk: 97,
        ..Default::default()
    };
    render_image(&renderer, cam, &kp3d, None, &opts)
        .unwrap()
        .rgb
}

#[test]
fn normalised_view_directions_make_the_image_independent_of_ray_length() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.safetensors");
    let rest = synth::rest_pose();
    Avatar::new(Config::tiny(), &rest, 3, &Device::Cpu)
        .unwrap()
        .save(&path)
        .unwrap();
    // A wide-angle camera: |d| reaches 1.5 at the corners.
    let c2w = look_at([0.0, -0.3, 2.2], [0.0, -0.2, 0.0], [0.0, -1.0, 0.0]).unwrap();
    let cam = Camera::new(20, 20, 10.0, 10.0, 10.0, 10.0, c2w).unwrap();

    let ours = load_avatar(&path, &Device::Cpu, ViewDirs::Normalized).unwrap();
    assert!(ours.config().quirks.normalize_view_dirs);
    let a = render(&ours, &cam, false);
    let b = render(&ours, &cam, true);
    let max_diff = max_abs_diff(&a, &b);
    assert!(
        max_diff < 1e-4,
        "normalised: raw vs unit rays differ by {max_diff}"
    );

    let reference = load_avatar(&path, &Device::Cpu, ViewDirs::Reference).unwrap();
    assert!(!reference.config().quirks.normalize_view_dirs);
    let c = render(&reference, &cam, false);
    let d = render(&reference, &cam, true);
    let max_diff = max_abs_diff(&c, &d);
    assert!(
        max_diff > 1e-3,
        "the reference's raw directions must change colours ({max_diff})"
    );
    // With unit input both modes agree: the choice only matters for raw directions.
    let max_diff = b
        .iter()
        .zip(&d)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max);
    assert!(max_diff < 1e-4, "{max_diff}");
}
