//! Pinhole cameras and per-pixel rays (docs/conventions.md, "Cameras").
//!
//! `c2w` uses the OpenGL/NeRF axes: camera +x right, +y up, looking along −z.
//! Pixel `(x, y)` lies at integer coordinates (no +0.5): the ray through it is
//! `d_cam = ((x−cx)/fx, −(y−cy)/fy, −1)`. There is no skew and no distortion.

use glam::{DMat3, DMat4, DVec3, DVec4};

use crate::error::{DataError, Result};
use crate::skeleton::mat4_from_rows;

/// Tolerance on `max|RᵀR − I|` for a rotation block.
pub const ORTHONORMAL_TOL: f64 = 1e-4;
/// Tolerance on the last row `(0,0,0,1)` of a rigid transform.
pub const LAST_ROW_TOL: f64 = 1e-6;

/// One pinhole camera.
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    /// Image width W (columns).
    pub width: usize,
    /// Image height H (rows).
    pub height: usize,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    /// Camera-to-world, row-major `[4][4]`, OpenGL camera axes.
    pub c2w: [[f32; 4]; 4],
}

/// Why a 4×4 matrix is not a rigid transform.
#[derive(Debug, Clone, PartialEq)]
pub struct RigidDefect {
    pub problem: String,
    pub expected: String,
    pub found: String,
}

/// Check that `m` (row-major) is `[R | t]` with R a proper rotation and last
/// row (0,0,0,1): finite, `max|RᵀR − I| ≤ 1e-4`, `det R > 0`.
pub fn check_rigid(m: &[[f32; 4]; 4]) -> std::result::Result<(), RigidDefect> {
    if let Some(v) = m.iter().flatten().find(|v| !v.is_finite()) {
        return Err(RigidDefect {
            problem: "non-finite entry".into(),
            expected: "finite values".into(),
            found: v.to_string(),
        });
    }
    let last = m[3];
    let want = [0.0f32, 0.0, 0.0, 1.0];
    let dev = last
        .iter()
        .zip(want)
        .map(|(a, b)| (*a as f64 - b as f64).abs())
        .fold(0.0, f64::max);
    if dev > LAST_ROW_TOL {
        return Err(RigidDefect {
            problem: "last row is not (0,0,0,1)".into(),
            expected: format!("(0,0,0,1) within {LAST_ROW_TOL:e}"),
            found: format!("{last:?}"),
        });
    }
    let r = DMat3::from_mat4(mat4_from_rows(m));
    let e = r.transpose() * r - DMat3::IDENTITY;
    let err = e
        .to_cols_array()
        .iter()
        .map(|v| v.abs())
        .fold(0.0, f64::max);
    if err > ORTHONORMAL_TOL {
        return Err(RigidDefect {
            problem: "rotation block is not orthonormal".into(),
            expected: format!("max|RᵀR − I| <= {ORTHONORMAL_TOL:e}"),
            found: format!("{err:e}"),
        });
    }
    let det = r.determinant();
    if det < 0.0 {
        return Err(RigidDefect {
            problem: "rotation block is a reflection".into(),
            expected: "det R > 0".into(),
            found: format!("det R = {det:.6}"),
        });
    }
    Ok(())
}

