//! The per-frame bounding cylinder `cyls = (x_c, z_c, r, y_top, y_bot)` and
//! its 2-D pixel box, which bound where rays are sampled.
//!
//! The cylinder axis is always world y (ground plane x–z): the reference's
//! box and near/far code hard-code it, so only head directions ±y exist.

use glam::{DVec3, DVec4};

use crate::camera::Camera;
use crate::skeleton::{vec3, Joints};

/// Which way the head points along world y.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HeadDir {
    /// −y: H36M-ZJU, PerfCap, Mixamo, SURREAL (the training convention).
    NegY,
    /// +y: AIST++.
    PosY,
}

impl HeadDir {
    /// From a `head_dir` vector; only (0,±1,0) (within 1e-4) is supported.
    pub fn from_vector(v: [f32; 3]) -> Option<HeadDir> {
        let close = |a: f32, b: f32| (a - b).abs() <= 1e-4;
        if close(v[0], 0.0) && close(v[2], 0.0) {
            if close(v[1], -1.0) {
                return Some(HeadDir::NegY);
            }
            if close(v[1], 1.0) {
                return Some(HeadDir::PosY);
            }
        }
        None
    }

    /// The unit vector.
    pub fn vector(self) -> [f32; 3] {
        match self {
            HeadDir::NegY => [0.0, -1.0, 0.0],
            HeadDir::PosY => [0.0, 1.0, 0.0],
        }
    }

    fn sign(self) -> f64 {
        match self {
            HeadDir::NegY => -1.0,
            HeadDir::PosY => 1.0,
        }
    }
}

/// Cylinder construction parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CylinderParams {
    /// Extension E in scene units (250 mm × 0.001 in all shipped data).
    pub extend: f64,
    /// Head-side ratio a.
    pub top_ratio: f64,
    /// Feet-side ratio b.
    pub bottom_ratio: f64,
    pub head: HeadDir,
}

impl CylinderParams {
    /// The stored `cyls` (E 0.25, a 1.0, b 0.25).
    pub fn training(head: HeadDir) -> Self {
        CylinderParams {
            extend: 0.25,
            top_ratio: 1.0,
            bottom_ratio: 0.25,
            head,
        }
    }

    /// The render / evaluation valid-pixel box (`kp_to_valid_rays`: a 1.6, b 1.1).
    pub fn render(head: HeadDir) -> Self {
        CylinderParams {
            extend: 0.25,
            top_ratio: 1.6,
            bottom_ratio: 1.1,
            head,
        }
    }
}

/// `(x_c, z_c, r, y_top, y_bot)` for one frame's joints `[24][3]`.
pub fn cylinder_from_joints(kp: &Joints, params: &CylinderParams) -> [f32; 5] {
    let root = vec3(&kp[0]);
    let s = params.head.sign();
    let e = params.extend;
    let mut r: f64 = 0.0;
    let mut hmax = f64::NEG_INFINITY; // max over joints of s·y: the head end
    let mut hmin = f64::INFINITY;
    for k in kp {
        let p = vec3(k);
        r = r.max(((p.x - root.x).powi(2) + (p.z - root.z).powi(2)).sqrt());
        hmax = hmax.max(s * p.y);
        hmin = hmin.min(s * p.y);
    }
    let top = s * (hmax + e * params.top_ratio);
    let bot = s * (hmin - e * params.bottom_ratio);
    [
        root.x as f32,
        root.z as f32,
        (r + e) as f32,
        top as f32,
        bot as f32,
    ]
}

/// A pixel rectangle: columns `x0 ≤ x < x1`, rows `y0 ≤ y < y1`. The
/// bottom-right bound is exclusive, as in the reference, so the last row and
/// column of the projected box are never included.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PixelBox {
    pub x0: i64,
    pub y0: i64,
    pub x1: i64,
    pub y1: i64,
}

