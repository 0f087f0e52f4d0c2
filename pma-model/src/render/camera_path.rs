//! Camera paths for rendering a trained avatar: an orbit around the body at the training
//! camera's distance, bullet time, and a default framing camera when no training camera is at
//! hand.
//!
//! All cameras use the training world convention (head toward −y unless told otherwise,
//! ground plane x–z, OpenGL camera axes: the camera looks along its −z and its +y is "up" in
//! the image, i.e. toward the head).
//!
//! # Ray directions at render time
//! The reference trains on unit ray directions but renders with unnormalised ones
//! (camera-space z = −1, |d| up to ≈ 1.17 at image corners), and feeds them to a
//! spherical-harmonics view encoding that assumes unit vectors (see docs/numerics.md, "Cameras
//! and rays"). Ray marching is invariant to |d| (step lengths are multiplied by it), the view
//! encoding is not. pma renders with the view directions normalised ([`ViewDirs::Normalized`],
//! the default of `pma render`), so a pixel's colour does not depend on where it sits in the
//! image or on the focal length; [`ViewDirs::Reference`] keeps the checkpoint's own setting for
//! parity with the reference.

use std::f64::consts::TAU;
use std::path::Path;

use candle_core::Device;
use glam::{DMat3, DVec3};
use pma_data::camera::Camera;
use pma_data::cylinder::{cylinder_from_joints, CylinderParams, HeadDir};
use pma_data::skeleton::{mat4_from_rows, mat4_to_rows, rigid, rot_y_ref, Joints};

use crate::error::{ModelError, Result};
use crate::network::checkpoint;
use crate::render::avatar::Avatar;

/// How render-time ray directions reach the view encoding (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ViewDirs {
    /// Unit directions, as in training (pma's choice).
    #[default]
    Normalized,
    /// Whatever the checkpoint's `quirks.normalize_view_dirs` says (the reference: raw).
    Reference,
}

/// Load a checkpoint (with its occupancy grid, if any) for rendering with the chosen
/// view-direction handling.
pub fn load_avatar(path: &Path, device: &Device, dirs: ViewDirs) -> Result<Avatar> {
    let ck = checkpoint::load(path, device)?;
    let mut cfg = ck.config;
    if dirs == ViewDirs::Normalized {
        cfg.quirks.normalize_view_dirs = true;
    }
    Ok(Avatar::from_tensors(cfg, ck.tensors, device)?.with_occupancy(ck.occupancy))
}

fn v3(a: [f32; 3]) -> DVec3 {
    DVec3::new(a[0] as f64, a[1] as f64, a[2] as f64)
}

fn finite3(what: &str, a: DVec3) -> Result<()> {
    if a.is_finite() {
        Ok(())
    } else {
        Err(ModelError::Input(format!("{what} is not finite: {a:?}")))
    }
}

/// Camera-to-world (OpenGL axes) of a camera at `eye` looking at `target`, with the image's
/// up direction toward `up` (the head direction). Row-major `[4][4]`.
pub fn look_at(eye: [f32; 3], target: [f32; 3], up: [f32; 3]) -> Result<[[f32; 4]; 4]> {
    let (eye, target, up) = (v3(eye), v3(target), v3(up));
    for (what, v) in [("eye", eye), ("target", target), ("up", up)] {
        finite3(what, v)?;
    }
    // The camera looks along its −z, so its +z points from the target back to the eye.
    let z = (eye - target)
        .try_normalize()
        .ok_or_else(|| ModelError::Input(format!("look_at: eye {eye:?} coincides with target")))?;
    let x = up.cross(z).try_normalize().ok_or_else(|| {
        ModelError::Input(format!(
            "look_at: viewing direction {z:?} is parallel to up {up:?}"
        ))
    })?;
    let y = z.cross(x);
    Ok(mat4_to_rows(&rigid(DMat3::from_cols(x, y, z), eye)))
}

/// The same intrinsics as `template` with another pose.
fn with_c2w(template: &Camera, c2w: [[f32; 4]; 4]) -> Result<Camera> {
    let cam = Camera { c2w, ..*template };
    cam.validate()?;
    Ok(cam)
}

