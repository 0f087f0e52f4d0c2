//! Step accounting of a whole request: what one training step and one inference pass would
//! launch, upload and wait for on a GPU ([`crate::compute::account`]), with estimated GPU
//! times, beside the official code's counts when given. The step runs for real, on a small
//! synthetic scene made once.

use std::path::PathBuf;
use std::sync::Arc;

use candle_core::Device;
use pma_data::dataset::{Dataset, Profile};
use serde::Serialize;

use super::{BenchError, BenchObserver, Result};
use crate::compute::account::{self, GpuEstimate, Recorded, Route, Summary, GPUS};
use crate::compute::account::{LAUNCH_S, SYNC_S};
use crate::eval::read_dataset;
use crate::train::account::{account_one_pass_extrapolated, account_step};
use crate::train::{BatchSource, DatasetSource, RunConfig, Trainer};

/// What to account.
#[derive(Debug, Clone)]
pub struct AccountRequest {
    /// The step: its preset's model, `rays_per_step` and `chunk_rays` (0 = automatic).
    pub run: RunConfig,
    /// The preset and device as the report names them.
    pub preset: String,
    pub device_name: String,
    pub route: Route,
    /// Account a one-pass step too large for memory by extrapolation from one-pass steps
    /// of this many rays, twice and three times as many.
    pub extrapolate_from: Option<usize>,
    /// The official code's counts, estimated beside pma's.
    pub official: Option<Recorded>,
    /// Free memory (bytes) of the GPU the inference pass is sized for on a CPU run accounted
    /// as CUDA ([`account::Account::model_free_memory`]); `None`: the CPU's call size.
    pub device_memory: Option<usize>,
    /// Where the accounting scene is made (once).
    pub scene_dir: PathBuf,
    /// Account a step that trains with an occupancy grid of these settings: one step runs
    /// first, unaccounted, and the refresh that ends its warm-up builds the grid, so the
    /// accounted step is a plain step that consults it (no refresh in it).
    pub occupancy: Option<crate::network::occupancy::OccupancyConfig>,
}

/// `account.json`.
#[derive(Debug, Serialize)]
pub struct AccountReport {
    pub preset: String,
    pub device: String,
    pub account_as: Route,
    pub rays: usize,
    /// `--chunk-rays` (0 = automatic).
    pub chunk_rays: usize,
    /// Chunks the step ran in.
    pub chunks: u64,
    /// Wall time of the accounted step(s) on this machine (they run for real), not a GPU
    /// figure.
    pub step_wall_s: f64,
    /// Set when the step was extrapolated from one-pass steps of these rays
    /// (`--extrapolate-from`).
    pub step_extrapolated_from: Option<[usize; 3]>,
    pub ops_per_step: u64,
    pub launches_per_step: u64,
    pub syncs_per_step: u64,
    /// Syncs of the read-back of a step's numbers, once every `read_every` steps for all of
    /// them (counted apart from the step).
    pub read_back_syncs: u64,
    pub read_every: u64,
    /// Explicit uploads plus dims/strides uploads.
    pub uploads_per_step: u64,
    pub explicit_uploads_per_step: u64,
    pub param_uploads_per_step: u64,
    /// Bytes the step's ops read and write.
    pub bytes_per_step: u64,
    /// Matmul FLOPs.
    pub flops_per_step: u64,
    /// The most bytes allocated during the step alive at once (activations, gradients, the
    /// new optimizer state; not the parameters and moments from before it): counted.
    pub peak_live_bytes_per_step: u64,
    pub step: Summary,
    /// `render_rays` of `rays` rays (the batch already made).
    pub inference: Summary,
    /// The free memory (bytes) of the GPU the inference pass's network calls were sized for
    /// (`--device-memory-gb`); absent: the CPU's 4,096 points per call.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub inference_device_memory: Option<usize>,
    /// With culling or the grid: what the accounted step's passes evaluated.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub left_out: Option<LeftOutAccount>,
    pub official: Option<Official>,
    pub cost_model: CostModel,
}

/// What the accounted step of a run with culling or the occupancy grid evaluated.
#[derive(Debug, Serialize)]
pub struct LeftOutAccount {
    /// The step's w^p culling threshold (rays culled too), if it culled.
    pub sample_threshold: Option<f64>,
    /// Share of the grid's cells occupied when the step ran, if it used the grid.
    pub occupied_fraction: Option<f64>,
    /// The step's samples (both passes), those that ran the network, and those the grid
    /// left out.
    pub samples: u64,
    pub samples_evaluated: u64,
    pub skipped_empty: u64,
}

/// The official code's recorded counts and their estimates.
#[derive(Debug, Serialize)]
pub struct Official {
    #[serde(flatten)]
    pub recorded: Recorded,
    pub est: Vec<GpuEstimate>,
}

/// How the estimates are made.
#[derive(Debug, Serialize)]
pub struct CostModel {
    pub formula: &'static str,
    pub est_launch_s: f64,
    pub est_sync_s: f64,
    pub gpus: Vec<account::Gpu>,
}