impl PixelBox {
    pub fn width(&self) -> usize {
        (self.x1 - self.x0).max(0) as usize
    }
    pub fn height(&self) -> usize {
        (self.y1 - self.y0).max(0) as usize
    }
    pub fn is_empty(&self) -> bool {
        self.width() == 0 || self.height() == 0
    }
    pub fn contains(&self, x: usize, y: usize) -> bool {
        let (x, y) = (x as i64, y as i64);
        x >= self.x0 && x < self.x1 && y >= self.y0 && y < self.y1
    }
}

/// Project the cylinder's two 50-point cap circles and take their pixel
/// bounding box, optionally scaled about its
/// centre (the training box sampler uses 1.3).
///
/// cyl: `[5]`. Returns `None` when a cap point is not in front of the camera
/// (the reference does not handle that case).
pub fn cylinder_box(cyl: &[f32; 5], cam: &Camera, scale: Option<f64>) -> Option<PixelBox> {
    const N: usize = 50;
    let e = cam.world_to_cv();
    let (xc, zc, r) = (cyl[0] as f64, cyl[1] as f64, cyl[2] as f64);
    let (mut umin, mut umax) = (f64::INFINITY, f64::NEG_INFINITY);
    let (mut vmin, mut vmax) = (f64::INFINITY, f64::NEG_INFINITY);
    for k in 0..N {
        // linspace(0, 2π, 50), both ends included.
        let a = 2.0 * std::f64::consts::PI * k as f64 / (N - 1) as f64;
        for y in [cyl[3] as f64, cyl[4] as f64] {
            let p = DVec3::new(xc + r * a.cos(), y, zc + r * a.sin());
            let c = e * DVec4::new(p.x, p.y, p.z, 1.0);
            if c.z <= 0.0 {
                return None;
            }
            // No principal point here: the reference adds int(cx), int(cy) after rounding.
            let u = cam.fx as f64 * c.x / c.z;
            let v = cam.fy as f64 * c.y / c.z;
            umin = umin.min(u);
            umax = umax.max(u);
            vmin = vmin.min(v);
            vmax = vmax.max(v);
        }
    }
    let (ox, oy) = (cam.cx.trunc() as i64, cam.cy.trunc() as i64);
    let (mut x0, mut x1) = (umin.floor() as i64 + ox, umax.ceil() as i64 + ox);
    let (mut y0, mut y1) = (vmin.floor() as i64 + oy, vmax.ceil() as i64 + oy);
    if let Some(s) = scale {
        // Scaled about the midpoint of the already-offset corners; the new
        // corners are truncated to integers like the reference's int cast.
        let (mx, my) = ((x0 + x1) as f64 * 0.5, (y0 + y1) as f64 * 0.5);
        let (hx, hy) = (0.5 * (x1 - x0) as f64 * s, 0.5 * (y1 - y0) as f64 * s);
        x0 = (mx - hx) as i64;
        x1 = (mx + hx) as i64;
        y0 = (my - hy) as i64;
        y1 = (my + hy) as i64;
    }
    let (w, h) = (cam.width as i64, cam.height as i64);
    Some(PixelBox {
        x0: x0.clamp(0, w - 1),
        y0: y0.clamp(0, h - 1),
        x1: x1.clamp(0, w - 1),
        y1: y1.clamp(0, h - 1),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn head_dir_sets_top_side() {
        let mut kp = [[0.0f32; 3]; 24];
        for (j, k) in kp.iter_mut().enumerate() {
            k[1] = j as f32 * 0.1; // y from 0 to 2.3
            k[0] = if j == 5 { 0.3 } else { 0.0 };
        }
        let down = cylinder_from_joints(&kp, &CylinderParams::training(HeadDir::NegY));
        assert!((down[2] - 0.55).abs() < 1e-6);
        assert!((down[3] - (0.0 - 0.25)).abs() < 1e-6, "{down:?}");
        assert!((down[4] - (2.3 + 0.0625)).abs() < 1e-6, "{down:?}");
        let up = cylinder_from_joints(&kp, &CylinderParams::training(HeadDir::PosY));
        assert!((up[3] - (2.3 + 0.25)).abs() < 1e-6, "{up:?}");
        assert!((up[4] - (0.0 - 0.0625)).abs() < 1e-6, "{up:?}");
    }
}
