//! `pma train --device cpu,cpu`: two CPU ranks (threads exchanging host buffers, the test
//! double of the GPU group) train as one device on the union batch, stop together on Ctrl-C
//! with one checkpoint, end with a clear error when a rank fails, and resume as one run.
//!
//! `--workers 1` keeps the one-device reference in the chunks it is given: with more
//! workers a step that fits one chunk is split over them, which changes the summation order.
//! The reference runs in chunks of half the step's rays, the ranks' slices: under
//! `--deterministic` the group sums the slices' gradients in rank order, as the one device
//! sums its chunks, so the models are equal bit for bit.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::run::{exits_2_with, kill, ok, pma, pma_within, tiny_scene, wait_for};
use candle_core::Device;
use pma_model::network::run_dir::LOCK_FILE;

/// `tiny`'s rays per step over two ranks.
const HALF: &str = "64";

fn train(data: &Path, out: &Path, device: &str, extra: &[&str]) -> Vec<String> {
    let mut args: Vec<String> = [
        "--workers",
        "1",
        "--deterministic",
        "train",
        "--data",
        data.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--device",
        device,
        "--chunk-rays",
        HALF,
        "--quiet",
    ]
    .map(String::from)
    .to_vec();
    args.extend(extra.iter().map(|s| s.to_string()));
    args
}

fn run(args: &[String]) -> std::process::Output {
    pma(&args.iter().map(String::as_str).collect::<Vec<_>>())
}

/// The model of a run directory as raw bits, by name.
fn model_bits(run: &Path) -> Vec<(String, Vec<u32>)> {
    let mut t: Vec<(String, Vec<u32>)> =
        candle_core::safetensors::load(run.join("model.safetensors"), &Device::Cpu)
            .unwrap()
            .into_iter()
            .map(|(n, t)| {
                let v = t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
                (n, v.into_iter().map(f32::to_bits).collect())
            })
            .collect();
    t.sort();
    t
}

fn assert_same_model(a: &Path, b: &Path) {
    let (ma, mb) = (model_bits(a), model_bits(b));
    assert_eq!(ma.len(), mb.len());
    for ((name, x), (_, y)) in ma.iter().zip(&mb) {
        let differ = x.iter().zip(y).filter(|(p, q)| p != q).count();
        assert_eq!(
            differ,
            0,
            "{name}: {differ} values differ between {} and {}",
            a.display(),
            b.display()
        );
    }
}

/// The iteration of a run's newest checkpoint.
fn checkpoint_iter(run: &Path) -> u64 {
    pma_model::network::run_dir::newest_checkpoint(run)
        .unwrap()
        .unwrap_or_else(|| panic!("no checkpoint in {}", run.display()))
        .iteration
}

/// The run's lock was released (its file stays, emptied of the holder's PID).
fn assert_unlocked(run: &Path) {
    let held = std::fs::read_to_string(run.join(LOCK_FILE)).unwrap_or_default();
    assert!(
        held.is_empty(),
        "{} still names a holder: {held}",
        run.display()
    );
}

#[test]
fn two_cpu_ranks_train_and_resume_as_one_device() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"), 2);
    let (one, two, resumed) = (
        tmp.path().join("one"),
        tmp.path().join("two"),
        tmp.path().join("resumed"),
    );
    let tiny = ["--preset", "tiny", "--iters", "6"];
    ok(run(&train(&data, &one, "cpu", &tiny)));
    let out = ok(run(&train(&data, &two, "cpu,cpu", &tiny)));
    assert!(
        String::from_utf8_lossy(&out.stdout).contains("done at iteration 6"),
        "{}",
        String::from_utf8_lossy(&out.stdout)
    );
    assert_same_model(&one, &two);
    // One writer: the run directory of the group is a one-device run's.
    assert!(two.join("log.csv").is_file() && two.join("config.toml").is_file());
    assert_unlocked(&two);

    ok(run(&train(
        &data,
        &resumed,
        "cpu,cpu",
        &["--preset", "tiny", "--iters", "3"],
    )));
    ok(run(&train(
        &data,
        &resumed,
        "cpu,cpu",
        &["--resume", "--iters", "6"],
    )));
    assert_same_model(&one, &resumed);
}

/// `--fast` trains on two ranks as on one device (six steps: culling and averaged weights;
/// the grid's warm-up is longer, `train_data_parallel` covers the grid).
#[test]
fn the_fast_recipe_trains_on_two_cpu_ranks_as_one_device() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"), 2);
    let (one, two) = (tmp.path().join("one"), tmp.path().join("two"));
    let fast = ["--preset", "tiny", "--iters", "6", "--fast"];
    ok(run(&train(&data, &one, "cpu", &fast)));
    ok(run(&train(&data, &two, "cpu,cpu", &fast)));
    assert_same_model(&one, &two);
}

