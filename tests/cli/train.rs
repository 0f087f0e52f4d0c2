//! `pma train` end to end on a tiny synthetic scene: run files, resume = uninterrupted run,
//! clear errors on bad input.

use std::collections::HashMap;
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use crate::run::{fails_with, kill, ok, pma, tiny_scene, wait_for};
use candle_core::{Device, Tensor};

/// The newest complete checkpoint directory of a run.
pub fn newest(run: &Path) -> std::path::PathBuf {
    pma_model::network::run_dir::newest_checkpoint(run)
        .unwrap()
        .unwrap_or_else(|| panic!("{} holds no complete checkpoint", run.display()))
        .path
}

fn tensors(path: &Path) -> HashMap<String, Tensor> {
    candle_core::safetensors::load(path, &Device::Cpu).unwrap()
}

fn assert_same_tensors(a: &Path, b: &Path) {
    let (ta, tb) = (tensors(a), tensors(b));
    assert_eq!(ta.len(), tb.len());
    for (name, x) in &ta {
        let y = &tb[name];
        let (x, y) = (
            x.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
            y.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
        );
        let same = x.iter().zip(&y).all(|(p, q)| p.to_bits() == q.to_bits());
        assert!(
            same,
            "{name} differs between {} and {}",
            a.display(),
            b.display()
        );
    }
}

#[test]
fn resumed_run_equals_uninterrupted_run_bit_for_bit() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"), 2);
    let data = data.to_str().unwrap();
    let a = tmp.path().join("a");
    let b = tmp.path().join("b");
    let (a_s, b_s) = (a.to_str().unwrap(), b.to_str().unwrap());

    ok(pma(&[
        "train", "--data", data, "--out", a_s, "--preset", "tiny", "--iters", "6", "--quiet",
    ]));
    ok(pma(&[
        "train", "--data", data, "--out", b_s, "--preset", "tiny", "--iters", "3", "--quiet",
    ]));
    ok(pma(&[
        "train", "--data", data, "--out", b_s, "--resume", "--iters", "6", "--quiet",
    ]));

    for f in [
        "config.toml",
        "model.safetensors",
        "log.csv",
        "psnr_vs_time.png",
    ] {
        assert!(a.join(f).is_file(), "missing {f}");
    }
    for f in [
        "config.toml",
        "model.safetensors",
        "train_state.safetensors",
        "log.csv",
    ] {
        assert!(newest(&a).join(f).is_file(), "missing checkpoint file {f}");
    }
    // The published model is the newest checkpoint's.
    assert_eq!(
        std::fs::read(a.join("model.safetensors")).unwrap(),
        std::fs::read(newest(&a).join("model.safetensors")).unwrap()
    );
    // The model is meant to be shipped and read by other accounts, like every other file.
    #[cfg(unix)]
    for run in [&a, &b] {
        crate::run::assert_default_modes(run);
    }
    assert_same_tensors(&a.join("model.safetensors"), &b.join("model.safetensors"));
    assert_same_tensors(
        &newest(&a).join("train_state.safetensors"),
        &newest(&b).join("train_state.safetensors"),
    );

    // Same losses in both logs (the resumed log continues the first session's rows).
    let rows = |p: &Path| -> Vec<(String, String)> {
        std::fs::read_to_string(p.join("log.csv"))
            .unwrap()
            .lines()
            .skip(1)
            .map(|l| {
                let f: Vec<&str> = l.split(',').collect();
                (f[0].to_string(), f[2].to_string())
            })
            .collect()
    };
    // Logged losses are means over the rows' intervals, and the resumed run's log has an
    // extra row where the first session ended, so intervals differ before the end; the last
    // row (iteration 6) covers the same steps in both runs.
    let (ra, rb) = (rows(&a), rows(&b));
    assert_eq!(ra.last(), rb.last(), "{ra:?} vs {rb:?}");
    assert!(rows(&a).iter().any(|r| r.0 == "6"), "{:?}", rows(&a));
}

#[test]
fn bad_input_gives_clear_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("run");
    let cfg = tmp.path().join("c.toml");
    std::fs::write(&cfg, "preset = \"tiny\"\n[train]\nrays_per_stp = 4\n").unwrap();
    let missing = Path::new("/nonexistent/x.npz");
    for (extra, needle) in [
        (&["--preset", "tiny"][..], "/nonexistent/x.npz"),
        (&["--preset", "huge"], "unknown preset \"huge\""),
        (&["--config", cfg.to_str().unwrap()], "train.rays_per_stp"),
        (&["--resume"], "config.toml"),
    ] {
        fails_with(
            pma(&[&train_args(missing, &out)[..], extra].concat()),
            needle,
        );
    }
}

