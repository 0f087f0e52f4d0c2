//! Marks `pma view`'s browser test ignored when it cannot run: outside CI (`CI=true`) on a
//! machine without Chromium, `cargo test` then lists it as ignored, with the reason, rather
//! than passing it silently. Under CI a missing Chromium still fails the test.

use std::path::Path;

/// Where the test looks for Chromium (`tests/cli/cdp.rs`, `chromium`).
const CHROMIUM: &str = "/usr/bin/chromium";

fn main() {
    println!("cargo::rustc-check-cfg=cfg(pma_no_chromium)");
    println!("cargo::rerun-if-env-changed=PMA_CHROMIUM");
    println!("cargo::rerun-if-env-changed=CI");
    // A path that does not exist would rerun this script on every build: watch the
    // directory Chromium is installed into instead.
    let bin = Path::new(CHROMIUM);
    let watched = if bin.exists() {
        bin
    } else {
        bin.parent().unwrap_or(bin)
    };
    if watched.exists() {
        println!("cargo::rerun-if-changed={}", watched.display());
    }
    let in_ci = std::env::var("CI").as_deref() == Ok("true");
    let found = std::env::var_os("PMA_CHROMIUM").is_some() || bin.is_file();
    if !found && !in_ci {
        println!("cargo::rustc-cfg=pma_no_chromium");
    }
}
