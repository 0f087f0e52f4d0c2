//! `pma bench --account`: what one training step and one inference pass would launch,
//! upload and wait for on a GPU ([`pma_model::compute::account`]), with estimated GPU times,
//! beside the official code's counts when given. Prints the tables and writes
//! `account.json`.

use std::collections::BTreeMap;
use std::sync::Arc;

use anyhow::Context as _;
use candle_core::Device;
use pma_model::compute::account::{
    self, Counts, GpuEstimate, Recorded, Route, Summary, GPUS, LAUNCH_S, SYNC_S,
};
use pma_model::train::account::{account_one_pass_extrapolated, account_step};
use pma_model::train::{BatchSource, DatasetSource, Preset, RunConfig, Trainer};

use super::super::{progress, read_dataset, refuse, write_json};
use super::Args;

/// `account.json`.
#[derive(Debug, serde::Serialize)]
struct AccountFile {
    preset: String,
    device: String,
    account_as: Route,
    rays: usize,
    /// `--chunk-rays` (0 = automatic).
    chunk_rays: usize,
    /// Chunks the step ran in.
    chunks: u64,
    /// Wall time of the accounted step(s) on this machine (they run for real), not a GPU
    /// figure.
    step_wall_s: f64,
    /// Set when the step was extrapolated from one-pass steps of these rays
    /// (`--extrapolate-from`).
    step_extrapolated_from: Option<[usize; 3]>,
    ops_per_step: u64,
    launches_per_step: u64,
    syncs_per_step: u64,
    /// Syncs of the read-back of a step's numbers, once every `read_every` steps for all of
    /// them (counted apart from the step).
    read_back_syncs: u64,
    read_every: u64,
    /// Explicit uploads plus dims/strides uploads.
    uploads_per_step: u64,
    explicit_uploads_per_step: u64,
    param_uploads_per_step: u64,
    /// Bytes the step's ops read and write.
    bytes_per_step: u64,
    /// Matmul FLOPs.
    flops_per_step: u64,
    step: Summary,
    /// `render_rays` of `rays` rays (the batch already made).
    inference: Summary,
    official: Option<Official>,
    cost_model: CostModel,
}

#[derive(Debug, serde::Serialize)]
struct Official {
    #[serde(flatten)]
    recorded: Recorded,
    est: Vec<GpuEstimate>,
}

