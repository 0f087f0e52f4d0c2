//! Marching cubes, PLY and the mesh preview on analytic fields and on the synthetic scene's
//! own geometry: bounding boxes, watertightness (every edge in exactly two triangles, in
//! opposite directions), Euler characteristics, enclosed volumes and orientation.
// Closures return `pma_model::error::Result`, whose error carries candle's (large) error.
#![allow(clippy::result_large_err)]

use glam::{DMat3, DVec3};
use pma_data::skeleton::{local_to_world, rigid_inverse};
use pma_data::synth::{self, primitive::Shape};
use pma_model::tools::mesh::{
    colour_vertices, extract, marching_cubes, read_ply, render_preview, sample_grid, write_ply,
    Grid, Mesh,
};
use proptest::prelude::*;

fn field_mesh(lo: [f32; 3], hi: [f32; 3], res: usize, f: impl Fn([f32; 3]) -> f32) -> (Grid, Mesh) {
    let grid = Grid::covering(lo, hi, res, 2).unwrap();
    let mesh = extract(
        &grid,
        0.0,
        4096,
        |pts| Ok(pts.iter().map(|&p| f(p)).collect()),
        &mut |_, _| {},
    )
    .unwrap();
    (grid, mesh)
}

fn dist(a: [f32; 3], b: [f32; 3]) -> f32 {
    (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f32>().sqrt()
}

fn assert_bounds(mesh: &Mesh, lo: [f32; 3], hi: [f32; 3], tol: f32) {
    let (mlo, mhi) = mesh.bounds().expect("non-empty mesh");
    for k in 0..3 {
        assert!(
            (mlo[k] - lo[k]).abs() <= tol && (mhi[k] - hi[k]).abs() <= tol,
            "axis {k}: mesh {:?}..{:?}, expected {lo:?}..{hi:?} within {tol}",
            mlo,
            mhi
        );
    }
}

#[test]
fn sphere_is_closed_genus_zero_with_outward_normals() {
    let (c, r) = ([0.3f32, -0.2, 0.1], 0.5f32);
    let lo = c.map(|x| x - r);
    let hi = c.map(|x| x + r);
    let (grid, mesh) = field_mesh(lo, hi, 40, |p| r - dist(p, c));
    let stats = mesh.edge_stats();
    assert!(stats.is_watertight(), "{stats:?}");
    assert_eq!(mesh.euler_characteristic(), 2);
    assert_bounds(&mesh, lo, hi, grid.spacing);
    let exact = 4.0 / 3.0 * std::f64::consts::PI * (r as f64).powi(3);
    let v = mesh.signed_volume();
    assert!(v > 0.0, "normals point inward: volume {v}");
    assert!((v - exact).abs() / exact < 0.02, "volume {v} vs {exact}");
    // Every vertex lies on the sphere up to the interpolation error of a cell.
    for p in &mesh.vertices {
        assert!((dist(*p, c) - r).abs() < 0.25 * grid.spacing, "{p:?}");
    }
    // Normals point away from the centre.
    for (p, n) in mesh.vertices.iter().zip(mesh.vertex_normals()) {
        let out: f32 = (0..3).map(|k| (p[k] - c[k]) * n[k]).sum();
        assert!(out > 0.0);
    }
}

#[test]
fn off_centre_capsule_keeps_world_axes() {
    // A capsule along world x: a mix-up of x and y (the reference's exporter swaps them)
    // would show in the bounding box.
    let (a, b, r) = ([-0.6f32, 1.2, 0.4], [0.5f32, 1.2, 0.4], 0.15f32);
    let lo = [a[0] - r, a[1] - r, a[2] - r];
    let hi = [b[0] + r, b[1] + r, b[2] + r];
    let (grid, mesh) = field_mesh(lo, hi, 64, |p| {
        let t = ((p[0] - a[0]) / (b[0] - a[0])).clamp(0.0, 1.0);
        let q = [a[0] + t * (b[0] - a[0]), a[1], a[2]];
        r - dist(p, q)
    });
    assert!(mesh.edge_stats().is_watertight());
    assert_eq!(mesh.euler_characteristic(), 2);
    assert_bounds(&mesh, lo, hi, grid.spacing);
    let exact = std::f64::consts::PI * (r as f64).powi(2) * (b[0] - a[0]) as f64
        + 4.0 / 3.0 * std::f64::consts::PI * (r as f64).powi(3);
    assert!((mesh.signed_volume() - exact).abs() / exact < 0.03);
}

#[test]
fn torus_and_two_spheres_have_the_right_topology() {
    let (big, small) = (0.6f32, 0.2f32);
    let lo = [-0.8, -0.2, -0.8];
    let hi = [0.8, 0.2, 0.8];
    let (_, torus) = field_mesh(lo, hi, 48, |p| {
        let q = (p[0] * p[0] + p[2] * p[2]).sqrt() - big;
        small - (q * q + p[1] * p[1]).sqrt()
    });
    assert!(torus.edge_stats().is_watertight());
    assert_eq!(torus.euler_characteristic(), 0);

    let (_, two) = field_mesh([-1.0, -0.3, -0.3], [1.0, 0.3, 0.3], 48, |p| {
        let d1 = 0.3 - dist(p, [-0.6, 0.0, 0.0]);
        let d2 = 0.3 - dist(p, [0.6, 0.0, 0.0]);
        d1.max(d2)
    });
    assert!(two.edge_stats().is_watertight());
    assert_eq!(two.euler_characteristic(), 4);
}

#[test]
fn surface_reaching_the_grid_border_is_closed() {
    // The field is positive everywhere: only the forced-outside border closes the surface.
    let grid = Grid::covering([0.0; 3], [1.0; 3], 8, 0).unwrap();
    let mesh = marching_cubes(&vec![1.0; grid.len()], &grid, 0.0).unwrap();
    assert!(mesh.edge_stats().is_watertight());
    assert_eq!(mesh.euler_characteristic(), 2);
    assert!(mesh.signed_volume() > 0.0);
}

#[test]
fn empty_and_bad_inputs() {
    let grid = Grid::covering([0.0; 3], [1.0; 3], 6, 0).unwrap();
    let m = marching_cubes(&vec![-1.0; grid.len()], &grid, 0.0).unwrap();
    assert!(m.triangles.is_empty() && m.bounds().is_none());
    assert!(marching_cubes(&[0.0; 3], &grid, 0.0).is_err());
    assert!(marching_cubes(&vec![0.0; grid.len()], &grid, f32::NAN).is_err());
    assert!(Grid::covering([0.0; 3], [1.0; 3], 1, 0).is_err());
    assert!(Grid::covering([0.0; 3], [0.0; 3], 8, 0).is_err());
    assert!(Grid::covering([0.0; 3], [f32::INFINITY, 1.0, 1.0], 8, 0).is_err());
    assert!(Grid::covering([0.0; 3], [1e6; 3], 100_000, 0).is_err());
    // A field that returns the wrong number of values is an error, not a panic.
    assert!(sample_grid(&grid, 7, |p| Ok(vec![0.0; p.len() + 1]), &mut |_, _| {}).is_err());
    assert!(sample_grid(&grid, 0, |p| Ok(vec![0.0; p.len()]), &mut |_, _| {}).is_err());
    // NaN samples count as outside.
    let mut v = vec![-1.0f32; grid.len()];
    v[grid.len() / 2] = f32::NAN;
    assert!(marching_cubes(&v, &grid, 0.0).unwrap().triangles.is_empty());
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]
    /// Random fields are full of ambiguous faces and cells; the mesh must stay closed and
    /// consistently oriented anyway.
    #[test]
    fn random_fields_give_watertight_meshes(
        vals in prop::collection::vec(-1.0f32..1.0, 7 * 6 * 5),
        threshold in -0.5f32..0.5,
    ) {
        let grid = Grid { origin: [0.0; 3], spacing: 0.1, dims: [7, 6, 5] };
        let mesh = marching_cubes(&vals, &grid, threshold).unwrap();
        let stats = mesh.edge_stats();
        prop_assert!(stats.is_watertight(), "{:?}", stats);
        // A closed orientable surface has an even Euler characteristic.
        prop_assert_eq!(mesh.euler_characteristic() % 2, 0);
        prop_assert!(mesh.triangles.is_empty() || mesh.signed_volume() > 0.0);
    }
}

