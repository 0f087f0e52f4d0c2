//! One training step under step accounting ([`crate::compute::account`]): what it would
//! launch, upload and wait for on a GPU, counted on whatever device the trainer runs on.

use std::time::Instant;

use super::{BatchSource, StepStats, TrainError, Trainer};
use crate::compute::account::{Account, Counts, Report, Route};

/// One accounted training step.
#[derive(Debug, Clone)]
pub struct StepAccount {
    /// Stages: `batch` (making the batch: its uploads), then the marks of
    /// [`crate::compute::profile`] in the order they first closed.
    pub report: Report,
    pub rays: usize,
    /// Chunks the step ran in: the times its `loss` stage closed.
    pub chunks: u64,
    /// The read-back of the step's numbers after it, counted apart: a run reads back once
    /// every [`Trainer::read_every`] steps, for all of them.
    pub read_back: Counts,
    pub stats: StepStats,
    /// Wall time of the accounted step on this machine (the step runs for real; not a GPU
    /// figure).
    pub wall_s: f64,
}

/// Account one step of `trainer` on the next batch of `source`, taking `route`'s kernels
/// ([`Route::Cuda`] on the CPU: the kernels, worker count and chunking a CUDA device would
/// get). The step is applied: the trainer moves on by one iteration.
pub fn account_step(
    trainer: &mut Trainer,
    source: &mut dyn BatchSource,
    route: Route,
) -> Result<StepAccount, TrainError> {
    let device = trainer.avatar().device().clone();
    let start = Instant::now();
    let account = Account::start(&device, route)?;
    let batch = source.next_batch()?;
    account.mark("batch");
    trainer.advance(&batch)?;
    let report = account.finish();
    let reading = Account::start(&device, route)?;
    let stats = trainer.read_back()?.pop().ok_or_else(|| {
        TrainError::Config("the accounted step has no numbers to read back".into())
    })?;
    let read_back = reading.finish().total;
    let chunks = report
        .stages
        .iter()
        .find(|s| s.name == "loss")
        .map_or(0, |s| s.times);
    Ok(StepAccount {
        report,
        rays: batch.rays.origins.dim(0)?,
        chunks,
        read_back,
        stats,
        wall_s: start.elapsed().as_secs_f64(),
    })
}

/// A one-pass step of more rays than fit in memory, accounted by extrapolation from three
/// that fit.
#[derive(Debug, Clone)]
pub struct Extrapolated {
    /// The step of `rays` rays, extrapolated ([`Report::extrapolate`]).
    pub report: Report,
    pub rays: usize,
    /// The rays of the three accounted steps.
    pub from: [usize; 3],
    /// Whether every op, launch, sync and upload count was the same in the three (only
    /// bytes and FLOPs grew with the rays).
    pub counts_constant: bool,
    /// The read-back after the last of the three ([`StepAccount::read_back`]).
    pub read_back: Counts,
    /// Wall time of the three accounted steps on this machine.
    pub wall_s: f64,
    /// The three accounted steps, for [`Self::at`].
    pub base: [Report; 3],
}

impl Extrapolated {
    /// The one-pass step of `rays` rays (a multiple of `from[0]`) from the same three steps.
    pub fn at(&self, rays: usize) -> Result<Report, TrainError> {
        let from = self.from[0];
        if rays == 0 || rays % from != 0 {
            return Err(TrainError::Config(format!(
                "extrapolating to {rays} rays needs a multiple of the {from} rays accounted"
            )));
        }
        let [a, b, c] = &self.base;
        Ok(Report::extrapolate([a, b, c], (rays / from - 1) as u64)?)
    }
}

/// Account the one-pass step of `run` (its `rays_per_step`, which must be a multiple of
/// `from`) from fresh trainers' one-pass steps of `from`, `2·from` and `3·from` rays on
/// `data`: the ops are the same whatever the rays in one pass (training evaluates the
/// points of a pose in one call), and bytes and FLOPs grow linearly; both are checked on
/// the three before the step is extrapolated, and it is refused otherwise.
pub fn account_one_pass_extrapolated(
    run: &super::RunConfig,
    data: std::sync::Arc<pma_data::dataset::Dataset>,
    device: &candle_core::Device,
    route: Route,
    from: usize,
) -> Result<Extrapolated, TrainError> {
    let rays = run.train.rays_per_step;
    if from == 0 || rays < from || rays % from != 0 {
        return Err(TrainError::Config(format!(
            "extrapolating to {rays} rays needs a multiple of the {from} rays accounted"
        )));
    }
    // The step of `rays` must itself run in one pass: rays per chunk at least `rays`, and
    // one worker (more workers split a CPU step into chunks for them).
    let chunk = super::chunk_rays(&run.train, &run.model, device);
    let workers = match route {
        Route::Cuda => 1,
        Route::Cpu => crate::compute::parallel::workers_on(device),
    };
    if chunk < rays || workers > 1 {
        return Err(TrainError::Config(format!(
            "only a one-pass step is extrapolated: {rays} rays run in chunks of {chunk} \
             rays on {workers} worker(s) (set chunk_rays >= rays)"
        )));
    }
    let start = Instant::now();
    let from = [from, 2 * from, 3 * from];
    let mut reports = Vec::with_capacity(3);
    let mut read_back = Counts::default();
    for n in from {
        let mut r = run.clone();
        r.train.rays_per_step = n;
        r.train.chunk_rays = n;
        let t = &r.train;
        let mut source = super::DatasetSource::new(
            data.clone(),
            t.rays_per_step,
            t.images_per_step,
            t.perturb_bg,
            t.seed,
            device,
        )?;
        let mut trainer = Trainer::new(r, data.clone(), device)?;
        let a = account_step(&mut trainer, &mut source, route)?;
        if a.chunks != 1 {
            return Err(TrainError::Config(format!(
                "the {n}-ray step ran in {} chunks, not one pass",
                a.chunks
            )));
        }
        reports.push(a.report);
        read_back = a.read_back;
    }
    let base: [Report; 3] = reports
        .try_into()
        .map_err(|_| TrainError::Config("three accounted steps expected".into()))?;
    let [a, b, c] = [&base[0], &base[1], &base[2]];
    let report = Report::extrapolate([a, b, c], (rays / from[0] - 1) as u64)?;
    let same = |f: fn(&crate::compute::account::Counts) -> u64| {
        f(&a.total) == f(&b.total) && f(&b.total) == f(&c.total)
    };
    let counts_constant = same(|c| c.ops)
        && same(|c| c.launches)
        && same(|c| c.syncs)
        && same(|c| c.uploads)
        && same(|c| c.param_uploads);
    Ok(Extrapolated {
        report,
        rays,
        from,
        counts_constant,
        read_back,
        wall_s: start.elapsed().as_secs_f64(),
        base,
    })
}
