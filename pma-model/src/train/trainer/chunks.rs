//! A step in chunks of rays: how many rays a chunk holds, the rows a chunk takes of the
//! batch, the samples and the density noise, and the loss and gradients summed over chunks.

use candle_core::{DType, Device, Tensor};
use rand_chacha::ChaCha8Rng;

use super::optimization::StepLoss;
use super::Trainer;
use crate::network::config::Config;
use crate::render::avatar::{GridObservation, Mode, PassOptions, PassStats, Rays};
use crate::render::options::GridFeed;
use crate::render::raycast::CoarseSamples;
use crate::train::batch::TrainBatch;
use crate::train::presets::TrainConfig;
use crate::train::TrainError;

/// Automatic chunking of a training step (`chunk_rays = 0`) on the CPU: at most this many
/// point × joint × feature elements per chunk (samples per ray × joints × the widest per-joint
/// feature). Forward and backward keep some 50 tensors of that size alive: a 512-ray chunk
/// of the paper config peaked near 8 GiB, so the budget is 128 rays of it (about 2 GiB).
pub const AUTO_CHUNK_POINT_JOINTS: usize = 128 * 72 * 24 * 128;

/// The loss, the gradients (in parameter order), what the passes did, what their
/// evaluated samples saw of the occupancy grid, and (when asked) the per-ray errors, of a
/// step or one of its chunks.
pub(super) type Gradients = (
    StepLoss,
    Vec<Option<Tensor>>,
    PassStats,
    Vec<GridObservation>,
    Option<RayErrors>,
);

/// Each ray's mean |fine − target| over the channels, [R'] on the device, with the batch
/// ray of each row.
pub(super) struct RayErrors {
    pub errors: Tensor,
    pub rays: Vec<usize>,
}

/// Rays per chunk of a training step (see [`TrainConfig::chunk_rays`]). Automatic chunks are
/// sized from the device ([`crate::compute::device::element_budget`]: a share of its free
/// memory) on a GPU, [`AUTO_CHUNK_POINT_JOINTS`] on the CPU.
pub fn chunk_rays(train: &TrainConfig, model: &Config, device: &Device) -> usize {
    if train.chunk_rays > 0 {
        return train.chunk_rays;
    }
    let width = model.win_hidden.max(model.point_enc_dim).max(1);
    let per_ray = (model.n_samples + model.n_importance) * model.n_joints * width;
    let budget = crate::compute::device::element_budget(device).unwrap_or(AUTO_CHUNK_POINT_JOINTS);
    (budget / per_ray.max(1)).max(1)
}

/// The density noise of one step: a standard normal for every coarse and every fine sample
/// of the batch, [R,Sc] and [R,Sf], drawn in the order a forward pass over the whole batch
/// asks for them (coarse, then fine). A chunk takes its rays' rows, so chunking never
/// changes the noise a sample gets.
struct StepNoise {
    coarse: Tensor,
    fine: Tensor,
}

impl StepNoise {
    fn draw(
        rng: &mut ChaCha8Rng,
        rays: usize,
        (sc, sf): (usize, usize),
        device: &Device,
    ) -> Result<Self, TrainError> {
        use rand_distr::Distribution;
        let mut block = |s: usize| -> candle_core::Result<Tensor> {
            let v: Vec<f32> = (0..rays * s)
                .map(|_| rand_distr::StandardNormal.sample(&mut *rng))
                .collect();
            Tensor::from_vec(v, (rays, s), device)
        };
        let coarse = block(sc)?;
        Ok(Self {
            coarse,
            fine: block(sf)?,
        })
    }
}

/// The rays `rows` of a batch: their rows of every per-ray tensor (`None` = all rays).
struct Rows<'a> {
    ids: Option<(Vec<usize>, Tensor)>,
    batch: &'a TrainBatch,
}

impl Rows<'_> {
    fn take(&self, t: &Tensor) -> candle_core::Result<Tensor> {
        match &self.ids {
            None => Ok(t.clone()),
            Some((_, idx)) => t.index_select(idx, 0),
        }
    }

    fn rays(&self) -> candle_core::Result<Rays> {
        let r = &self.batch.rays;
        Ok(Rays {
            origins: self.take(&r.origins)?,
            dirs: self.take(&r.dirs)?,
            bgs: r.bgs.as_ref().map(|b| self.take(b)).transpose()?,
            framecodes: match &self.ids {
                None => r.framecodes.clone(),
                Some((rows, _)) => rows.iter().map(|&i| r.framecodes[i]).collect(),
            },
        })
    }

    fn samples(&self, c: &CoarseSamples) -> candle_core::Result<CoarseSamples> {
        Ok(CoarseSamples {
            bounds: match (&c.bounds, &self.ids) {
                (Some(b), Some((rows, _))) => Some(b.select(rows)),
                (b, _) => b.clone(),
            },
            z: self.take(&c.z)?,
            pts: self.take(&c.pts)?,
            fine_u: match &self.ids {
                Some((rows, _)) => c.fine_u_of(rows),
                None => c.fine_u.clone(),
            },
        })
    }
}