/// A circle of camera positions around a vertical axis (world y), all looking at the axis.
#[derive(Debug, Clone, PartialEq)]
pub struct Orbit {
    /// Intrinsics (and image size) of every camera.
    pub template: Camera,
    /// Horizontal distance from the axis.
    pub radius: f64,
    /// Camera height relative to the target (world y).
    pub height: f64,
    /// Azimuth of the first camera: `atan2(x, z)` of its offset from the target.
    pub start: f64,
    /// Head direction: the image's up.
    pub head: HeadDir,
}

impl Orbit {
    /// The orbit through `cam` around the vertical axis through `target`: same distance,
    /// height and intrinsics, starting where `cam` is.
    pub fn through(cam: &Camera, target: [f32; 3], head: HeadDir) -> Result<Orbit> {
        cam.validate()?;
        let off = v3(cam.origin()) - v3(target);
        finite3("orbit target", v3(target))?;
        let radius = off.x.hypot(off.z);
        if radius < 1e-6 * off.length().max(1.0) {
            return Err(ModelError::Input(format!(
                "orbit: the camera at {:?} is on the vertical axis through the target {target:?}; \
                 there is no circle to follow",
                cam.origin()
            )));
        }
        Ok(Orbit {
            template: cam.clone(),
            radius,
            height: off.y,
            start: off.x.atan2(off.z),
            head,
        })
    }

    /// Keep the orbit's elevation angle but move the camera to `distance` from the target.
    pub fn at_distance(mut self, distance: f64) -> Result<Orbit> {
        if !(distance.is_finite() && distance > 0.0) {
            return Err(ModelError::Input(format!(
                "orbit distance must be finite and > 0, found {distance}"
            )));
        }
        let k = distance / self.radius.hypot(self.height);
        self.radius *= k;
        self.height *= k;
        Ok(self)
    }

    /// Distance from the camera to the target.
    pub fn distance(&self) -> f64 {
        self.radius.hypot(self.height)
    }

    /// The camera `angle` radians along the orbit (same sense as bullet time's `Ry`),
    /// looking at `target` (which may move from frame to frame, e.g. with the root).
    pub fn camera(&self, target: [f32; 3], angle: f64) -> Result<Camera> {
        let phi = self.start - angle;
        let eye = v3(target)
            + DVec3::new(
                self.radius * phi.sin(),
                self.height,
                self.radius * phi.cos(),
            );
        let c2w = look_at(
            [eye.x as f32, eye.y as f32, eye.z as f32],
            target,
            self.head.vector(),
        )?;
        with_c2w(&self.template, c2w)
    }

    /// `n` cameras evenly spaced over one turn, looking at `target`.
    pub fn cameras(&self, target: [f32; 3], n: usize) -> Result<Vec<Camera>> {
        (0..n)
            .map(|k| self.camera(target, TAU * k as f64 / n as f64))
            .collect()
    }
}

/// Bullet time, as the reference's render script defines it: `c2w_k = Ry(2πk/n)·c2w` with the
/// reference's transposed `Ry`, applied after shifting the camera by −`pivot`. The shift is
/// undone afterwards, so the body can stay where it is (the image equals the reference's
/// re-centred one: moving camera and body by the same translation changes nothing). k = 0 is
/// `cam` itself.
pub fn bullet_time(cam: &Camera, pivot: [f32; 3], n: usize) -> Result<Vec<Camera>> {
    cam.validate()?;
    if n == 0 {
        return Err(ModelError::Input(
            "bullet time needs at least 1 view".into(),
        ));
    }
    let p = v3(pivot);
    finite3("bullet-time pivot", p)?;
    let c2w = mat4_from_rows(&cam.c2w);
    (0..n)
        .map(|k| {
            let ry = rigid(rot_y_ref(TAU * k as f64 / n as f64), DVec3::ZERO);
            let m = rigid(DMat3::IDENTITY, p) * ry * rigid(DMat3::IDENTITY, -p) * c2w;
            with_c2w(cam, mat4_to_rows(&m))
        })
        .collect()
}

/// Vertical field of view of [`framing_camera`], degrees.
pub const FRAMING_FOV_DEG: f64 = 30.0;

