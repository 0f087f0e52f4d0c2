//! `pma eval` end to end: table on stdout, eval.json with the documented shape, side-by-side
//! PNGs, and clear errors for a bad split or a missing model.

use crate::run::{ok, pma, pma_eval, read_json, s, trained_scene};

#[test]
fn eval_writes_table_json_and_pngs() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, model) = trained_scene(tmp.path(), 2, "2");
    let out_dir = tmp.path().join("eval");
    let freq_png = tmp.path().join("freq.png");
    let out = ok(pma_eval(
        &model,
        &scene,
        &[
            "--split",
            "novel_pose",
            "--out",
            s(&out_dir),
            "--pngs",
            "2",
            "--freq-png",
            s(&freq_png),
        ],
    ));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains("PSNR") && stdout.contains("mean"),
        "{stdout}"
    );
    // 24-px images are under LPIPS's 31x31 minimum: the column is there, the value n/a.
    assert!(
        stdout.contains("LPIPS") && stdout.contains("n/a"),
        "{stdout}"
    );

    let json = read_json(&out_dir.join("eval.json"));
    assert_eq!(json["split"], "novel_pose");
    let per_image = json["per_image"].as_array().unwrap();
    assert_eq!(
        per_image.len(),
        2 * 2,
        "2 training cameras x (1 walk + 1 dance) frames"
    );
    let mean_psnr = per_image
        .iter()
        .map(|r| r["psnr"].as_f64().unwrap())
        .sum::<f64>()
        / per_image.len() as f64;
    assert!((json["psnr"].as_f64().unwrap() - mean_psnr).abs() < 1e-9);
    let ssim = json["ssim"].as_f64().unwrap();
    assert!(ssim.is_finite() && ssim <= 1.0);
    assert!(json["lpips"].is_null(), "{}", json["lpips"]);
    assert!(per_image.iter().all(|r| r["lpips"].is_null()));
    assert!(
        json["baseline_psnr"].as_f64().unwrap().is_finite(),
        "train.npz is beside the split"
    );
    let pngs = json["pngs"].as_array().unwrap();
    assert_eq!(pngs.len(), 2);
    for p in pngs {
        let img = image::open(p.as_str().unwrap()).unwrap();
        // Ground truth | render | error map of a square image, with two 4-px gaps.
        assert_eq!(img.width(), 3 * img.height() + 8);
    }

    // Frequency histograms: a distance per image and for the split, the split's mean
    // histograms over the bins, and their plot.
    let freq = |r: &serde_json::Value| r["freq_distance"].as_f64().unwrap();
    assert!(per_image
        .iter()
        .all(|r| freq(r).is_finite() && freq(r) >= 0.0));
    let mean_freq = per_image.iter().map(freq).sum::<f64>() / per_image.len() as f64;
    assert!((freq(&json) - mean_freq).abs() < 1e-9);
    let edges = json["freq_bin_edges"].as_array().unwrap();
    for key in ["freq_hist_render", "freq_hist_gt"] {
        let hist: Vec<f64> = json[key]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        assert_eq!(hist.len() + 1, edges.len(), "{key}");
        // Each image's histogram sums to 1, or is all zeros for a flat crop: a 2-step
        // model may render one.
        let sum = hist.iter().sum::<f64>();
        assert!(
            hist.iter().all(|&v| v >= 0.0) && sum < 1.0 + 1e-9,
            "{key}: {hist:?}"
        );
        if key == "freq_hist_gt" {
            assert!((sum - 1.0).abs() < 1e-9, "{key}: {hist:?}");
        }
    }
    let plot = image::open(&freq_png).unwrap().to_rgb8();
    assert_eq!((plot.width(), plot.height()), (900, 540));
    // Not blank: axes, labels, at least the ground truth's curve.
    let inked = plot.pixels().filter(|p| p.0 != [255, 255, 255]).count();
    assert!(inked > 5000, "{inked} non-white pixels");
}

#[test]
fn eval_rejects_bad_split_and_missing_model() {
    let tmp = tempfile::tempdir().unwrap();
    let out = pma(&[
        "eval",
        "--model",
        "/nonexistent/m.safetensors",
        "--data",
        tmp.path().to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent/m.safetensors"));

    // A real model, so that the split is what gets refused.
    let (scene, model) = trained_scene(tmp.path(), 2, "1");
    let train = scene.join("train.npz");
    let out = pma_eval(&model, &scene, &["--split", "holdout"]);
    assert!(!out.status.success());
    assert_eq!(
        out.status.code(),
        Some(2),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stderr).contains("unknown split \"holdout\""));

    // train.npz has no eval_tag: it does not hold the novel-pose images, and must not be
    // scored as if it did.
    let e = tmp.path().join("e");
    let out = pma_eval(&model, &train, &["--split", "novel_pose", "--out", s(&e)]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains("train.npz") && err.contains("novel_pose"),
        "{err}"
    );
    assert!(!e.join("eval.json").exists());
}