impl Trainer {
    /// Rays per chunk for a batch of `rays`: [`chunk_rays`], fixed at the first step, and on
    /// the CPU at most a worker's share, so every worker has a chunk.
    pub(super) fn chunk_size(&mut self, rays: usize) -> usize {
        let device = self.avatar.device().clone();
        let chunk = *self
            .chunk
            .get_or_insert_with(|| chunk_rays(&self.run.train, self.avatar.config(), &device));
        let workers = crate::compute::parallel::workers_on(&device);
        if workers > 1 {
            chunk.min(rays.div_ceil(workers))
        } else {
            chunk
        }
    }

    /// The loss and the gradients of one step on `batch`, computed `chunk` rays at a time
    /// (at least one ray per pose); one chunk is the whole batch in one pass.
    ///
    /// The per-pose work (GNN, `layer_pose`, box scales), the ray casting and the density
    /// noise are done once for the batch. Every chunk takes the same slice of each pose's
    /// block of rays, so it is itself a batch of all P poses: it takes its rows of the
    /// samples and the noise, renders, and differentiates its share of the loss (the L1 terms
    /// are sums scaled by `1/(3R)` of the whole batch, the same two multiplications as the
    /// mean; the box-volume term goes with the first chunk). Shares and gradients are summed
    /// in chunk order on the device. What chunking changes is only the order of float
    /// summation.
    ///
    /// With `ray_errors` the result carries each ray's error for the error map, in the
    /// order of the chunks' rows (nothing is read back here).
    pub(super) fn gradients(
        &mut self,
        batch: &TrainBatch,
        chunk: usize,
        opts: &PassOptions,
        ray_errors: bool,
    ) -> Result<Gradients, TrainError> {
        let r = batch.rays.origins.dim(0)?;
        let n_poses = batch.poses.bones.len();
        if n_poses == 0 || r % n_poses != 0 {
            return Err(TrainError::Config(format!(
                "{r} rays cannot be split into {n_poses} equal per-pose blocks"
            )));
        }
        let k = r / n_poses;
        let per_pose = (chunk / n_poses).clamp(1, k);
        // A rank of a data-parallel group takes its slice of each pose's block; its chunks
        // keep the numbering of the whole batch (the first one carries the box-volume term).
        let (lo, hi) = match &self.group {
            Some(g) => g.share(k),
            None => (0, k),
        };
        let device = self.avatar.device().clone();
        let avatar = &self.avatar;
        let pose = avatar.pose_features(&batch.poses, None)?;
        crate::compute::profile::mark("pose features", &device);
        let coarse = avatar.cast(&batch.rays, &batch.poses, &pose, opts)?;
        crate::compute::profile::mark("cast", &device);
        let cfg = avatar.config();
        let noise = match cfg.density_noise_std > 0.0 {
            true => Some(StepNoise::draw(
                &mut self.noise_rng,
                r,
                (cfg.n_samples, cfg.n_importance),
                &device,
            )?),
            false => None,
        };
        let weights = self.run.train.loss_weights();
        let params = &self.params;
        let feed = self.run.train.occupancy.as_ref().filter(|_| opts.occupancy);
        let feed_seed = self.run.train.seed ^ self.opt.iter.wrapping_mul(0x9e37_79b9_7f4a_7c15);
        let run_chunk = |start: usize| -> Result<Gradients, TrainError> {
            // Each chunk feeds the grid with probes of its own.
            let opts = &PassOptions {
                grid_feed: feed.map(|o| GridFeed {
                    probe_share: o.probe_share,
                    seed: feed_seed ^ (start as u64).wrapping_mul(0xd6e8_feb8_6659_fd93),
                }),
                ..opts.clone()
            };
            let len = per_pose.min(hi - start);
            let ids = (len < k)
                .then(|| -> candle_core::Result<_> {
                    let rows: Vec<usize> = (0..n_poses)
                        .flat_map(|p| p * k + start..p * k + start + len)
                        .collect();
                    let idx: Vec<u32> = rows.iter().map(|&i| i as u32).collect();
                    let n = idx.len();
                    Ok((rows, Tensor::from_vec(idx, n, &device)?))
                })
                .transpose()?;
            crate::compute::device::injected_oom(len * n_poses)?;
            let rows = Rows { ids, batch };
            let rays = rows.rays()?;
            let target = rows.take(&batch.target)?;
            let ray_weights = batch.weights.as_ref().map(|w| rows.take(w)).transpose()?;
            let samples = rows.samples(&coarse)?;
            crate::compute::profile::mark("chunk rows", &device);
            let mut blocks = match &noise {
                Some(n) => vec![rows.take(&n.coarse)?, rows.take(&n.fine)?],
                None => Vec::new(),
            }
            .into_iter();
            let mut noise_fn = |n: usize| -> crate::error::Result<Tensor> {
                let block = blocks.next().ok_or_else(|| {
                    crate::error::ModelError::Input("density noise: a third call in a pass".into())
                })?;
                if block.elem_count() != n {
                    return Err(crate::error::ModelError::Input(format!(
                        "density noise: {n} samples requested, the step drew {}",
                        block.elem_count()
                    )));
                }
                Ok(block.flatten_all()?)
            };
            let mut mode = match noise {
                Some(_) => Mode::Train(Some(&mut noise_fn)),
                None => Mode::Train(None),
            };
            let out = avatar.forward_cast(&rays, &batch.poses, &pose, samples, &mut mode, opts)?;
            let share = crate::train::loss::loss_share_weighted(
                &out,
                &target,
                ray_weights.as_ref(),
                &weights,
                r,
                start == 0,
            )?;
            let errors = ray_errors
                .then(|| -> candle_core::Result<RayErrors> {
                    let e = (out.fine.rgb.detach() - &target)?.abs()?.mean(1)?;
                    let rays = match &rows.ids {
                        Some((ids, _)) => ids.clone(),
                        None => (0..r).collect(),
                    };
                    Ok(RayErrors { errors: e, rays })
                })
                .transpose()?;
            let f64_of = |t: &Tensor| t.detach().to_dtype(DType::F64);
            let mse = (&out.fine.rgb.detach() - &target)?.sqr()?.sum_all()?;
            let numbers = StepLoss {
                total: f64_of(&share.total)?,
                fine: f64_of(&share.fine)?,
                coarse: f64_of(&share.coarse)?,
                scale: f64_of(&share.scale)?,
                mse: (f64_of(&mse)? / (3 * r) as f64)?,
            };
            crate::compute::profile::mark("loss", &device);
            let store = share.total.backward()?;
            crate::compute::profile::mark("backward", &device);
            let grads = params
                .iter()
                .map(|v| store.get(v.as_tensor()).map(|d| d.detach()))
                .collect();
            Ok((numbers, grads, out.stats, out.observed, errors))
        };
        let mut loss = StepLoss::zeros(&device)?;
        let mut grads: Vec<Option<Tensor>> = vec![None; params.len()];
        let mut stats = PassStats::default();
        let mut seen = Vec::new();
        let mut errors: Vec<RayErrors> = Vec::new();
        let starts: Vec<usize> = (lo..hi).step_by(per_pose).collect();
        // One wave of chunks per round of workers; sums are taken in chunk order, so the
        // result is the sequential loop's, bit for bit, whatever the worker count.
        let workers = crate::compute::parallel::workers_on(&device);
        for wave in starts.chunks(workers) {
            crate::interrupt::check()?;
            let outs =
                crate::compute::parallel::map_ordered(workers, wave.len(), |i| run_chunk(wave[i]))?;
            for (part, chunk_grads, chunk_stats, chunk_seen, chunk_errors) in outs {
                stats.add(&chunk_stats);
                seen.extend(chunk_seen);
                errors.extend(chunk_errors);
                loss = StepLoss {
                    total: (loss.total + part.total)?,
                    fine: (loss.fine + part.fine)?,
                    coarse: (loss.coarse + part.coarse)?,
                    scale: (loss.scale + part.scale)?,
                    mse: (loss.mse + part.mse)?,
                };
                for (g, d) in grads.iter_mut().zip(chunk_grads) {
                    if let Some(d) = d {
                        *g = Some(match g.take() {
                            Some(sum) => (sum + d)?,
                            None => d,
                        });
                    }
                }
            }
        }
        // With several workers this thread waits here for the others' chunks: that wait and
        // the sums are this stage's, not the optimizer's.
        let errors = match errors.len() {
            0 => None,
            1 => errors.pop(),
            _ => {
                let parts: Vec<&Tensor> = errors.iter().map(|e| &e.errors).collect();
                Some(RayErrors {
                    errors: Tensor::cat(&parts, 0)?,
                    rays: errors.iter().flat_map(|e| e.rays.iter().copied()).collect(),
                })
            }
        };
        crate::compute::profile::mark("chunk sums", &device);
        Ok((loss, grads, stats, seen, errors))
    }
}
