//! `pma ablate`: the paper's ablation table with the run-time column it lacks. Trains each
//! model variant (`pma_model::network::config::Variant`) with the same seed, data and wall-clock
//! budget, then scores novel views and novel poses:
//!
//! ```text
//! DIR/scene/...                      the embedded synthetic scene (unless --data)
//! DIR/runs/<variant>/...             each variant's run (model, log.csv, plot)
//! DIR/ablation.json, ablation.md     parameters, ms/step, iterations, PSNR/SSIM/LPIPS per split
//! DIR/error_vs_time.png              held-out PSNR against wall time, one curve per variant
//! ```

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::Context as _;
use pma_model::eval::EvalOptions;
use pma_model::network::config::Variant;
use pma_model::render::avatar::Avatar;
use pma_model::train::{Preset, RunConfig, TrainLog, TrainRequest, LOG_FILE};

use super::demo::make_scene;
use super::eval::score_split;
use super::plot::plot_curves;
use super::train::train;
use super::{write_json, Refused};

#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Training data: a `train.npz` with `novel_view.npz` and `novel_pose.npz` beside it.
    /// Default: the embedded synthetic scene, made in DIR/scene.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Training budget per variant, in minutes.
    #[arg(long, default_value_t = 2.0)]
    pub minutes: f64,
    /// Stop each run after this many iterations even if budget is left.
    #[arg(long)]
    pub iters: Option<u64>,
    /// The variants to train, comma-separated.
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "full,only-gnn,only-syn,only-wp,only-wf,no-window"
    )]
    pub variants: Vec<Variant>,
    /// Training preset.
    #[arg(long, default_value = "cpu-small")]
    pub preset: String,
    /// Output directory.
    #[arg(long, default_value = "runs/ablate")]
    pub out: PathBuf,
    /// Score at most this many images per split, evenly spread over it (0 = all).
    #[arg(long, default_value_t = 16)]
    pub max_eval_images: usize,
    /// Random seed shared by every variant.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// No progress bars.
    #[arg(long)]
    pub quiet: bool,
}

