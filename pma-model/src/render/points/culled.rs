//! The culled route: only the samples that culling, the occupancy grid and the early stop
//! keep run the network ([`CullCtx`]); the rest take their ray's far-away constant or zeros.

use std::sync::Arc;

use candle_core::{DType, Tensor};

use super::plan::{evaluate, evaluate_padded, ConstRows, Evaluated, Planner, Stage};
use super::{inference_point_chunk, Counts};
use crate::compute::host::host_f32;
use crate::compute::ops::rows::select_rows;
use crate::error::{ModelError, Result};
use crate::network::occupancy::OccupancyGrid;
use crate::network::{Network, PoseFeatures};
use crate::render::batch::{Mode, Poses};
use crate::render::cull::{ray_fates, SampleFate, WindowTest};
use crate::render::options::{
    GridFeed, GridObservation, PassOptions, SampleFill, EARLY_STOP_SEGMENT,
};
use crate::render::raycast::RayBounds;
use pma_data::skeleton::N_JOINTS;

/// The smallest network call of an early-stop segment split over the workers.
const MIN_MARCH_CHUNK: usize = 512;

/// Culling state of one forward pass (coarse and fine share the far-away constants).
pub(super) struct CullCtx {
    test: Option<WindowTest>,
    /// The occupancy grid to consult, when the pass uses it.
    grid: Option<Arc<OccupancyGrid>>,
    /// `ray_hits_body` when rays are culled.
    ray_alive: Option<Vec<bool>>,
    fill: SampleFill,
    consts: ConstRows,
    /// What this route's network calls did so far.
    pub(super) counts: Counts,
    /// The network's numerics (its row gathers).
    numerics: crate::compute::numerics::Numerics,
    /// Points per network call in inference ([`inference_point_chunk`]).
    point_chunk: usize,
    /// The fates of the last [`Self::run`], [R·S] in sample order.
    last_fates: Vec<SampleFate>,
    /// The host copy of the samples [R·S·3] the last [`Self::fates`] tested (when the pass
    /// has a window test): the joint grouping's plan reads them again.
    host_pts: Vec<f32>,
    /// Per ray, the depth z from which its samples are behind its early stop (infinite:
    /// not stopped); empty when the pass did not march.
    stop_z: Vec<f32>,
    /// With `cull_joints` on the CPU: the exact-zero window test that says which joints a
    /// sample needs (calls are grouped by it).
    joint_test: Option<WindowTest>,
    /// Training with the grid: how this pass feeds it.
    feed: Option<GridFeed>,
    /// Window tests run so far in this pass (each [`Self::fates`] call; picks the probes).
    tests_run: u64,
    /// What the evaluated samples of this pass saw of the grid (with `feed`).
    observed: Vec<GridObservation>,
}

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

