//! `pma bench --account`: what one training step and one inference pass would launch,
//! upload and wait for on a GPU (`pma_model::bench::account` counts), with estimated GPU
//! times, beside the official code's counts when given. Prints the tables and writes
//! `account.json`.

use std::collections::BTreeMap;

use candle_core::Device;
use pma_model::bench::{AccountReport, AccountRequest};
use pma_model::compute::account::{Counts, GpuEstimate, Recorded, Route, StageOp, Summary, GPUS};
use pma_model::compute::account::{LAUNCH_S, SYNC_S};
use pma_model::train::{Preset, RunConfig};

use super::super::progress::Phases;
use super::super::{refuse, write_json};
use super::Args;

pub fn run(args: &Args, dev: &Device) -> anyhow::Result<()> {
    let route: Route = match args.account_as.parse() {
        Ok(r) => r,
        Err(_) => refuse!(
            "--account-as: expected `cuda` or `cpu`, found `{}`",
            args.account_as
        ),
    };
    if route == Route::Cpu && !dev.is_cpu() {
        refuse!("--account-as cpu needs --device cpu (a GPU run takes the cuda route)");
    }
    let official = match &args.official_json {
        Some(p) => Some(Recorded::read(p)?),
        None => None,
    };
    let preset: Preset = args.preset.parse()?;
    let mut run = RunConfig::from_preset(preset);
    run.numerics = super::super::numerics();
    run.train.rays_per_step = args.rays;
    run.train.chunk_rays = args.chunk_rays;
    if let Err(e) = run.train.validate() {
        refuse!(
            "--rays {} / --chunk-rays {}: {e}",
            args.rays,
            args.chunk_rays
        );
    }
    if let Some(t) = args.account_cull {
        if !(t.is_finite() && (0.0..1.0).contains(&t)) {
            refuse!("--account-cull: expected a w^p threshold in [0, 1), found {t}");
        }
        if args.extrapolate_from.is_some() {
            // What culling keeps depends on the rays, so the counts are not affine in them.
            refuse!("--account-cull: a culled step is not extrapolated (drop --extrapolate-from)");
        }
        run.train.culling = pma_model::render::Culling {
            rays: true,
            sample_threshold: Some(t),
            sample_fill: pma_model::render::SampleFill::Network,
        };
    }
    if !args.gpus.is_empty() && args.gpus.first() != Some(&1) {
        refuse!(
            "--gpus: the first count must be 1 (the one-GPU step the others are compared with)"
        );
    }
    let device_memory = match args.device_memory_gb {
        None => None,
        Some(gb) if gb.is_finite() && gb > 0.0 && gb <= 1e6 => Some((gb * 1e9) as usize),
        Some(gb) => refuse!("--device-memory-gb must be a positive number of GB, found {gb}"),
    };
    let req = AccountRequest {
        run,
        device_memory,
        preset: args.preset.clone(),
        device_name: args.device.clone(),
        route,
        extrapolate_from: args.extrapolate_from,
        official,
        scene_dir: args.out.join("account-scene"),
        occupancy: args
            .occupancy
            .then(pma_model::network::occupancy::OccupancyConfig::default),
        gpus: args.gpus.clone(),
    };
    let report = pma_model::bench::account(req, dev, &mut Phases::new(args.quiet))?;
    print_tables(&report);
    let path = args.out.join("account.json");
    write_json(&report, &path)?;
    println!("wrote {}", path.display());
    Ok(())
}

fn gb(b: u64) -> f64 {
    b as f64 / 1e9
}

fn est_ms(e: &[GpuEstimate], gpu: &str) -> f64 {
    e.iter()
        .find(|g| g.gpu == gpu)
        .map_or(f64::NAN, |g| g.est_fp32_matmul.est_s * 1e3)
}

