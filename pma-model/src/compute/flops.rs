//! Cost accounting for throughput reports: the matmul FLOPs of one network point and an
//! estimate of the machine's fp32 peak, so a GFLOP/s figure can be read as a share of it.
//!
//! FLOPs count 2·in·out per linear layer per row (per joint for the per-joint layers);
//! element-wise work, the GNN (once per pose) and ray casting are left out. A training step
//! costs [`TRAIN_FACTOR`] times the forward: every matmul is joined by one for the input
//! gradient and one for the weight gradient.
//!
//! The peak is cores × GHz × FLOP/cycle/core from /proc/cpuinfo: `cpu MHz` (the current
//! clock, so a lower bound of the boost peak), the number of `processor` entries, and 32
//! FLOP/cycle with `avx2`+`fma` or `avx512f` (two 8-wide FMA pipes; Zen 4 runs 512-bit FMAs
//! as two 256-bit halves), 8 otherwise.

use crate::Config;

/// Matmul FLOPs of a training step per point over those of a forward evaluation. The
/// layers that read the sample points need no input gradient, so this overcounts by their
/// share (under 0.5 % of the paper model's FLOPs).
pub const TRAIN_FACTOR: f64 = 3.0;

/// Matmul FLOPs of one network evaluation of one point (see the module docs).
pub fn per_point(c: &Config) -> f64 {
    let lin = |i: usize, o: usize| 2.0 * i as f64 * o as f64;
    let j = c.n_joints as f64;
    let (ce, h, f) = (c.point_enc_dim, c.win_hidden, c.freq_dim);
    // World → joint frames ([3,72]) and bone alignment (24 × [3,3]).
    let mut total = lin(3, 3 * c.n_joints) + j * lin(3, 3);
    // Both point encoders and the window's point projection, per joint.
    total += j * (2.0 * lin(3, ce) + lin(ce, h));
    // Window: two sine layers and the last layer; f^m = w·g.
    total += 2.0 * lin(h, h) + lin(h, c.n_joints) + lin(c.n_joints, c.gnn_width.max(h));
    // Pose extractor: sine layers, then the frequency/phase head (2 · n_pm · freq_dim).
    let ph = c.pose_extractor_hidden;
    total += lin(h, ph)
        + (c.pose_extractor_depth.saturating_sub(1)) as f64 * lin(ph, ph)
        + lin(ph, 2 * c.n_pm * f);
    // Modulated layers.
    total += lin(c.n_joints * ce, f) + (c.n_pm.saturating_sub(1)) as f64 * lin(f, f);
    // Density trunk (skip layers take the modulator output again), σ head, feature,
    // colour head on [feature; SH; frame code].
    let s_dim = c.n_pm * f;
    let w = c.trunk_width;
    total += lin(s_dim, w);
    for l in 1..c.trunk_depth {
        let input = if c.skips.contains(&(l - 1)) {
            w + s_dim
        } else {
            w
        };
        total += lin(input, w);
    }
    let view = c.sh_degree * c.sh_degree + if c.use_framecodes { c.framecode_ch } else { 0 };
    total += lin(w, 1) + lin(w, w) + lin(w + view, c.view_width) + lin(c.view_width, 3);
    total
}

/// Estimated fp32 peak of this machine in GFLOP/s and how it was estimated.
pub fn fp32_peak() -> (f64, String) {
    let info = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let cores = info
        .lines()
        .filter(|l| l.starts_with("processor"))
        .count()
        .max(1);
    let mhz = info
        .lines()
        .find(|l| l.starts_with("cpu MHz"))
        .and_then(|l| l.split(':').nth(1))
        .and_then(|v| v.trim().parse::<f64>().ok())
        .unwrap_or(2000.0);
    let flags = info
        .lines()
        .find(|l| l.starts_with("flags"))
        .unwrap_or_default();
    let has = |f: &str| flags.split_whitespace().any(|x| x == f);
    let per_cycle = if has("avx512f") || (has("avx2") && has("fma")) {
        32.0
    } else {
        8.0
    };
    let peak = cores as f64 * mhz / 1e3 * per_cycle;
    (
        peak,
        format!(
            "{cores} logical cores x {:.2} GHz (cpu MHz) x {per_cycle} FLOP/cycle/core (avx2+fma: two 8-wide FMA pipes)",
            mhz / 1e3
        ),
    )
}
