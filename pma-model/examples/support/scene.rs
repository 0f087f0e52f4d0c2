#![allow(dead_code)]
//! Shared by the measurement examples: a small synthetic scene of 16 training images and
//! helpers to read peak memory and take medians.

use std::path::Path;
use std::sync::Arc;

use pma_data::dataset::{Dataset, Profile, ReadOptions};

/// 4 cameras × 4 walk frames at 96×96: 16 training images, as many as the paper's step uses.
pub fn scene(dir: &Path) -> Result<Arc<Dataset>, Box<dyn std::error::Error>> {
    let cfg = pma_data::synth::SynthConfig::small(96, 4, 4);
    pma_data::synth::generate(&cfg, dir, &mut |_, _| {})?;
    Ok(Arc::new(Dataset::read(
        dir.join("train.npz"),
        &ReadOptions::new(Profile::Train),
    )?))
}

/// Peak resident set size of this process so far (`VmHWM`), in MiB.
pub fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

/// Median wall seconds of `f` over `runs` calls, after one untimed warm-up call.
pub fn median_seconds(
    runs: usize,
    mut f: impl FnMut() -> Result<(), Box<dyn std::error::Error>>,
) -> Result<f64, Box<dyn std::error::Error>> {
    f()?;
    let mut times = Vec::with_capacity(runs);
    for _ in 0..runs {
        let t = std::time::Instant::now();
        f()?;
        times.push(t.elapsed().as_secs_f64());
    }
    Ok(median(times))
}

/// `--name value` from the command line, parsed, or `default`.
pub fn arg<T: std::str::FromStr>(name: &str, default: T) -> T {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}
