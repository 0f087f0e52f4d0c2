//! `pma forward` end to end: golden inputs in, golden outputs out; bad batches rejected.

use std::path::{Path, PathBuf};
use std::process::Command;

use candle_core::{DType, Device, Tensor};
use pma_data::dataset::npz::{MemberData, NpyData, NpzReader, NpzWriter};

fn fixtures() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("fixtures/golden")
}

fn write_batch(path: &Path, skip: Option<&str>) {
    let g = candle_core::safetensors::load(fixtures().join("golden.safetensors"), &Device::Cpu)
        .unwrap();
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
    let status = Command::new(env!("CARGO_BIN_EXE_pma"))
        .args(["forward", "--model"])
        .arg(fixtures().join("model.safetensors"))
        .arg("--batch")
        .arg(&batch)
        .arg("--out")
        .arg(&out)
        .status()
        .unwrap();
    assert!(status.success());
    let g = candle_core::safetensors::load(fixtures().join("golden.safetensors"), &Device::Cpu)
        .unwrap();
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
    let o = Command::new(env!("CARGO_BIN_EXE_pma"))
        .args(["forward", "--model"])
        .arg(fixtures().join("model.safetensors"))
        .arg("--batch")
        .arg(&batch)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("skts"), "error should name the key: {err}");
    assert!(!out.exists(), "no output on failure");
}
