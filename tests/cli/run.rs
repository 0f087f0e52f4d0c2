//! Running the `pma` binary and judging its exit, shared by every end-to-end test.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

pub fn pma(args: &[&str]) -> Output {
    pma_env(args, &[])
}

/// Runs pma with the environment variables `env` set.
pub fn pma_env(args: &[&str], env: &[(&str, &str)]) -> Output {
    let mut c = Command::new(env!("CARGO_BIN_EXE_pma"));
    c.args(args).stdin(std::process::Stdio::null());
    for (k, v) in env {
        c.env(k, v);
    }
    c.output().expect("running pma")
}

/// A path as a command-line argument.
pub fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// `pma eval --model MODEL --data DATA EXTRA...`.
pub fn pma_eval(model: &Path, data: &Path, extra: &[&str]) -> Output {
    pma(&[&["eval", "--model", s(model), "--data", s(data)], extra].concat())
}

/// Runs pma, failing the test if it has not ended within `secs` (a hang).
pub fn pma_within(args: &[&str], secs: u64) -> Output {
    use std::process::Stdio;
    use std::time::{Duration, Instant};
    let mut child = Command::new(env!("CARGO_BIN_EXE_pma"))
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(secs);
    loop {
        if child.try_wait().unwrap().is_some() {
            return child.wait_with_output().unwrap();
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let out = child.wait_with_output().unwrap();
            panic!(
                "pma {args:?} still running after {secs} s (a hang): {}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Sends `sig` (`-INT`, `-TERM`...) to the process `pid`.
pub fn kill(pid: u32, sig: &str) {
    let st = Command::new("kill")
        .args([sig, &pid.to_string()])
        .status()
        .unwrap();
    assert!(st.success());
}

/// Waits until `ready`, failing the test after `secs` seconds.
pub fn wait_for(what: &str, secs: u64, mut ready: impl FnMut() -> bool) {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(secs);
    while !ready() {
        assert!(
            std::time::Instant::now() < deadline,
            "{what} within {secs} s"
        );
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
}

/// The run succeeded; otherwise fail with its exit status, stdout and stderr.
pub fn ok(out: Output) -> Output {
    assert!(
        out.status.success(),
        "pma failed: {}\nstdout:\n{}\nstderr:\n{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// The run failed cleanly: non-zero exit, `needle` in stderr, and no panic.
pub fn fails_with(out: Output, needle: &str) {
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success(),
        "expected failure containing {needle:?}, got success"
    );
    assert!(err.contains(needle), "stderr lacks {needle:?}:\n{err}");
    assert!(!err.contains("panicked"), "{err}");
}

/// A JSON file a command wrote.
pub fn read_json(path: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Exit status 2 (refused input: one line of pma's own, or a usage error), `needle` in
/// stderr, and no panic.
pub fn exits_2_with(out: Output, needle: &str) {
    assert_eq!(
        out.status.code(),
        Some(2),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    fails_with(out, needle);
}

/// Exit status `code`, exactly one stderr line holding every needle, no panic, no text of
/// a dependency's destructor; that line.
pub fn exits(out: &Output, code: i32, needles: &[&str]) -> String {
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert_eq!(out.status.code(), Some(code), "expected exit {code}: {err}");
    assert_eq!(err.trim_end().lines().count(), 1, "not one line:\n{err}");
    for n in needles {
        assert!(err.contains(n), "stderr lacks {n:?}: {err}");
    }
    for bad in ["panicked", "ZipWriter", "backtrace"] {
        assert!(!err.contains(bad), "{err}");
    }
    err.trim_end().to_string()
}

/// Refused input: [`exits`] with status 2.
pub fn refused(out: &Output, needles: &[&str]) -> String {
    exits(out, 2, needles)
}

/// `pma train --data DATA --out RUN --preset tiny --iters ITERS --quiet EXTRA...` with `env`
/// set; the run must succeed.
pub fn train_tiny_with(
    data: &Path,
    run: &Path,
    iters: &str,
    extra: &[&str],
    env: &[(&str, &str)],
) -> Output {
    let args = [
        "train",
        "--data",
        s(data),
        "--out",
        s(run),
        "--preset",
        "tiny",
        "--iters",
        iters,
        "--quiet",
    ];
    ok(pma_env(&[&args[..], extra].concat(), env))
}

/// [`train_tiny_with`] without extra flags: the trained model's path.
pub fn train_tiny(data: &Path, run: &Path, iters: &str) -> PathBuf {
    train_tiny_with(data, run, iters, &[], &[]);
    run.join("model.safetensors")
}

/// An untrained `tiny` avatar (seed 1) on the synthetic scene's rest pose, saved in `dir`.
pub fn untrained_tiny(dir: &Path) -> PathBuf {
    let path = dir.join("tiny.safetensors");
    pma_model::render::avatar::Avatar::new(
        pma_model::Config::tiny(),
        &pma_data::synth::rest_pose(),
        1,
        &candle_core::Device::Cpu,
    )
    .unwrap()
    .save(&path)
    .unwrap();
    path
}

/// The embedded AIST++ dance converted by `pma convert motion` to `out` with `extra` flags;
/// `out`.
pub fn aist_motion(out: &Path, extra: &[&str]) -> PathBuf {
    let src = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/pma-data/assets/motion/aist_demo.npz"
    );
    ok(pma(
        &[&["convert", "motion", src, "-o", s(out)], extra].concat()
    ));
    out.to_path_buf()
}

/// A converted motion file.
pub fn read_motion(path: &Path) -> pma_data::dataset::Dataset {
    use pma_data::dataset::{Dataset, Profile, ReadOptions};
    Dataset::read(path, &ReadOptions::new(Profile::Motion)).unwrap()
}

/// A resolution-16 occupancy grid where about 30 % of each joint's cells hold density 1 (a
/// fixed pseudo-random pattern drawn from `seed`) and the rest 0; no dilation.
pub fn patterned_grid(seed: u64) -> pma_model::network::occupancy::OccupancyGrid {
    use pma_model::network::occupancy::{OccupancyConfig, OccupancyGrid};
    let cfg = OccupancyConfig {
        resolution: 16,
        dilation: 0,
        ..Default::default()
    };
    let mut grid = OccupancyGrid::new(cfg).unwrap();
    let mut state = seed;
    for j in 0..24 {
        for c in 0..16 * 16 * 16 {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let occupied = (state >> 40) % 10 < 3;
            grid.update_max(j, c, if occupied { 1.0 } else { 0.0 })
                .unwrap();
        }
    }
    grid.finish_refresh();
    grid
}

/// The number in `text` just before `word` (e.g. 12 in "12 of" for word "of").
pub fn number_before(text: &str, word: &str) -> u64 {
    let head = &text[..text
        .find(word)
        .unwrap_or_else(|| panic!("{word:?} in {text:?}"))];
    head.split_whitespace().last().unwrap().parse().unwrap()
}

/// A scene small enough for debug builds: 24 px, 2 training cameras, 3 frames, one test
/// camera every `novel_view_stride` frames. Returns the training split's path.
pub fn tiny_scene(dir: &Path, novel_view_stride: usize) -> PathBuf {
    let cfg = pma_data::synth::SynthConfig {
        novel_view_stride,
        ..pma_data::synth::SynthConfig::small(24, 2, 3)
    };
    pma_data::synth::generate(&cfg, dir, &mut |_, _| {}).expect("synth");
    dir.join("train.npz")
}

/// A [`tiny_scene`] in `dir/scene` and a `tiny` model trained `iters` iterations on it in
/// `dir/run`: the scene directory and the model's path.
pub fn trained_scene(dir: &Path, novel_view_stride: usize, iters: &str) -> (PathBuf, PathBuf) {
    let scene = dir.join("scene");
    let train = tiny_scene(&scene, novel_view_stride);
    let model = train_tiny(&train, &dir.join("run"), iters);
    (scene, model)
}

/// Every file under `dir` (recursively) has the mode `File::create` gives: 0666 less the
/// umask (0644 under the usual 022). pma inherits the test's umask.
#[cfg(unix)]
pub fn assert_default_modes(dir: &Path) {
    use std::os::unix::fs::PermissionsExt;
    let umask = std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("Umask:"))
                .and_then(|v| u32::from_str_radix(v.trim(), 8).ok())
        })
        .unwrap_or(0o022);
    let want = 0o666 & !umask;
    let mut files = 0;
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).unwrap() {
            let path = entry.unwrap().path();
            let meta = std::fs::symlink_metadata(&path).unwrap();
            if meta.is_dir() {
                stack.push(path);
            } else {
                let mode = meta.permissions().mode() & 0o777;
                assert_eq!(
                    mode,
                    want,
                    "{}: mode {mode:o}, expected {want:o}",
                    path.display()
                );
                files += 1;
            }
        }
    }
    assert!(files > 0, "no files under {}", dir.display());
}

/// Make a FIFO at `path` (no writer: opening it for reading would block).
#[cfg(unix)]
pub fn mkfifo(path: &Path) {
    let c = std::ffi::CString::new(path.to_str().unwrap()).unwrap();
    // SAFETY: a plain libc call with a valid NUL-terminated path.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
}
