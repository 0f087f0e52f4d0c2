//! `pma mesh` end to end. A tiny avatar whose density head is forced to a constant makes the
//! expected surface known exactly: the union of the posed part boxes.

use std::path::{Path, PathBuf};

use crate::run::{aist_motion, fails_with, number_before, ok, pma, read_motion, s};
use candle_core::{Device, Tensor};
use pma_model::render::avatar::Avatar;
use pma_model::tools::mesh::read_ply;
use pma_model::Config;

/// A tiny avatar with density 50 everywhere the network is asked (σ weights 0, bias 50).
fn solid_model(dir: &Path) -> PathBuf {
    let a = Avatar::new(
        Config::tiny(),
        &pma_data::synth::rest_pose(),
        5,
        &Device::Cpu,
    )
    .unwrap();
    let mut t = a.tensors();
    let w = t["sigma_linear.weight"].zeros_like().unwrap();
    let b = Tensor::new(&[50f32], &Device::Cpu).unwrap();
    t.insert("sigma_linear.weight".into(), w);
    t.insert("sigma_linear.bias".into(), b);
    let solid = Avatar::from_tensors(a.config().clone(), t, &Device::Cpu).unwrap();
    let path = dir.join("solid.safetensors");
    solid.save(&path).unwrap();
    path
}

/// Bounds of the union of part boxes for `bones` at `root`, computed here from the posed
/// bone frames and the box sizes (not through the mesh code's own box list): each box is
/// `|M_j x| <= bound·s_j` with M_j = A_j·skt_j rigid, so its corners are `R_jᵀ (c − t_j)`.
fn box_bounds(model: &Path, bones: &[[f32; 3]; 24], root: [f32; 3]) -> ([f32; 3], [f32; 3]) {
    let a = Avatar::load(model, &Device::Cpu).unwrap();
    let (poses, _) = a.pose_from_bones(bones, root).unwrap();
    let frames = a.bone_frames(&poses.skts).unwrap();
    let scales = a
        .axis_scale()
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
    let bound = a.config().box_bound;
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for j in 0..24 {
        let m = frames.world_to_box_f64(0, j);
        for corner in 0..8 {
            let c: [f64; 3] = std::array::from_fn(|k| {
                let h = bound * scales[3 * j + k] as f64;
                if corner >> k & 1 == 1 {
                    h
                } else {
                    -h
                }
            });
            for axis in 0..3 {
                let x: f64 = (0..3).map(|r| m[r][axis] * (c[r] - m[r][3])).sum();
                lo[axis] = lo[axis].min(x as f32);
                hi[axis] = hi[axis].max(x as f32);
            }
        }
    }
    (lo, hi)
}

fn upright() -> [[f32; 3]; 24] {
    let mut b = [[0f32; 3]; 24];
    b[0] = [std::f32::consts::PI, 0.0, 0.0];
    b
}

#[test]
fn solid_avatar_mesh_is_the_closed_union_of_its_part_boxes() {
    let tmp = tempfile::tempdir().unwrap();
    let model = solid_model(tmp.path());
    let ply = tmp.path().join("rest.ply");
    let png = tmp.path().join("rest.png");
    let stdout = ok(pma(&[
        "mesh",
        "--model",
        s(&model),
        "--res",
        "40",
        "--preview",
        s(&png),
        "--preview-res",
        "48",
        "-o",
        s(&ply),
        "--quiet",
        "--device",
        "cpu",
    ]))
    .stdout;
    let text = String::from_utf8_lossy(&stdout);
    assert!(text.contains("watertight"), "{text}");
    let mesh = read_ply(&ply).unwrap();
    assert!(mesh.edge_stats().is_watertight());
    let colours = mesh.colours.as_ref().expect("vertex colours");
    assert_eq!(colours.len(), mesh.vertices.len());
    assert!(colours.iter().flatten().all(|c| (0.0..=1.0).contains(c)));
    let (lo, hi) = box_bounds(&model, &upright(), [0.0; 3]);
    let (mlo, mhi) = mesh.bounds().unwrap();
    let cell = (0..3).map(|k| hi[k] - lo[k]).fold(0f32, f32::max) / 39.0;
    for k in 0..3 {
        assert!(
            (mlo[k] - lo[k]).abs() <= 1.5 * cell && (mhi[k] - hi[k]).abs() <= 1.5 * cell,
            "axis {k}: mesh {mlo:?}..{mhi:?}, boxes {lo:?}..{hi:?}"
        );
    }
    // Upright in the training convention: the body's long axis is world y.
    assert!(mhi[1] - mlo[1] > 1.5 * (mhi[2] - mlo[2]));
    assert_eq!(image::image_dimensions(&png).unwrap(), (48, 48));
    let img = image::open(&png).unwrap().to_rgb8();
    assert_eq!(img.get_pixel(0, 0).0, [255, 255, 255], "background corner");
    assert_ne!(
        img.get_pixel(24, 24).0,
        [255, 255, 255],
        "the body at the centre"
    );
}