/// A camera that frames a posed body when no training camera is available: it looks at the
/// centre of the body's render cylinder (a = 1.6, b = 1.1, see docs/conventions.md, "Cameras")
/// from the direction `facing` (projected onto the ground plane; e.g. where the body faces),
/// slightly from above, far enough for the cylinder to fill ~90 % of the image.
pub fn framing_camera(
    kp3d: &Joints,
    head: HeadDir,
    facing: [f32; 3],
    width: usize,
    height: usize,
) -> Result<Camera> {
    if width == 0 || height == 0 {
        return Err(ModelError::Input(format!(
            "framing camera: empty image {width}x{height}"
        )));
    }
    if let Some(j) = kp3d.iter().position(|k| k.iter().any(|v| !v.is_finite())) {
        return Err(ModelError::Input(format!(
            "framing camera: joint {j} is {:?}",
            kp3d[j]
        )));
    }
    let cyl = cylinder_from_joints(kp3d, &CylinderParams::render(head));
    let (xc, zc, r, top, bot) = (
        cyl[0] as f64,
        cyl[1] as f64,
        cyl[2] as f64,
        cyl[3] as f64,
        cyl[4] as f64,
    );
    let target = DVec3::new(xc, 0.5 * (top + bot), zc);
    let extent_v = (top - bot).abs();
    let extent_h = 2.0 * r;
    let f = height as f64 / (2.0 * (0.5 * FRAMING_FOV_DEG.to_radians()).tan());
    // Pinhole: an extent e at distance D covers f·e/D pixels.
    let dist = (f * extent_v / (0.9 * height as f64)).max(f * extent_h / (0.9 * width as f64)) + r;
    let mut dir = DVec3::new(facing[0] as f64, 0.0, facing[2] as f64);
    dir = dir.try_normalize().unwrap_or(DVec3::Z);
    // 10° above the target: the head side is along `head`.
    let up = v3(head.vector());
    let elev = 10f64.to_radians();
    let eye = target + (dir * elev.cos() + up * elev.sin()) * dist;
    let c2w = look_at(
        [eye.x as f32, eye.y as f32, eye.z as f32],
        [target.x as f32, target.y as f32, target.z as f32],
        head.vector(),
    )?;
    Ok(Camera::new(
        width,
        height,
        f as f32,
        f as f32,
        width as f32 / 2.0,
        height as f32 / 2.0,
        c2w,
    )?)
}

/// Where a posed body faces: the root's rotation applied to SMPL's canonical facing (+z).
pub fn facing(bones: &Joints) -> [f32; 3] {
    let r0 = pma_data::skeleton::axis_angle_to_matrix(v3(bones[0]));
    let f = r0 * DVec3::Z;
    [f.x as f32, f.y as f32, f.z as f32]
}

/// Parse `WxH` (e.g. `256x256`).
pub fn parse_resolution(s: &str) -> Result<(usize, usize)> {
    let bad = || {
        ModelError::Input(format!(
            "resolution {s:?}: expected WxH with 1 <= W, H <= 8192 (e.g. 256x256)"
        ))
    };
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(bad)?;
    let w: usize = w.trim().parse().map_err(|_| bad())?;
    let h: usize = h.trim().parse().map_err(|_| bad())?;
    if !(1..=8192).contains(&w) || !(1..=8192).contains(&h) {
        return Err(bad());
    }
    Ok((w, h))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resolution_parsing() {
        assert_eq!(parse_resolution("256x128").unwrap(), (256, 128));
        assert_eq!(parse_resolution("32X24").unwrap(), (32, 24));
        for bad in ["", "256", "0x10", "10x", "ax3", "9000x10"] {
            assert!(parse_resolution(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn look_at_rejects_degenerate_input() {
        assert!(look_at([0.0; 3], [0.0; 3], [0.0, -1.0, 0.0]).is_err());
        assert!(look_at([0.0, 2.0, 0.0], [0.0; 3], [0.0, -1.0, 0.0]).is_err());
        assert!(look_at([f32::NAN, 0.0, 1.0], [0.0; 3], [0.0, -1.0, 0.0]).is_err());
    }
}