fn print_stage_table(title: &str, s: &Summary) {
    println!("\n{title}");
    let gpus: Vec<&str> = GPUS.iter().map(|g| g.name).collect();
    print!(
        "{:<30} {:>5} {:>8} {:>8} {:>6} {:>7} {:>7} {:>9} {:>9}",
        "stage", "times", "ops", "launches", "syncs", "uploads", "params", "GB moved", "GFLOP"
    );
    for g in &gpus {
        print!(" {:>16}", format!("est {g} ms"));
    }
    println!();
    let row = |name: &str, times: u64, c: &Counts, est: &[GpuEstimate]| {
        print!(
            "{:<30} {:>5} {:>8} {:>8} {:>6} {:>7} {:>7} {:>9.3} {:>9.2}",
            name,
            times,
            c.ops,
            c.launches,
            c.syncs,
            c.uploads,
            c.param_uploads,
            gb(c.bytes()),
            c.flops as f64 / 1e9
        );
        for g in &gpus {
            print!(" {:>16.2}", est_ms(est, g));
        }
        println!();
    };
    for st in &s.stages {
        row(&st.name, st.times, &st.counts, &st.est);
    }
    row("total", 1, &s.total, &s.est);
}

fn print_tables(f: &AccountReport) {
    println!(
        "step accounting: {} preset, {} rays, device {}, counted as {} would run it \
         (counts are exact; times are estimates)",
        f.preset, f.rays, f.device, f.account_as
    );
    let how = match f.step_extrapolated_from {
        None => format!("it ran for real in {:.1} s here", f.step_wall_s),
        Some(from) => format!(
            "EXTRAPOLATED from one-pass steps of {from:?} rays (ran for real in {:.1} s here; \
             every count exactly affine in the rays across them)",
            f.step_wall_s
        ),
    };
    print_stage_table(
        &format!(
            "training step: {} chunk(s) (--chunk-rays {}); {how}",
            f.chunks, f.chunk_rays
        ),
        &f.step,
    );
    if let Some(o) = &f.left_out {
        let what = match (o.sample_threshold, o.occupied_fraction) {
            (Some(t), Some(g)) => format!(
                "culling (rays, w^p <= {t}) and the occupancy grid ({:.1} % of cells occupied)",
                100.0 * g
            ),
            (Some(t), None) => format!("culling (rays, w^p <= {t})"),
            (None, Some(g)) => format!("occupancy grid ({:.1} % of cells occupied)", 100.0 * g),
            (None, None) => "nothing left out".into(),
        };
        println!(
            "{what}: the step ran {} of {} samples through the network ({:.1} %), {} left out \
             as empty",
            o.samples_evaluated,
            o.samples,
            100.0 * o.samples_evaluated as f64 / o.samples.max(1) as f64,
            o.skipped_empty
        );
    }
    let sized = match f.inference_device_memory {
        Some(b) => format!(
            "network calls sized for a GPU with {:.0} GB free",
            b as f64 / 1e9
        ),
        None => "network calls of 4,096 points (the CPU's)".into(),
    };
    print_stage_table(
        &format!("inference pass (render_rays, {} rays; {sized})", f.rays),
        &f.inference,
    );

    let mut top: Vec<(&str, &StageOp)> = f
        .step
        .stages
        .iter()
        .flat_map(|s| s.ops.iter().map(move |o| (s.name.as_str(), o)))
        .collect();
    top.sort_by(|a, b| b.1.est_h200_s.total_cmp(&a.1.est_h200_s));
    println!(
        "\nops of the step by estimated H200 time (first 15 of {} stage/op pairs):",
        top.len()
    );
    for (stage, o) in top.iter().take(15) {
        println!(
            "  {:<20} {:<22} {:>6} launches {:>9.3} GB {:>9.2} GFLOP {:>8.2} est ms",
            stage,
            o.name,
            o.launches,
            gb(o.bytes),
            o.flops as f64 / 1e9,
            o.est_h200_s * 1e3
        );
    }

    println!("\nper training step (times are estimates)");
    let off = f.official.as_ref();
    let col = |v: Option<String>| v.unwrap_or_else(|| "-".into());
    println!(
        "{:<46} {:>22} {:>22}",
        "",
        format!("pma ({}, {} rays)", f.account_as, f.rays),
        col(off.map(|o| format!("official ({} rays)", o.recorded.rays)))
    );
    if let Some(from) = off.and_then(|o| o.recorded.extrapolated_from.as_ref()) {
        println!(
            "(the official column is EXTRAPOLATED from steps of {from:?} rays: every op the \
             same, its bytes and FLOPs exactly affine in the rays)"
        );
    }
    let line = |name: &str, pma: String, official: Option<String>| {
        println!("{:<46} {:>22} {:>22}", name, pma, col(official));
    };
    let oc = off.map(|o| o.recorded.counts);
    line(
        "ops (launches)",
        format!("{} ({})", f.ops_per_step, f.launches_per_step),
        oc.map(|c| format!("{} ({})", c.ops, c.launches)),
    );
    line(
        "syncs (device -> host reads)",
        f.syncs_per_step.to_string(),
        oc.map(|c| c.syncs.to_string()),
    );
    line(
        &format!("read-back of the numbers (every {} steps)", f.read_every),
        format!("{} sync(s)", f.read_back_syncs),
        None,
    );
    line(
        "uploads (explicit + dims/strides)",
        format!(
            "{} + {}",
            f.explicit_uploads_per_step, f.param_uploads_per_step
        ),
        oc.map(|_| "not counted".to_string()),
    );
    line(
        "GB moved (ops' bytes read + written)",
        format!("{:.2}", gb(f.bytes_per_step)),
        oc.map(|c| format!("{:.2}", gb(c.bytes()))),
    );
    line(
        "GB peak live memory (allocated in the step)",
        format!("{:.2}", gb(f.peak_live_bytes_per_step)),
        oc.map(|_| "not counted".to_string()),
    );
    line(
        "TFLOP (matmul)",
        format!("{:.3}", f.flops_per_step as f64 / 1e12),
        oc.map(|c| format!("{:.3}", c.flops as f64 / 1e12)),
    );
    for g in GPUS {
        line(
            &format!("est step s on {} (estimate, FP32 matmul)", g.name),
            format!("{:.3}", est_ms(&f.step.est, g.name) / 1e3),
            off.map(|o| format!("{:.3}", est_ms(&o.est, g.name) / 1e3)),
        );
    }
    if let Some(o) = off {
        let kinds: BTreeMap<&String, &u64> = o.recorded.syncs_by_kind.iter().collect();
        println!("official syncs by kind: {kinds:?}");
    }
    print_scaling(f);
    println!(
        "estimates: per op max(bytes / memory bandwidth, FLOPs / FP32 peak) + {:.0} us per \
         launch or upload, {:.0} us per sync (assumed); datasheet figures in account.json",
        LAUNCH_S * 1e6,
        SYNC_S * 1e6
    );
}

