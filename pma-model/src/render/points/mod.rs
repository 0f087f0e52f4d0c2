//! How the samples of a forward pass go through the network.
//!
//! [`Network::eval_poses`] is the network on the points of some poses. A forward pass hands
//! its samples to one [`PointEval`], stage by stage (coarse, fine, or both in one round), and
//! gets raw [R,S,4] back (rgb, density after noise and ReLU); which route they take is
//! decided once, when the pass begins:
//!
//! * **dense** ([`dense`]): one call for all poses with the graph kept (training, the parity
//!   hook);
//! * **chunked** ([`dense`]): bounded chunks on the CPU workers, outputs detached
//!   (inference);
//! * **culled** ([`culled`]): only the samples culling, the occupancy grid and the early stop
//!   keep ([`crate::render::cull`]); the rest are filled from the network's far-away
//!   constant or with zeros. Gradients reach the evaluated samples and the constants, so
//!   training with culling at threshold 0 has parity's loss and its gradients up to float
//!   summation order (docs/numerics.md, "Empty rays and culling"). On the CPU the kept
//!   samples of a pose go out in calls of at most a chunk; a GPU gets one padded call for
//!   all poses ([`plan`]). With `cull_joints` a CPU plan sorts the kept samples by the
//!   joints they need and each call carries only its samples' joints ([`joints`],
//!   [`Network::eval_joints`]).
//!
//! Nothing here calls back into the pass that uses it.

use std::sync::Arc;

use candle_core::Tensor;

use crate::error::{ModelError, Result};
use crate::network::occupancy::OccupancyGrid;
use crate::network::trace::Trace;
use crate::network::{Network, PoseFeatures};
use crate::render::batch::{Mode, Poses};
use crate::render::options::{GridObservation, PassOptions, PassStats};
use crate::render::raycast::{CoarseSamples, FineSamples, RayBounds};
use pma_data::skeleton::N_JOINTS;

mod culled;
mod dense;
pub(crate) mod joints;
mod plan;

use culled::CullCtx;
pub use dense::{inference_point_chunk, INFERENCE_POINT_CHUNK};

/// The samples of one forward pass on their route through the network (see the module
/// docs), and what the route did.
pub(crate) struct PointEval<'a> {
    net: &'a Network,
    pose: &'a PoseFeatures,
    /// [R,V] view features of the pass's rays.
    view: &'a Tensor,
    route: Route,
    /// The early stop's transmittance threshold (the coarse stage marches).
    early_stop: Option<f64>,
    /// What the dense and chunked routes did (the culled route counts its own).
    counts: Counts,
    /// Samples of the coarse stage that went through the network.
    coarse_evaluated: usize,
}

enum Route {
    Dense,
    Chunked,
    Culled(Box<CullCtx>),
}

/// What the network calls of a pass did so far.
#[derive(Debug, Clone, Copy, Default)]
struct Counts {
    /// Points that went through the network (far-away constants included).
    points: usize,
    /// Samples that went through the network (far-away constants not included).
    samples: usize,
    /// Samples left out because the occupancy grid marks their cells empty.
    skipped_empty: usize,
    /// Samples left out behind their ray's early stop.
    stopped_early: usize,
    /// Σ over the network calls of points × joints carried (24 per point unless calls are
    /// grouped by joints, [`PassOptions::cull_joints`]).
    joint_rows: usize,
}

