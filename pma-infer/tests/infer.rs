//! The inference-only binary renders a checkpoint to a PNG and fails cleanly on bad input.

use std::process::Command;

use candle_core::Device;
use pma_model::avatar::Avatar;
use pma_model::Config;

fn infer(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_pma-infer"))
        .args(args)
        .output()
        .expect("running pma-infer")
}

#[test]
fn renders_one_png_and_rejects_bad_input() {
    let tmp = tempfile::tempdir().unwrap();
    let model = tmp.path().join("tiny.safetensors");
    Avatar::new(
        Config::tiny(),
        &pma_data::synth::rest_pose(),
        2,
        &Device::Cpu,
    )
    .unwrap()
    .save(&model)
    .unwrap();
    let png = tmp.path().join("out.png");
    let out = infer(&[model.to_str().unwrap(), png.to_str().unwrap(), "24"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(image::image_dimensions(&png).unwrap(), (24, 24));
    assert!(String::from_utf8_lossy(&out.stdout).contains("render"));

    for (args, needle) in [
        (vec![model.to_str().unwrap()], "usage"),
        (
            vec![model.to_str().unwrap(), png.to_str().unwrap(), "3"],
            "SIZE must be",
        ),
        (
            vec!["/nonexistent.safetensors", png.to_str().unwrap()],
            "nonexistent",
        ),
    ] {
        let out = infer(&args);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && err.contains(needle),
            "{args:?}: {err}"
        );
        assert!(!err.contains("panicked"));
    }
}