#[test]
fn mesh_of_a_retargeted_motion_frame() {
    let tmp = tempfile::tempdir().unwrap();
    let model = solid_model(tmp.path());
    let dance = aist_motion(&tmp.path().join("dance.npz"), &["--frames", "0:10"]);
    let ply = tmp.path().join("f7.ply");
    ok(pma(&[
        "mesh",
        "--model",
        s(&model),
        "--poses",
        s(&dance),
        "--frame",
        "7",
        "--res",
        "32",
        "--no-colour",
        "-o",
        s(&ply),
        "--quiet",
    ]));
    let mesh = read_ply(&ply).unwrap();
    assert!(mesh.colours.is_none());
    assert!(mesh.edge_stats().is_watertight());
    // The mesh sits where frame 7's boxes are (same rest pose: root scale 1).
    let ds = read_motion(&dance);
    let r = ds.root_locs.as_ref().unwrap().row(7).to_vec();
    let (lo, hi) = box_bounds(&model, &ds.pose_bones(7), [r[0], r[1], r[2]]);
    let (mlo, mhi) = mesh.bounds().unwrap();
    let cell = (0..3).map(|k| hi[k] - lo[k]).fold(0f32, f32::max) / 31.0;
    for k in 0..3 {
        assert!((mlo[k] - lo[k]).abs() <= 1.5 * cell && (mhi[k] - hi[k]).abs() <= 1.5 * cell);
    }
}

#[test]
fn mesh_errors_are_clear() {
    let tmp = tempfile::tempdir().unwrap();
    let model = solid_model(tmp.path());
    let ply = tmp.path().join("x.ply");
    let run = |extra: &[&str]| {
        let mut a = vec![
            "mesh",
            "--model",
            s(&model),
            "-o",
            s(&ply),
            "--quiet",
            "--res",
            "16",
        ];
        a.extend_from_slice(extra);
        pma(&a)
    };
    fails_with(
        run(&["--threshold", "1000"]),
        "no surface at density threshold 1000",
    );
    fails_with(
        pma(&["mesh", "--model", s(&model), "-o", s(&ply), "--res", "1"]),
        "--res must be in 2..=1024",
    );
    let motion = aist_motion(&tmp.path().join("m.npz"), &["--frames", "0:3"]);
    fails_with(
        run(&["--poses", s(&motion), "--frame", "3"]),
        "--frame 3 is past the 3 pose(s)",
    );
    fails_with(
        pma(&[
            "mesh",
            "--model",
            s(&tmp.path().join("none.safetensors")),
            "-o",
            s(&ply),
        ]),
        "none.safetensors",
    );
    assert!(!ply.exists(), "nothing is written on failure");
}

/// A tiny avatar whose density has structure: the density head's weights scaled up and its
/// bias lowered, so that relu(σ) is well above the surface threshold in parts of the body
/// and exactly 0 elsewhere, including far from the bones (where the network returns its
/// constant). With these values about a third of the grid's cells end up occupied.
fn structured_model(dir: &Path) -> PathBuf {
    let a = Avatar::new(
        Config {
            n_framecodes: 2,
            ..Config::tiny()
        },
        &pma_data::synth::rest_pose(),
        3,
        &Device::Cpu,
    )
    .unwrap();
    let mut t = a.tensors();
    let w = (t["sigma_linear.weight"].clone() * 200.0).unwrap();
    let b = Tensor::new(&[-16f32], &Device::Cpu).unwrap();
    t.insert("sigma_linear.weight".into(), w);
    t.insert("sigma_linear.bias".into(), b);
    let path = dir.join("structured.safetensors");
    Avatar::from_tensors(a.config().clone(), t, &Device::Cpu)
        .unwrap()
        .save(&path)
        .unwrap();
    path
}