impl Camera {
    /// Build and validate a camera.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        width: usize,
        height: usize,
        fx: f32,
        fy: f32,
        cx: f32,
        cy: f32,
        c2w: [[f32; 4]; 4],
    ) -> Result<Self> {
        let cam = Camera {
            width,
            height,
            fx,
            fy,
            cx,
            cy,
            c2w,
        };
        cam.validate()?;
        Ok(cam)
    }

    /// Reject cameras that would produce garbage rays: empty image,
    /// non-positive or non-finite focal, non-finite centre, non-rigid `c2w`.
    pub fn validate(&self) -> Result<()> {
        let bad = |problem: &str, expected: &str, found: String| DataError::Camera {
            problem: problem.into(),
            expected: expected.into(),
            found,
        };
        if self.width == 0 || self.height == 0 {
            return Err(bad(
                "empty image",
                "width and height >= 1",
                format!("{}x{}", self.width, self.height),
            ));
        }
        for (name, f) in [("fx", self.fx), ("fy", self.fy)] {
            if !(f.is_finite() && f > 0.0) {
                return Err(bad(
                    "focal length",
                    "finite and > 0",
                    format!("{name} = {f}"),
                ));
            }
        }
        for (name, c) in [("cx", self.cx), ("cy", self.cy)] {
            if !c.is_finite() {
                return Err(bad("principal point", "finite", format!("{name} = {c}")));
            }
        }
        check_rigid(&self.c2w).map_err(|d| DataError::Camera {
            problem: format!("c2w: {}", d.problem),
            expected: d.expected,
            found: d.found,
        })
    }

    /// Camera-to-world as glam f64.
    pub fn c2w_f64(&self) -> DMat4 {
        mat4_from_rows(&self.c2w)
    }

    /// Camera centre in world coordinates.
    pub fn origin(&self) -> [f32; 3] {
        [self.c2w[0][3], self.c2w[1][3], self.c2w[2][3]]
    }

    /// World direction of the ray through pixel `(x, y)`; unit length when
    /// `normalize`, otherwise its camera-space z component is −1.
    pub fn ray_dir(&self, x: usize, y: usize, normalize: bool) -> [f32; 3] {
        let d_cam = DVec3::new(
            (x as f64 - self.cx as f64) / self.fx as f64,
            -(y as f64 - self.cy as f64) / self.fy as f64,
            -1.0,
        );
        let mut d = DMat3::from_mat4(self.c2w_f64()) * d_cam;
        if normalize {
            d = d.normalize();
        }
        [d.x as f32, d.y as f32, d.z as f32]
    }

    /// Rays through flat pixel indices `p = y·W + x`.
    /// Returns (origins `[R][3]`, directions `[R][3]`).
    pub fn rays(&self, pixels: &[usize], normalize: bool) -> (Vec<[f32; 3]>, Vec<[f32; 3]>) {
        let o = self.origin();
        let dirs = pixels
            .iter()
            .map(|&p| self.ray_dir(p % self.width, p / self.width, normalize))
            .collect();
        (vec![o; pixels.len()], dirs)
    }

    /// OpenCV world→camera extrinsic `E = (c2w·diag(1,−1,−1,1))⁻¹`
    /// (x right, y down, z forward).
    pub fn world_to_cv(&self) -> DMat4 {
        let flip = DMat4::from_diagonal(DVec4::new(1.0, -1.0, -1.0, 1.0));
        crate::skeleton::rigid_inverse(&(self.c2w_f64() * flip))
    }

    /// A world point in OpenGL camera coordinates (`c2w⁻¹·X`); in front of
    /// the camera means z < 0.
    pub fn to_camera_gl(&self, x: [f32; 3]) -> DVec3 {
        let p = crate::skeleton::rigid_inverse(&self.c2w_f64())
            * DVec4::new(x[0] as f64, x[1] as f64, x[2] as f64, 1.0);
        p.truncate()
    }

    /// Pixel coordinates `(u, v)` of a world point, or `None` when it is not
    /// in front of the camera.
    pub fn project(&self, x: [f32; 3]) -> Option<[f64; 2]> {
        let p = self.world_to_cv() * DVec4::new(x[0] as f64, x[1] as f64, x[2] as f64, 1.0);
        if p.z <= 0.0 {
            return None;
        }
        Some([
            self.fx as f64 * p.x / p.z + self.cx as f64,
            self.fy as f64 * p.y / p.z + self.cy as f64,
        ])
    }

    /// The same camera for images of `width × height` (intrinsics scaled
    /// per axis).
    pub fn resized(&self, width: usize, height: usize) -> Camera {
        let sx = width as f32 / self.width as f32;
        let sy = height as f32 / self.height as f32;
        Camera {
            width,
            height,
            fx: self.fx * sx,
            fy: self.fy * sy,
            cx: self.cx * sx,
            cy: self.cy * sy,
            c2w: self.c2w,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam() -> Camera {
        let mut c2w = [[0.0f32; 4]; 4];
        // Looking along world +z from z = −5: camera z axis = world −z.
        c2w[0] = [1.0, 0.0, 0.0, 0.0];
        c2w[1] = [0.0, -1.0, 0.0, 0.0];
        c2w[2] = [0.0, 0.0, -1.0, -5.0];
        c2w[3] = [0.0, 0.0, 0.0, 1.0];
        Camera::new(64, 48, 50.0, 60.0, 32.0, 24.0, c2w).unwrap()
    }

    #[test]
    fn projection_inverts_rays() {
        let c = cam();
        for (x, y) in [(0usize, 0usize), (10, 40), (63, 47)] {
            let d = c.ray_dir(x, y, false);
            let o = c.origin();
            let p = [o[0] + 3.0 * d[0], o[1] + 3.0 * d[1], o[2] + 3.0 * d[2]];
            let uv = c.project(p).unwrap();
            assert!((uv[0] - x as f64).abs() < 1e-4 && (uv[1] - y as f64).abs() < 1e-4);
            assert!(c.to_camera_gl(p).z < 0.0);
        }
    }

    #[test]
    fn rejects_bad_focal_and_reflection() {
        let mut c = cam();
        c.fx = 0.0;
        assert!(c.validate().is_err());
        let mut c = cam();
        c.c2w[0][0] = -1.0; // det −1
        assert!(matches!(c.validate(), Err(DataError::Camera { .. })));
    }
}
