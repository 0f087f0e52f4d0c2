//! `pma forward` end to end: golden inputs in, golden outputs out; bad batches rejected.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::Output;

use crate::run::{ok, pma, s};
use candle_core::{DType, Device, Tensor};
use pma_data::dataset::npz::{MemberData, NpyData, NpzReader, NpzWriter};

fn fixtures() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("fixtures/golden")
}

/// The golden case's tensors.
fn golden() -> HashMap<String, Tensor> {
    candle_core::safetensors::load(fixtures().join("golden.safetensors"), &Device::Cpu).unwrap()
}

/// `pma forward --model MODEL --batch BATCH --out OUT EXTRA...`.
fn forward(model: &Path, batch: &Path, out: &Path, extra: &[&str]) -> Output {
    let args = [
        "forward",
        "--model",
        s(model),
        "--batch",
        s(batch),
        "--out",
        s(out),
    ];
    pma(&[&args[..], extra].concat())
}

pub(crate) fn write_batch(path: &Path, skip: Option<&str>) {
    let g = golden();
    let file = std::fs::File::create(path).unwrap();
    let mut w = NpzWriter::new(file, false, path.display().to_string());
    for key in [
        "rays_o",
        "rays_d",
        "kp3d",
        "skts",
        "bones",
        "cyls",
        "bgs",
        "rest_pose",
        "cam_idxs",
    ] {
        if Some(key) == skip {
            continue;
        }
        let t: &Tensor = &g[&format!("input/{key}")];
        if t.dtype() == DType::I64 {
            let v = t.flatten_all().unwrap().to_vec1::<i64>().unwrap();
            w.add(key, t.dims(), MemberData::I64(&v)).unwrap();
        } else {
            let v = t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            w.add(key, t.dims(), MemberData::F32(&v)).unwrap();
        }
    }
    w.finish().unwrap();
}

#[test]
fn forward_reproduces_golden_outputs() {
    let dir = tempfile::tempdir().unwrap();
    let batch = dir.path().join("batch.npz");
    let out = dir.path().join("out.npz");
    write_batch(&batch, None);
    ok(forward(
        &fixtures().join("model.safetensors"),
        &batch,
        &out,
        &[],
    ));
    let g = golden();
    let mut r = NpzReader::open(&out).unwrap();
    for (ours, reference) in [
        ("rgb_map", "out/rgb_map"),
        ("acc_map", "out/acc_map"),
        ("rgb0", "out/rgb0"),
        ("z_vals", "raycast/z_vals_merged"),
        ("raw", "render_coarse/raw"),
    ] {
        let a = r.read(ours).unwrap();
        let NpyData::F32(v) = a.data else {
            panic!("{ours} is not f32")
        };
        let refv = g[reference]
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        assert_eq!(v.len(), refv.len(), "{ours}");
        let err = v
            .iter()
            .zip(&refv)
            .fold(0f32, |m, (x, y)| m.max((x - y).abs() / y.abs().max(1.0)));
        assert!(err <= 1e-4, "{ours}: max error {err:e}");
    }
}

#[test]
fn forward_rejects_a_batch_without_skts() {
    let dir = tempfile::tempdir().unwrap();
    let batch = dir.path().join("batch.npz");
    let out = dir.path().join("out.npz");
    write_batch(&batch, Some("skts"));
    let o = forward(&fixtures().join("model.safetensors"), &batch, &out, &[]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("skts"), "error should name the key: {err}");
    assert!(!out.exists(), "no output on failure");
}

