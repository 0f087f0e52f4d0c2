//! Checkpoint format: loading the reference export as it is, round trips with metadata,
//! and strict loading that reports every problem at once.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
use pma_model::error::ModelError;
use pma_model::network::checkpoint::{self, param_names, tensor_layout, TensorKind};
use pma_model::Config;

fn golden_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures/golden")
}

fn golden_model() -> checkpoint::Checkpoint {
    checkpoint::load(&golden_dir().join("model.safetensors"), &Device::Cpu)
        .expect("golden model loads")
}

fn problems(err: ModelError) -> Vec<String> {
    match err {
        ModelError::Checkpoint { problems, .. } => problems,
        other => panic!("expected a checkpoint error, got {other}"),
    }
}

#[test]
fn loads_reference_export_and_infers_config() {
    let ck = golden_model();
    assert!(ck.meta.config_inferred);
    assert_eq!(ck.meta.format_version, None);
    let mut expected = Config::paper();
    expected.n_framecodes = 780;
    assert_eq!(ck.config, expected);
    assert_eq!(ck.tensors.len(), 71);
    assert_eq!(ck.meta.rest_pose.len(), 24);
    // The golden rest pose is the SMPL table x 0.435, pelvis at the origin.
    assert_eq!(ck.meta.rest_pose[0], [0.0, 0.0, 0.0]);

    let n_params: usize = tensor_layout(&ck.config)
        .iter()
        .filter(|t| t.kind == TensorKind::Param)
        .map(|t| t.shape.iter().product::<usize>())
        .sum();
    assert_eq!(n_params, 3_111_524, "golden README parameter count");
}

#[test]
fn param_names_match_reference_order() {
    let manifest: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(golden_dir().join("manifest.json")).unwrap())
            .unwrap();
    let reference: Vec<String> = manifest["param_names"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap().to_string())
        .collect();
    assert_eq!(reference.len(), 64);
    assert_eq!(param_names(&Config::paper()), reference);
}

#[test]
fn save_load_round_trip_keeps_tensors_and_metadata() {
    let ck = golden_model();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("model.safetensors");
    checkpoint::save(&path, &ck.tensors, &ck.config).unwrap();
    // Atomic write: only the target file is left in the directory.
    let entries: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(entries, vec![std::ffi::OsString::from("model.safetensors")]);

    let back = checkpoint::load(&path, &Device::Cpu).unwrap();
    assert_eq!(back.meta.format_version, Some(1));
    assert!(!back.meta.config_inferred);
    assert_eq!(back.config, ck.config);
    assert_eq!(back.meta.rest_pose, ck.meta.rest_pose);
    assert_eq!(back.meta.skeleton.names.len(), 24);
    assert_eq!(back.meta.skeleton.names[0], "pelvis");
    assert_eq!(back.meta.skeleton.parents[15], 12);
    assert_eq!(back.tensors.len(), ck.tensors.len());
    for (name, t) in &ck.tensors {
        let a = t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let b = back.tensors[name]
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        assert!(
            a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()),
            "{name} changed"
        );
    }

    // The raw header carries the documented metadata keys.
    let bytes = std::fs::read(&path).unwrap();
    let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).unwrap();
    let meta = header.metadata().as_ref().unwrap();
    assert_eq!(meta["format"], "pma-checkpoint");
    assert_eq!(meta["format_version"], "1");
    assert_eq!(meta["n_framecodes"], "780");
    let cfg: Config = serde_json::from_str(&meta["config"]).unwrap();
    assert_eq!(cfg, ck.config);
}

/// The golden tensors with one missing, one unexpected and one mis-shaped entry.
fn broken_tensors() -> HashMap<String, Tensor> {
    let mut t = golden_model().tensors;
    t.remove("win_fun.last_layer.layer.bias");
    t.insert(
        "extra.weight".into(),
        Tensor::zeros((2, 2), candle_core::DType::F32, &Device::Cpu).unwrap(),
    );
    t.insert(
        "sigma_linear.weight".into(),
        Tensor::zeros((2, 256), candle_core::DType::F32, &Device::Cpu).unwrap(),
    );
    t
}

fn assert_lists_all_three(p: &[String]) {
    assert!(
        p.iter()
            .any(|s| s.contains("missing") && s.contains("win_fun.last_layer.layer.bias")),
        "{p:?}"
    );
    assert!(
        p.iter()
            .any(|s| s.contains("unexpected") && s.contains("extra.weight")),
        "{p:?}"
    );
    assert!(
        p.iter().any(|s| s.contains("sigma_linear.weight")
            && s.contains("[1, 256]")
            && s.contains("[2, 256]")),
        "{p:?}"
    );
    assert_eq!(p.len(), 3, "{p:?}");
}

#[test]
fn strict_loading_lists_every_problem() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.safetensors");
    // A plain state_dict export (no pma metadata) with three problems.
    let t = broken_tensors();
    let bytes = safetensors::serialize(t.iter().map(|(n, t)| (n.as_str(), t)), None).unwrap();
    std::fs::write(&path, bytes).unwrap();
    let err = checkpoint::load(&path, &Device::Cpu).unwrap_err();
    let msg = err.to_string();
    assert!(
        msg.contains("bad.safetensors"),
        "error names the file: {msg}"
    );
    assert_lists_all_three(&problems(err));
}

#[test]
fn save_refuses_inconsistent_tensors() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("never.safetensors");
    let err = checkpoint::save(
        &path,
        &broken_tensors(),
        &Config {
            n_framecodes: 780,
            ..Config::paper()
        },
    )
    .unwrap_err();
    assert_lists_all_three(&problems(err));
    assert!(!path.exists());
}

#[test]
fn config_that_disagrees_with_tensors_is_an_error() {
    let ck = golden_model();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("mismatch.safetensors");
    // Metadata claims 100 frame codes while the table holds 780.
    let cfg = Config {
        n_framecodes: 100,
        ..ck.config.clone()
    };
    let mut meta = HashMap::new();
    meta.insert("format".to_string(), "pma-checkpoint".to_string());
    meta.insert("format_version".to_string(), "1".to_string());
    meta.insert("config".to_string(), serde_json::to_string(&cfg).unwrap());
    meta.insert(
        "skeleton".to_string(),
        serde_json::to_string(&checkpoint::SkeletonMeta::smpl()).unwrap(),
    );
    meta.insert(
        "rest_pose".to_string(),
        serde_json::to_string(&ck.meta.rest_pose).unwrap(),
    );
    meta.insert("n_framecodes".to_string(), "100".to_string());
    let bytes = safetensors::serialize(ck.tensors.iter().map(|(n, t)| (n.as_str(), t)), Some(meta))
        .unwrap();
    std::fs::write(&path, bytes).unwrap();

    let p = problems(checkpoint::load(&path, &Device::Cpu).unwrap_err());
    assert!(
        p.iter().any(|s| s.contains("framecodes.codes.weight")
            && s.contains("[100, 128]")
            && s.contains("[780, 128]")),
        "{p:?}"
    );
}

#[test]
fn missing_file_is_an_io_error_naming_it() {
    let err = checkpoint::load(
        Path::new("/nonexistent/dir/model.safetensors"),
        &Device::Cpu,
    )
    .unwrap_err();
    assert!(matches!(
        err,
        ModelError::File(pma_data::FileError::Read { .. })
    ));
    assert!(err
        .to_string()
        .contains("/nonexistent/dir/model.safetensors"));
}
