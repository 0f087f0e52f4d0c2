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
