//! `pma bench --quick`: the smallest run writes bench.json with one row per option and the
//! error-vs-time plot; bad flags fail with a message.

use std::path::Path;
use std::process::Output;

use crate::run::{exits_2_with, fails_with, ok, pma, read_json, s};

/// `pma bench --account --quiet --preset tiny`, the start of every accounting run here.
const ACCOUNT_TINY: [&str; 5] = ["bench", "--account", "--quiet", "--preset", "tiny"];

#[test]
fn quick_bench_writes_every_field() {
    let dir = tempfile::tempdir().unwrap();
    ok(pma(&[
        "bench",
        "--quick",
        "--quiet",
        "--device",
        "cpu",
        "--thresholds",
        "0,1e-2",
        "--out",
        s(dir.path()),
    ]));
    let json = read_json(&dir.path().join("bench.json"));
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
            "rays+samples@1e-2+early-stop@1e-2",
            "rays+samples@1e-2+joints",
            "rays+samples@1e-2+early-stop@1e-2+joints",
            "fast-sine",
            "rays+samples@1e-2+fast-sine"
        ]
    );
    let fast: Vec<bool> = options
        .iter()
        .map(|o| o["fast_sine"].as_bool().unwrap())
        .collect();
    assert_eq!(
        fast,
        [false, false, false, false, false, false, false, true, true]
    );
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
    // The early stop only leaves out more than the culling it is added to.
    assert!(
        pts(4) <= pts(3),
        "early stop ran more points than without it"
    );
    assert_eq!(options[4]["early_stop"].as_f64(), Some(1e-2));
    // Grouping the calls by joints runs the same samples, and renders what the option
    // without it renders up to float summation order.
    for (grouped, plain) in [(5, 3), (6, 4)] {
        assert_eq!(options[grouped]["cull_joints"].as_bool(), Some(true));
        assert_eq!(
            pts(grouped),
            pts(plain),
            "grouping changed the network points"
        );
        let joints = |i: usize| options[i]["joints_per_point"].as_f64().unwrap();
        assert_eq!(joints(plain), 24.0, "ungrouped calls carry every joint");
        assert!(joints(grouped) > 0.0 && joints(grouped) <= 24.0);
        let d = (diff_vs_parity(grouped) - diff_vs_parity(plain)).abs();
        assert!(d < 1e-4, "grouping moved the render against parity by {d}");
    }
    // The vectorised sine leaves out no points, and its render is near parity's (last-bit
    // differences through the network), not identical and not far.
    assert_eq!(pts(7), pts(0));
    let diff = options[7]["max_abs_diff_vs_parity"].as_f64().unwrap();
    assert!(diff < 1e-3, "fast sine moved the render by {diff}");
    // Options that differ from another only in how a render places, stops or groups its
    // samples train alike: they are scored on that option's run, not a run of their own.
    let steps = |i: usize| {
        (
            options[i]["budget_iterations"].as_u64(),
            options[i]["ms_per_step"].as_f64(),
        )
    };
    for (extended, base) in [(4, 3), (5, 3), (6, 3)] {
        assert_eq!(
            steps(extended),
            steps(base),
            "option {extended} trained apart"
        );
    }
    assert!(steps(3).0.is_some_and(|n| n >= 2), "{:?}", steps(3));
    if cfg!(target_os = "linux") {
        let rss = json["training_peak_rss_mib"].as_f64();
        assert!(rss.is_some_and(|v| v > 0.0), "training peak RSS: {rss:?}");
    }
    assert!(dir.path().join("error_vs_time.png").is_file());
}

#[test]
fn bad_thresholds_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let out = s(dir.path());
    fails_with(
        pma(&["bench", "--quick", "--thresholds", "2", "--out", out]),
        "--thresholds",
    );
    exits_2_with(
        pma(&["bench", "--quick", "--early-stop", "0", "--out", out]),
        "--early-stop",
    );
}

/// `pma bench --quiet --forward-only` on `batch` with the golden model, into `out`.
fn forward_bench(batch: &Path, out: &Path, extra: &[&str]) -> Output {
    let model = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/golden/model.safetensors");
    let args = [
        "bench",
        "--quiet",
        "--forward-only",
        "--forward-batch",
        s(batch),
        "--forward-model",
        s(&model),
        "--out",
        s(out),
    ];
    pma(&[&args[..], extra].concat())
}

/// `--forward-only`: one warm-up and `--repeats` whole `pma forward` processes on a batch,
/// reported as the `forward` row (structure only; times are not asserted).
#[test]
fn forward_only_bench_times_whole_forward_processes() {
    let dir = tempfile::tempdir().unwrap();
    let batch = dir.path().join("batch.npz");
    super::forward::write_batch(&batch, None);
    let out = ok(forward_bench(&batch, dir.path(), &["--repeats", "2"]));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains("pma forward (whole process) 64 rays"),
        "{stdout}"
    );
    let json = read_json(&dir.path().join("bench.json"));
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
    let out = forward_bench(&batch, dir.path(), &[]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("skts"), "{err}");
}