/// Account one training step of `req.run` and one inference pass of its rays on `dev`.
pub fn account(
    req: AccountRequest,
    dev: &Device,
    obs: &mut dyn BenchObserver,
) -> Result<AccountReport> {
    let mut run = req.run;
    if let Some(cfg) = &req.occupancy {
        if req.extrapolate_from.is_some() {
            return Err(BenchError::Setting(
                "--occupancy: a grid step is not extrapolated (drop --extrapolate-from)".into(),
            ));
        }
        run.train.occupancy = Some(crate::network::occupancy::OccupancyConfig {
            warmup_steps: 1,
            ..cfg.clone()
        });
    }
    let data = account_scene(&req.scene_dir, run.train.images_per_step, obs)?;
    let t = &run.train;
    let (rays, chunk_rays) = (t.rays_per_step, t.chunk_rays);
    let mut source = DatasetSource::new(
        data.clone(),
        t.rays_per_step,
        t.images_per_step,
        t.perturb_bg,
        t.seed,
        dev,
    )?;
    let mut trainer = Trainer::new(run, data.clone(), dev)?;

    obs.phase("step accounting", 2);
    obs.progress(
        0,
        &format!(
            "one {} training step of {rays} rays (it runs for real)",
            req.preset
        ),
    );
    let read_every = match req.route {
        Route::Cpu => trainer.read_every(),
        Route::Cuda => match trainer.run_config().train.read_every {
            0 => crate::train::AUTO_READ_EVERY_DEVICE,
            k => k,
        },
    };
    if req.occupancy.is_some() {
        obs.note("one unaccounted step first: the refresh that ends it builds the grid");
        let batch = source.next_batch()?;
        trainer.advance(&batch)?;
        trainer.read_back()?;
    }
    let before = trainer.pass_totals();
    let (step, chunks, wall_s, extrapolated_from, read_back) = match req.extrapolate_from {
        None => {
            let a = account_step(&mut trainer, &mut source, req.route)?;
            (a.report, a.chunks, a.wall_s, None, a.read_back)
        }
        Some(n) => {
            let e = account_one_pass_extrapolated(trainer.run_config(), data, dev, req.route, n)?;
            if !e.counts_constant {
                obs.warning(&format!(
                    "op, sync or upload counts grew with the rays across {:?}; \
                     extrapolated linearly (they were exactly affine)",
                    e.from
                ));
            }
            (e.report, 1, e.wall_s, Some(e.from), e.read_back)
        }
    };
    let grid = req
        .occupancy
        .as_ref()
        .and(trainer.avatar().occupancy())
        .map(|g| g.occupied_fraction());
    let sample_threshold = trainer.run_config().train.culling.sample_threshold;
    let left_out = match grid.is_some() || sample_threshold.is_some() {
        true => {
            let after = trainer.pass_totals();
            let evaluated = |p: &crate::render::PassStats| p.coarse_evaluated + p.fine_evaluated;
            Some(LeftOutAccount {
                sample_threshold,
                occupied_fraction: grid,
                samples: after.samples - before.samples,
                samples_evaluated: evaluated(&after) - evaluated(&before),
                skipped_empty: after.skipped_empty - before.skipped_empty,
            })
        }
        false => None,
    };
    obs.progress(1, "one inference pass");
    let batch = source.next_batch()?;
    let avatar = trainer.avatar();
    let counting = account::Account::start(dev, req.route)?;
    if let Some(bytes) = req.device_memory {
        counting.model_free_memory(bytes);
    }
    avatar.render_rays(&batch.rays, &batch.poses, &Default::default())?;
    let inference = counting.finish();
    obs.phase_end();

    let s = step.summary();
    let total = s.total;
    Ok(AccountReport {
        preset: req.preset,
        device: req.device_name,
        account_as: req.route,
        rays,
        chunk_rays,
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
        peak_live_bytes_per_step: s.peak_live_bytes,
        step: s,
        inference: inference.summary(),
        inference_device_memory: req.device_memory,
        left_out,
        official: req.official.map(|r| Official {
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
    })
}

/// 16 training images (4 cameras × 4 walk frames, 96×96), as many as the paper's step
/// samples from, made once in `dir`.
fn account_scene(
    dir: &std::path::Path,
    images_per_step: usize,
    obs: &mut dyn BenchObserver,
) -> Result<Arc<Dataset>> {
    let synth = pma_data::synth::SynthConfig::small(96, 4, 4);
    if !dir.join("train.npz").is_file() {
        obs.note(&format!(
            "synthesising the accounting scene into {}",
            dir.display()
        ));
        pma_data::synth::generate(&synth, dir, &mut |_, _| {}).map_err(|source| {
            BenchError::Scene {
                what: "accounting",
                source: Box::new(source),
            }
        })?;
    }
    let path = dir.join("train.npz");
    let data = read_dataset(&path, Profile::Train)?;
    for w in &data.warnings {
        obs.warning(&format!("{}: {w}", path.display()));
    }
    if data.n_images() < images_per_step {
        return Err(BenchError::Setting(format!(
            "{}: {} images, the preset samples {images_per_step} per step",
            dir.display(),
            data.n_images()
        )));
    }
    Ok(Arc::new(data))
}
