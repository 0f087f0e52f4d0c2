//! Running the `pma` binary and judging its exit, shared by every end-to-end test.

use std::process::{Command, Output};

pub fn pma(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_pma"))
        .args(args)
        .output()
        .expect("running pma")
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

/// A scene small enough for debug builds: 24 px, 2 training cameras, 3 frames, one test
/// camera every `novel_view_stride` frames. Returns the training split's path.
pub fn tiny_scene(dir: &std::path::Path, novel_view_stride: usize) -> std::path::PathBuf {
    let cfg = pma_data::synth::SynthConfig {
        res: 24,
        train_cams: 2,
        test_cams: 1,
        frames: 3,
        novel_view_stride,
        novel_pose_walk: 1,
        novel_pose_dance: 1,
        ..Default::default()
    };
    pma_data::synth::generate(&cfg, dir, &mut |_, _| {}).expect("synth");
    dir.join("train.npz")
}

/// Every file under `dir` (recursively) has the mode `File::create` gives: 0666 less the
/// umask (0644 under the usual 022). pma inherits the test's umask.
#[cfg(unix)]
pub fn assert_default_modes(dir: &std::path::Path) {
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
pub fn mkfifo(path: &std::path::Path) {
    let c = std::ffi::CString::new(path.to_str().unwrap()).unwrap();
    // SAFETY: a plain libc call with a valid NUL-terminated path.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
}