#[derive(Debug, serde::Serialize)]
struct CostModel {
    formula: &'static str,
    est_launch_s: f64,
    est_sync_s: f64,
    gpus: Vec<account::Gpu>,
}

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
    run.train.rays_per_step = args.rays;
    run.train.chunk_rays = args.chunk_rays;
    if let Err(e) = run.train.validate() {
        refuse!(
            "--rays {} / --chunk-rays {}: {e}",
            args.rays,
            args.chunk_rays
        );
    }
    let data = account_scene(args, run.train.images_per_step)?;
    let t = &run.train;
    let mut source = DatasetSource::new(
        data.clone(),
        t.rays_per_step,
        t.images_per_step,
        t.perturb_bg,
        t.seed,
        dev,
    )?;
    let mut trainer = Trainer::new(run, data.clone(), dev)?;

    let bar = progress::bar(args.quiet, 2, "step accounting");
    bar.enable_steady_tick(std::time::Duration::from_millis(500));
    bar.set_message(format!(
        "one {} training step of {} rays (it runs for real)",
        args.preset, args.rays
    ));
    let read_every = match route {
        Route::Cpu => trainer.read_every(),
        Route::Cuda => match trainer.run_config().train.read_every {
            0 => pma_model::train::AUTO_READ_EVERY_DEVICE,
            k => k,
        },
    };
    let (step, chunks, wall_s, extrapolated_from, read_back) = match args.extrapolate_from {
        None => {
            let a = account_step(&mut trainer, &mut source, route)?;
            (a.report, a.chunks, a.wall_s, None, a.read_back)
        }
        Some(n) => {
            let e = account_one_pass_extrapolated(trainer.run_config(), data, dev, route, n)?;
            if !e.counts_constant {
                eprintln!(
                    "warning: op, sync or upload counts grew with the rays across {:?};                      extrapolated linearly (they were exactly affine)",
                    e.from
                );
            }
            (e.report, 1, e.wall_s, Some(e.from), e.read_back)
        }
    };
    bar.inc(1);
    bar.set_message("one inference pass");
    let batch = source.next_batch()?;
    let avatar = trainer.avatar();
    let (_, inference) = account::measure(dev, route, || -> anyhow::Result<_> {
        Ok(avatar.render_rays(&batch.rays, &batch.poses, &Default::default())?)
    })?;
    bar.finish_and_clear();

    let s = step.summary();
    let total = s.total;
    let file = AccountFile {
        preset: args.preset.clone(),
        device: args.device.clone(),
        account_as: route,
        rays: args.rays,
        chunk_rays: args.chunk_rays,
        chunks,
        step_wall_s: wall_s,
        step_extrapolated_from: extrapolated_from,
        ops_per_step: total.ops,
        launches_per_step: total.launches,
        syncs_per_step: total.syncs,
        read_back_syncs: read_back.syncs,
        read_every,
        uploads_per_step: total.all_uploads(),
        explicit_uploads_per_step: total.uploads,
        param_uploads_per_step: total.param_uploads,
        bytes_per_step: total.bytes(),
        flops_per_step: total.flops,
        step: s,
        inference: inference.summary(),
        official: official.map(|r| Official {
            est: r.estimates(),
            recorded: r,
        }),
        cost_model: CostModel {
            formula: "estimate: per op max(bytes / bandwidth, FLOPs / peak) + launches x launch \
                      overhead; per upload (explicit or dims/strides) one launch overhead; per \
                      sync a latency; uploaded and read-back bytes over the host link",
            est_launch_s: LAUNCH_S,
            est_sync_s: SYNC_S,
            gpus: GPUS.to_vec(),
        },
    };
    print_tables(&file);
    let path = args.out.join("account.json");
    write_json(&file, &path)?;
    println!("wrote {}", path.display());
    Ok(())
}

/// 16 training images (4 cameras × 4 walk frames, 96×96), as many as the paper's step
/// samples from, made once in `--out`.
fn account_scene(
    args: &Args,
    images_per_step: usize,
) -> anyhow::Result<Arc<pma_data::dataset::Dataset>> {
    let dir = args.out.join("account-scene");
    let synth = pma_data::synth::SynthConfig {
        train_cams: 4,
        test_cams: 1,
        frames: 4,
        novel_pose_walk: 1,
        novel_pose_dance: 1,
        ..Default::default()
    };
    if !dir.join("train.npz").is_file() {
        println!("synthesising the accounting scene into {}", dir.display());
        pma_data::synth::generate(&synth, &dir, &mut |_, _| {})
            .context("synthesising the accounting scene")?;
    }
    let data = read_dataset(&dir.join("train.npz"), pma_data::dataset::Profile::Train)?;
    if data.n_images() < images_per_step {
        refuse!(
            "{}: {} images, the preset samples {images_per_step} per step",
            dir.display(),
            data.n_images()
        );
    }
    Ok(Arc::new(data))
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

fn print_tables(f: &AccountFile) {
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
    print_stage_table(
        &format!("inference pass (render_rays, {} rays)", f.rays),
        &f.inference,
    );

    let mut top: Vec<(&String, &Counts)> = f.step.ops.iter().collect();
    top.sort_by_key(|(_, c)| std::cmp::Reverse(c.launches));
    println!("\nops of the step by launches (first 12 of {}):", top.len());
    for (name, c) in top.iter().take(12) {
        println!(
            "  {:<24} {:>7} ops {:>7} launches {:>6} params {:>9.3} GB {:>9.2} GFLOP",
            name,
            c.ops,
            c.launches,
            c.param_uploads,
            gb(c.bytes()),
            c.flops as f64 / 1e9
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
    println!(
        "estimates: per op max(bytes / memory bandwidth, FLOPs / FP32 peak) + {:.0} us per \
         launch or upload, {:.0} us per sync (assumed); datasheet figures in account.json",
        LAUNCH_S * 1e6,
        SYNC_S * 1e6
    );
}
