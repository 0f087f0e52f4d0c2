//! `pma demo` end to end on a tiny budget: synthesises the scene, trains, evaluates both
//! held-out splits and writes summary.json in the shape other tools read.

use crate::run::{ok, pma, read_json, s};

#[test]
fn demo_writes_summary_renders_and_plot() {
    let tmp = tempfile::tempdir().unwrap();
    let out_dir = tmp.path().join("demo");
    ok(pma(&[
        "demo",
        "--out",
        s(&out_dir),
        "--preset",
        "tiny",
        "--iters",
        "3",
        "--minutes",
        "5",
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
    ]));

    // Scene, run, evaluations, renders and plots: one mode rule for all of them.
    #[cfg(unix)]
    crate::run::assert_default_modes(&out_dir);

    let summary = read_json(&out_dir.join("summary.json"));
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