/// One row of the table.
#[derive(Debug, Clone, serde::Serialize)]
pub struct VariantRow {
    pub variant: String,
    pub parameters: usize,
    pub iterations: u64,
    /// Training milliseconds per step (held-out evaluations excluded).
    pub ms_per_step: f64,
    pub wall_s: f64,
    /// Per split: PSNR, SSIM and the file scored.
    pub splits: std::collections::BTreeMap<String, SplitScore>,
    /// (wall seconds, held-out PSNR) during training.
    pub curve: Vec<(f64, f64)>,
    pub model: PathBuf,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct SplitScore {
    pub psnr: f64,
    pub ssim: f64,
    pub lpips: f64,
    pub images: usize,
}

const SPLITS: [&str; 2] = ["novel_view", "novel_pose"];

pub fn run(args: Args) -> anyhow::Result<()> {
    let preset: Preset = args.preset.parse().map_err(Refused::new)?;
    if args.variants.is_empty() {
        return Err(Refused::new("--variants: name at least one variant").into());
    }
    super::check_minutes("--minutes", Some(args.minutes))?;
    super::check_paths(
        pma_data::fsio::PathCheck::new()
            .input_opt("--data", args.data.as_deref())
            .output_dir("--out", &args.out, ["ablation.json", "ablation.md"]),
    )?;
    pma_data::fsio::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let train_data = match &args.data {
        Some(p) => p.clone(),
        None => make_scene(None, None, args.quiet, &args.out.join("scene"))?.join("train.npz"),
    };
    let dir = train_data.parent().unwrap_or(Path::new(".")).to_path_buf();
    for s in SPLITS {
        let p = dir.join(format!("{s}.npz"));
        if !p.is_file() {
            return Err(Refused::new(format!(
                "{}: the {s} split is missing beside the training data",
                p.display()
            ))
            .into());
        }
    }
    let mut rows = Vec::new();
    for (i, &v) in args.variants.iter().enumerate() {
        println!("[{}/{}] variant `{v}`", i + 1, args.variants.len());
        rows.push(run_variant(&args, preset, v, &train_data, &dir)?);
    }
    let json = args.out.join("ablation.json");
    write_json(&rows, &json)?;
    let md = table(&rows, &args, preset);
    pma_data::fsio::write_atomic(&args.out.join("ablation.md"), md.as_bytes())
        .context("writing ablation.md")?;
    let curves: Vec<(String, Vec<(f64, f64)>)> = rows
        .iter()
        .map(|r| (r.variant.clone(), r.curve.clone()))
        .collect();
    plot_curves(
        &curves,
        "pma ablate: held-out (novel view) PSNR vs wall-clock time",
        "wall-clock time [min]",
        &args.out.join("error_vs_time.png"),
    )?;
    println!("{md}");
    println!(
        "wrote {} and ablation.md, error_vs_time.png",
        json.display()
    );
    Ok(())
}

/// Train one variant for the budget, then score both held-out splits.
fn run_variant(
    args: &Args,
    preset: Preset,
    v: Variant,
    train_data: &Path,
    dir: &Path,
) -> anyhow::Result<VariantRow> {
    let mut run = RunConfig::from_preset(preset);
    run.model.variant = v;
    run.train.seed = args.seed;
    run.train.iters = args.iters.unwrap_or(pma_model::train::presets::MAX_ITERS);
    let run_dir = args.out.join("runs").join(v.name());
    let req = TrainRequest {
        data: train_data.to_path_buf(),
        out: run_dir.clone(),
        run: Some(run.clone()),
        resume: false,
        overwrite: true,
        iters: None,
        minutes: Some(args.minutes),
        eval_data: Some(dir.join("novel_view.npz")),
        chunk_rays: None,
        device: candle_core::Device::Cpu,
        numerics: super::numerics(),
    };
    let title = format!("pma ablate `{v}`: held-out PSNR vs wall-clock time");
    let outcome = train(&req, &super::train::Ranks::One, args.quiet, &title)?;
    let train_s = (outcome.session_s - outcome.eval_s).max(1e-9);
    let ms_per_step = 1e3 * train_s / outcome.session_iterations.max(1) as f64;
    let log = TrainLog::read(&run_dir.join(LOG_FILE))?;
    let curve = log
        .rows
        .iter()
        .filter_map(|r| r.eval_psnr.map(|p| (r.wall_s, p)))
        .collect();
    let avatar =
        Avatar::load(&outcome.model, &candle_core::Device::Cpu)?.with_numerics(super::numerics());
    let parameters = avatar
        .trainable()
        .iter()
        .map(|(_, var)| var.as_tensor().elem_count())
        .sum();
    let mut splits = BTreeMap::new();
    for name in SPLITS {
        splits.insert(name.to_string(), score(args, &run, &avatar, dir, name)?);
    }
    Ok(VariantRow {
        variant: v.name().to_string(),
        parameters,
        iterations: outcome.iterations,
        ms_per_step,
        wall_s: outcome.wall_s,
        splits,
        curve,
        model: outcome.model,
    })
}

fn score(
    args: &Args,
    run: &RunConfig,
    avatar: &Avatar,
    dir: &Path,
    name: &str,
) -> anyhow::Result<SplitScore> {
    let path = dir.join(format!("{name}.npz"));
    let opts = EvalOptions::quick(run.train.render_chunk);
    let report = score_split(avatar, &path, name, args.max_eval_images, &opts, args.quiet)?;
    println!(
        "      {name}: PSNR {:.2} dB, SSIM {:.4}, LPIPS {:.4} over {} images",
        report.psnr, report.ssim, report.lpips, report.images
    );
    Ok(SplitScore {
        psnr: report.psnr,
        ssim: report.ssim,
        lpips: report.lpips,
        images: report.images,
    })
}

/// The Markdown table: the paper's columns plus the cost of each variant.
fn table(rows: &[VariantRow], args: &Args, preset: Preset) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "# pma ablate: preset `{preset}`, {} min per variant, seed {}\n",
        args.minutes, args.seed
    );
    let _ = writeln!(
        s,
        "| variant | parameters | ms/step | iterations | novel view PSNR | SSIM | LPIPS | novel pose PSNR | SSIM | LPIPS |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|---|");
    for r in rows {
        let (nv, np) = (&r.splits["novel_view"], &r.splits["novel_pose"]);
        let _ = writeln!(
            s,
            "| {} | {} | {:.1} | {} | {:.2} | {:.4} | {:.4} | {:.2} | {:.4} | {:.4} |",
            r.variant,
            r.parameters,
            r.ms_per_step,
            r.iterations,
            nv.psnr,
            nv.ssim,
            nv.lpips,
            np.psnr,
            np.ssim,
            np.lpips
        );
    }
    s
}
