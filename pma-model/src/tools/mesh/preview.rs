//! A quick shaded picture of a mesh.

use pma_data::camera::Camera;

use super::*;
use crate::error::Result;

/// Rasterise `mesh` through `cam` with a z-buffer: vertex colours (grey without), lit by a
/// head light. Returns [H,W,3] in [0,1] over `background`.
pub fn render_preview(mesh: &Mesh, cam: &Camera, background: [f32; 3]) -> Result<Vec<f32>> {
    cam.validate()?;
    let (w, h) = (cam.width, cam.height);
    let mut rgb: Vec<f32> = (0..w * h).flat_map(|_| background).collect();
    let mut depth = vec![f64::INFINITY; w * h];
    let e = cam.world_to_cv();
    let normals = mesh.vertex_normals();
    let proj: Vec<Option<[f64; 3]>> = mesh
        .vertices
        .iter()
        .map(|p| {
            let q = e * glam::DVec4::new(p[0] as f64, p[1] as f64, p[2] as f64, 1.0);
            (q.z > 1e-6).then(|| {
                [
                    cam.fx as f64 * q.x / q.z + cam.cx as f64,
                    cam.fy as f64 * q.y / q.z + cam.cy as f64,
                    q.z,
                ]
            })
        })
        .collect();
    let o = cam.origin().map(f64::from);
    let shade = |i: usize| -> [f32; 3] {
        let p = mesh.vertices[i].map(f64::from);
        let mut l = [o[0] - p[0], o[1] - p[1], o[2] - p[2]];
        let n = (l[0] * l[0] + l[1] * l[1] + l[2] * l[2]).sqrt().max(1e-12);
        l = l.map(|x| x / n);
        let nn = normals[i];
        let lam = (0..3).map(|k| nn[k] as f64 * l[k]).sum::<f64>().abs();
        let base = mesh.colours.as_ref().map_or([0.8; 3], |c| c[i]);
        base.map(|c| c * (0.35 + 0.65 * lam as f32))
    };
    for t in &mesh.triangles {
        let (Some(a), Some(b), Some(c)) = (
            proj[t[0] as usize],
            proj[t[1] as usize],
            proj[t[2] as usize],
        ) else {
            continue;
        };
        let area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
        if area.abs() < 1e-12 {
            continue;
        }
        let cols = [
            shade(t[0] as usize),
            shade(t[1] as usize),
            shade(t[2] as usize),
        ];
        let x0 = a[0].min(b[0]).min(c[0]).floor().max(0.0) as usize;
        let y0 = a[1].min(b[1]).min(c[1]).floor().max(0.0) as usize;
        let x1 = (a[0].max(b[0]).max(c[0]).ceil() as i64).min(w as i64 - 1);
        let y1 = (a[1].max(b[1]).max(c[1]).ceil() as i64).min(h as i64 - 1);
        if x1 < 0 || y1 < 0 {
            continue;
        }
        for y in y0..=y1 as usize {
            for x in x0..=x1 as usize {
                let (px, py) = (x as f64, y as f64);
                let w0 = ((b[0] - px) * (c[1] - py) - (b[1] - py) * (c[0] - px)) / area;
                let w1 = ((c[0] - px) * (a[1] - py) - (c[1] - py) * (a[0] - px)) / area;
                let w2 = 1.0 - w0 - w1;
                if w0 < 0.0 || w1 < 0.0 || w2 < 0.0 {
                    continue;
                }
                let z = w0 * a[2] + w1 * b[2] + w2 * c[2];
                let p = y * w + x;
                if z < depth[p] {
                    depth[p] = z;
                    for k in 0..3 {
                        rgb[3 * p + k] = (w0 as f32 * cols[0][k]
                            + w1 as f32 * cols[1][k]
                            + w2 as f32 * cols[2][k])
                            .clamp(0.0, 1.0);
                    }
                }
            }
        }
    }
    Ok(rgb)
}