#[test]
fn account_writes_the_step_counts() {
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
        &ACCOUNT_TINY[..],
        &["--rays", "32", "--official-json", s(&off), "--out", out],
    ]
    .concat()))
    .stdout;
    let text = String::from_utf8_lossy(&stdout);
    assert!(text.contains("official (32 rays)"), "{text}");
    let json = read_json(&dir.path().join("account.json"));
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
    let dir = tempfile::tempdir().unwrap();
    let base = [&ACCOUNT_TINY[..], &["--out", s(dir.path())]].concat();
    let refusals: &[(&[&str], &str)] = &[
        (&["--account-as", "gpu"], "--account-as"),
        (&["--rays", "31"], "--rays 31"),
        (
            &["--official-json", "/nonexistent/official.json"],
            "official.json",
        ),
        (&["--device-memory-gb", "0"], "--device-memory-gb"),
        (&["--device-memory-gb=-4"], "--device-memory-gb"),
        (&["--device-memory-gb", "nan"], "--device-memory-gb"),
        // A chunked step is not extrapolated.
        (
            &[
                "--rays",
                "32",
                "--chunk-rays",
                "8",
                "--extrapolate-from",
                "8",
            ],
            "one-pass",
        ),
        (&["--account-cull=1"], "--account-cull"),
        (&["--account-cull=-0.5"], "--account-cull"),
        (&["--account-cull=nan"], "--account-cull"),
        // A culled step is not extrapolated.
        (
            &[
                "--rays",
                "96",
                "--extrapolate-from",
                "32",
                "--account-cull",
                "0.6",
            ],
            "--account-cull",
        ),
    ];
    for (extra, needle) in refusals {
        exits_2_with(pma(&[&base[..], extra].concat()), needle);
    }
}

fn u(v: &serde_json::Value, key: &str) -> u64 {
    v[key].as_u64().unwrap_or_else(|| panic!("{key} in {v}"))
}

/// The rows of one ray set, by option name.
fn rows(
    json: &serde_json::Value,
    set: &str,
) -> std::collections::BTreeMap<String, serde_json::Value> {
    json[set]
        .as_array()
        .unwrap_or_else(|| panic!("{set} in {json}"))
        .iter()
        .map(|r| (r["option"].as_str().unwrap().to_string(), r.clone()))
        .collect()
}

/// What must hold between the rows of one ray set whatever the model: parity evaluates
/// everything; a culled ray skips all its samples (so ray culling's coarse and fine shares
/// are both the share of rays that hit a box); each way of leaving work out only removes
/// coarse samples from what the parts it combines keep (the coarse samples are placed
/// before any decision; the fine ones follow the coarse weights, which the options change).
/// The combined row keeps no more than the grid alone when both use one grid
/// (`shared_grid`); built grids differ per span, so then only culling bounds it.
fn check_rows(json: &serde_json::Value, set: &str, shared_grid: bool) {
    let r = rows(json, set);
    let (sc, sf) = (
        u(json, "coarse_samples_per_ray"),
        u(json, "fine_samples_per_ray"),
    );
    let p = &r["parity"];
    let rays = u(p, "rays");
    assert!(rays > 0, "{set}: {p}");
    for row in r.values() {
        assert_eq!(u(row, "rays"), rays, "{set}: {row}");
        assert_eq!(u(row, "coarse_samples"), rays * sc);
        assert_eq!(u(row, "fine_samples"), rays * sf);
        assert!(u(row, "coarse_evaluated") + u(row, "skipped_empty") <= rays * (sc + sf));
    }
    assert_eq!(u(p, "coarse_evaluated"), rays * sc, "{set}");
    assert_eq!(u(p, "fine_evaluated"), rays * sf, "{set}");
    assert_eq!(u(p, "skipped_empty"), 0);
    let ray = &r["rays"];
    let hit = u(ray, "coarse_evaluated") / sc;
    assert_eq!(u(ray, "coarse_evaluated"), hit * sc, "{set}: {ray}");
    assert_eq!(u(ray, "fine_evaluated"), hit * sf, "{set}: {ray}");
    assert!(
        hit < rays,
        "{set}: some rays of the body box miss every bone box"
    );
    let c = |name: &str| u(&r[name], "coarse_evaluated");
    assert!(c("samples<=0.6") < rays * sc);
    assert!(c("rays+samples<=0.6") <= c("rays").min(c("samples<=0.6")));
    let all = "rays+samples<=0.6+occupancy";
    assert!(c(all) <= c("rays+samples<=0.6"), "{set}");
    if shared_grid {
        assert!(c(all) <= c("occupancy"), "{set}");
    }
    for name in ["rays", "samples<=0.6", "rays+samples<=0.6"] {
        assert_eq!(u(&r[name], "skipped_empty"), 0, "{set}: {name}");
    }
}

