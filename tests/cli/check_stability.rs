//! `pma check-stability`: the probe table on a fresh avatar and on a checkpoint, and a
//! non-zero exit when a checkpoint produces non-finite values.

use std::process::Command;

use candle_core::{Device, Tensor};
use pma_model::render::avatar::Avatar;
use pma_model::Config;

fn pma() -> Command {
    Command::new(env!("CARGO_BIN_EXE_pma"))
}

#[test]
fn fresh_tiny_avatar_passes_and_prints_every_case() {
    let out = pma()
        .args([
            "check-stability",
            "--preset",
            "tiny",
            "--quiet",
            "--fixes",
            "--strict",
        ])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for case in [
        "pose: every joint pi about x",
        "AIST++ frame",
        "gamma 1e4",
        "axis scale",
        "composite all-zero density",
        "ray bounds",
    ] {
        assert!(stdout.contains(case), "missing `{case}` in\n{stdout}");
    }
    assert!(
        stdout.contains("non-finite values: 0; broken invariants: 0"),
        "{stdout}"
    );
}

#[test]
fn a_poisoned_checkpoint_fails() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = Config {
        n_framecodes: 2,
        ..Config::tiny()
    };
    let a = Avatar::new(cfg.clone(), &pma_data::synth::rest_pose(), 0, &Device::Cpu).unwrap();
    let good = tmp.path().join("good.safetensors");
    a.save(&good).unwrap();
    let out = pma()
        .args(["check-stability", "--quiet", "--model"])
        .arg(&good)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );

    // A NaN in the density head reaches every output.
    let mut t = a.tensors();
    let b = t["sigma_linear.bias"].clone();
    t.insert(
        "sigma_linear.bias".into(),
        Tensor::full(f32::NAN, b.shape(), &Device::Cpu).unwrap(),
    );
    let bad = tmp.path().join("bad.safetensors");
    Avatar::from_tensors(cfg, t, &Device::Cpu)
        .unwrap()
        .save(&bad)
        .unwrap();
    let out = pma()
        .args(["check-stability", "--quiet", "--model"])
        .arg(&bad)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(!out.status.success(), "{stdout}");
    assert!(String::from_utf8_lossy(&out.stderr).contains("non-finite"));
}
