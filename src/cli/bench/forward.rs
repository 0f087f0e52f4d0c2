//! `pma bench --forward-batch`: the wall time of whole `pma forward` processes of this
//! executable (start-up, loading, the pass, writing), as a user running the parity hook
//! sees it.

use std::path::Path;

use anyhow::Context as _;
use pma_model::bench::measure::median;
use pma_model::bench::ForwardResult;

/// One warm-up and `repeats` timed runs of this executable's `pma forward` on `batch`
/// with `model`, writing into `scratch` (the output is removed afterwards).
pub fn time(
    batch: &Path,
    model: &Path,
    repeats: usize,
    scratch: &Path,
) -> anyhow::Result<ForwardResult> {
    let rays = pma_model::render::batch_file::count_rays(batch)?;
    let exe = std::env::current_exe().context("locating the pma executable")?;
    let out = scratch.join("forward_out.npz");
    let mut runs = Vec::with_capacity(repeats);
    for i in 0..=repeats {
        let mut cmd = std::process::Command::new(&exe);
        let workers = pma_model::compute::parallel::workers();
        if workers > 1 {
            // This process set these for its own workers (`configure_cpu`); a child that
            // inherited them would take them for the user's and run one worker.
            cmd.env_remove("RAYON_NUM_THREADS")
                .env_remove("CANDLE_NUM_THREADS");
        }
        // The same worker count as this process (`pma --workers N bench` included).
        cmd.args(["--workers", &workers.to_string()]);
        let t = std::time::Instant::now();
        let o = cmd
            .args(["forward", "--model"])
            .arg(model)
            .arg("--batch")
            .arg(batch)
            .arg("--out")
            .arg(&out)
            .output()
            .with_context(|| format!("running {} forward", exe.display()))?;
        let secs = t.elapsed().as_secs_f64();
        if !o.status.success() {
            anyhow::bail!(
                "pma forward on {} failed: {}",
                batch.display(),
                String::from_utf8_lossy(&o.stderr).trim()
            );
        }
        if i > 0 {
            runs.push(secs);
        }
    }
    // The output is only a by-product of the timing.
    let _ = std::fs::remove_file(&out);
    let median_s = median(&mut runs.clone());
    Ok(ForwardResult {
        batch: batch.display().to_string(),
        model: model.display().to_string(),
        rays,
        runs_s: runs,
        median_s,
        rays_per_s: rays as f64 / median_s,
    })
}

/// The `forward` line of the table.
pub fn print(f: &ForwardResult) {
    println!(
        "pma forward (whole process) {} rays: median {:.3} s over {} runs ({:.0} rays/s; {})",
        f.rays,
        f.median_s,
        f.runs_s.len(),
        f.rays_per_s,
        f.batch
    );
}