#[test]
fn shares_count_the_samples_each_pass_runs() {
    let dir = tempfile::tempdir().unwrap();
    let out = |name: &str| dir.path().join(name);
    let s = |p: &std::path::Path| p.to_str().unwrap().to_string();
    let shares = |args: &[String]| {
        let mut a: Vec<String> = [
            "bench",
            "--shares",
            "--quick",
            "--quiet",
            "--shares-batches",
            "2",
        ]
        .iter()
        .map(|x| x.to_string())
        .collect();
        a.extend_from_slice(args);
        let refs: Vec<&str> = a.iter().map(String::as_str).collect();
        ok(pma(&refs))
    };
    let read = |d: &std::path::Path| -> serde_json::Value { read_json(&d.join("shares.json")) };

    // The preset trained in-process for --quick's 2 steps, its grid built from its density.
    let first = shares(&["--out".into(), s(&out("a"))]);
    let text = String::from_utf8_lossy(&first.stdout).to_string();
    assert!(text.contains("a count (deterministic"), "{text}");
    let json = read(&out("a"));
    assert_eq!(json["train_steps"], 2);
    assert_eq!(json["batches"], 2);
    assert!(json["grid"]
        .as_str()
        .unwrap()
        .starts_with("built over 2 training poses"));
    // One grid per span: the grid alone over the whole window, the culling row's narrower.
    let grid = json["grid"].as_str().unwrap();
    assert!(
        grid.contains("occupancy: |x̄| < 2.000") && grid.contains("+occupancy: |x̄| < 0.797"),
        "{grid}"
    );
    check_rows(&json, "render", false);
    check_rows(&json, "training_batches", false);

    // The same model with a grid of known occupancy saved with it: the grid is used as
    // saved, leaves samples out and keeps others, and two runs give the same counts.
    let model = out("a").join("shares-model.safetensors");
    let gridded = out("gridded.safetensors");
    pma_model::render::avatar::Avatar::load(&model, &candle_core::Device::Cpu)
        .unwrap()
        .with_occupancy(Some(crate::run::patterned_grid(5)))
        .save(&gridded)
        .unwrap();
    for d in ["b", "c"] {
        shares(&["--model".into(), s(&gridded), "--out".into(), s(&out(d))]);
    }
    let (b, c) = (read(&out("b")), read(&out("c")));
    assert_eq!(b, c, "counts repeat");
    assert!(b["grid"]
        .as_str()
        .unwrap()
        .starts_with("saved with the model (16^3"));
    assert!(b["train_steps"].is_null());
    for set in ["render", "training_batches"] {
        check_rows(&b, set, true);
        let occ = &rows(&b, set)["occupancy"];
        let (skipped, kept) = (u(occ, "skipped_empty"), u(occ, "coarse_evaluated"));
        assert!(skipped > 0 && kept > 0, "{set}: {occ}");
    }

    // Bad flags: one line, exit 2.
    let o = pma(&[
        "bench",
        "--shares",
        "--quick",
        "--shares-threshold",
        "1.5",
        "--out",
        &s(&out("d")),
    ]);
    exits_2_with(o, "--shares-threshold");
    let o = pma(&["bench", "--shares-steps", "3", "--out", &s(&out("d"))]);
    assert_eq!(o.status.code(), Some(2));
}

