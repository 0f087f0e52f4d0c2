//! Running the `pma` binary and judging its exit, shared by every end-to-end test.

use std::process::{Command, Output};

pub fn pma(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_pma"))
        .args(args)
        .output()
        .expect("running pma")
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