/// The estimated data-parallel tables (`--gpus`).
fn print_scaling(f: &AccountReport) {
    let Some(first) = f.scaling.first() else {
        return;
    };
    println!(
        "\ndata-parallel training, ESTIMATED on {} GPUs ({} within a node of 8, {} between \
         nodes; FP32 matmuls): nothing here is measured",
        first.gpu, first.intra, first.inter
    );
    for (title, rows) in [
        (
            "the step's batch split over the GPUs (the run one GPU trains)",
            &f.scaling,
        ),
        (
            "a whole batch per GPU (a global batch N times larger: another run)",
            &f.scaling_batch_per_gpu,
        ),
    ] {
        println!("{title}:");
        println!(
            "{:>5} {:>5} {:>11} {:>10} {:>12} {:>13} {:>9} {:>14} {:>11} {:>12} {:>11} {:>11}",
            "GPUs",
            "nodes",
            "global rays",
            "rays/rank",
            "all-reduces",
            "MB/rank/step",
            "launches",
            "est compute ms",
            "est link ms",
            "est step ms",
            "est speedup",
            "est effic."
        );
        for r in rows {
            println!(
                "{:>5} {:>5} {:>11} {:>10} {:>12} {:>13.2} {:>9} {:>14.2} {:>11.3} {:>12.2} {:>11.2} {:>10.0}%",
                r.gpus,
                r.nodes,
                r.global_rays,
                r.rays_per_rank,
                r.all_reduces,
                r.all_reduce_bytes as f64 / 1e6,
                r.launches,
                r.est_compute_s * 1e3,
                r.est_link_s * 1e3,
                r.est_step_s * 1e3,
                r.est_speedup,
                r.est_efficiency * 100.0
            );
        }
    }
}