/// `--account --occupancy`: the accounted step trains with a grid (built by the unaccounted
/// step before it) and says what the grid left out; `--account-cull T` says what culling
/// left out; the same flags without either have no such block. A grid step is not
/// extrapolated.
#[test]
fn account_with_the_occupancy_grid() {
    let dir = tempfile::tempdir().unwrap();
    let account_printed = |name: &str, extra: &[&str]| -> (serde_json::Value, String) {
        let out = dir.path().join(name);
        let a = [
            &["--workers", "1"][..],
            &ACCOUNT_TINY,
            &["--rays", "32", "--out", s(&out)],
            extra,
        ]
        .concat();
        let stdout = ok(pma(&a)).stdout;
        (
            read_json(&out.join("account.json")),
            String::from_utf8_lossy(&stdout).into_owned(),
        )
    };
    let account = |name: &str, extra: &[&str]| account_printed(name, extra).0;
    let (culled, text) = account_printed("culled", &["--account-cull", "0.6"]);
    assert!(text.contains("culling (rays, w^p <= 0.6)"), "{text}");
    let left = &culled["left_out"];
    assert_eq!(left["sample_threshold"], 0.6);
    let (all, ran) = (u(left, "samples"), u(left, "samples_evaluated"));
    assert!(
        ran > 0 && ran < all,
        "{ran} of {all} samples ran the network"
    );
    let plain = account("plain", &[]);
    assert!(plain.get("left_out").is_none(), "{plain}");
    let grid = account("grid", &["--occupancy"]);
    let o = &grid["left_out"];
    assert!(o["occupied_fraction"].as_f64().is_some(), "{o}");
    assert!(o["sample_threshold"].is_null(), "{o}");
    let (samples, evaluated, skipped) = (
        u(o, "samples"),
        u(o, "samples_evaluated"),
        u(o, "skipped_empty"),
    );
    let cfg = pma_model::Config::tiny();
    assert_eq!(
        samples,
        32 * (cfg.n_samples + cfg.n_importance) as u64,
        "{o}"
    );
    assert!(skipped > 0 && evaluated + skipped <= samples, "{o}");
    // Fewer samples through the network: fewer matmul FLOPs in the step.
    assert!(u(&grid, "flops_per_step") < u(&plain, "flops_per_step"));

    let x = dir.path().join("x");
    let flags = [
        "--rays",
        "96",
        "--extrapolate-from",
        "32",
        "--occupancy",
        "--out",
        s(&x),
    ];
    let o = pma(&[&ACCOUNT_TINY[..], &flags].concat());
    exits_2_with(o, "--occupancy");
}

/// `--time-to-quality` on a few seconds of training: one row per option (parity first, the
/// recipe last), a curve per run that starts from the shared initial score, parity's own
/// minutes to its marks at most the marks, the table and the plot written; bad marks are
/// refused.
#[test]
fn time_to_quality_writes_the_table_and_plot() {
    let dir = tempfile::tempdir().unwrap();
    let run = |extra: &[&str]| {
        let out = s(dir.path());
        let base = [
            "bench",
            "--time-to-quality",
            "--quick",
            "--quiet",
            "--out",
            out,
        ];
        pma(&[&base[..], extra].concat())
    };
    ok(run(&[
        "--ttq-seeds",
        "5",
        "--ttq-marks",
        "0.02,0.04",
        "--ttq-points",
        "2",
    ]));
    let json = read_json(&dir.path().join("quality.json"));
    let options = json["options"].as_array().unwrap();
    let names: Vec<&str> = options
        .iter()
        .map(|o| o["name"].as_str().unwrap())
        .collect();
    assert_eq!(names.first(), Some(&"parity"));
    assert_eq!(names.last(), Some(&"all options together"));
    assert_eq!(names.len(), 12, "{names:?}");
    let initial = options[0]["seeds"][0]["runs"][0]["curve"][0][1]
        .as_f64()
        .unwrap();
    for o in options {
        let seed = &o["seeds"][0];
        let runs = seed["runs"].as_array().unwrap();
        // A budgeted option trains one run per mark.
        let per_mark = o["budgeted"].as_bool().unwrap();
        assert_eq!(runs.len(), if per_mark { 2 } else { 1 }, "{}", o["name"]);
        for r in runs {
            assert_eq!(r["curve"][0][1].as_f64(), Some(initial), "{}", o["name"]);
            assert!(r["iterations"].as_u64().unwrap() > 0, "{}", o["name"]);
        }
        assert_eq!(seed["psnr_at_marks"].as_array().unwrap().len(), 2);
    }
    // Parity reaches its own PSNR at each mark no later than the mark.
    for (t, m) in options[0]["minutes_to_parity"]
        .as_array()
        .unwrap()
        .iter()
        .zip([0.02, 0.04])
    {
        assert!(t.as_f64().is_some_and(|t| t <= m + 1e-9), "{t} vs {m}");
    }
    let md = std::fs::read_to_string(dir.path().join("quality.md")).unwrap();
    assert!(
        md.contains("| all options together (a run per mark) |"),
        "{md}"
    );
    assert!(dir.path().join("time_to_quality.png").is_file());
    // --ttq-options picks the rows; parity always runs; an unknown key is refused.
    ok(run(&[
        "--ttq-seeds",
        "5",
        "--ttq-marks",
        "0.02",
        "--ttq-points",
        "1",
        "--ttq-options",
        "recipe",
    ]));
    let json = read_json(&dir.path().join("quality.json"));
    let names: Vec<&str> = json["options"]
        .as_array()
        .unwrap()
        .iter()
        .map(|o| o["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["parity", "the fast recipe"]);
    exits_2_with(run(&["--ttq-options", "nope"]), "--ttq-options");

    exits_2_with(run(&["--ttq-marks", "2,1"]), "--ttq-marks");
}