#[test]
fn ctrl_c_stops_both_ranks_at_one_step_and_the_run_resumes() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"), 2);
    let out = tmp.path().join("run");
    let args = train(
        &data,
        &out,
        "cpu,cpu",
        &["--preset", "tiny", "--iters", "1000000"],
    );
    let child = Command::new(env!("CARGO_BIN_EXE_pma"))
        .args(&args)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // The first log row (iteration 5) means steps finished on both ranks.
    wait_for("a log row", 300, || out.join("log.csv").exists());
    let sent = Instant::now();
    kill(child.id(), "-INT");
    let output = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(130), "{stderr}");
    assert!(stderr.contains("interrupted at iteration"), "{stderr}");
    assert!(
        sent.elapsed() < Duration::from_secs(60),
        "the group took {:?} to stop",
        sent.elapsed()
    );
    let stopped = checkpoint_iter(&out);
    assert!(stopped >= 5);
    assert!(
        stderr.contains(&format!("interrupted at iteration {stopped}")),
        "{stderr}"
    );
    assert_unlocked(&out);
    let target = (stopped + 2).to_string();
    ok(run(&train(
        &data,
        &out,
        "cpu,cpu",
        &["--resume", "--iters", &target],
    )));
    assert_eq!(checkpoint_iter(&out), stopped + 2);

    // The same iterations without an interruption give the same model.
    let straight = tmp.path().join("straight");
    ok(run(&train(
        &data,
        &straight,
        "cpu,cpu",
        &["--preset", "tiny", "--iters", &target],
    )));
    assert_same_model(&straight, &out);
}

#[test]
fn a_failing_rank_stops_the_group_with_a_clear_error_and_the_run_resumes() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"), 2);
    let (out, straight) = (tmp.path().join("run"), tmp.path().join("straight"));
    ok(run(&train(
        &data,
        &out,
        "cpu,cpu",
        &["--preset", "tiny", "--iters", "3"],
    )));
    // Rank 1 fails before iteration 5, as a rank whose device or process broke would.
    let args = train(&data, &out, "cpu,cpu", &["--resume", "--iters", "8"]);
    let start = Instant::now();
    let mut child = Command::new(env!("CARGO_BIN_EXE_pma"));
    child.args(&args).env("PMA_FAULT_RANK_FAILS", "1@5");
    let failed = child.output().unwrap();
    let stderr = String::from_utf8_lossy(&failed.stderr);
    assert_eq!(failed.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("rank 1 of 2"), "{stderr}");
    assert!(stderr.contains("iteration 5"), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(start.elapsed() < Duration::from_secs(120));
    // The last complete checkpoint is intact, and the group resumes from it.
    assert_eq!(checkpoint_iter(&out), 3);
    ok(run(&train(
        &data,
        &out,
        "cpu,cpu",
        &["--resume", "--iters", "8"],
    )));
    ok(run(&train(
        &data,
        &straight,
        "cpu,cpu",
        &["--preset", "tiny", "--iters", "8"],
    )));
    assert_same_model(&straight, &out);
}

#[test]
fn bad_device_lists_are_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"), 2);
    let out = tmp.path().join("run");
    let d = data.to_str().unwrap();
    let o = out.to_str().unwrap();
    for (device, needle) in [
        ("cpu,", "unknown device"),
        ("cpu,tpu", "unknown device"),
        ("cuda:0,0", "appears twice"),
        ("cuda:0,1", "needs a binary built"),
    ] {
        let out = pma_within(
            &[
                "train", "--data", d, "--out", o, "--device", device, "--quiet",
            ],
            60,
        );
        exits_2_with(out, needle);
    }
    exits_2_with(
        pma(&[
            "train",
            "--data",
            d,
            "--out",
            o,
            "--group-timeout",
            "5",
            "--quiet",
        ]),
        "--group-timeout needs several devices",
    );
    // The error map draws rays from the errors one device saw: one rank sees only its
    // slice. Refused before the run directory is made.
    let out = pma_within(
        &[
            "train",
            "--data",
            d,
            "--out",
            o,
            "--device",
            "cpu,cpu",
            "--preset",
            "tiny",
            "--iters",
            "2",
            "--quiet",
            "--error-map",
        ],
        60,
    );
    exits_2_with(out, "the error map");
    assert!(
        !std::path::Path::new(o).exists(),
        "--error-map: the run directory was left"
    );
    // --distributed needs a launcher's variables, then a CUDA device for its local rank.
    let launcher_vars = [
        "RANK",
        "WORLD_SIZE",
        "LOCAL_RANK",
        "SLURM_PROCID",
        "SLURM_NTASKS",
    ];
    let mut bare = Command::new(env!("CARGO_BIN_EXE_pma"));
    bare.args(["train", "--data", d, "--out", o, "--distributed", "--quiet"]);
    for v in launcher_vars {
        bare.env_remove(v);
    }
    exits_2_with(bare.output().unwrap(), "no launcher's rank and size");
    let mut ranked = Command::new(env!("CARGO_BIN_EXE_pma"));
    ranked
        .args(["train", "--data", d, "--out", o, "--distributed", "--quiet"])
        .envs([("RANK", "1"), ("WORLD_SIZE", "2"), ("LOCAL_RANK", "1")]);
    exits_2_with(ranked.output().unwrap(), "cuda:1");
    // Two ranks cannot split a pose's rays that number fewer than them.
    let cfg = tmp.path().join("one-ray.toml");
    std::fs::write(
        &cfg,
        "preset = \"tiny\"\n[train]\nrays_per_step = 2\nimages_per_step = 2\n",
    )
    .unwrap();
    let out = pma(&[
        "train",
        "--data",
        d,
        "--out",
        o,
        "--config",
        cfg.to_str().unwrap(),
        "--device",
        "cpu,cpu",
        "--iters",
        "1",
        "--quiet",
    ]);
    exits_2_with(out, "cannot be split over 2 devices");
}