/// The golden batch grown to `rays` rays in `poses` per-pose blocks: directions of the golden
/// rays, nudged per copy so no two rays coincide; later blocks get slightly bent bones.
fn write_grown_batch(path: &Path, rays: usize, poses: usize) {
    let g = golden();
    let f = |k: &str| {
        g[&format!("input/{k}")]
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap()
    };
    let cams = g["input/cam_idxs"]
        .flatten_all()
        .unwrap()
        .to_vec1::<i64>()
        .unwrap();
    let n0 = cams.len();
    let per_ray = |v: &[f32], w: usize, block: &dyn Fn(usize, usize, f32) -> f32| {
        (0..rays)
            .flat_map(|i| (0..w).map(move |c| (i, c)))
            .map(|(i, c)| block(i, c, v[(i % n0) * w + c]))
            .collect::<Vec<f32>>()
    };
    let same = |_: usize, _: usize, x: f32| x;
    let block = rays / poses;
    let (o, d) = (f("rays_o"), f("rays_d"));
    let mut dirs = per_ray(&d, 3, &same);
    for (i, v) in dirs.chunks_exact_mut(3).enumerate() {
        let k = (i / n0) as f32;
        let nudge = [(1.3 * k).sin(), (0.7 * k).cos(), (2.1 * k).sin()];
        for (x, e) in v.iter_mut().zip(nudge) {
            *x += 0.01 * e;
        }
        let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        v.iter_mut().for_each(|x| *x /= n);
    }
    let bend =
        |i: usize, c: usize, x: f32| x + 0.05 * (i / block) as f32 * ((c % 7) as f32 - 3.0) / 3.0;
    let arrays: Vec<(&str, Vec<usize>, Vec<f32>)> = vec![
        ("rays_o", vec![rays, 3], per_ray(&o, 3, &same)),
        ("rays_d", vec![rays, 3], dirs),
        ("kp3d", vec![rays, 24, 3], per_ray(&f("kp3d"), 72, &same)),
        (
            "skts",
            vec![rays, 24, 4, 4],
            per_ray(&f("skts"), 384, &same),
        ),
        ("bones", vec![rays, 24, 3], per_ray(&f("bones"), 72, &bend)),
        ("cyls", vec![rays, 5], per_ray(&f("cyls"), 5, &same)),
        ("bgs", vec![rays, 3], per_ray(&f("bgs"), 3, &same)),
        ("rest_pose", vec![24, 3], f("rest_pose")),
    ];
    let file = std::fs::File::create(path).unwrap();
    let mut w = NpzWriter::new(file, false, path.display().to_string());
    for (k, shape, v) in &arrays {
        w.add(k, shape, MemberData::F32(v)).unwrap();
    }
    let cam: Vec<i64> = (0..rays).map(|i| cams[i % n0]).collect();
    w.add("cam_idxs", &[rays], MemberData::I64(&cam)).unwrap();
    w.add("N_unique", &[1], MemberData::I64(&[poses as i64]))
        .unwrap();
    w.finish().unwrap();
}

/// A freshly initialised model of `preset` for the golden rest pose.
fn preset_model(path: &Path, cfg: pma_model::Config) {
    let g = golden();
    let r = g["input/rest_pose"]
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
    let mut rest = [[0f32; 3]; 24];
    for (j, row) in rest.iter_mut().enumerate() {
        row.copy_from_slice(&r[j * 3..j * 3 + 3]);
    }
    pma_model::render::avatar::Avatar::new(cfg, &rest, 7, &Device::Cpu)
        .unwrap()
        .save(path)
        .unwrap();
}

/// Every array of an npz as (name, shape, raw f32 bits).
fn npz_bits(path: &Path) -> Vec<(String, Vec<usize>, Vec<u32>)> {
    let mut r = NpzReader::open(path).unwrap();
    let mut keys = r.keys();
    keys.sort();
    keys.into_iter()
        .map(|k| {
            let a = r.read(&k).unwrap();
            let NpyData::F32(v) = a.data else {
                panic!("{k} is not f32")
            };
            (k, a.shape, v.iter().map(|x| x.to_bits()).collect())
        })
        .collect()
}

fn run_forward(model: &Path, batch: &Path, out: &Path, extra: &[&str]) {
    ok(forward(model, batch, out, extra));
}