impl<'a> PointEval<'a> {
    /// The route of a pass of `net` with `pose`'s features and view features `view`, for
    /// `mode` and the pass's options (`grid`: the avatar's occupancy grid, needed when the
    /// options ask for it). A traced pass never leaves work out: the trace needs the
    /// intermediates of every sample.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        net: &'a Network,
        pose: &'a PoseFeatures,
        view: &'a Tensor,
        mode: &Mode,
        poses: &Poses,
        bounds: Option<&RayBounds>,
        traced: bool,
        opts: &PassOptions,
        grid: Option<&Arc<OccupancyGrid>>,
    ) -> Result<Self> {
        let route = if !traced && opts.leaves_out_work() {
            let grid = match (opts.occupancy, grid) {
                (false, _) => None,
                (true, Some(g)) => Some(g.clone()),
                (true, None) => {
                    return Err(ModelError::Input(
                        "occupancy: the model has no occupancy grid (train with `--occupancy` \
                         or build one with `pma occupancy build`)"
                            .into(),
                    ))
                }
            };
            let ctx = CullCtx::new(net, opts, grid, poses, pose, bounds)?;
            Route::Culled(Box::new(ctx))
        } else if mode.is_inference() {
            Route::Chunked
        } else {
            Route::Dense
        };
        Ok(Self {
            net,
            pose,
            view,
            route,
            early_stop: opts.early_stop,
            counts: Counts::default(),
            coarse_evaluated: 0,
        })
    }

    /// The coarse stage: raw [R,Sc,4] of the coarse samples. With the early stop they run
    /// front to back in segments, leaving out the samples of rays whose transmittance fell
    /// below the threshold (inference only; a pass on another route, traced, runs every
    /// sample).
    pub fn coarse(
        &mut self,
        samples: &CoarseSamples,
        dirs: &Tensor,
        mode: &mut Mode,
        trace: Option<&mut Trace>,
    ) -> Result<Tensor> {
        let raw = match self.early_stop {
            Some(eps) => self.march(samples, dirs, mode, eps, trace)?,
            None => self.run(&samples.pts, None, mode, "coarse", trace)?,
        };
        self.coarse_evaluated = self.counts().samples;
        Ok(raw)
    }

    /// The fine stage: raw [R,Sf,4] of the importance samples, leaving out those behind the
    /// depth where the coarse stage stopped their ray.
    pub fn fine(
        &mut self,
        samples: &FineSamples,
        mode: &mut Mode,
        trace: Option<&mut Trace>,
    ) -> Result<Tensor> {
        self.run(&samples.pts, Some(&samples.z), mode, "fine", trace)
    }

    /// Importance weights [R,Sc] of the coarse samples along dirs [R,3] from the occupancy
    /// grid instead of the coarse render; refused when the pass consults no grid.
    pub fn grid_weights(&self, samples: &CoarseSamples, dirs: &Tensor) -> Result<Tensor> {
        let weights = match &self.route {
            Route::Culled(c) => c.grid_weights(&samples.pts, &samples.z, dirs)?,
            _ => None,
        };
        weights.ok_or_else(|| {
            ModelError::Input(
                "occupancy: placing the fine samples from the grid needs a pass that consults \
                 the grid"
                    .into(),
            )
        })
    }

    /// The coarse and the fine stage in one round of network calls (inference, fine samples
    /// placed without the coarse render). Returns (raw coarse [R,Sc,4], raw fine [R,Sf,4]).
    pub fn coarse_and_fine(
        &mut self,
        coarse: &CoarseSamples,
        fine: &FineSamples,
        mode: &mut Mode,
    ) -> Result<(Tensor, Tensor)> {
        if !mode.is_inference() {
            return Err(ModelError::Input(
                "occupancy: placing the fine samples from the grid is a rendering option \
                 (training places them from its coarse render)"
                    .into(),
            ));
        }
        let sc = coarse.pts.dim(1)?;
        let sf = fine.pts.dim(1)?;
        let all = Tensor::cat(&[&coarse.pts, &fine.pts], 1)?;
        let raw = self.run(&all, None, mode, "coarse+fine", None)?;
        self.coarse_evaluated = match &self.route {
            Route::Culled(c) => c.coarse_evaluated(sc, sc + sf),
            // The other routes run every sample.
            _ => coarse.pts.dim(0)? * sc,
        };
        Ok((raw.narrow(1, 0, sc)?, raw.narrow(1, sc, sf)?))
    }

    /// What the pass did, its `samples` samples in all, and what its evaluated samples saw
    /// of the grid (empty unless the pass feeds the grid, [`PassOptions::grid_feed`]).
    pub fn finish(mut self, samples: usize) -> (PassStats, Vec<GridObservation>) {
        let counts = self.counts();
        let (rays_culled, observed) = match &mut self.route {
            Route::Culled(c) => (c.rays_culled(), c.take_observed()),
            _ => (0, Vec::new()),
        };
        let stats = PassStats {
            samples: samples as u64,
            points_evaluated: counts.points as u64,
            coarse_evaluated: self.coarse_evaluated as u64,
            fine_evaluated: (counts.samples - self.coarse_evaluated) as u64,
            skipped_empty: counts.skipped_empty as u64,
            stopped_early: counts.stopped_early as u64,
            joint_rows: counts.joint_rows as u64,
            rays_culled: rays_culled as u64,
        };
        (stats, observed)
    }

    /// What the network calls of this pass did so far.
    fn counts(&self) -> Counts {
        match &self.route {
            Route::Culled(c) => c.counts,
            _ => self.counts,
        }
    }

    /// The coarse stage with the early stop (see [`Self::coarse`]).
    fn march(
        &mut self,
        samples: &CoarseSamples,
        dirs: &Tensor,
        mode: &mut Mode,
        eps: f64,
        trace: Option<&mut Trace>,
    ) -> Result<Tensor> {
        if !mode.is_inference() {
            return Err(ModelError::Input(
                "early_stop: stopping rays early is a rendering option (every sample of a \
                 training step takes part in its gradients)"
                    .into(),
            ));
        }
        let Route::Culled(c) = &mut self.route else {
            return self.run(&samples.pts, None, mode, "coarse", trace);
        };
        let pts = &samples.pts;
        let (rgb, sigma_raw) =
            c.march(self.net, self.pose, pts, &samples.z, dirs, self.view, eps)?;
        let (r, s, _) = pts.dims3()?;
        let density = density(self.net, sigma_raw, mode, r * s)?;
        Ok(Tensor::cat(&[rgb, density], 1)?.reshape((r, s, 4))?)
    }

    /// raw: [R,S,4] for the samples pts: [R,S,3]; with the samples' z [R,S], those behind
    /// their ray's early stop are left out.
    fn run(
        &mut self,
        pts: &Tensor,
        z: Option<&Tensor>,
        mode: &mut Mode,
        stage: &str,
        trace: Option<&mut Trace>,
    ) -> Result<Tensor> {
        let (net, pose, view) = (self.net, self.pose, self.view);
        let (r, s, _) = pts.dims3()?;
        let (rgb, sigma_raw, alive) = match &mut self.route {
            Route::Dense => {
                let (rgb, sigma) = dense::dense(net, pose, pts, view, stage, trace)?;
                self.counts.add_all(r * s);
                (rgb, sigma, None)
            }
            Route::Chunked => {
                let (rgb, sigma) = dense::chunked(net, pose, pts, view)?;
                self.counts.add_all(r * s);
                (rgb, sigma, None)
            }
            Route::Culled(c) => c.run(net, pose, pts, z, view, mode)?,
        };
        let density = density(net, sigma_raw, mode, r * s)?;
        let density = match alive {
            // Zero-filled samples have no density even where noise would have given some.
            Some(alive) => density.broadcast_mul(&alive.to_dtype(density.dtype())?)?,
            None => density,
        };
        Ok(Tensor::cat(&[rgb, density], 1)?.reshape((r, s, 4))?)
    }
}

impl Counts {
    /// `n` samples, every one through the network with all joints.
    fn add_all(&mut self, n: usize) {
        self.points += n;
        self.samples += n;
        self.joint_rows += n * N_JOINTS;
    }
}

/// relu(σ_raw + noise): the noise is drawn for every sample, culled or not, so the noise
/// stream of a culled pass stays aligned with parity mode.
fn density(net: &Network, sigma_raw: Tensor, mode: &mut Mode, n: usize) -> Result<Tensor> {
    let std = net.config().density_noise_std;
    let sigma = match mode {
        Mode::Train(Some(noise)) if std > 0.0 => {
            let eps = noise(n)?.reshape((n, 1))?;
            (&sigma_raw + (eps * std)?)?
        }
        _ => sigma_raw,
    };
    Ok(sigma.relu()?)
}
