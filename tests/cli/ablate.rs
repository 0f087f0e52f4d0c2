//! `pma ablate` end to end on a tiny scene: every variant asked for trains, is scored on both
//! held-out splits, and lands in the table, the JSON and the plot; bad input is refused.

use crate::run::{exits_2_with, ok, pma, read_json};

#[test]
fn ablate_tabulates_each_variant() {
    let tmp = tempfile::tempdir().unwrap();
    let train = crate::run::tiny_scene(&tmp.path().join("scene"), 1);
    let out = tmp.path().join("abl");
    ok(pma(&[
        "ablate",
        "--data",
        train.to_str().unwrap(),
        "--preset",
        "tiny",
        "--iters",
        "2",
        "--minutes",
        "1",
        "--variants",
        "full,only-gnn,no-window",
        "--max-eval-images",
        "1",
        "--quiet",
        "--out",
        out.to_str().unwrap(),
    ]));
    let json = read_json(&out.join("ablation.json"));
    let rows = json.as_array().unwrap();
    let names: Vec<&str> = rows
        .iter()
        .map(|r| r["variant"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["full", "only-gnn", "no-window"]);
    let params: Vec<u64> = rows
        .iter()
        .map(|r| r["parameters"].as_u64().unwrap())
        .collect();
    // only-gnn drops the synthesis branch and no-window the feature window.
    assert!(params[1] < params[0] && params[2] < params[0], "{params:?}");
    for r in rows {
        assert_eq!(r["iterations"].as_u64(), Some(2));
        assert!(r["ms_per_step"].as_f64().unwrap() > 0.0);
        for split in ["novel_view", "novel_pose"] {
            let psnr = r["splits"][split]["psnr"].as_f64().unwrap();
            assert!(psnr.is_finite() && psnr > 0.0, "{split}: {psnr}");
            // LPIPS needs crops of 31×31 pixels or more; this scene's are smaller (null).
            let lpips = &r["splits"][split]["lpips"];
            assert!(
                lpips.is_null() || lpips.as_f64().is_some_and(|v| v >= 0.0),
                "{split}: {lpips}"
            );
        }
        // Each variant's checkpoint names it.
        let model = std::path::PathBuf::from(r["model"].as_str().unwrap());
        let ck = pma_model::network::checkpoint::load(&model, &candle_core::Device::Cpu).unwrap();
        assert_eq!(ck.config.variant.name(), r["variant"].as_str().unwrap());
    }
    let md = std::fs::read_to_string(out.join("ablation.md")).unwrap();
    assert!(
        md.contains("| only-gnn |") && md.contains("ms/step"),
        "{md}"
    );
    assert!(out.join("error_vs_time.png").is_file());
}

#[test]
fn ablate_refuses_unknown_variants_and_missing_splits() {
    let tmp = tempfile::tempdir().unwrap();
    let out = pma(&["ablate", "--variants", "full,half", "--out", "x"]);
    exits_2_with(out, "half");
    let lone = tmp.path().join("lone");
    std::fs::create_dir_all(&lone).unwrap();
    let train = crate::run::tiny_scene(&tmp.path().join("scene"), 1);
    std::fs::copy(&train, lone.join("train.npz")).unwrap();
    let out = pma(&[
        "ablate",
        "--data",
        lone.join("train.npz").to_str().unwrap(),
        "--out",
        tmp.path().join("o").to_str().unwrap(),
    ]);
    exits_2_with(out, "novel_view");
}