/// Without the density noise a network whose initial densities are all zero never trains
/// (ReLU(raw) passes no gradient where raw ≤ 0): such a run is refused before it writes
/// anything, naming the setting; a seed whose network starts open trains without noise.
#[test]
fn a_run_that_cannot_open_its_density_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"), 2);
    let cfg = tmp.path().join("c.toml");
    let config = |seed: u64| {
        let text = format!(
            "preset = \"tiny\"\n[model]\ndensity_noise_std = 0.0\n[train]\nseed = {seed}\n"
        );
        std::fs::write(&cfg, text).unwrap();
    };
    let run = |name: &str| {
        let out = tmp.path().join(name);
        let args = [
            &train_args(&data, &out)[..],
            &["--config", cfg.to_str().unwrap()],
        ]
        .concat();
        (
            pma(&[&args[..], &["--iters", "2", "--quiet"]].concat()),
            out,
        )
    };
    // Seed 0 of the tiny network starts with every density closed on this scene.
    config(0);
    let (refused, out) = run("closed");
    assert_eq!(refused.status.code(), Some(2));
    fails_with(refused, "density_noise_std = 0");
    assert!(!out.exists(), "a refused run leaves {}", out.display());
    config(1);
    let (trained, out) = run("open");
    ok(trained);
    assert!(out.join("model.safetensors").is_file());
}

/// `pma train --data DATA --out OUT`.
fn train_args<'a>(data: &'a Path, out: &'a Path) -> [&'a str; 5] {
    let s = |p: &'a Path| p.to_str().unwrap();
    ["train", "--data", s(data), "--out", s(out)]
}

/// Without `--preset` a CPU run trains `cpu-small`, not the paper's GPU network, and its
/// first log line says so and why; a named preset is used as named, without that line.
#[test]
fn a_run_without_preset_gets_the_cpu_preset_and_says_why() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"), 2);
    let run = |dir: &str, extra: &[&str]| {
        let out = tmp.path().join(dir);
        let args = train_args(&data, &out);
        let o = ok(pma(
            &[&args[..], &["--iters", "1", "--quiet"], extra].concat()
        ));
        let config = std::fs::read_to_string(out.join("config.toml")).unwrap();
        (String::from_utf8_lossy(&o.stdout).into_owned(), config)
    };
    let (stdout, config) = run("chosen", &[]);
    assert_eq!(
        stdout.lines().next(),
        Some("preset cpu-small (chosen for the CPU; --preset default for the paper's network)"),
        "{stdout}"
    );
    assert!(config.contains("\npreset = \"cpu-small\"\n"), "{config}");
    let (stdout, config) = run("named", &["--preset", "tiny"]);
    assert!(!stdout.contains("chosen"), "{stdout}");
    assert!(config.contains("\npreset = \"tiny\"\n"), "{config}");
}

#[test]
fn existing_run_is_not_overwritten_without_resume() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"), 2);
    let out = tmp.path().join("run");
    let args = [&train_args(&data, &out)[..], &["--preset", "tiny"]].concat();
    ok(pma(&[&args[..], &["--iters", "1", "--quiet"]].concat()));
    fails_with(
        pma(&[&args[..], &["--iters", "2", "--quiet"]].concat()),
        "--resume",
    );
}

#[test]
fn ctrl_c_writes_a_checkpoint_that_resumes() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"), 2);
    let out = tmp.path().join("run");
    let child = Command::new(env!("CARGO_BIN_EXE_pma"))
        .args(train_args(&data, &out))
        .args(["--preset", "tiny", "--iters", "1000000", "--quiet"])
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // log.csv appears at the first log row (iteration 5 of `tiny`): steps have finished, so
    // the interrupt has a checkpoint to write however slow the machine is.
    wait_for("a first log row", 300, || out.join("log.csv").exists());
    kill(child.id(), "-INT");
    let output = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(130), "{stderr}");
    assert!(stderr.contains("interrupted at iteration"), "{stderr}");

    let state = tensors(&newest(&out).join("train_state.safetensors"));
    assert!(!state.is_empty());
    let bytes = std::fs::read(newest(&out).join("train_state.safetensors")).unwrap();
    let meta = safetensors_meta(&bytes);
    let done: u64 = meta["global_iter"].parse().unwrap();
    assert!(done >= 1, "no iteration finished before the interrupt");
    let iters = (done + 2).to_string();
    let resume = ["--resume", "--iters", &iters, "--quiet"];
    ok(pma(&[&train_args(&data, &out)[..], &resume].concat()));
}