impl CullCtx {
    pub fn new(
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
            counts: Counts::default(),
            numerics: net.numerics(),
            point_chunk: inference_point_chunk(pose.g.device(), cfg),
            last_fates: Vec::new(),
            host_pts: Vec::new(),
            stop_z: Vec::new(),
            joint_test,
            feed: opts.grid_feed,
            tests_run: 0,
            observed: Vec::new(),
        })
    }

    /// Rays of this pass that ray culling left without any sample to run.
    pub fn rays_culled(&self) -> usize {
        self.ray_alive
            .as_ref()
            .map_or(0, |alive| alive.iter().filter(|&&a| !a).count())
    }

    /// What this pass's evaluated samples saw of the grid, taken out.
    pub fn take_observed(&mut self) -> Vec<GridObservation> {
        std::mem::take(&mut self.observed)
    }

    /// Of the last [`Self::run`] on rays of `sc` coarse samples followed by their fine ones,
    /// the coarse samples that ran the network.
    pub fn coarse_evaluated(&self, sc: usize, s: usize) -> usize {
        self.last_fates
            .chunks(s)
            .map(|ray| {
                ray[..sc]
                    .iter()
                    .filter(|f| **f == SampleFate::Evaluate)
                    .count()
            })
            .sum()
    }

    /// The planner of this pass's calls.
    fn planner(&self) -> Planner<'_> {
        Planner {
            test: self.test.as_ref(),
            joint_test: self.joint_test.as_ref(),
            host_pts: &self.host_pts,
            numerics: self.numerics,
        }
    }

    /// Count what a plan's calls did.
    fn tally(&mut self, e: &Evaluated) {
        self.counts.points += e.points;
        self.counts.samples += e.samples;
        self.counts.joint_rows += e.joint_rows;
    }

    /// Importance weights of the coarse samples from the grid ([`WindowTest::grid_weights`]),
    /// or `None` when the pass consults no grid.
    pub fn grid_weights(&self, pts: &Tensor, z: &Tensor, dirs: &Tensor) -> Result<Option<Tensor>> {
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
    /// empty under noise). With the samples' z [R,S], those behind their ray's early stop
    /// (when the pass marched) are left out.
    ///
    /// The far-away points ride in the same network call as the evaluated samples: gemm's
    /// result for a row depends (by an ulp) on the size of the call, not on the row's place
    /// in it, and parity mode evaluates culled samples inside large calls.
    pub fn run(
        &mut self,
        net: &Network,
        pose: &PoseFeatures,
        pts: &Tensor,
        z: Option<&Tensor>,
        view: &Tensor,
        mode: &Mode,
    ) -> Result<(Tensor, Tensor, Option<Tensor>)> {
        let (r, s, _) = pts.dims3()?;
        let n = r * s;
        let behind = match z {
            Some(z) if !self.stop_z.is_empty() => Some(host_f32(z)?),
            _ => None,
        };
        let mut fates = self.fates(pts)?;
        if let Some(z) = behind.as_deref() {
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
        let stage = Stage {
            n_poses,
            pts,
            view,
            fates: &fates,
            far_rays: &far_rays,
            chunk,
        };
        let padded = match one_call {
            true => self.planner().plan_padded(stage)?,
            false => None,
        };
        let inference = mode.is_inference();
        let (evaluated, eval_row) = match padded {
            Some(plan) => {
                let (e, eval_row) = evaluate_padded(net, pose, plan, inference, &mut self.consts)?;
                (e, Some(eval_row))
            }
            None => {
                let plan = self.planner().plan(stage)?;
                let eval_row = plan.order.as_ref().map(|order| rows_of(order, n));
                (
                    evaluate(net, pose, plan, inference, &mut self.consts)?,
                    eval_row,
                )
            }
        };
        self.tally(&evaluated);
        let (rgb, sigma_raw, any_zero) = self.scatter(
            evaluated.rgbs,
            evaluated.sigmas,
            evaluated.rows,
            &fates,
            s,
            network_fill,
            pts,
            eval_row.as_deref(),
        )?;
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
        self.counts.skipped_empty += fates.iter().filter(|f| **f == SampleFate::Empty).count();
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
                    self.counts.stopped_early += 1;
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

    /// The coarse stage with the early stop (inference): the samples to evaluate run in
    /// segments of [`EARLY_STOP_SEGMENT`] samples per ray, front to back; after each
    /// segment a ray whose transmittance exp(−Σ relu(σ)·δ) is below `eps` stops, and its
    /// later samples (and the fine samples at or behind the next sample's depth) are
    /// [`SampleFate::Behind`]. Filled samples count as empty in the transmittance, so a ray
    /// never stops earlier than its evaluated samples say. Returns (rgb [n,3], sigma_raw [n,1]).
    #[allow(clippy::too_many_arguments)]
    pub fn march(
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
            let plan = self.planner().plan(Stage {
                n_poses: pose.g.dim(0)?,
                pts,
                view,
                fates: &segment,
                far_rays: &far_rays,
                chunk: Some(chunk),
            })?;
            let kept = plan.order.clone().unwrap_or(kept);
            let segment_out = evaluate(net, pose, plan, true, &mut self.consts)?;
            self.tally(&segment_out);
            let Evaluated {
                rgbs: seg_rgbs,
                sigmas: seg_sigmas,
                rows: evaluated,
                ..
            } = segment_out;
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
        self.counts.points += 1;
        self.counts.joint_rows += N_JOINTS;
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
