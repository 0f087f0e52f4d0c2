//! Per-stage timing of training steps and renders, on when the environment has
//! `PMA_PROFILE=1`.
//!
//! GPU work is asynchronous: a host timer around a stage measures only the launches. Each
//! [`mark`] therefore synchronises the device first, so the time between two marks is the
//! stage's own GPU time (plus the launch overhead the sync exposes). The syncs slow the step
//! down: the profile is for finding the expensive stage, not for it/s figures. Off (the
//! default), a mark is one relaxed load.
//!
//! The per-step line goes straight to stderr ([`print_step`], and [`print_render`] once per
//! render of several frames): a diagnostic that must reach a log file even when the front
//! end shows nothing (no terminal, `--quiet`).
//!
//! Marks are attributed per thread: with several CPU workers running chunks at once the
//! stages overlap, so the figures are meaningful with one worker (GPU runs, or
//! `RAYON_NUM_THREADS=1`).

use std::cell::Cell;
use std::sync::{Mutex, OnceLock};
use std::time::Instant;

use candle_core::Device;

/// Whether `PMA_PROFILE=1` is set (read once).
pub fn enabled() -> bool {
    static ON: OnceLock<bool> = OnceLock::new();
    *ON.get_or_init(|| std::env::var("PMA_PROFILE").is_ok_and(|v| v == "1"))
}

thread_local! {
    static LAST: Cell<Option<Instant>> = const { Cell::new(None) };
}

/// (seconds, count) per stage since the last [`take_report`], in first-seen order.
static TOTALS: Mutex<Vec<(&'static str, f64, u64)>> = Mutex::new(Vec::new());

/// Start this thread's timeline (after a device sync), e.g. at the top of a step.
pub fn start(device: &Device) {
    if !enabled() {
        return;
    }
    let _ = device.synchronize();
    LAST.with(|l| l.set(Some(Instant::now())));
}

/// End stage `name`: wait for the device, then add the time since the previous mark (or
/// [`start`]) to the stage. A mark without a start only starts the timeline. In an accounted
/// run ([`crate::compute::account`]) it also closes the stage's counts.
pub fn mark(name: &'static str, device: &Device) {
    crate::compute::account::mark(name);
    if !enabled() {
        return;
    }
    let _ = device.synchronize();
    let now = Instant::now();
    if let Some(prev) = LAST.with(|l| l.replace(Some(now))) {
        let dt = now.duration_since(prev).as_secs_f64();
        let mut t = TOTALS.lock().unwrap_or_else(|e| e.into_inner());
        match t.iter_mut().find(|(n, _, _)| *n == name) {
            Some(e) => {
                e.1 += dt;
                e.2 += 1;
            }
            None => t.push((name, dt, 1)),
        }
    }
}

/// The stages since the last report, one `name ms (count)` each, and reset; `None` when
/// profiling is off or nothing was marked.
pub fn take_report() -> Option<String> {
    if !enabled() {
        return None;
    }
    let mut t = TOTALS.lock().unwrap_or_else(|e| e.into_inner());
    if t.is_empty() {
        return None;
    }
    let total: f64 = t.iter().map(|e| e.1).sum();
    let mut parts = vec![format!("total {:.1} ms", total * 1e3)];
    for (name, s, n) in t.drain(..) {
        parts.push(format!("{name} {:.1} ms ({n}x)", s * 1e3));
    }
    Some(parts.join(", "))
}

/// Print the stages of step `iter` to stderr and reset (nothing when profiling is off).
pub fn print_step(iter: u64) {
    if let Some(p) = take_report() {
        eprintln!("iteration {iter} profile (PMA_PROFILE=1): {p}");
    }
}

/// Print the stages summed over a render of `frames` frames to stderr and reset (nothing
/// when profiling is off). Each image chunk starts its own timeline.
pub fn print_render(frames: usize) {
    if let Some(p) = take_report() {
        eprintln!("render of {frames} frame(s) profile (PMA_PROFILE=1): {p}");
    }
}