/// `pma mesh --occupancy` on a model whose grid `pma occupancy build` made from its own
/// density: the grid leaves out a fifth of the in-box points and the mesh stays the mesh.
///
/// Tolerance: a point is left out when every joint whose window reaches it saw at most the
/// grid's threshold τ = 0.5 in its (dilated) cell. If that held for the point itself, zeroing
/// it keeps every grid point on the same side of the surface threshold 5 (same triangles),
/// and on an edge from a (σ ≥ 5) to b (σ_b ≤ τ, now 0) the interpolated vertex moves by
/// σ_b (σ_a − 5) / (σ_a (σ_a − σ_b)) ≤ τ / 5 of the edge: 0.1 × the grid spacing. A grid
/// that cut the body would change the triangles or move vertices farther. (Measured: the two
/// meshes are identical; the skipped points had density exactly 0.)
#[test]
fn mesh_with_the_occupancy_grid_is_the_mesh_without_it() {
    let tmp = tempfile::tempdir().unwrap();
    let model = structured_model(tmp.path());
    let scene = crate::run::tiny_scene(&tmp.path().join("scene"), 1);
    let gridded = tmp.path().join("gridded.safetensors");
    ok(pma(&[
        "occupancy",
        "build",
        "--model",
        s(&model),
        "--data",
        s(&scene),
        "--poses",
        "3",
        "--out",
        s(&gridded),
        "--quiet",
    ]));
    let mesh = |model: &Path, extra: &[&str], name: &str| {
        let ply = tmp.path().join(name);
        let mut a = vec![
            "mesh",
            "--model",
            s(model),
            "--poses",
            s(&scene),
            "--frame",
            "1",
            "--res",
            "48",
            "-o",
            s(&ply),
            "--quiet",
        ];
        a.extend_from_slice(extra);
        (pma(&a), ply)
    };
    let (out, plain_ply) = mesh(&gridded, &[], "plain.ply");
    let plain_stdout = String::from_utf8_lossy(&ok(out).stdout).to_string();
    assert!(!plain_stdout.contains("occupancy grid"), "{plain_stdout}");
    let (out, occ_ply) = mesh(&gridded, &["--occupancy"], "occ.ply");
    let stdout = String::from_utf8_lossy(&ok(out).stdout).to_string();
    let line = stdout
        .lines()
        .find(|l| l.starts_with("occupancy grid: "))
        .unwrap_or_else(|| panic!("no grid line in\n{stdout}"));
    let (skipped, points) = (
        number_before(line, "of"),
        number_before(line, "density points"),
    );
    assert!(skipped * 10 >= points && skipped < points, "{line}");

    let (plain, occ) = (read_ply(&plain_ply).unwrap(), read_ply(&occ_ply).unwrap());
    assert!(plain.triangles.len() > 100, "a real surface");
    assert!(
        plain.triangles == occ.triangles && plain.vertices.len() == occ.vertices.len(),
        "the grid changed the surface: {} / {} triangles, {} / {} vertices",
        plain.triangles.len(),
        occ.triangles.len(),
        plain.vertices.len(),
        occ.vertices.len()
    );
    let spacing: f32 = {
        let at = stdout.find("spacing ").unwrap() + "spacing ".len();
        stdout[at..].split(')').next().unwrap().parse().unwrap()
    };
    let moved = plain
        .vertices
        .iter()
        .zip(&occ.vertices)
        .flat_map(|(a, b)| (0..3).map(move |k| (a[k] - b[k]).abs()))
        .fold(0f32, f32::max);
    println!("{line}; largest vertex move {moved} (spacing {spacing})");
    assert!(moved <= 0.1 * spacing, "moved {moved}, spacing {spacing}");

    // A model without a grid: refused with exit 2 and one line.
    let (out, _) = mesh(&model, &["--occupancy"], "none.ply");
    assert_eq!(out.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&out.stderr).to_string();
    assert_eq!(stderr.trim_end().lines().count(), 1, "{stderr}");
    assert!(stderr.contains("no occupancy grid"), "{stderr}");
    fails_with(out, "--occupancy: ");
    assert!(!tmp.path().join("none.ply").exists());
}