/// World-space bounding box of one synthetic part.
fn part_bounds(shape: &Shape, l2w: &glam::DMat4) -> (DVec3, DVec3) {
    let r = DMat3::from_mat4(*l2w);
    let to_world = |p: DVec3| l2w.transform_point3(p);
    match *shape {
        Shape::Capsule { a, b, radius } => {
            let (a, b) = (to_world(a), to_world(b));
            (a.min(b) - radius, a.max(b) + radius)
        }
        Shape::Ellipsoid {
            centre,
            axes,
            radii,
        } => {
            let m = r * axes;
            let c = to_world(centre);
            let half = DVec3::new(
                (m.row(0) * radii).length(),
                (m.row(1) * radii).length(),
                (m.row(2) * radii).length(),
            );
            (c - half, c + half)
        }
    }
}

#[test]
fn synthetic_figure_mesh_matches_its_geometry() {
    let rest = synth::rest_pose();
    let fig = synth::Figure::new(&rest, 0);
    let walk = synth::walk_motion(&rest).unwrap();
    let f = 20;
    let root = walk.root[f];
    let l2w = local_to_world(
        &rest,
        &walk.bones[f],
        DVec3::new(root[0] as f64, root[1] as f64, root[2] as f64),
    );
    let w2l: Vec<glam::DMat4> = l2w.iter().map(rigid_inverse).collect();
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for part in &fig.parts {
        let (a, b) = part_bounds(&part.shape, &l2w[part.joint]);
        lo = lo.min(a);
        hi = hi.max(b);
    }
    let lo32 = lo.as_vec3().to_array();
    let hi32 = hi.as_vec3().to_array();
    let grid = Grid::covering(lo32, hi32, 96, 2).unwrap();
    // Density 10 inside the figure, 0 outside; threshold 5 as PM's exporter.
    let mesh = extract(
        &grid,
        5.0,
        8192,
        |pts| {
            Ok(pts
                .iter()
                .map(|p| {
                    let p = DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64);
                    let inside = fig
                        .parts
                        .iter()
                        .any(|part| part.shape.contains(w2l[part.joint].transform_point3(p)));
                    if inside {
                        10.0
                    } else {
                        0.0
                    }
                })
                .collect())
        },
        &mut |_, _| {},
    )
    .unwrap();
    let stats = mesh.edge_stats();
    assert!(stats.is_watertight(), "{stats:?}");
    // A step field puts vertices at edge midpoints: within a cell of the true surface.
    assert_bounds(&mesh, lo32, hi32, 1.5 * grid.spacing);
    // The figure is upright in the training convention: head toward −y, so its height is y.
    let (mlo, mhi) = mesh.bounds().unwrap();
    assert!(mhi[1] - mlo[1] > 1.4, "{mlo:?}..{mhi:?}");
}

