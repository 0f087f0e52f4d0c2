//! `pma mesh` end to end. A tiny avatar whose density head is forced to a constant makes the
//! expected surface known exactly: the union of the posed part boxes.

use std::path::{Path, PathBuf};

use crate::run::{fails_with, ok, pma};
use candle_core::{Device, Tensor};
use pma_model::render::avatar::Avatar;
use pma_model::tools::mesh::read_ply;
use pma_model::Config;

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

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
    let dance = tmp.path().join("dance.npz");
    let src = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/pma-data/assets/motion/aist_demo.npz"
    );
    ok(pma(&[
        "convert",
        "motion",
        src,
        "-o",
        s(&dance),
        "--frames",
        "0:10",
    ]));
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
    let ds = pma_data::dataset::Dataset::read(
        &dance,
        &pma_data::dataset::ReadOptions::new(pma_data::dataset::Profile::Motion),
    )
    .unwrap();
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
    let motion = tmp.path().join("m.npz");
    let src = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/pma-data/assets/motion/aist_demo.npz"
    );
    ok(pma(&[
        "convert",
        "motion",
        src,
        "-o",
        s(&motion),
        "--frames",
        "0:3",
    ]));
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