/// The inference path (default) and the graph path (`--grad`) write the same bytes: golden
/// model and batch (one point chunk), the golden `dense` case, batches of several chunks
/// and two poses, and a preset model.
#[test]
fn forward_fast_path_is_bit_identical_to_the_graph_path() {
    let dir = tempfile::tempdir().unwrap();
    let golden_batch = dir.path().join("golden.npz");
    write_batch(&golden_batch, None);
    let grown = dir.path().join("grown.npz");
    // 2 poses x 96 rays x 48 coarse samples: two point chunks per pose, the last one partial.
    write_grown_batch(&grown, 192, 2);
    let small = dir.path().join("cpu_small.safetensors");
    let mut cfg = pma_model::Config::cpu_small();
    cfg.n_framecodes = 4;
    preset_model(&small, cfg);
    // cpu-small: 16 coarse samples, so 640 rays in one pose are 3 chunks.
    let grown_small = dir.path().join("grown_small.npz");
    write_grown_batch(&grown_small, 640, 1);
    let golden = fixtures().join("model.safetensors");
    let sigma = fixtures().join("dense/sigma_override.safetensors");
    let sigma = sigma.to_str().unwrap();
    let cases: Vec<(&str, &Path, &Path, Vec<&str>)> = vec![
        ("golden", &golden, &golden_batch, vec![]),
        (
            "golden eval codes",
            &golden,
            &golden_batch,
            vec!["--train-mode", "false"],
        ),
        (
            "golden dense",
            &golden,
            &golden_batch,
            vec!["--sigma-override", sigma],
        ),
        (
            "golden dense, grown",
            &golden,
            &grown,
            vec!["--sigma-override", sigma],
        ),
        ("cpu-small, grown", &small, &grown_small, vec![]),
    ];
    for (name, model, batch, extra) in cases {
        let fast = dir.path().join("fast.npz");
        let graph = dir.path().join("graph.npz");
        run_forward(model, batch, &fast, &extra);
        let mut with_grad = extra.clone();
        with_grad.push("--grad");
        run_forward(model, batch, &graph, &with_grad);
        let (a, b) = (npz_bits(&fast), npz_bits(&graph));
        assert_eq!(
            a.iter().map(|x| &x.0).collect::<Vec<_>>(),
            b.iter().map(|x| &x.0).collect::<Vec<_>>(),
            "{name}: output names"
        );
        assert!(a.len() >= 14, "{name}: {} outputs", a.len());
        for (x, y) in a.iter().zip(&b) {
            assert_eq!(x.1, y.1, "{name}: shape of {}", x.0);
            let diff = x.2.iter().zip(&y.2).filter(|(p, q)| p != q).count();
            assert_eq!(
                diff,
                0,
                "{name}: {} differs in {diff} of {} values",
                x.0,
                x.2.len()
            );
        }
    }
}

/// Training-mode frame codes refuse a batch whose indices are all −1 on both paths; the
/// evaluation rule (`--train-mode false`) gives it the mean code.
#[test]
fn forward_all_negative_codes_follow_the_mode() {
    let dir = tempfile::tempdir().unwrap();
    let batch = dir.path().join("batch.npz");
    write_grown_batch(&batch, 64, 1);
    // Rewrite cam_idxs to −1 by rebuilding the npz without them.
    let mut r = NpzReader::open(&batch).unwrap();
    let arrays: Vec<_> = r
        .keys()
        .into_iter()
        .map(|k| {
            let a = r.read(&k).unwrap();
            (k, a)
        })
        .collect();
    let neg = dir.path().join("neg.npz");
    let mut w = NpzWriter::new(
        std::fs::File::create(&neg).unwrap(),
        false,
        neg.display().to_string(),
    );
    for (k, a) in &arrays {
        match (&a.data, k.as_str()) {
            (NpyData::I64(v), "cam_idxs") => w
                .add(k, &a.shape, MemberData::I64(&vec![-1; v.len()]))
                .unwrap(),
            (NpyData::I64(v), _) => w.add(k, &a.shape, MemberData::I64(v)).unwrap(),
            (NpyData::F32(v), _) => w.add(k, &a.shape, MemberData::F32(v)).unwrap(),
            _ => panic!("{k}: unexpected type"),
        }
    }
    w.finish().unwrap();
    let model = fixtures().join("model.safetensors");
    for grad in [false, true] {
        let out = dir.path().join("out.npz");
        let o = forward(&model, &neg, &out, if grad { &["--grad"] } else { &[] });
        assert!(
            !o.status.success(),
            "grad {grad}: all −1 codes accepted in training mode"
        );
        assert!(!out.exists());
    }
    let (fast, graph) = (dir.path().join("f.npz"), dir.path().join("g.npz"));
    run_forward(&model, &neg, &fast, &["--train-mode", "false"]);
    run_forward(&model, &neg, &graph, &["--train-mode", "false", "--grad"]);
    assert_eq!(npz_bits(&fast), npz_bits(&graph));
}