#[test]
fn ply_round_trip_keeps_geometry_and_colours() {
    let (_, mut mesh) = field_mesh([-0.5; 3], [0.5; 3], 12, |p| 0.5 - dist(p, [0.0; 3]));
    colour_vertices(&mut mesh, 17, |pts, dirs| {
        // Colour = where the view comes from, which must be the inward normal.
        Ok(pts
            .iter()
            .zip(dirs)
            .map(|(p, d)| {
                let n = dist(*p, [0.0; 3]);
                let along: f32 = (0..3).map(|k| -d[k] * p[k] / n).sum();
                assert!(along > 0.9, "view direction {d:?} at {p:?}");
                [0.25, 0.5, 1.0]
            })
            .collect())
    })
    .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.ply");
    write_ply(&mesh, &path).unwrap();
    let back = read_ply(&path).unwrap();
    assert_eq!(back.vertices, mesh.vertices);
    assert_eq!(back.triangles, mesh.triangles);
    for c in back.colours.unwrap() {
        for (x, want) in c.iter().zip([0.25, 0.5, 1.0]) {
            assert!((x - want).abs() <= 0.5 / 255.0 + 1e-6);
        }
    }
    // No temporary files are left next to the output.
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    // Garbage is an error.
    std::fs::write(&path, b"ply\nformat ascii 1.0\nend_header\n").unwrap();
    assert!(read_ply(&path).is_err());
    std::fs::write(&path, b"not a ply").unwrap();
    assert!(read_ply(&path).is_err());
}

#[test]
fn preview_shows_the_mesh_in_front_of_the_camera() {
    let (_, mesh) = field_mesh([-0.5; 3], [0.5; 3], 16, |p| 0.5 - dist(p, [0.0; 3]));
    let c2w = pma_model::render::camera_path::look_at([0.0, 0.0, 3.0], [0.0; 3], [0.0, -1.0, 0.0])
        .unwrap();
    let cam = pma_data::camera::Camera::new(32, 32, 40.0, 40.0, 16.0, 16.0, c2w).unwrap();
    let img = render_preview(&mesh, &cam, [0.0; 3]).unwrap();
    let px = |x: usize, y: usize| img[3 * (y * 32 + x)];
    assert!(px(16, 16) > 0.5, "centre is lit");
    assert_eq!(px(0, 0), 0.0, "corner is background");
    // Seen from behind, nothing.
    let c2w =
        pma_model::render::camera_path::look_at([0.0, 0.0, 3.0], [0.0, 0.0, 6.0], [0.0, -1.0, 0.0])
            .unwrap();
    let away = pma_data::camera::Camera::new(32, 32, 40.0, 40.0, 16.0, 16.0, c2w).unwrap();
    assert!(render_preview(&mesh, &away, [0.0; 3])
        .unwrap()
        .iter()
        .all(|&v| v == 0.0));
}
