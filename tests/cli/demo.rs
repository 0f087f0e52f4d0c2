//! `pma demo` end to end on a tiny budget: synthesises the scene, trains, evaluates both
//! held-out splits and writes summary.json in the shape other tools read; it trains with the
//! fast recipe and says so, and `--parity` trains without it.

use std::path::Path;
use std::process::Output;

use crate::run::{ok, pma, read_json, s};

/// `pma demo` on the tiny preset and a 24-pixel scene of 2 frames, with `extra` flags.
fn demo(out_dir: &Path, extra: &[&str]) -> Output {
    let base = [
        "demo",
        "--out",
        s(out_dir),
        "--preset",
        "tiny",
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
    ];
    ok(pma(&[&base[..], extra].concat()))
}

#[test]
fn demo_writes_summary_renders_and_plot() {
    let tmp = tempfile::tempdir().unwrap();
    let out_dir = tmp.path().join("demo");
    let out = demo(&out_dir, &["--iters", "3", "--minutes", "5"]);

    // Scene, run, evaluations, renders and plots: one mode rule for all of them.
    #[cfg(unix)]
    crate::run::assert_default_modes(&out_dir);

    let summary = read_json(&out_dir.join("summary.json"));
    assert_eq!(summary["iterations"], 3);
    // The fast recipe, named in the output and the summary; the curve's images beside the
    // evaluation's.
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("fast recipe"), "{stdout}");
    let options: Vec<&str> = summary["options"]
        .as_array()
        .unwrap()
        .iter()
        .map(|o| o.as_str().unwrap())
        .collect();
    assert_eq!(
        options,
        [
            "--cull-rays --cull-samples 0.6",
            "--occupancy",
            "--average",
            "--pose-boost"
        ],
        "{options:?}"
    );
    assert!(stdout.contains(&format!(
        "curve scores {} novel-view",
        summary["curve_images"]
    )));
    let config = std::fs::read_to_string(out_dir.join("run/config.toml")).unwrap();
    assert!(config.contains("[train.occupancy]"), "{config}");
    assert!(config.contains("[train.average]"), "{config}");
    // The pose side's boost spans the budget (--minutes 5).
    let boost = config
        .split("[train.pose_boost]")
        .nth(1)
        .unwrap_or_default();
    assert!(boost.contains("seconds = 300.0"), "{config}");
    assert!(!config.contains("[train.error_map]"), "{config}");
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

/// `--parity` trains the preset as it is: no recipe option in the summary or the run's
/// configuration. Without `--iters` the budget alone ends the run.
#[test]
fn demo_parity_trains_without_the_recipe() {
    let tmp = tempfile::tempdir().unwrap();
    let out_dir = tmp.path().join("demo");
    let out = demo(&out_dir, &["--parity", "--minutes", "0.02"]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("--parity"), "{stdout}");
    let summary = read_json(&out_dir.join("summary.json"));
    assert_eq!(summary["options"], serde_json::json!([]));
    assert!(summary["iterations"].as_u64().unwrap() > 0);
    let config = std::fs::read_to_string(out_dir.join("run/config.toml")).unwrap();
    for key in [
        "error_map",
        "anneal",
        "pose_boost",
        "average",
        "occupancy",
        "coarse_from_grid",
    ] {
        assert!(!config.contains(key), "{key} in {config}");
    }
}
