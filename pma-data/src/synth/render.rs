//! Analytic ray tracing of the posed figure: one ray per pixel through the
//! pixel's integer coordinates (docs/conventions.md, "Cameras"),
//! nearest hit over all parts, Lambert shading under one fixed directional
//! light. The mask is exactly "this pixel's ray hits a part".

use glam::{DMat3, DMat4, DVec3};

use super::figure::Figure;
use crate::camera::Camera;
use crate::skeleton::N_JOINTS;

/// A fixed world-space directional light plus ambient term.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Light {
    /// Unit vector from the surface toward the light (world).
    pub dir: DVec3,
    pub ambient: f64,
    pub diffuse: f64,
}

impl Default for Light {
    /// Light from above (world −y is up), front-left; ambient high enough
    /// that textures stay readable on the shadowed side.
    fn default() -> Self {
        Light {
            dir: DVec3::new(0.35, -1.0, 0.55).normalize(),
            ambient: 0.45,
            diffuse: 0.55,
        }
    }
}

/// One rendered image.
#[derive(Clone, Debug, PartialEq)]
pub struct Rendered {
    /// RGB, `[H·W·3]` row-major; black where nothing is hit.
    pub rgb: Vec<u8>,
    /// `[H·W]`, 1 where a ray hits the figure, else 0.
    pub mask: Vec<u8>,
}

/// Inclusive pixel rectangle a part can cover, from its bounding sphere.
/// The sphere lies inside the camera-aligned cube around it; the cube's
/// projected corners bound the sphere's image. `None`: the part is
/// entirely off-screen.
fn screen_rect(cam: &Camera, w2cv: &DMat4, centre: DVec3, radius: f64) -> Option<[usize; 4]> {
    let (w, h) = (cam.width as f64, cam.height as f64);
    let c = w2cv.transform_point3(centre);
    if c.z - radius <= 1e-9 {
        // Straddles or is behind the camera plane: no projective bound.
        return Some([0, 0, cam.width - 1, cam.height - 1]);
    }
    let (mut u0, mut u1, mut v0, mut v1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for sx in [-1.0, 1.0] {
        for sy in [-1.0, 1.0] {
            for sz in [-1.0, 1.0] {
                let p = c + DVec3::new(sx, sy, sz) * radius;
                let u = cam.fx as f64 * p.x / p.z + cam.cx as f64;
                let v = cam.fy as f64 * p.y / p.z + cam.cy as f64;
                u0 = u0.min(u);
                u1 = u1.max(u);
                v0 = v0.min(v);
                v1 = v1.max(v);
            }
        }
    }
    let (x0, x1) = (u0.floor().max(0.0), u1.ceil().min(w - 1.0));
    let (y0, y1) = (v0.floor().max(0.0), v1.ceil().min(h - 1.0));
    if x0 > x1 || y0 > y1 {
        return None;
    }
    Some([x0 as usize, y0 as usize, x1 as usize, y1 as usize])
}

/// Renders `fig` posed by the joint local-to-world transforms `l2w`.
pub fn render(fig: &Figure, l2w: &[DMat4; N_JOINTS], cam: &Camera, light: &Light) -> Rendered {
    let (w, h) = (cam.width, cam.height);
    let o = DVec3::from(cam.origin().map(f64::from));
    let dirs: Vec<DVec3> = (0..w * h)
        .map(|p| DVec3::from(cam.ray_dir(p % w, p / w, true).map(f64::from)))
        .collect();
    let w2cv = cam.world_to_cv();

    // Nearest hit per pixel: (t, part index).
    let mut best_t = vec![f64::INFINITY; w * h];
    let mut best_part = vec![usize::MAX; w * h];
    let w2l: Vec<DMat4> = l2w.iter().map(|m| m.inverse()).collect();
    for (k, part) in fig.parts.iter().enumerate() {
        let (c_local, radius) = part.shape.bounding_sphere();
        let c_world = l2w[part.joint].transform_point3(c_local);
        let Some([x0, y0, x1, y1]) = screen_rect(cam, &w2cv, c_world, radius) else {
            continue;
        };
        let to_local = &w2l[part.joint];
        let o_local = to_local.transform_point3(o);
        for y in y0..=y1 {
            for x in x0..=x1 {
                let p = y * w + x;
                let d_local = to_local.transform_vector3(dirs[p]);
                if let Some(t) = part.shape.intersect(o_local, d_local) {
                    if t < best_t[p] {
                        best_t[p] = t;
                        best_part[p] = k;
                    }
                }
            }
        }
    }

    let mut rgb = vec![0u8; w * h * 3];
    let mut mask = vec![0u8; w * h];
    for p in 0..w * h {
        let k = best_part[p];
        if k == usize::MAX {
            continue;
        }
        let part = &fig.parts[k];
        let l2w_j = &l2w[part.joint];
        let to_local = &w2l[part.joint];
        let hit = to_local.transform_point3(o + dirs[p] * best_t[p]);
        let normal = part.shape.normal(hit);
        let light_local = DMat3::from_mat4(*l2w_j).transpose() * light.dir;
        let shade = light.ambient + light.diffuse * normal.dot(light_local).max(0.0);
        let albedo = part.texture.albedo(&part.tex_point(hit));
        for c in 0..3 {
            rgb[3 * p + c] = (albedo[c] * shade * 255.0).round().clamp(0.0, 255.0) as u8;
        }
        mask[p] = 1;
    }
    Rendered { rgb, mask }
}

/// Grows a {0,1} mask by `radius` pixels (square neighbourhood), the
/// "sampling mask" band around the silhouette.
pub fn dilate(mask: &[u8], width: usize, height: usize, radius: usize) -> Vec<u8> {
    // Separable: max over rows, then over columns.
    let mut rows = vec![0u8; mask.len()];
    for y in 0..height {
        for x in 0..width {
            let lo = x.saturating_sub(radius);
            let hi = (x + radius).min(width - 1);
            rows[y * width + x] = mask[y * width + lo..=y * width + hi]
                .iter()
                .copied()
                .max()
                .unwrap_or(0);
        }
    }
    let mut out = vec![0u8; mask.len()];
    for y in 0..height {
        let lo = y.saturating_sub(radius);
        let hi = (y + radius).min(height - 1);
        for x in 0..width {
            out[y * width + x] = (lo..=hi).map(|yy| rows[yy * width + x]).max().unwrap_or(0);
        }
    }
    out
}
