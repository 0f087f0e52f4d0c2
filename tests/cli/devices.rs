//! `--device` and `--tf32` on every command that computes: a backend missing from the build
//! and TF32 off CUDA are refused with exit 2 before any work (the `--device cpu` runs are in
//! the commands' own tests).

use crate::run::{pma, refused};

#[test]
fn cuda_on_a_cpu_only_build_names_the_feature() {
    if candle_core::utils::cuda_is_available() {
        return; // a CUDA build: the device exists (or fails to open for another reason)
    }
    let tmp = tempfile::tempdir().unwrap();
    let d = |name: &str| tmp.path().join(name).to_str().unwrap().to_string();
    let (out, model, data) = (d("out"), d("missing.safetensors"), d("missing.npz"));
    let cases: Vec<Vec<&str>> = vec![
        vec!["demo", "--out", &out, "--preset", "tiny"],
        vec!["mesh", "--model", &model, "-o", &out],
        vec!["bench", "--quick", "--out", &out],
        vec!["eval", "--model", &model, "--data", &data],
    ];
    for args in cases {
        let mut a = args.clone();
        a.extend(["--device", "cuda"]);
        let o = pma(&a);
        refused(&o, &["device `cuda`", "--features cuda"]);
    }
}

#[test]
fn tf32_off_cuda_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let model = tmp.path().join("missing.safetensors");
    refused(
        &pma(&["bench", "--quick", "--tf32", "--out", out.to_str().unwrap()]),
        &["--tf32 needs a CUDA device"],
    );
    refused(
        &pma(&[
            "eval",
            "--model",
            model.to_str().unwrap(),
            "--data",
            out.to_str().unwrap(),
            "--device",
            "cpu",
            "--tf32",
        ]),
        &["--tf32 needs a CUDA device"],
    );
}
