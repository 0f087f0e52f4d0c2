//! How the samples of a forward pass go through the network.
//!
//! [`Network::eval_poses`] is the network on the points of some poses. A forward pass hands
//! all samples of a stage (coarse, then fine) to one [`PointEval`], which decides how they
//! reach it:
//!
//! * **dense**: one call for all poses with the graph kept (training, the parity hook);
//! * **chunked**: bounded chunks on the CPU workers, outputs detached (inference);
//! * **culled**: only the samples culling and the occupancy grid keep
//!   ([`crate::render::cull`]); the rest are filled from the network's far-away constant or
//!   with zeros. Gradients reach the evaluated
//!   samples and the constants, so training with culling at threshold 0 has parity's loss
//!   and its gradients up to float summation order (docs/numerics.md, "Empty rays and
//!   culling"). On the CPU the kept samples of a pose go out in calls of at most a chunk; a
//!   GPU gets one padded call for all poses ([`PaddedPlan`]). With `cull_joints` a CPU
//!   plan sorts the kept samples by the joints they need and each call carries only its
//!   samples' joints ([`Network::eval_joints`]).
//!
//! Whatever the route, the result is raw [R,S,4] (rgb, density after noise and ReLU).

use std::sync::Arc;

use candle_core::{DType, Tensor};

use crate::compute::host::host_f32;
use crate::compute::ops::rows::select_rows;
use crate::error::{ModelError, Result};
use crate::network::occupancy::OccupancyGrid;
use crate::network::trace::Trace;
use crate::network::{Network, PoseFeatures};
use crate::render::batch::{Mode, Poses};
use crate::render::cull::{ray_fates, JointMask, SampleFate, WindowTest, ALL_JOINTS};
use crate::render::options::{
    GridFeed, GridObservation, PassOptions, SampleFill, EARLY_STOP_SEGMENT,
};
use crate::render::raycast::RayBounds;
use pma_data::skeleton::N_JOINTS;

/// Points per network call in inference on the CPU: the largest per-point tensors are
/// [n,24,128] f32, 48 MiB each at 4,096 points, a handful alive per worker; many chunks also
/// keep the workers balanced. Larger chunks were no faster.
pub const INFERENCE_POINT_CHUNK: usize = 4_096;

/// The smallest network call of an early-stop segment split over the workers.
const MIN_MARCH_CHUNK: usize = 512;

/// Points per network call of an inference pass on `device` for a network of `cfg`: on a
/// GPU as many as its memory budget holds ([`crate::compute::device::element_budget`], a
/// point being joints × the widest per-joint feature), at least [`INFERENCE_POINT_CHUNK`]:
/// each call is ~170 kernel launches whatever its size, so a GPU wants few large calls. The
/// CPU keeps [`INFERENCE_POINT_CHUNK`].
pub fn inference_point_chunk(
    device: &candle_core::Device,
    cfg: &crate::network::config::Config,
) -> usize {
    let per_point = cfg.n_joints * cfg.win_hidden.max(cfg.point_enc_dim).max(1);
    // A real GPU's free memory is read once: the memory pool keeps what the first passes
    // allocated, which would read as used afterwards.
    static GPU_BUDGET: std::sync::OnceLock<Option<usize>> = std::sync::OnceLock::new();
    let budget = match device.is_cpu() {
        true => crate::compute::device::element_budget(device),
        false => *GPU_BUDGET.get_or_init(|| crate::compute::device::element_budget(device)),
    };
    budget.map_or(INFERENCE_POINT_CHUNK, |b| {
        (b / per_point.max(1)).max(INFERENCE_POINT_CHUNK)
    })
}

/// The route of one forward pass's samples (see the module docs).
pub(crate) struct PointEval {
    route: Route,
    /// Points that went through the network in this pass (far-away constants included).
    evaluated: usize,
    /// Samples of this pass that went through the network (far-away constants not included).
    samples_evaluated: usize,
    /// Samples left out because the occupancy grid marks their cells empty.
    skipped_empty: usize,
    /// Samples left out behind their ray's early stop.
    stopped_early: usize,
    /// Σ over the network calls of points × joints carried.
    joint_rows: usize,
}

enum Route {
    Dense,
    Chunked,
    Culled(Box<CullCtx>),
}

