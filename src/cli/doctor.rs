//! `pma doctor`: a self-test of a device (`pma_model::doctor`): prints a table, writes
//! `doctor.json`, exits 0 when every check passes and 1 otherwise.

use std::path::{Path, PathBuf};

use anyhow::Result;

use super::Refused;
use pma_model::doctor::{self, DoctorOptions, DoctorReport};
use pma_model::train::Preset;

#[derive(clap::Args)]
pub struct Args {
    /// The device to test: cpu, cuda, cuda:N. On the CPU the CUDA kernels run on an
    /// emulated grid, so every check runs.
    #[arg(long, default_value = "cpu")]
    device: String,
    /// The official code's golden case (the repository's fixtures/golden). Default:
    /// fixtures/golden under the current directory, or in the source tree pma was built from.
    #[arg(long, conflicts_with = "no_golden")]
    golden: Option<PathBuf>,
    /// Skip the golden case.
    #[arg(long)]
    no_golden: bool,
    /// Steps of the training burst (0: none).
    #[arg(long, default_value_t = 20)]
    steps: usize,
    /// The burst's preset: default, cpu-small or tiny. Default: default on a GPU,
    /// cpu-small on the CPU.
    #[arg(long)]
    preset: Option<String>,
    /// Where the report's JSON goes.
    #[arg(long, default_value = "doctor.json")]
    json: PathBuf,
    /// Only the table, no progress lines.
    #[arg(long)]
    quiet: bool,
}

pub fn run(args: Args) -> Result<()> {
    let device = super::device(&args.device)?;
    let burst_preset = args
        .preset
        .as_deref()
        .map(|p| p.parse::<Preset>().map_err(Refused::new))
        .transpose()?;
    let golden = match args.golden {
        _ if args.no_golden => None,
        Some(dir) if dir.join("golden.safetensors").is_file() => Some(dir),
        Some(dir) => {
            return Err(Refused::new(format!(
                "--golden {}: expected a directory holding golden.safetensors (the repository's fixtures/golden)",
                dir.display()
            ))
            .into())
        }
        None => [
            PathBuf::from("fixtures/golden"),
            Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/golden"),
        ]
        .into_iter()
        .find(|d| d.join("golden.safetensors").is_file()),
    };
    let opts = DoctorOptions {
        golden,
        burst_steps: args.steps,
        burst_preset,
    };
    let quiet = args.quiet;
    let report = doctor::run(&device, &opts, &mut |section| {
        if !quiet {
            eprintln!("doctor: {section}");
        }
    });
    print_table(&report);
    super::write_json(&report, &args.json)?;
    println!("report: {}", args.json.display());
    let failed = report.checks.iter().filter(|c| !c.passed).count();
    if failed > 0 {
        anyhow::bail!(
            "doctor: {failed} of {} checks failed on {}",
            report.checks.len(),
            report.device.spec
        );
    }
    Ok(())
}

fn print_table(r: &DoctorReport) {
    let d = &r.device;
    let gib = |b: Option<u64>| {
        b.map_or("?".into(), |b| {
            format!("{:.1} GiB", b as f64 / (1u64 << 30) as f64)
        })
    };
    println!("device   {} ({})", d.spec, d.name);
    println!(
        "memory   {} total, {} free; {} cores; CUDA driver {}; NVRTC {}; compute capability {}",
        gib(d.memory_total_bytes),
        gib(d.memory_free_bytes),
        d.cores,
        d.driver.as_deref().unwrap_or("-"),
        d.nvrtc.as_deref().unwrap_or("-"),
        d.compute_capability
            .map_or("-".into(), |(major, minor)| format!("{major}.{minor}"))
    );
    println!("golden   {}", r.golden);
    println!();
    println!(
        "{:<30} {:<58} {:>10} {:>9}  result",
        "section", "check", "max error", "tolerance"
    );
    for c in &r.checks {
        let num = |v: Option<f64>| v.map_or("-".into(), |v| format!("{v:.2e}"));
        println!(
            "{:<30} {:<58} {:>10} {:>9}  {}{}",
            c.section,
            c.what,
            num(c.max_err),
            num(c.tol),
            if c.passed { "pass" } else { "FAIL" },
            if c.note.is_empty() {
                String::new()
            } else {
                format!("  ({})", c.note)
            }
        );
    }
    if let Some(b) = &r.burst {
        println!();
        println!(
            "burst    {} steps of {} ({} rays, {} per chunk): {:.2} it/s after a first step of {:.2} s; peak memory {}",
            b.steps,
            b.preset,
            b.rays_per_step,
            b.chunk_rays,
            b.it_per_s,
            b.first_step_s,
            gib(b.peak_memory_bytes)
        );
    }
    let off: Vec<String> = r
        .kernel_states
        .iter()
        .filter(|(_, s)| s.starts_with("off"))
        .map(|(m, s)| format!("{m} ({s})"))
        .collect();
    if !off.is_empty() {
        println!(
            "kernels switched off (their ops run on candle's generic ops): {}",
            off.join("; ")
        );
    }
    let failed = r.checks.iter().filter(|c| !c.passed).count();
    println!(
        "{} of {} checks passed{}",
        r.checks.len() - failed,
        r.checks.len(),
        if failed == 0 {
            ""
        } else {
            ": see docs/gpu.md, \"When the doctor fails\""
        }
    );
}