/// Ctrl-C in the middle of a step of the paper-size `default` network on the CPU: the step
/// is undone, the checkpoint of the last complete step is written, and `--resume` continues
/// bit for bit like a run that was never interrupted.
///
/// The network is the `default` preset's; only the batch is cut (64 rays from 4 images
/// instead of 3,072 from 16) so that the uninterrupted and resumed steps fit a CI budget: a
/// full `default` step takes minutes in a debug build. Interruption is polled within a step
/// (per pose in the forward pass, per wave of ray chunks), so the batch size does not change
/// the latency being checked.
#[test]
fn ctrl_c_mid_step_on_the_default_network_resumes_bit_for_bit() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = tiny_scene(&tmp.path().join("scene"), 2);
    // Alone in its directory, so no held-out split is picked up: the run goes straight into
    // its first step.
    let data = tmp.path().join("alone").join("train.npz");
    std::fs::create_dir_all(data.parent().unwrap()).unwrap();
    std::fs::copy(&scene, &data).unwrap();
    let cfg = tmp.path().join("default_small_batch.toml");
    std::fs::write(
        &cfg,
        "preset = \"default\"\n[train]\nrays_per_step = 64\nimages_per_step = 4\n",
    )
    .unwrap();
    let train = |out: &Path, extra: &[&str]| -> Vec<String> {
        let mut v: Vec<String> = ["train", "--data", data.to_str().unwrap()]
            .iter()
            .chain(&["--out", out.to_str().unwrap(), "--quiet"])
            .map(|s| s.to_string())
            .collect();
        v.extend(extra.iter().map(|s| s.to_string()));
        v
    };
    let run = |args: Vec<String>| ok(pma(&args.iter().map(String::as_str).collect::<Vec<_>>()));

    let out = tmp.path().join("run");
    let child = Command::new(env!("CARGO_BIN_EXE_pma"))
        .args(train(
            &out,
            &["--config", cfg.to_str().unwrap(), "--iters", "1000"],
        ))
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // config.toml appears once the trainer exists; the first step starts right after and
    // takes seconds.
    wait_for("the start of training", 120, || {
        out.join("config.toml").exists()
    });
    std::thread::sleep(Duration::from_millis(300));
    let sent = Instant::now();
    kill(child.id(), "-INT");
    let output = child.wait_with_output().unwrap();
    let latency = sent.elapsed();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(130), "{stderr}");
    // Liveness, not speed: the longest stretch without a poll is the backward pass of one
    // ray chunk (about a second in a debug build), then a 12 MB checkpoint is written. 20 s
    // leaves room for a loaded 2-core CI machine; without polling inside the step, a
    // `default` step runs on for minutes.
    assert!(
        latency < Duration::from_secs(20),
        "exit took {latency:?} after SIGINT:\n{stderr}"
    );
    let ckpt = newest(&out);
    let bytes = std::fs::read(ckpt.join("train_state.safetensors")).unwrap();
    let done: u64 = safetensors_meta(&bytes)["global_iter"].parse().unwrap();
    assert!(
        stderr.contains(&format!("continues from iteration {done}")),
        "{stderr}"
    );
    #[cfg(unix)]
    crate::run::assert_default_modes(&out);
    // Only complete files: no temporary left behind.
    let mut names: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    let ckpt_name = ckpt.file_name().unwrap().to_string_lossy().into_owned();
    assert_eq!(
        names,
        [
            ".lock",
            &ckpt_name,
            "config.toml",
            "log.csv",
            "model.safetensors",
            "psnr_vs_time.png",
        ],
    );

    // One more iteration, resumed and uninterrupted: the step cut short left no trace.
    let target = (done + 1).to_string();
    let resumed = run(train(&out, &["--resume", "--iters", &target]));
    assert!(
        String::from_utf8_lossy(&resumed.stdout).contains(&format!("done at iteration {target}")),
        "{}",
        String::from_utf8_lossy(&resumed.stdout)
    );
    let straight = tmp.path().join("straight");
    run(train(
        &straight,
        &["--config", cfg.to_str().unwrap(), "--iters", &target],
    ));
    assert_same_tensors(
        &out.join("model.safetensors"),
        &straight.join("model.safetensors"),
    );
    assert_same_tensors(
        &newest(&out).join("train_state.safetensors"),
        &newest(&straight).join("train_state.safetensors"),
    );
}

/// The header metadata of a safetensors file.
fn safetensors_meta(bytes: &[u8]) -> HashMap<String, String> {
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    let meta = header["__metadata__"]
        .as_object()
        .unwrap()
        .iter()
        .map(|(k, v)| (k.clone(), v.as_str().unwrap().to_string()))
        .collect();
    meta
}
