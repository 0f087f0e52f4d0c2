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

#[test]
fn account_writes_the_step_counts() {
    use super::run::{ok, pma};
    let dir = tempfile::tempdir().unwrap();
    let off = dir.path().join("official.json");
    // A recorded run in count_official.py's layout (two ops).
    std::fs::write(
        &off,
        r#"{"what": "test", "rays": 32, "counts": {"ops": 2, "launches": 2, "syncs": 1,
            "sync_bytes": 4, "uploads": 0, "upload_bytes": 0, "param_uploads": 0,
            "bytes_read": 100, "bytes_written": 50, "flops": 10},
            "costs": [{"op": "mm", "launches": 1, "bytes": 100, "flops": 10},
                      {"op": "add", "launches": 1, "bytes": 50, "flops": 0}]}"#,
    )
    .unwrap();
    let out = dir.path().to_str().unwrap();
    let stdout = ok(pma(&[
        "bench",
        "--account",
        "--quiet",
        "--preset",
        "tiny",
        "--rays",
        "32",
        "--official-json",
        off.to_str().unwrap(),
        "--out",
        out,
    ]))
    .stdout;
    let text = String::from_utf8_lossy(&stdout);
    assert!(text.contains("official (32 rays)"), "{text}");
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("account.json")).unwrap()).unwrap();
    // The tiny step in one pass reads nothing back inside it; its numbers come back in one
    // read (as tests/model/account.rs counts them).
    assert_eq!(json["syncs_per_step"], 0);
    assert_eq!(json["read_back_syncs"], 1);
    assert_eq!(json["account_as"], "cuda");
    for key in [
        "ops_per_step",
        "uploads_per_step",
        "bytes_per_step",
        "flops_per_step",
    ] {
        assert!(json[key].as_u64().is_some_and(|v| v > 0), "{key}");
    }
    let stages: Vec<&str> = json["step"]["stages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["name"].as_str().unwrap())
        .collect();
    for s in [
        "batch",
        "pose features",
        "cast",
        "coarse network",
        "backward",
        "grad norm + Adam",
    ] {
        assert!(stages.contains(&s), "{s} missing from {stages:?}");
    }
    assert!(json["inference"]["total"]["ops"].as_u64().unwrap() > 0);
    let est = &json["official"]["est"][0]["est_fp32_matmul"]["est_s"];
    assert!(est.as_f64().is_some_and(|v| v > 0.0), "{est}");
    assert_eq!(json["step"]["est"].as_array().unwrap().len(), 3);
}

#[test]
fn account_refuses_bad_flags() {
    use super::run::{fails_with, pma};
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().to_str().unwrap();
    let base = [
        "bench",
        "--account",
        "--quiet",
        "--preset",
        "tiny",
        "--out",
        out,
    ];
    let with = |extra: &[&str]| {
        let mut a = base.to_vec();
        a.extend_from_slice(extra);
        pma(&a)
    };
    let o = with(&["--account-as", "gpu"]);
    assert_eq!(o.status.code(), Some(2));
    fails_with(o, "--account-as");
    let o = with(&["--rays", "31"]);
    assert_eq!(o.status.code(), Some(2));
    fails_with(o, "--rays 31");
    let o = with(&["--official-json", "/nonexistent/official.json"]);
    assert_eq!(o.status.code(), Some(2));
    fails_with(o, "official.json");
    // A chunked step is not extrapolated.
    let o = with(&[
        "--rays",
        "32",
        "--chunk-rays",
        "8",
        "--extrapolate-from",
        "8",
    ]);
    assert_eq!(o.status.code(), Some(2));
    fails_with(o, "one-pass");
}