impl PointEval {
    /// The route for `mode` and the pass's options (`grid`: the avatar's occupancy grid,
    /// needed when the options ask for it). A traced pass never leaves work out: the trace
    /// needs the intermediates of every sample.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        net: &Network,
        mode: &Mode,
        poses: &Poses,
        pose: &PoseFeatures,
        bounds: Option<&RayBounds>,
        traced: bool,
        opts: &PassOptions,
        grid: Option<&Arc<OccupancyGrid>>,
    ) -> Result<Self> {
        if !traced && opts.leaves_out_work() {
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
            return Ok(Self::on(Route::Culled(Box::new(ctx))));
        }
        Ok(Self::on(if mode.is_inference() {
            Route::Chunked
        } else {
            Route::Dense
        }))
    }

    fn on(route: Route) -> Self {
        Self {
            route,
            evaluated: 0,
            samples_evaluated: 0,
            skipped_empty: 0,
            stopped_early: 0,
            joint_rows: 0,
        }
    }

    /// Σ over this pass's network calls of points × joints the call carried (24 per point
    /// unless calls are grouped by joints, [`PassOptions::cull_joints`]).
    pub fn joint_rows(&self) -> usize {
        self.joint_rows
    }

    /// Points that went through the network so far in this pass (far-away constants
    /// included).
    pub fn evaluated(&self) -> usize {
        self.evaluated
    }

    /// Samples that went through the network so far in this pass.
    pub fn samples_evaluated(&self) -> usize {
        self.samples_evaluated
    }

    /// Samples left out so far because the occupancy grid marks their cells empty.
    pub fn skipped_empty(&self) -> usize {
        self.skipped_empty
    }

    /// Samples left out so far behind their rays' early stops.
    pub fn stopped_early(&self) -> usize {
        self.stopped_early
    }

    /// What this pass's evaluated samples saw of the grid, taken out (empty unless the pass
    /// feeds the grid, [`PassOptions::grid_feed`]).
    pub fn take_observed(&mut self) -> Vec<GridObservation> {
        match &mut self.route {
            Route::Culled(ctx) => std::mem::take(&mut ctx.observed),
            _ => Vec::new(),
        }
    }

    /// Rays of this pass that ray culling left without any sample to run.
    pub fn rays_culled(&self) -> usize {
        match &self.route {
            Route::Culled(ctx) => ctx
                .ray_alive
                .as_ref()
                .map_or(0, |alive| alive.iter().filter(|&&a| !a).count()),
            _ => 0,
        }
    }

    /// The coarse pass with the early stop: like [`Self::run`] on pts [R,S,3] at z [R,S]
    /// along dirs [R,3], but front to back in segments, leaving out the samples of rays whose
    /// transmittance fell below `eps` (inference only). A pass on another route (traced)
    /// runs every sample.
    #[allow(clippy::too_many_arguments)]
    pub fn march(
        &mut self,
        net: &Network,
        pose: &PoseFeatures,
        (pts, z, dirs): (&Tensor, &Tensor, &Tensor),
        view: &Tensor,
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
            return self.run(net, pose, pts, view, mode, "coarse", trace);
        };
        let before = c.counters();
        let (rgb, sigma_raw) = c.march(net, pose, pts, z, dirs, view, eps)?;
        self.count(before);
        let (r, s, _) = pts.dims3()?;
        let density = density(net, sigma_raw, mode, r * s)?;
        Ok(Tensor::cat(&[rgb, density], 1)?.reshape((r, s, 4))?)
    }

    /// The fine pass: [`Self::run`], leaving out the samples (at z [R,S]) behind the depth
    /// where [`Self::march`] stopped their ray; the same as `run` when no ray stopped.
    #[allow(clippy::too_many_arguments)]
    pub fn run_fine(
        &mut self,
        net: &Network,
        pose: &PoseFeatures,
        pts: &Tensor,
        z: &Tensor,
        view: &Tensor,
        mode: &mut Mode,
        trace: Option<&mut Trace>,
    ) -> Result<Tensor> {
        self.run_at(net, pose, pts, Some(z), view, mode, "fine", trace)
    }

    /// Add what the culled route did since `before` (its [`CullCtx::counters`] then) to
    /// this pass.
    fn count(&mut self, before: [usize; 5]) {
        if let Route::Culled(c) = &self.route {
            let now = c.counters();
            self.evaluated += now[0] - before[0];
            self.samples_evaluated += now[1] - before[1];
            self.skipped_empty += now[2] - before[2];
            self.stopped_early += now[3] - before[3];
            self.joint_rows += now[4] - before[4];
        }
    }

    /// Importance weights [R,S] of the coarse samples pts: [R,S,3] at z: [R,S] along dirs:
    /// [R,3] from the occupancy grid instead of the coarse render; refused when the pass
    /// consults no grid.
    pub fn grid_weights(&self, pts: &Tensor, z: &Tensor, dirs: &Tensor) -> Result<Tensor> {
        let weights = match &self.route {
            Route::Culled(c) => c.grid_weights(pts, z, dirs)?,
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

    /// The coarse samples [R,Sc,3] and the fine ones [R,Sf,3] of the same rays in one round
    /// of network calls (inference, fine samples placed without the coarse render). Returns
    /// (raw coarse [R,Sc,4], raw fine [R,Sf,4], coarse samples that ran the network).
    #[allow(clippy::too_many_arguments)]
    pub fn run_together(
        &mut self,
        net: &Network,
        pose: &PoseFeatures,
        coarse: &Tensor,
        fine: &Tensor,
        view: &Tensor,
        mode: &mut Mode,
    ) -> Result<(Tensor, Tensor, usize)> {
        if !mode.is_inference() {
            return Err(ModelError::Input(
                "occupancy: placing the fine samples from the grid is a rendering option \
                 (training places them from its coarse render)"
                    .into(),
            ));
        }
        let sc = coarse.dim(1)?;
        let sf = fine.dim(1)?;
        let all = Tensor::cat(&[coarse, fine], 1)?;
        let raw = self.run(net, pose, &all, view, mode, "coarse+fine", None)?;
        let coarse_evaluated = match &self.route {
            Route::Culled(c) => c
                .last_fates
                .chunks(sc + sf)
                .map(|ray| {
                    ray[..sc]
                        .iter()
                        .filter(|f| **f == SampleFate::Evaluate)
                        .count()
                })
                .sum(),
            // The other routes run every sample.
            _ => coarse.dim(0)? * sc,
        };
        Ok((
            raw.narrow(1, 0, sc)?,
            raw.narrow(1, sc, sf)?,
            coarse_evaluated,
        ))
    }

    /// raw: [R,S,4] for the samples pts: [R,S,3] with view features view: [R,V].
    #[allow(clippy::too_many_arguments)]
    pub fn run(
        &mut self,
        net: &Network,
        pose: &PoseFeatures,
        pts: &Tensor,
        view: &Tensor,
        mode: &mut Mode,
        stage: &str,
        trace: Option<&mut Trace>,
    ) -> Result<Tensor> {
        self.run_at(net, pose, pts, None, view, mode, stage, trace)
    }

    /// [`Self::run`]; with the samples' z [R,S], those behind their ray's early stop are left
    /// out.
    #[allow(clippy::too_many_arguments)]
    fn run_at(
        &mut self,
        net: &Network,
        pose: &PoseFeatures,
        pts: &Tensor,
        z: Option<&Tensor>,
        view: &Tensor,
        mode: &mut Mode,
        stage: &str,
        trace: Option<&mut Trace>,
    ) -> Result<Tensor> {
        let (r, s, _) = pts.dims3()?;
        let (rgb, sigma_raw, alive) = match &mut self.route {
            Route::Dense => {
                let (rgb, sigma) = dense(net, pose, pts, view, stage, trace)?;
                self.evaluated += r * s;
                self.samples_evaluated += r * s;
                self.joint_rows += r * s * N_JOINTS;
                (rgb, sigma, None)
            }
            Route::Chunked => {
                let (rgb, sigma) = chunked(net, pose, pts, view)?;
                self.evaluated += r * s;
                self.samples_evaluated += r * s;
                self.joint_rows += r * s * N_JOINTS;
                (rgb, sigma, None)
            }
            Route::Culled(c) => {
                let before = c.counters();
                let behind = match z {
                    Some(z) if !c.stop_z.is_empty() => Some(host_f32(z)?),
                    _ => None,
                };
                let out = c.run(net, pose, pts, view, mode, behind.as_deref())?;
                self.count(before);
                out
            }
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

/// Every sample of pose p: pts [k·S,3] and the view features of its rays repeated per sample.
fn pose_block(pts: &Tensor, view: &Tensor, p: usize, k: usize) -> Result<(Tensor, Tensor)> {
    let (_, s, _) = pts.dims3()?;
    let vdim = view.dim(1)?;
    let pts_p = pts.narrow(0, p * k, k)?.reshape((k * s, 3))?;
    let view_p = view
        .narrow(0, p * k, k)?
        .unsqueeze(1)?
        .broadcast_as((k, s, vdim))?
        .reshape((k * s, vdim))?;
    Ok((pts_p, view_p))
}

/// One network call for all poses of the pass, graph kept: the samples are grouped by pose
/// in equal blocks, which is what [`Network::eval_poses`] takes. The trace is in ray order.
fn dense(
    net: &Network,
    pose: &PoseFeatures,
    pts: &Tensor,
    view: &Tensor,
    stage: &str,
    trace: Option<&mut Trace>,
) -> Result<(Tensor, Tensor)> {
    crate::interrupt::check()?;
    let (r, s, _) = pts.dims3()?;
    let vdim = view.dim(1)?;
    let pts_all = pts.reshape((r * s, 3))?;
    let view_all = view
        .unsqueeze(1)?
        .broadcast_as((r, s, vdim))?
        .reshape((r * s, vdim))?;
    let traced = trace.map(|t| (t, stage));
    net.eval_poses(pose, 0..pose.g.dim(0)?, &pts_all, &view_all, traced)
}

/// Every (pose, chunk) pair is one job for the workers; outputs stay in ray order.
fn chunked(
    net: &Network,
    pose: &PoseFeatures,
    pts: &Tensor,
    view: &Tensor,
) -> Result<(Tensor, Tensor)> {
    let (r, s, _) = pts.dims3()?;
    let n_poses = pose.g.dim(0)?;
    let chunk = inference_point_chunk(pts.device(), net.config());
    let k = r / n_poses;
    let n = k * s;
    if chunk >= n && !crate::compute::account::cpu_route(pts.device()) {
        return pose_groups(net, pose, pts, view, (chunk / n.max(1)).clamp(1, n_poses));
    }
    let per_pose = n.div_ceil(chunk);
    let inputs = (0..n_poses)
        .map(|p| pose_block(pts, view, p, k))
        .collect::<Result<Vec<_>>>()?;
    let workers = crate::compute::parallel::workers_on(pts.device());
    let outs = crate::compute::parallel::map_ordered(workers, n_poses * per_pose, |i| {
        crate::interrupt::check()?;
        let (p, c) = (i / per_pose, i % per_pose);
        let (start, len) = (c * chunk, chunk.min(n - c * chunk));
        let (pts_p, view_p) = &inputs[p];
        let (rgb, sigma_raw) = net.eval_points(
            pose,
            p,
            &pts_p.narrow(0, start, len)?,
            &view_p.narrow(0, start, len)?,
            None,
        )?;
        // Detached at once: the weights are variables, so the outputs would otherwise keep
        // the chunk's whole graph alive until every chunk is done.
        Ok::<_, ModelError>((rgb.detach(), sigma_raw.detach()))
    })?;
    let (rgbs, sigmas): (Vec<_>, Vec<_>) = outs.into_iter().unzip();
    Ok((Tensor::cat(&rgbs, 0)?, Tensor::cat(&sigmas, 0)?))
}

/// On a GPU whose calls hold more than a pose's samples: one network call per `group` poses
/// (the whole pass when it fits), outputs detached at once, in ray order.
fn pose_groups(
    net: &Network,
    pose: &PoseFeatures,
    pts: &Tensor,
    view: &Tensor,
    group: usize,
) -> Result<(Tensor, Tensor)> {
    let (r, s, _) = pts.dims3()?;
    let vdim = view.dim(1)?;
    let n_poses = pose.g.dim(0)?;
    let k = r / n_poses;
    let (mut rgbs, mut sigmas) = (Vec::new(), Vec::new());
    for p0 in (0..n_poses).step_by(group.max(1)) {
        crate::interrupt::check()?;
        let p1 = (p0 + group).min(n_poses);
        let m = (p1 - p0) * k;
        let pts_g = pts.narrow(0, p0 * k, m)?.reshape((m * s, 3))?;
        let view_g = view
            .narrow(0, p0 * k, m)?
            .unsqueeze(1)?
            .broadcast_as((m, s, vdim))?
            .reshape((m * s, vdim))?;
        let (rgb, sigma) = net.eval_poses(pose, p0..p1, &pts_g, &view_g, None)?;
        rgbs.push(rgb.detach());
        sigmas.push(sigma.detach());
    }
    Ok((Tensor::cat(&rgbs, 0)?, Tensor::cat(&sigmas, 0)?))
}

/// Culling state of one forward pass (coarse and fine share the far-away constants).
pub(crate) struct CullCtx {
    test: Option<WindowTest>,
    /// The occupancy grid to consult, when the pass uses it.
    grid: Option<Arc<OccupancyGrid>>,
    /// `ray_hits_body` when rays are culled.
    ray_alive: Option<Vec<bool>>,
    fill: SampleFill,
    consts: ConstRows,
    /// Points this route sent through the network (far-away constants included).
    evaluated: usize,
    /// The network's numerics (its row gathers).
    numerics: crate::compute::numerics::Numerics,
    /// Points per network call in inference ([`inference_point_chunk`]).
    point_chunk: usize,
    /// Samples this route sent through the network.
    samples_evaluated: usize,
    /// Samples left out because their cells are empty.
    skipped_empty: usize,
    /// The fates of the last [`Self::run`], [R·S] in sample order.
    last_fates: Vec<SampleFate>,
    /// The host copy of the samples [R·S·3] the last [`Self::fates`] tested (when the pass
    /// has a window test): the joint grouping's plan reads them again.
    host_pts: Vec<f32>,
    /// Per ray, the depth z from which its samples are behind its early stop (infinite:
    /// not stopped); empty when the pass did not march.
    stop_z: Vec<f32>,
    /// Samples left out behind their rays' early stops.
    stopped_early: usize,
    /// With `cull_joints` on the CPU: the exact-zero window test that says which joints a
    /// sample needs (calls are grouped by it).
    joint_test: Option<WindowTest>,
    /// Σ over the calls of points × joints carried.
    joint_rows: usize,
    /// Training with the grid: how this pass feeds it.
    feed: Option<GridFeed>,
    /// Window tests run so far in this pass (each [`Self::fates`] call; picks the probes).
    tests_run: u64,
    /// What the evaluated samples of this pass saw of the grid (with `feed`).
    observed: Vec<GridObservation>,
}

/// SMPL's joints limb by limb (left leg, right leg, spine, neck and head, left arm, right
/// arm), each from the body outwards: samples sorted by their joints in this order lie limb
/// by limb, so that consecutive samples need neighbouring joints.
const CHAIN: [u32; N_JOINTS] = [
    1, 4, 7, 10, 2, 5, 8, 11, 0, 3, 6, 9, 12, 15, 13, 16, 18, 20, 22, 14, 17, 19, 21, 23,
];

/// A joint mask with its bits moved to their joints' places in [`CHAIN`] (the sort key of
/// the joint grouping).
pub(crate) fn chain_key(mask: JointMask) -> u32 {
    CHAIN
        .iter()
        .enumerate()
        .filter(|&(_, &j)| mask >> j & 1 == 1)
        .fold(0, |key, (place, _)| key | 1 << place)
}

/// The calls over samples sorted by [`chain_key`] with joint masks `masks`: (start, len,
/// union of their masks). A call takes at most `chunk` samples and, once it holds
/// [`MIN_JOINT_CALL`], no sample that would make it carry more than [`MAX_CALL_JOINTS`]
/// joints: much smaller calls pay the per-op overhead of the ~170 ops a call runs.
pub(crate) fn joint_calls(masks: &[JointMask], chunk: usize) -> Vec<(usize, usize, JointMask)> {
    let mut calls = Vec::new();
    let (mut start, mut union): (usize, JointMask) = (0, 0);
    for (i, &m) in masks.iter().enumerate() {
        let len = i - start;
        let grown = union | m;
        if len == chunk || (len >= MIN_JOINT_CALL && grown.count_ones() > MAX_CALL_JOINTS) {
            calls.push((start, len, union));
            (start, union) = (i, m);
        } else {
            union = grown;
        }
    }
    calls.push((start, masks.len() - start, union));
    calls
}

/// The joints a call with union mask `union` carries: `None` (all 24) for a full or an
/// empty mask.
pub(crate) fn call_joints(union: JointMask) -> Option<Vec<u32>> {
    let count = union.count_ones() as usize;
    (count > 0 && count < N_JOINTS).then(|| {
        (0..N_JOINTS as u32)
            .filter(|j| union >> j & 1 == 1)
            .collect()
    })
}

/// Fewest samples of a call that may be closed early to keep its joints few. A `cpu-small`
/// point costs no more in a call of 256 than of 4,096 (example `joint_cost --points`; 64
/// costs ~1.3× more), and the smaller floor lets calls carry fewer joints: 256 with
/// [`MAX_CALL_JOINTS`] 4 rendered ~1.2× faster on one worker than 1,024 with 8.
const MIN_JOINT_CALL: usize = 256;
/// Joints a call should not exceed (once it holds [`MIN_JOINT_CALL`] samples).
const MAX_CALL_JOINTS: u32 = 4;

/// The row of each of n samples given the samples in row order (0 for samples not listed).
fn rows_of(order: &[usize], n: usize) -> Vec<u32> {
    let mut rows = vec![0u32; n];
    for (row, &i) in order.iter().enumerate() {
        rows[i] = row as u32;
    }
    rows
}

/// Whether a sample of this fate takes the far-away constant (or zeros) instead of running
/// the network.
fn filled(f: &SampleFate) -> bool {
    matches!(
        f,
        SampleFate::Outside | SampleFate::Empty | SampleFate::Behind
    )
}

/// Network outputs at the far-away point, one row per ray that needed one.
#[derive(Default)]
struct ConstRows {
    /// Row of each ray (u32::MAX: not computed).
    row_of_ray: Vec<u32>,
    rgb: Vec<Tensor>,
    sigma: Vec<Tensor>,
    rows: usize,
    /// Row 0 serves every ray (inference, constant density 0).
    shared: bool,
    /// Whether the shared constant was tried in this forward pass.
    probed: bool,
}

impl ConstRows {
    /// File the far-away rows rgb [m,3] and sigma_raw [m,1] of `rays` (in that order).
    fn add(&mut self, rays: &[usize], rgb: Tensor, sigma_raw: Tensor) {
        for (i, &ray) in rays.iter().enumerate() {
            self.row_of_ray[ray] = (self.rows + i) as u32;
        }
        self.rows += rays.len();
        self.rgb.push(rgb);
        self.sigma.push(sigma_raw);
    }
}

/// The network calls of one culled stage: every row they read, gathered once per pass
/// (per pose, its kept samples in sample order, then in inference its far-away points), the
/// calls as ranges of those rows, and in training the far-away points' own call.
struct Plan {
    /// [rows,3] points and the view features of their rays.
    pts: Tensor,
    view: Tensor,
    jobs: Vec<Job>,
    /// The evaluated samples in the order of the calls' rows, when that is not sample order
    /// (samples grouped by their joints).
    order: Option<Vec<usize>>,
    far: Option<FarCall>,
}

/// Training: the far-away points of the rays that still need their constant, as one call
/// ([`Network::eval_shared`]): one point per pose of the batch, so the call sees equal
/// blocks, the network once per pose and the colour head once per ray (in a `cpu-small`
/// step with culling about one point in ten was a ray's far-away point). Inference keeps
/// them as rows of the pose's last call, one per ray: there the constant is bit for bit what
/// parity computes at samples whose window is exactly 0 (a separate small call rounds
/// differently in the last bit), which is what makes culling at threshold 0 exact.
struct FarCall {
    n_poses: usize,
    /// [P,3]: pose p's far-away point (a pose none of whose rays needs one repeats another
    /// pose's point; its row is computed and not read).
    pts: Tensor,
    /// The rays, in pose order.
    rays: Vec<usize>,
    /// [rays,V] view features and [rays] (u32) the pose of each ray.
    view: Tensor,
    rows: Tensor,
}

/// The culled stage as ONE network call over every pose (a GPU's plan): pose p's block of
/// `block` rows holds its kept samples in sample order, then the far-away points of its rays
/// in `far`, then copies of one of its samples up to the longest block (their outputs are
/// not read), so that [`Network::eval_poses`] sees equal blocks.
struct PaddedPlan {
    pts: Tensor,
    view: Tensor,
    n_poses: usize,
    block: usize,
    /// Row of the call's output of each sample (evaluated samples only; others 0).
    eval_row: Vec<u32>,
    /// Kept samples in all blocks.
    kept: usize,
    /// (ray, row of the call's output) of each far-away point.
    far: Vec<(usize, u32)>,
}

/// One network call of the culled route on rows `start..start + len + far_rays.len()` of
/// the plan, all of pose p: `len` kept samples, then (in inference) the far-away points of
/// `far_rays` (the rays that still need their constant).
struct Job {
    p: usize,
    start: usize,
    len: usize,
    far_rays: Vec<usize>,
    /// The joints the call carries (`None`: all).
    joints: Option<Vec<u32>>,
}

impl CullCtx {
    fn new(
        net: &Network,
        opts: &PassOptions,
        grid: Option<Arc<OccupancyGrid>>,
        poses: &Poses,
        pose: &PoseFeatures,
        bounds: Option<&RayBounds>,
    ) -> Result<Self> {
        let cfg = net.config();
        opts.validate(cfg)?;
        let c = &opts.culling;
        let ray_alive = match (c.rays, bounds) {
            (false, _) => None,
            (true, Some(b)) => Some(b.ray_hits_body.clone()),
            (true, None) => {
                return Err(ModelError::Input(
                    "ray culling needs the host ray bounds (cast on the host)".into(),
                ))
            }
        };
        let (skts, scales) = (host_f32(&poses.skts)?, host_f32(&pose.scales)?);
        let window_test = |t: f64| {
            let a = (cfg.window_alpha, cfg.window_beta);
            WindowTest::new(net.bone_align(), &skts, &scales, a.0, a.1, t)
        };
        let test = opts.window_threshold().map(window_test).transpose()?;
        // Joint groups are a CPU plan's: a GPU's one padded call per stage keeps all joints.
        let cpu_plan = pose.g.device().is_cpu() && !crate::compute::account::emulates_cuda();
        let joint_test = match opts.cull_joints && cpu_plan {
            true => Some(window_test(0.0)?),
            false => None,
        };
        Ok(Self {
            test,
            grid,
            ray_alive,
            fill: c.sample_fill,
            consts: ConstRows::default(),
            evaluated: 0,
            numerics: net.numerics(),
            point_chunk: inference_point_chunk(pose.g.device(), cfg),
            samples_evaluated: 0,
            skipped_empty: 0,
            last_fates: Vec::new(),
            host_pts: Vec::new(),
            stop_z: Vec::new(),
            stopped_early: 0,
            joint_test,
            joint_rows: 0,
            feed: opts.grid_feed,
            tests_run: 0,
            observed: Vec::new(),
        })
    }

    /// (points evaluated, samples evaluated, samples skipped as empty, samples stopped early,
    /// joint rows) so far.
    fn counters(&self) -> [usize; 5] {
        [
            self.evaluated,
            self.samples_evaluated,
            self.skipped_empty,
            self.stopped_early,
            self.joint_rows,
        ]
    }

    /// Importance weights of the coarse samples from the grid ([`WindowTest::grid_weights`]),
    /// or `None` when the pass consults no grid.
    fn grid_weights(&self, pts: &Tensor, z: &Tensor, dirs: &Tensor) -> Result<Option<Tensor>> {
        let (Some(test), Some(grid)) = (&self.test, &self.grid) else {
            return Ok(None);
        };
        let (r, s, _) = pts.dims3()?;
        let w = test.grid_weights(
            &host_f32(pts)?,
            &host_f32(z)?,
            &host_f32(dirs)?,
            r,
            s,
            self.ray_alive.as_deref(),
            grid,
        )?;
        Ok(Some(
            Tensor::from_vec(w, (r, s), z.device())?.to_dtype(z.dtype())?,
        ))
    }

    /// (rgb [n,3], sigma_raw [n,1], the alive mask [n,1] when zero-filled samples must stay
    /// empty under noise). `behind`: the samples' z [R·S], to leave out those behind their
    /// ray's early stop.
    ///
    /// The far-away points ride in the same network call as the evaluated samples: gemm's
    /// result for a row depends (by an ulp) on the size of the call, not on the row's place
    /// in it, and parity mode evaluates culled samples inside large calls.
    fn run(
        &mut self,
        net: &Network,
        pose: &PoseFeatures,
        pts: &Tensor,
        view: &Tensor,
        mode: &Mode,
        behind: Option<&[f32]>,
    ) -> Result<(Tensor, Tensor, Option<Tensor>)> {
        let (r, s, _) = pts.dims3()?;
        let n = r * s;
        let mut fates = self.fates(pts)?;
        if let Some(z) = behind {
            if z.len() != n || self.stop_z.len() != r {
                return Err(ModelError::shape("early stop: z", [n], [z.len()]));
            }
            self.mark_behind(&mut fates, z, s, 0..r);
        }
        self.last_fates.clone_from(&fates);
        let network_fill = self.fill == SampleFill::Network;
        let noisy = matches!(mode, Mode::Train(Some(_))) && net.config().density_noise_std > 0.0;
        let far_rays = self.far_rays(net, pose, view, &fates, s, mode.is_inference() && !noisy)?;
        let n_poses = pose.g.dim(0)?;
        let chunk = mode.is_inference().then_some(self.point_chunk);
        // A GPU wants one call for all poses (each call is ~170 launches whatever its size);
        // the CPU's workers take one pose (or chunk) each.
        let one_call = !pts.device().is_cpu() || crate::compute::account::emulates_cuda();
        let padded = match one_call {
            true => self.plan_padded(n_poses, pts, view, &fates, &far_rays, chunk)?,
            false => None,
        };
        let (rgb, sigma_raw, any_zero) = match padded {
            Some(plan) => {
                let (rgb, sigma, rows, eval_row) =
                    self.evaluate_padded(net, pose, plan, mode.is_inference())?;
                self.scatter(
                    vec![rgb],
                    vec![sigma],
                    rows,
                    &fates,
                    s,
                    network_fill,
                    pts,
                    Some(&eval_row),
                )?
            }
            None => {
                let plan = self.plan(n_poses, pts, view, &fates, &far_rays, chunk)?;
                let eval_row = plan.order.as_ref().map(|order| rows_of(order, n));
                let (rgbs, sigmas, evaluated) =
                    self.evaluate(net, pose, plan, mode.is_inference())?;
                let eval_row = eval_row.as_deref();
                self.scatter(
                    rgbs,
                    sigmas,
                    evaluated,
                    &fates,
                    s,
                    network_fill,
                    pts,
                    eval_row,
                )?
            }
        };
        self.observe(&fates, &sigma_raw, r, s)?;
        let alive = if noisy && any_zero {
            let alive: Vec<f32> = fates
                .iter()
                .map(|f| match f {
                    SampleFate::Evaluate => 1.0,
                    f if filled(f) && network_fill => 1.0,
                    _ => 0.0,
                })
                .collect();
            Some(Tensor::from_vec(alive, (n, 1), pts.device())?)
        } else {
            None
        };
        Ok((rgb, sigma_raw, alive))
    }

    /// The fate of every sample of pts [R,S,3] by the window test, ray culling and the grid.
    fn fates(&mut self, pts: &Tensor) -> Result<Vec<SampleFate>> {
        let (r, s, _) = pts.dims3()?;
        let mut fates = match (&self.test, &self.ray_alive) {
            (Some(t), alive) => {
                self.host_pts = host_f32(pts)?;
                t.fates(&self.host_pts, r, s, alive.as_deref(), self.grid.as_deref())?
            }
            (None, Some(alive)) => ray_fates(r, s, alive)?,
            (None, None) => vec![SampleFate::Evaluate; r * s],
        };
        if let Some(feed) = &self.feed {
            for (i, f) in fates.iter_mut().enumerate() {
                if *f == SampleFate::Empty && feed.probes(self.tests_run, i as u64) {
                    *f = SampleFate::Evaluate;
                }
            }
        }
        self.tests_run += 1;
        self.skipped_empty += fates.iter().filter(|f| **f == SampleFate::Empty).count();
        Ok(fates)
    }

    /// Record what the evaluated samples of pts [R,S,3] (their fates and relu of sigma_raw
    /// [R·S,1]) saw of the grid, when this pass feeds it. Reads σ back to the host.
    fn observe(
        &mut self,
        fates: &[SampleFate],
        sigma_raw: &Tensor,
        r: usize,
        s: usize,
    ) -> Result<()> {
        let (Some(_), Some(test), Some(grid)) = (&self.feed, &self.test, &self.grid) else {
            return Ok(());
        };
        // A non-finite density (a step the optimizer will skip) says nothing about a cell.
        let sigma: Vec<f32> = host_f32(&sigma_raw.detach())?
            .into_iter()
            .map(|v| if v.is_finite() { v.max(0.0) } else { 0.0 })
            .collect();
        let per_pose = r / test.n_poses().max(1);
        let evaluated: Vec<bool> = fates.iter().map(|f| *f == SampleFate::Evaluate).collect();
        for ray in 0..r {
            let span = ray * s..(ray + 1) * s;
            if !evaluated[span.clone()].contains(&true) {
                continue;
            }
            test.observe_ray(
                ray / per_pose.max(1),
                &self.host_pts[3 * span.start..3 * span.end],
                &evaluated[span.clone()],
                &sigma[span],
                grid,
                &mut self.observed,
            );
        }
        Ok(())
    }

    /// Mark [`SampleFate::Behind`] the samples to evaluate of `rays` (at z [R·S], S per ray)
    /// that lie at or behind their ray's stop depth.
    fn mark_behind(
        &mut self,
        fates: &mut [SampleFate],
        z: &[f32],
        s: usize,
        rays: impl IntoIterator<Item = usize>,
    ) {
        for ray in rays {
            let stop = self.stop_z[ray];
            for i in ray * s..(ray + 1) * s {
                if fates[i] == SampleFate::Evaluate && z[i] >= stop {
                    fates[i] = SampleFate::Behind;
                    self.stopped_early += 1;
                }
            }
        }
    }

    /// The rays (of `fates`, S per ray) whose filled samples still need their far-away
    /// constant evaluated; `probe`: whether one shared constant may serve every ray
    /// (inference without noise).
    fn far_rays(
        &mut self,
        net: &Network,
        pose: &PoseFeatures,
        view: &Tensor,
        fates: &[SampleFate],
        s: usize,
        probe: bool,
    ) -> Result<Vec<usize>> {
        let r = fates.len() / s.max(1);
        let need: Vec<usize> = if self.fill == SampleFill::Network {
            (0..r)
                .filter(|&ray| fates[ray * s..(ray + 1) * s].iter().any(filled))
                .collect()
        } else {
            Vec::new()
        };
        if self.consts.row_of_ray.len() != r {
            self.consts.row_of_ray = vec![u32::MAX; r];
        }
        if !need.is_empty() && probe && !self.consts.probed {
            self.probe_shared_constant(net, pose, view, need[0])?;
        }
        Ok(if self.consts.shared {
            Vec::new()
        } else {
            need.into_iter()
                .filter(|&ray| self.consts.row_of_ray[ray] == u32::MAX)
                .collect()
        })
    }

    /// The coarse pass of [`PointEval::march`] (inference): the samples to evaluate run in
    /// segments of [`EARLY_STOP_SEGMENT`] samples per ray, front to back; after each
    /// segment a ray whose transmittance exp(−Σ relu(σ)·δ) is below `eps` stops, and its
    /// later samples (and the fine samples at or behind the next sample's depth) are
    /// [`SampleFate::Behind`]. Filled samples count as empty in the transmittance, so a ray
    /// never stops earlier than its evaluated samples say. Returns (rgb [n,3], sigma_raw [n,1]).
    #[allow(clippy::too_many_arguments)]
    fn march(
        &mut self,
        net: &Network,
        pose: &PoseFeatures,
        pts: &Tensor,
        z: &Tensor,
        dirs: &Tensor,
        view: &Tensor,
        eps: f64,
    ) -> Result<(Tensor, Tensor)> {
        let (r, s, _) = pts.dims3()?;
        let zh = host_f32(z)?;
        let dh = host_f32(dirs)?;
        if zh.len() != r * s || dh.len() != r * 3 {
            return Err(ModelError::shape("early stop: z", [r, s], z.dims()));
        }
        let mut fates = self.fates(pts)?;
        let network_fill = self.fill == SampleFill::Network;
        self.stop_z = vec![f32::INFINITY; r];
        // Optical depth so far, per ray.
        let mut tau = vec![0f64; r];
        let (mut rgbs, mut sigmas) = (Vec::new(), Vec::new());
        let mut eval_row = vec![u32::MAX; r * s];
        let mut rows = 0usize;
        let norm: Vec<f32> = dh
            .chunks_exact(3)
            .map(|d| (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt())
            .collect();
        // The fates of one segment; every other sample stays out of its calls.
        let mut segment = vec![SampleFate::RayCulled; r * s];
        for start in (0..s).step_by(EARLY_STOP_SEGMENT) {
            let end = (start + EARLY_STOP_SEGMENT).min(s);
            // The segment's samples to evaluate, in sample order (the plan's row order).
            let mut kept = Vec::new();
            for ray in 0..r {
                for i in ray * s + start..ray * s + end {
                    segment[i] = fates[i];
                    if fates[i] == SampleFate::Evaluate {
                        kept.push(i);
                    }
                }
            }
            let far_rays = self.far_rays(net, pose, view, &segment, s, true)?;
            // A segment is a fraction of a pass: its calls are split so that every worker
            // gets one (the stop is approximate anyway, so call sizes may change the bits).
            let workers = crate::compute::parallel::workers_on(pts.device()).max(1);
            let chunk = self
                .point_chunk
                .min(kept.len().div_ceil(workers).max(MIN_MARCH_CHUNK));
            let plan = self.plan(pose.g.dim(0)?, pts, view, &segment, &far_rays, Some(chunk))?;
            let kept = plan.order.clone().unwrap_or(kept);
            let (seg_rgbs, seg_sigmas, evaluated) = self.evaluate(net, pose, plan, true)?;
            for ray in 0..r {
                segment[ray * s + start..ray * s + end].fill(SampleFate::RayCulled);
            }
            if evaluated == 0 {
                continue;
            }
            let sigma_host = Tensor::cat(&seg_sigmas, 0)?
                .flatten_all()?
                .to_dtype(DType::F32)?
                .to_vec1::<f32>()?;
            for (j, &i) in kept.iter().enumerate() {
                eval_row[i] = (rows + j) as u32;
                let (ray, k) = (i / s, i % s);
                if k + 1 < s {
                    let delta = (zh[i + 1] - zh[i]) * norm[ray];
                    tau[ray] += f64::from(sigma_host[j].max(0.0) * delta);
                }
            }
            rows += evaluated;
            rgbs.extend(seg_rgbs);
            sigmas.extend(seg_sigmas);
            if end < s {
                let stopping: Vec<usize> = (0..r)
                    .filter(|&ray| self.stop_z[ray].is_infinite() && (-tau[ray]).exp() < eps)
                    .collect();
                for &ray in &stopping {
                    self.stop_z[ray] = zh[ray * s + end];
                }
                self.mark_behind(&mut fates, &zh, s, stopping);
            }
        }
        self.last_fates.clone_from(&fates);
        let (rgb, sigma_raw, _) = self.scatter(
            rgbs,
            sigmas,
            rows,
            &fates,
            s,
            network_fill,
            pts,
            Some(&eval_row),
        )?;
        Ok((rgb, sigma_raw))
    }

    /// The network calls: per pose, the kept samples in chunks of `chunk`; the far-away
    /// points of `far_rays` at the back of the pose's last call. `None`: training (the graph
    /// is kept), one chunk per pose and the far-away points in a call of their own
    /// ([`FarCall`]).
    ///
    /// All rows are gathered at once and each call reads a range of them, but every call
    /// gets the rows, in the order and number, of a gather per call: a point's output can
    /// change in the last bits with its call's size and its place in it (gemm's
    /// matrix-vector path for the one-column σ head treats the rows past the last full
    /// vector apart), so regrouping the calls would change the outputs.
    fn plan(
        &self,
        n_poses: usize,
        pts: &Tensor,
        view: &Tensor,
        fates: &[SampleFate],
        far_rays: &[usize],
        chunk: Option<usize>,
    ) -> Result<Plan> {
        let (r, s, _) = pts.dims3()?;
        let k = r / n_poses;
        let n = r * s;
        // `run` and `march` plan the samples whose fates they just took: their host copy is
        // the one the window test read (a pass with joint grouping always has that test).
        let host = match &self.joint_test {
            Some(_) if self.host_pts.len() == n * 3 => {
                Some(std::borrow::Cow::Borrowed(&self.host_pts))
            }
            Some(_) => Some(std::borrow::Cow::Owned(host_f32(pts)?)),
            None => None,
        };
        let far_apart = chunk.is_none();
        // Rows of the source: i < n is sample i; n + q is the q-th far-away point.
        let mut src: Vec<u32> = Vec::new();
        let mut rays_of: Vec<u32> = Vec::new();
        let mut far_points = Vec::new();
        let mut jobs = Vec::new();
        for p in 0..n_poses {
            let first = src.len();
            let mut samples: Vec<usize> = (p * k * s..(p + 1) * k * s)
                .filter(|&i| fates[i] == SampleFate::Evaluate)
                .collect();
            // Samples that need the same joints side by side, so that each call needs few.
            let masks = match (&self.joint_test, &host) {
                (Some(test), Some(host)) => {
                    let masks = test.live_joints(host, r, s, &samples)?;
                    let mut keyed: Vec<(u32, JointMask, usize)> = masks
                        .into_iter()
                        .zip(samples)
                        .map(|(mask, i)| (chain_key(mask), mask, i))
                        .collect();
                    keyed.sort_by_key(|&(key, _, _)| key);
                    samples = keyed.iter().map(|&(_, _, i)| i).collect();
                    Some(
                        keyed
                            .into_iter()
                            .map(|(_, mask, _)| mask)
                            .collect::<Vec<_>>(),
                    )
                }
                _ => None,
            };
            src.extend(samples.iter().map(|&i| i as u32));
            let kept = src.len() - first;
            rays_of.extend(src[first..].iter().map(|&i| i / s as u32));
            let far_p: Vec<usize> = match far_apart {
                true => Vec::new(),
                false => far_rays
                    .iter()
                    .copied()
                    .filter(|&ray| ray / k == p)
                    .collect(),
            };
            if kept == 0 && far_p.is_empty() {
                continue;
            }
            let chunk = chunk.unwrap_or(kept.max(1)).max(1);
            let calls = match &masks {
                Some(m) => joint_calls(m, chunk),
                None => (0..kept.div_ceil(chunk).max(1))
                    .map(|c| (c * chunk, chunk.min(kept - c * chunk), ALL_JOINTS))
                    .collect(),
            };
            let n_calls = calls.len();
            for (c, (start, len, union)) in calls.into_iter().enumerate() {
                let joints = call_joints(union);
                jobs.push(Job {
                    p,
                    start: first + start,
                    len,
                    far_rays: if c + 1 == n_calls {
                        far_p.clone()
                    } else {
                        Vec::new()
                    },
                    joints,
                });
            }
            if !far_p.is_empty() {
                let test = self.test.as_ref().ok_or_else(|| {
                    ModelError::Input("culling: constants need the window test".into())
                })?;
                far_points.extend(test.far_point(p)?);
                let row = (n + far_points.len() / 3 - 1) as u32;
                src.extend(std::iter::repeat_n(row, far_p.len()));
                rays_of.extend(far_p.iter().map(|&ray| ray as u32));
            }
        }
        let order = self
            .joint_test
            .as_ref()
            .map(|_| src.iter().map(|&i| i as usize).filter(|&i| i < n).collect());
        let far = match far_apart {
            true => self.far_call(n_poses, k, view, far_rays, pts.dtype())?,
            false => None,
        };
        let (pts, view) = self.gather(pts, far_points, src, view, rays_of)?;
        Ok(Plan {
            pts,
            view,
            jobs,
            order,
            far,
        })
    }

    /// The [`FarCall`] of the rays `far_rays` (k rays per pose), or `None` without any.
    fn far_call(
        &self,
        n_poses: usize,
        k: usize,
        view: &Tensor,
        far_rays: &[usize],
        dtype: DType,
    ) -> Result<Option<FarCall>> {
        if far_rays.is_empty() {
            return Ok(None);
        }
        let test = self
            .test
            .as_ref()
            .ok_or_else(|| ModelError::Input("culling: constants need the window test".into()))?;
        let mut rays = far_rays.to_vec();
        rays.sort_unstable();
        let mut own = vec![None; n_poses];
        for &ray in &rays {
            if own[ray / k].is_none() {
                own[ray / k] = Some(test.far_point(ray / k)?);
            }
        }
        let filler = own
            .iter()
            .flatten()
            .copied()
            .next()
            .expect("a ray needs a point");
        let points: Vec<f32> = own.iter().flat_map(|o| o.unwrap_or(filler)).collect();
        let dev = view.device();
        let m = rays.len();
        let pose_of: Vec<u32> = rays.iter().map(|&ray| (ray / k) as u32).collect();
        let ids: Vec<u32> = rays.iter().map(|&ray| ray as u32).collect();
        Ok(Some(FarCall {
            n_poses,
            pts: Tensor::from_vec(points, (n_poses, 3), dev)?.to_dtype(dtype)?,
            view: select_rows(view, &Tensor::from_vec(ids, m, dev)?, self.numerics)?,
            rows: Tensor::from_vec(pose_of, m, dev)?,
            rays,
        }))
    }

    /// The rows `src` of the samples pts [R,S,3] followed by the points `far` (x, y, z
    /// each; row R·S + q is the q-th), and the view rows `rays_of`: the inputs of a plan's
    /// calls, gathered once.
    fn gather(
        &self,
        pts: &Tensor,
        far: Vec<f32>,
        src: Vec<u32>,
        view: &Tensor,
        rays_of: Vec<u32>,
    ) -> Result<(Tensor, Tensor)> {
        let dev = pts.device();
        let (r, s, _) = pts.dims3()?;
        let pts_flat = pts.reshape((r * s, 3))?;
        let source = match far.is_empty() {
            true => pts_flat,
            false => {
                let m = far.len() / 3;
                let far = Tensor::from_vec(far, (m, 3), dev)?.to_dtype(pts.dtype())?;
                Tensor::cat(&[pts_flat, far], 0)?
            }
        };
        let rows = src.len();
        Ok((
            select_rows(&source, &Tensor::from_vec(src, rows, dev)?, self.numerics)?,
            select_rows(view, &Tensor::from_vec(rays_of, rows, dev)?, self.numerics)?,
        ))
    }

    /// [`PaddedPlan`] for `fates`, or `None` when no sample needs the network or the call
    /// would exceed `chunk` points (then per-pose calls, [`Self::plan`]).
    fn plan_padded(
        &self,
        n_poses: usize,
        pts: &Tensor,
        view: &Tensor,
        fates: &[SampleFate],
        far_rays: &[usize],
        chunk: Option<usize>,
    ) -> Result<Option<PaddedPlan>> {
        let (r, s, _) = pts.dims3()?;
        let k = r / n_poses;
        let n = r * s;
        let kept: Vec<usize> = (0..n_poses)
            .map(|p| {
                fates[p * k * s..(p + 1) * k * s]
                    .iter()
                    .filter(|f| **f == SampleFate::Evaluate)
                    .count()
            })
            .collect();
        let mut far_of = vec![Vec::new(); n_poses];
        for &ray in far_rays {
            far_of[ray / k].push(ray);
        }
        let block = (0..n_poses)
            .map(|p| kept[p] + far_of[p].len())
            .max()
            .unwrap_or(0);
        if block == 0 || chunk.is_some_and(|c| n_poses * block > c) {
            return Ok(None);
        }
        let far_point: Vec<[f32; 3]> = match far_rays.is_empty() {
            true => Vec::new(),
            false => {
                let test = self.test.as_ref().ok_or_else(|| {
                    ModelError::Input("culling: constants need the window test".into())
                })?;
                (0..n_poses)
                    .map(|p| test.far_point(p))
                    .collect::<Result<_>>()?
            }
        };
        // Rows of the source: i < n is sample i; n + p is pose p's far-away point.
        let mut src: Vec<u32> = Vec::with_capacity(n_poses * block);
        let mut rays_of: Vec<u32> = Vec::with_capacity(n_poses * block);
        let mut eval_row = vec![0u32; n];
        let mut far = Vec::with_capacity(far_rays.len());
        for (p, far_p) in far_of.iter().enumerate() {
            let first = p * k * s;
            for i in first..first + k * s {
                if fates[i] == SampleFate::Evaluate {
                    eval_row[i] = src.len() as u32;
                    src.push(i as u32);
                    rays_of.push((i / s) as u32);
                }
            }
            for &ray in far_p {
                far.push((ray, src.len() as u32));
                src.push((n + p) as u32);
                rays_of.push(ray as u32);
            }
            src.resize(src.len() + block - kept[p] - far_p.len(), first as u32);
            rays_of.resize(
                rays_of.len() + block - kept[p] - far_p.len(),
                (first / s) as u32,
            );
        }
        let (pts, view) = self.gather(pts, far_point.concat(), src, view, rays_of)?;
        Ok(Some(PaddedPlan {
            pts,
            view,
            n_poses,
            block,
            eval_row,
            kept: kept.iter().sum(),
            far,
        }))
    }

    /// Run a [`PaddedPlan`]'s call and file its far-away rows under their rays. Returns
    /// (rgb, sigma_raw of all its rows, their count, the row of each evaluated sample).
    fn evaluate_padded(
        &mut self,
        net: &Network,
        pose: &PoseFeatures,
        plan: PaddedPlan,
        inference: bool,
    ) -> Result<(Tensor, Tensor, usize, Vec<u32>)> {
        crate::interrupt::check()?;
        let rows = plan.n_poses * plan.block;
        let (mut rgb, mut sigma) =
            net.eval_poses(pose, 0..plan.n_poses, &plan.pts, &plan.view, None)?;
        if inference {
            (rgb, sigma) = (rgb.detach(), sigma.detach());
        }
        if !plan.far.is_empty() {
            // The constants stay readable by the later stages of the pass (the fine samples
            // of a ray whose coarse samples needed one): the call's output is kept whole.
            let consts = &mut self.consts;
            for &(ray, row) in &plan.far {
                consts.row_of_ray[ray] = consts.rows as u32 + row;
            }
            consts.rows += rows;
            consts.rgb.push(rgb.clone());
            consts.sigma.push(sigma.clone());
        }
        self.evaluated += rows;
        self.joint_rows += rows * N_JOINTS;
        self.samples_evaluated += plan.kept;
        Ok((rgb, sigma, rows, plan.eval_row))
    }

    /// Run the jobs and the far-away call on the workers; keep the kept samples' rows in
    /// order and file the far-away rows under their rays. Returns (rgb rows, sigma rows,
    /// samples evaluated).
    fn evaluate(
        &mut self,
        net: &Network,
        pose: &PoseFeatures,
        plan: Plan,
        inference: bool,
    ) -> Result<(Vec<Tensor>, Vec<Tensor>, usize)> {
        let Plan {
            pts,
            view,
            jobs,
            far,
            ..
        } = plan;
        let workers = crate::compute::parallel::workers_on(net.device());
        let calls = jobs.len() + usize::from(far.is_some());
        let mut outs = crate::compute::parallel::map_ordered(workers, calls, |i| {
            crate::interrupt::check()?;
            let (rgb, sigma_raw) = match (jobs.get(i), &far) {
                (Some(job), _) => {
                    let rows = job.len + job.far_rays.len();
                    net.eval_joints(
                        pose,
                        job.p..job.p + 1,
                        &pts.narrow(0, job.start, rows)?,
                        &view.narrow(0, job.start, rows)?,
                        job.joints.as_deref(),
                        None,
                    )?
                }
                (None, Some(f)) => net.eval_shared(pose, 0..f.n_poses, &f.pts, &f.view, &f.rows)?,
                (None, None) => unreachable!("one call per job and one for the far-away points"),
            };
            // In inference the chunk's graph goes at once (see `chunked`).
            Ok::<_, ModelError>(if inference {
                (rgb.detach(), sigma_raw.detach())
            } else {
                (rgb, sigma_raw)
            })
        })?;
        let mut far_points = 0;
        let far_out = far.as_ref().and_then(|_| outs.pop());
        if let (Some(f), Some((rgb, sigma_raw))) = (far, far_out) {
            self.consts.add(&f.rays, rgb, sigma_raw);
            far_points = f.n_poses;
            self.joint_rows += f.n_poses * N_JOINTS;
        }
        let (mut rgbs, mut sigmas) = (Vec::new(), Vec::new());
        let mut evaluated = 0usize;
        for (job, (rgb, sigma_raw)) in jobs.into_iter().zip(outs) {
            if job.len > 0 {
                rgbs.push(rgb.narrow(0, 0, job.len)?);
                sigmas.push(sigma_raw.narrow(0, 0, job.len)?);
            }
            let far_len = job.far_rays.len();
            if far_len > 0 {
                self.consts.add(
                    &job.far_rays,
                    rgb.narrow(0, job.len, far_len)?,
                    sigma_raw.narrow(0, job.len, far_len)?,
                );
                far_points += far_len;
            }
            evaluated += job.len;
            self.joint_rows += (job.len + far_len) * job.joints.as_ref().map_or(N_JOINTS, Vec::len);
        }
        self.evaluated += evaluated + far_points;
        self.samples_evaluated += evaluated;
        Ok((rgbs, sigmas, evaluated))
    }

    /// Every sample's row: its own evaluation, its ray's far-away constant, or a zero row.
    /// The evaluated rows are in sample order, or at `eval_row[i]` for sample i when given.
    /// Returns (rgb [n,3], sigma_raw [n,1], whether any sample got the zero row).
    #[allow(clippy::too_many_arguments)]
    fn scatter(
        &self,
        rgbs: Vec<Tensor>,
        sigmas: Vec<Tensor>,
        evaluated: usize,
        fates: &[SampleFate],
        s: usize,
        network_fill: bool,
        pts: &Tensor,
        eval_row: Option<&[u32]>,
    ) -> Result<(Tensor, Tensor, bool)> {
        let dev = pts.device();
        let consts = &self.consts;
        let zero_row = (evaluated + consts.rows) as u32;
        let mut next = 0u32;
        let mut any_zero = false;
        let idx: Vec<u32> = fates
            .iter()
            .enumerate()
            .map(|(i, fate)| match fate {
                SampleFate::Evaluate => {
                    next += 1;
                    eval_row.map_or(next - 1, |rows| rows[i])
                }
                f if filled(f) && network_fill => {
                    evaluated as u32
                        + if consts.shared {
                            0
                        } else {
                            consts.row_of_ray[i / s]
                        }
                }
                _ => {
                    any_zero = true;
                    zero_row
                }
            })
            .collect();
        let out_dtype = rgbs
            .first()
            .or(consts.rgb.first())
            .map_or(pts.dtype(), |t| t.dtype());
        let mut rgb_rows = rgbs;
        let mut sigma_rows = sigmas;
        rgb_rows.extend(consts.rgb.iter().cloned());
        sigma_rows.extend(consts.sigma.iter().cloned());
        rgb_rows.push(Tensor::zeros((1, 3), out_dtype, dev)?);
        sigma_rows.push(Tensor::zeros((1, 1), out_dtype, dev)?);
        let n = fates.len();
        let idx = Tensor::from_vec(idx, n, dev)?;
        // Row gathers whose backward (training with culling) is parallel on CUDA.
        let rgb = select_rows(&Tensor::cat(&rgb_rows, 0)?, &idx, self.numerics)?;
        let sigma_raw = select_rows(&Tensor::cat(&sigma_rows, 0)?, &idx, self.numerics)?;
        Ok((rgb, sigma_raw, any_zero))
    }

    /// Inference without noise: the far-away density is one global constant (f^m and every
    /// windowed feature are 0 there). When it is ≤ 0 the colour of culled samples carries zero
    /// weight in every rendered output, so one evaluation (along ray `ray`) serves all rays;
    /// their raw colour is then the one seen along that ray. Decided once per forward pass.
    fn probe_shared_constant(
        &mut self,
        net: &Network,
        pose: &PoseFeatures,
        view: &Tensor,
        ray: usize,
    ) -> Result<()> {
        let consts = &mut self.consts;
        consts.probed = true;
        let Some(test) = self.test.as_ref() else {
            return Ok(());
        };
        let rays_per_pose = view.dim(0)? / pose.g.dim(0)?;
        let p = ray / rays_per_pose;
        let far = test.far_point(p)?;
        let pts = Tensor::from_vec(far.to_vec(), (1, 3), view.device())?;
        let view_c = view.narrow(0, ray, 1)?;
        let (rgb, sigma) = net.eval_points(pose, p, &pts, &view_c, None)?;
        self.evaluated += 1;
        self.joint_rows += N_JOINTS;
        let sigma0 = sigma
            .flatten_all()?
            .to_dtype(DType::F32)?
            .to_vec1::<f32>()?[0];
        if sigma0 <= 0.0 {
            consts.shared = true;
            consts.rows = 1;
            consts.rgb = vec![rgb.detach()];
            consts.sigma = vec![sigma.detach()];
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::cull::WindowTest;
    use candle_core::Device;
    use pma_data::skeleton::N_JOINTS;

    /// The rows of each network call as a gather per call builds them: per pose, the kept
    /// samples in chunks, the far-away points after the last chunk.
    fn per_call_rows(
        test: &WindowTest,
        host: &[f32],
        view: &[f32],
        vdim: usize,
        (r, s, n_poses): (usize, usize, usize),
        fates: &[SampleFate],
        far_rays: &[usize],
    ) -> Vec<(usize, Vec<f32>, Vec<f32>, usize)> {
        let k = r / n_poses;
        let mut out = Vec::new();
        for p in 0..n_poses {
            let idx: Vec<usize> = (p * k * s..(p + 1) * k * s)
                .filter(|&i| fates[i] == SampleFate::Evaluate)
                .collect();
            let far_p: Vec<usize> = far_rays
                .iter()
                .copied()
                .filter(|&ray| ray / k == p)
                .collect();
            if idx.is_empty() && far_p.is_empty() {
                continue;
            }
            let parts: Vec<&[usize]> = if idx.is_empty() {
                vec![&[]]
            } else {
                idx.chunks(INFERENCE_POINT_CHUNK).collect()
            };
            for (c, part) in parts.iter().enumerate() {
                let mut rows: Vec<f32> = part
                    .iter()
                    .flat_map(|&i| host[3 * i..3 * i + 3].to_vec())
                    .collect();
                let mut rays: Vec<usize> = part.iter().map(|&i| i / s).collect();
                if c + 1 == parts.len() {
                    for &ray in &far_p {
                        rows.extend(test.far_point(p).unwrap());
                        rays.push(ray);
                    }
                }
                let v = rays
                    .iter()
                    .flat_map(|&ray| view[vdim * ray..vdim * (ray + 1)].to_vec())
                    .collect();
                out.push((p, rows, v, part.len()));
            }
        }
        out
    }

    /// Gathering once per pass changes no network call: same pose, same rows bit for bit,
    /// same size, with several calls per pose, far-away points and a threshold of 0.2. In
    /// training the far-away points are a call of their own.
    #[test]
    fn one_gather_per_pass_feeds_every_call_the_rows_of_a_gather_per_call() {
        let dev = Device::Cpu;
        let mut eye = vec![0f32; N_JOINTS * 16];
        for j in 0..N_JOINTS {
            for d in 0..4 {
                eye[j * 16 + 5 * d] = 1.0;
            }
        }
        let n_poses = 2;
        let test = WindowTest::new(
            &eye,
            &eye.repeat(n_poses),
            &vec![0.7f32; N_JOINTS * 3],
            2.0,
            6,
            0.2,
        )
        .unwrap();
        let (r, s, vdim) = (2 * 1200, 16, 5);
        let mut state = 12345u64;
        let mut rnd = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
        };
        let host: Vec<f32> = (0..r * s * 3).map(|_| rnd()).collect();
        let view_host: Vec<f32> = (0..r * vdim).map(|_| rnd()).collect();
        let pts = Tensor::from_vec(host.clone(), (r, s, 3), &dev).unwrap();
        let view = Tensor::from_vec(view_host.clone(), (r, vdim), &dev).unwrap();
        let mut alive = vec![true; r];
        alive[7] = false;
        alive[1500] = false;
        let fates = test.fates(&host, r, s, Some(&alive), None).unwrap();
        let kept = fates.iter().filter(|f| **f == SampleFate::Evaluate).count();
        let outside = fates.iter().filter(|f| **f == SampleFate::Outside).count();
        assert!(
            kept > 2 * INFERENCE_POINT_CHUNK && outside > 0,
            "kept {kept}, outside {outside}"
        );
        let far_rays: Vec<usize> = (0..r)
            .filter(|&ray| fates[ray * s..(ray + 1) * s].contains(&SampleFate::Outside))
            .step_by(3)
            .collect();
        let ctx = CullCtx {
            test: Some(test.clone()),
            grid: None,
            ray_alive: Some(alive),
            fill: SampleFill::Network,
            consts: ConstRows::default(),
            evaluated: 0,
            numerics: Default::default(),
            point_chunk: INFERENCE_POINT_CHUNK,
            samples_evaluated: 0,
            skipped_empty: 0,
            last_fates: Vec::new(),
            host_pts: Vec::new(),
            stop_z: Vec::new(),
            stopped_early: 0,
            joint_test: None,
            joint_rows: 0,
            feed: None,
            tests_run: 0,
            observed: Vec::new(),
        };
        let bits = |x: &[f32]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        let reference = per_call_rows(
            &test,
            &host,
            &view_host,
            vdim,
            (r, s, n_poses),
            &fates,
            &far_rays,
        );
        let plan = ctx
            .plan(
                n_poses,
                &pts,
                &view,
                &fates,
                &far_rays,
                Some(INFERENCE_POINT_CHUNK),
            )
            .unwrap();
        assert_eq!(plan.jobs.len(), reference.len());
        assert!(reference.len() > n_poses, "some pose needs several calls");
        for (job, (p, rows, v, len)) in plan.jobs.iter().zip(&reference) {
            let n = job.len + job.far_rays.len();
            assert_eq!((job.p, job.len, n), (*p, *len, rows.len() / 3));
            let got = plan.pts.narrow(0, job.start, n).unwrap();
            let got_v = plan.view.narrow(0, job.start, n).unwrap();
            let got: Vec<f32> = got.flatten_all().unwrap().to_vec1().unwrap();
            let got_v: Vec<f32> = got_v.flatten_all().unwrap().to_vec1().unwrap();
            assert_eq!(bits(&got), bits(rows));
            assert_eq!(bits(&got_v), bits(v));
        }
        assert!(
            plan.far.is_none(),
            "inference keeps the far-away rows in its calls"
        );

        // Training (no chunk): one call per pose with its kept samples, and the far-away
        // points in a call of their own, one point per pose and the view of each ray.
        let plan = ctx
            .plan(n_poses, &pts, &view, &fates, &far_rays, None)
            .unwrap();
        let k = r / n_poses;
        assert_eq!(plan.jobs.len(), n_poses);
        for (p, job) in plan.jobs.iter().enumerate() {
            let kept: Vec<f32> = (p * k * s..(p + 1) * k * s)
                .filter(|&i| fates[i] == SampleFate::Evaluate)
                .flat_map(|i| host[3 * i..3 * i + 3].to_vec())
                .collect();
            assert!(job.far_rays.is_empty());
            assert_eq!((job.p, job.len), (p, kept.len() / 3));
            let got = plan.pts.narrow(0, job.start, job.len).unwrap();
            let got: Vec<f32> = got.flatten_all().unwrap().to_vec1().unwrap();
            assert_eq!(bits(&got), bits(&kept));
        }
        let far = plan.far.expect("far-away rays make a far-away call");
        assert_eq!(far.n_poses, n_poses);
        assert_eq!(far.rays, far_rays, "every far-away ray once, in pose order");
        let pose_of: Vec<u32> = far.rows.to_vec1().unwrap();
        let want: Vec<u32> = far_rays.iter().map(|&ray| (ray / k) as u32).collect();
        assert_eq!(pose_of, want);
        let got_v: Vec<f32> = far.view.flatten_all().unwrap().to_vec1().unwrap();
        let want_v: Vec<f32> = far_rays
            .iter()
            .flat_map(|&ray| view_host[vdim * ray..vdim * (ray + 1)].to_vec())
            .collect();
        assert_eq!(bits(&got_v), bits(&want_v));
        let got_p: Vec<f32> = far.pts.flatten_all().unwrap().to_vec1().unwrap();
        for p in 0..n_poses {
            let want = test.far_point(p).unwrap();
            assert_eq!(bits(&got_p[3 * p..3 * p + 3]), bits(&want), "pose {p}");
        }
    }

    #[test]
    fn joint_calls_cover_the_samples_and_keep_their_joints_few() {
        // Masks as sorted samples come: runs of neighbouring joints.
        let masks: Vec<u32> = (0..5000u32).map(|i| 0b11 << (i / 400).min(22)).collect();
        for chunk in [4096, 1500, 700] {
            let calls = joint_calls(&masks, chunk);
            let mut next = 0;
            for &(start, len, union) in &calls {
                assert_eq!(start, next, "calls are contiguous");
                assert!(
                    len > 0 && len <= chunk,
                    "call of {len} samples (chunk {chunk})"
                );
                let want = masks[start..start + len].iter().fold(0, |a, b| a | b);
                assert_eq!(union, want, "union of the call's masks");
                // A call is only closed for its joints once it is big enough.
                if start + len < masks.len() && len < chunk {
                    assert!(len >= MIN_JOINT_CALL);
                    assert!((union | masks[start + len]).count_ones() > MAX_CALL_JOINTS);
                }
                next = start + len;
            }
            assert_eq!(next, masks.len(), "every sample is in a call");
            if chunk >= MIN_JOINT_CALL {
                let widest = calls.iter().map(|c| c.2.count_ones()).max().unwrap();
                assert!(widest <= MAX_CALL_JOINTS, "a call carries {widest} joints");
            }
        }
        // chain_key keeps a mask's joints (one bit per joint) and orders limb by limb.
        assert_eq!(chain_key(ALL_JOINTS), ALL_JOINTS);
        assert!(
            chain_key(1 << 1) < chain_key(1 << 2),
            "left leg before right leg"
        );
        assert!(
            chain_key(1 << 10) < chain_key(1 << 0),
            "legs before the spine"
        );
        assert!(
            chain_key(1 << 22) < chain_key(1 << 14),
            "left arm before right arm"
        );
    }
}
