//! `pma demo` end to end on a tiny budget: synthesises the scene, trains, evaluates both
//! held-out splits and writes summary.json in the shape other tools read.

use std::process::Command;

#[test]
fn demo_writes_summary_renders_and_plot() {
    let tmp = tempfile::tempdir().unwrap();
    let out_dir = tmp.path().join("demo");
    let out = Command::new(env!("CARGO_BIN_EXE_pma"))
        .args([
            "demo",
            "--out",
            out_dir.to_str().unwrap(),
            "--preset",
            "tiny",
            "--iters",
            "3",
            "--minutes",
            "5",
        ])
        .args([
            "--res",
            "24",
            "--frames",
            "2",
            "--max-eval-images",
            "2",
            "--pngs",
            "1",
            "--quiet",
            "--device",
            "cpu",
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "demo failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );

    // Scene, run, evaluations, renders and plots: one mode rule for all of them.
    #[cfg(unix)]
    crate::run::assert_default_modes(&out_dir);

    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out_dir.join("summary.json")).unwrap())
            .unwrap();
    assert_eq!(summary["iterations"], 3);
    assert!(summary["wall_s"].as_f64().unwrap() > 0.0);
    for key in ["model", "data"] {
        let p = summary[key].as_str().unwrap();
        assert!(std::path::Path::new(p).is_file(), "{key}: {p}");
    }
    for split in ["novel_view", "novel_pose"] {
        let s = &summary["splits"][split];
        for key in ["psnr", "ssim", "baseline_psnr"] {
            assert!(s[key].as_f64().unwrap().is_finite(), "{split}.{key}: {s}");
        }
        assert_eq!(s["images"], 2);
    }
    assert!(out_dir.join("psnr_vs_time.png").is_file());
    assert!(out_dir.join("run/log.csv").is_file());
    let renders: Vec<_> = std::fs::read_dir(out_dir.join("renders"))
        .unwrap()
        .collect();
    assert_eq!(renders.len(), 2, "one side-by-side PNG per split");
}
