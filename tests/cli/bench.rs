//! `pma bench --quick`: the smallest run writes bench.json with one row per option and the
//! error-vs-time plot; bad flags fail with a message.

use std::process::Command;

#[test]
fn quick_bench_writes_every_field() {
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_pma"))
        .args([
            "bench",
            "--quick",
            "--quiet",
            "--device",
            "cpu",
            "--thresholds",
            "0,1e-2",
            "--out",
        ])
        .arg(dir.path())
        .output()
        .expect("running pma");
    assert!(
        out.status.success(),
        "pma bench failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("bench.json")).unwrap()).unwrap();
    for key in ["flops_per_point", "peak_gflops", "inactive_joint_fraction"] {
        let v = json[key].as_f64();
        assert!(v.is_some_and(|v| v.is_finite() && v >= 0.0), "{key}: {v:?}");
    }
    let options = json["options"].as_array().unwrap();
    let names: Vec<&str> = options
        .iter()
        .map(|o| o["name"].as_str().unwrap())
        .collect();
    assert_eq!(
        names,
        [
            "parity",
            "rays",
            "rays+samples@0e0",
            "rays+samples@1e-2",
            "fast-sine",
            "rays+samples@1e-2+fast-sine"
        ]
    );
    let fast: Vec<bool> = options
        .iter()
        .map(|o| o["fast_sine"].as_bool().unwrap())
        .collect();
    assert_eq!(fast, [false, false, false, false, true, true]);
    for o in options {
        for key in [
            "ms_per_image",
            "rays_per_s",
            "network_points_per_s",
            "samples_per_s",
            "gflops",
            "ms_per_step",
            "train_gflops",
            "peak_rss_mib",
            "heldout_psnr",
            "speedup_vs_parity",
        ] {
            let v = o[key].as_f64();
            assert!(
                v.is_some_and(|v| v.is_finite() && v > 0.0),
                "{}: {key} = {v:?}",
                o["name"]
            );
        }
        assert!(o["budget_heldout_psnr"].as_f64().is_some());
    }
    // Threshold 0 leaves the render unchanged against parity ("rays" culling aside, which
    // only touches rays that miss every box): its points are fewer than parity's.
    let pts = |i: usize| options[i]["network_points_per_image"].as_u64().unwrap();
    assert!(pts(2) < pts(0), "culling did not leave points out");
    // Sample culling at threshold 0 only skips samples whose window is exactly 0, whose
    // outputs the far-away constant reproduces: on top of ray culling it changes nothing
    // beyond last-bit differences of the network calls' sizes.
    let diff_vs_parity = |i: usize| options[i]["max_abs_diff_vs_parity"].as_f64().unwrap();
    assert!(
        diff_vs_parity(2) <= diff_vs_parity(1) + 1e-5 && diff_vs_parity(2) < 1e-4,
        "threshold 0 moved the render: {} (rays alone {})",
        diff_vs_parity(2),
        diff_vs_parity(1)
    );
    // The vectorised sine leaves out no points, and its render is near parity's (last-bit
    // differences through the network), not identical and not far.
    assert_eq!(pts(4), pts(0));
    let diff = options[4]["max_abs_diff_vs_parity"].as_f64().unwrap();
    assert!(diff < 1e-3, "fast sine moved the render by {diff}");
    assert!(dir.path().join("error_vs_time.png").is_file());
}

#[test]
fn bad_thresholds_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_pma"))
        .args(["bench", "--quick", "--thresholds", "2", "--out"])
        .arg(dir.path())
        .output()
        .expect("running pma");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("--thresholds"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
}

/// `--forward-only`: one warm-up and `--repeats` whole `pma forward` processes on a batch,
/// reported as the `forward` row (structure only; times are not asserted).
#[test]
fn forward_only_bench_times_whole_forward_processes() {
    let dir = tempfile::tempdir().unwrap();
    let batch = dir.path().join("batch.npz");
    super::forward::write_batch(&batch, None);
    let fixtures = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("fixtures/golden");
    let out = Command::new(env!("CARGO_BIN_EXE_pma"))
        .args([
            "bench",
            "--quiet",
            "--forward-only",
            "--repeats",
            "2",
            "--forward-batch",
        ])
        .arg(&batch)
        .arg("--forward-model")
        .arg(fixtures.join("model.safetensors"))
        .arg("--out")
        .arg(dir.path())
        .output()
        .expect("running pma");
    assert!(
        out.status.success(),
        "pma bench failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains("pma forward (whole process) 64 rays"),
        "{stdout}"
    );
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("bench.json")).unwrap()).unwrap();
    let f = &json["forward"];
    assert_eq!(f["rays"].as_u64(), Some(64));
    let runs = f["runs_s"].as_array().unwrap();
    assert_eq!(runs.len(), 2, "one warm-up, then --repeats runs");
    let median = f["median_s"].as_f64().unwrap();
    assert!(runs.iter().all(|r| r.as_f64().is_some_and(|r| r > 0.0)));
    assert!(
        runs.iter().any(|r| r.as_f64() == Some(median)),
        "median is one of the runs"
    );
    assert!(f["rays_per_s"].as_f64().is_some_and(|v| v > 0.0));
    assert!(json["options"].as_array().unwrap().is_empty());
    assert!(!dir.path().join("forward_out.npz").exists());
}

#[test]
fn forward_bench_reports_a_failing_forward() {
    let dir = tempfile::tempdir().unwrap();
    let batch = dir.path().join("batch.npz");
    super::forward::write_batch(&batch, Some("skts"));
    let fixtures = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("fixtures/golden");
    let out = Command::new(env!("CARGO_BIN_EXE_pma"))
        .args(["bench", "--quiet", "--forward-only", "--forward-batch"])
        .arg(&batch)
        .arg("--forward-model")
        .arg(fixtures.join("model.safetensors"))
        .arg("--out")
        .arg(dir.path())
        .output()
        .expect("running pma");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("skts"), "{err}");
}
