//! How the samples of a forward pass go through the network.
//!
//! [`Avatar::eval_points`] is the network on the points of one pose. A forward pass hands
//! all samples of a stage (coarse, then fine) to one [`PointEval`], which decides how they
//! reach it:
//!
//! * **dense**: one call per pose with the graph kept (training, the parity hook);
//! * **chunked**: bounded chunks on the CPU workers, outputs detached (inference);
//! * **culled**: only the samples culling keeps ([`crate::cull`]); the rest are filled
//!   from the network's far-away constant or with zeros. Gradients reach the evaluated
//!   samples and the constants, so training with culling at threshold 0 is parity too.
//!
//! Whatever the route, the result is raw [R,S,4] (rgb, density after noise and ReLU).

use candle_core::{DType, Tensor};

use crate::avatar::Avatar;
use crate::batch::{Mode, PoseFeatures, Poses};
use crate::config::{Culling, SampleFill};
use crate::cull::{ray_fates, SampleFate, WindowTest};
use crate::error::{ModelError, Result};
use crate::host::host_f32;
use crate::raycast::RayBounds;
use crate::trace::Trace;

/// Points per network call in inference: the largest per-point tensors are [n,24,128] f32,
/// 48 MiB each at 4,096 points, a handful alive per worker; many chunks also keep the
/// workers balanced. Larger chunks were no faster.
pub const INFERENCE_POINT_CHUNK: usize = 4_096;

/// The route of one forward pass's samples (see the module docs).
pub(crate) enum PointEval {
    Dense,
    Chunked,
    Culled(Box<CullCtx>),
}

impl PointEval {
    /// The route for `mode` and the avatar's culling options. A traced pass never culls:
    /// the trace needs the intermediates of every sample.
    pub fn new(
        avatar: &Avatar,
        mode: &Mode,
        poses: &Poses,
        pose: &PoseFeatures,
        bounds: &RayBounds,
        traced: bool,
    ) -> Result<Self> {
        let culling = &avatar.config().culling;
        if !traced && !culling.is_off() {
            return Ok(Self::Culled(Box::new(CullCtx::new(
                avatar, culling, poses, pose, bounds,
            )?)));
        }
        Ok(if mode.is_inference() {
            Self::Chunked
        } else {
            Self::Dense
        })
    }

    /// raw: [R,S,4] for the samples pts: [R,S,3] with view features view: [R,V].
    #[allow(clippy::too_many_arguments)]
    pub fn run(
        &mut self,
        avatar: &Avatar,
        pose: &PoseFeatures,
        pts: &Tensor,
        view: &Tensor,
        mode: &mut Mode,
        stage: &str,
        trace: Option<&mut Trace>,
    ) -> Result<Tensor> {
        let (r, s, _) = pts.dims3()?;
        let (rgb, sigma_raw, alive) = match self {
            Self::Dense => {
                let (rgb, sigma) = dense(avatar, pose, pts, view, stage, trace)?;
                (rgb, sigma, None)
            }
            Self::Chunked => {
                let (rgb, sigma) = chunked(avatar, pose, pts, view)?;
                (rgb, sigma, None)
            }
            Self::Culled(c) => c.run(avatar, pose, pts, view, mode)?,
        };
        let density = density(avatar, sigma_raw, mode, r * s)?;
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
fn density(avatar: &Avatar, sigma_raw: Tensor, mode: &mut Mode, n: usize) -> Result<Tensor> {
    let std = avatar.config().density_noise_std;
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

/// One network call per pose, graph kept; per-pose traces joined in ray order.
fn dense(
    avatar: &Avatar,
    pose: &PoseFeatures,
    pts: &Tensor,
    view: &Tensor,
    stage: &str,
    trace: Option<&mut Trace>,
) -> Result<(Tensor, Tensor)> {
    let (r, s, _) = pts.dims3()?;
    avatar.count_points(r * s);
    let n_poses = pose.g.dim(0)?;
    let k = r / n_poses;
    let (mut rgbs, mut sigmas, mut traces) = (Vec::new(), Vec::new(), Vec::new());
    for p in 0..n_poses {
        crate::interrupt::check()?;
        let (pts_p, view_p) = pose_block(pts, view, p, k)?;
        let mut tp = Trace::default();
        let traced = trace.is_some().then_some((&mut tp, stage));
        let (rgb, sigma_raw) = avatar.eval_points(pose, p, &pts_p, &view_p, traced)?;
        traces.push(tp);
        rgbs.push(rgb);
        sigmas.push(sigma_raw);
    }
    if let Some(t) = trace {
        t.concat_poses(&traces)?;
    }
    Ok((Tensor::cat(&rgbs, 0)?, Tensor::cat(&sigmas, 0)?))
}

/// Every (pose, chunk) pair is one job for the workers; outputs stay in ray order.
fn chunked(
    avatar: &Avatar,
    pose: &PoseFeatures,
    pts: &Tensor,
    view: &Tensor,
) -> Result<(Tensor, Tensor)> {
    let (r, s, _) = pts.dims3()?;
    avatar.count_points(r * s);
    let n_poses = pose.g.dim(0)?;
    let k = r / n_poses;
    let n = k * s;
    let chunk = INFERENCE_POINT_CHUNK;
    let per_pose = n.div_ceil(chunk);
    let inputs = (0..n_poses)
        .map(|p| pose_block(pts, view, p, k))
        .collect::<Result<Vec<_>>>()?;
    let workers = crate::parallel::workers_on(pts.device());
    let outs = crate::parallel::map_ordered(workers, n_poses * per_pose, |i| {
        crate::interrupt::check()?;
        let (p, c) = (i / per_pose, i % per_pose);
        let (start, len) = (c * chunk, chunk.min(n - c * chunk));
        let (pts_p, view_p) = &inputs[p];
        let (rgb, sigma_raw) = avatar.eval_points(
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

/// Culling state of one forward pass (coarse and fine share the far-away constants).
pub(crate) struct CullCtx {
    test: Option<WindowTest>,
    /// `ray_hits_body` when rays are culled.
    ray_alive: Option<Vec<bool>>,
    fill: SampleFill,
    consts: ConstRows,
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

/// One network call of the culled route: the kept samples of one chunk of pose p, then
/// the far-away points of the rays that still need their constant.
struct Job {
    p: usize,
    pts: Tensor,
    view: Tensor,
    /// Kept samples at the front of the call.
    len: usize,
    /// Rays whose far-away constant rides at the back of the call.
    far_rays: Vec<usize>,
}

impl CullCtx {
    fn new(
        avatar: &Avatar,
        c: &Culling,
        poses: &Poses,
        pose: &PoseFeatures,
        bounds: &RayBounds,
    ) -> Result<Self> {
        let cfg = avatar.config();
        let test = match c.sample_threshold {
            Some(t) => Some(WindowTest::new(
                avatar.bone_align(),
                &host_f32(&poses.skts)?,
                &host_f32(&pose.scales)?,
                cfg.window_alpha,
                cfg.window_beta,
                t,
            )?),
            None => None,
        };
        Ok(Self {
            test,
            ray_alive: c.rays.then(|| bounds.ray_hits_body.clone()),
            fill: c.sample_fill,
            consts: ConstRows::default(),
        })
    }

    /// (rgb [n,3], sigma_raw [n,1], the alive mask [n,1] when zero-filled samples must stay
    /// empty under noise).
    ///
    /// The far-away points ride in the same network call as the evaluated samples: gemm's
    /// result for a row depends (by an ulp) on the size of the call, not on the row's place
    /// in it, and parity mode evaluates culled samples inside large calls.
    fn run(
        &mut self,
        avatar: &Avatar,
        pose: &PoseFeatures,
        pts: &Tensor,
        view: &Tensor,
        mode: &Mode,
    ) -> Result<(Tensor, Tensor, Option<Tensor>)> {
        let (r, s, _) = pts.dims3()?;
        let n = r * s;
        let fates = match (&self.test, &self.ray_alive) {
            (Some(t), alive) => t.fates(&host_f32(pts)?, r, s, alive.as_deref())?,
            (None, Some(alive)) => ray_fates(r, s, alive)?,
            (None, None) => vec![SampleFate::Evaluate; n],
        };
        let network_fill = self.fill == SampleFill::Network;
        let noisy = matches!(mode, Mode::Train(Some(_))) && avatar.config().density_noise_std > 0.0;
        let need: Vec<usize> = if network_fill {
            (0..r)
                .filter(|&ray| fates[ray * s..(ray + 1) * s].contains(&SampleFate::Outside))
                .collect()
        } else {
            Vec::new()
        };
        if self.consts.row_of_ray.len() != r {
            self.consts.row_of_ray = vec![u32::MAX; r];
        }
        if !need.is_empty() && mode.is_inference() && !noisy && !self.consts.probed {
            self.probe_shared_constant(avatar, pose, view, need[0])?;
        }
        let far_rays: Vec<usize> = if self.consts.shared {
            Vec::new()
        } else {
            need.into_iter()
                .filter(|&ray| self.consts.row_of_ray[ray] == u32::MAX)
                .collect()
        };
        let jobs = self.plan(pose, pts, view, &fates, &far_rays, mode.is_inference())?;
        let (rgbs, sigmas, evaluated) = self.evaluate(avatar, pose, jobs, mode.is_inference())?;
        let (rgb, sigma_raw, any_zero) =
            self.scatter(rgbs, sigmas, evaluated, &fates, s, network_fill, pts)?;
        let alive = if noisy && any_zero {
            let alive: Vec<f32> = fates
                .iter()
                .map(|f| match f {
                    SampleFate::Evaluate => 1.0,
                    SampleFate::Outside if network_fill => 1.0,
                    _ => 0.0,
                })
                .collect();
            Some(Tensor::from_vec(alive, (n, 1), pts.device())?)
        } else {
            None
        };
        Ok((rgb, sigma_raw, alive))
    }

    /// The network calls: per pose, the kept samples in chunks (one chunk when the graph is
    /// kept), the far-away points of `far_rays` at the back of the pose's last call.
    fn plan(
        &self,
        pose: &PoseFeatures,
        pts: &Tensor,
        view: &Tensor,
        fates: &[SampleFate],
        far_rays: &[usize],
        inference: bool,
    ) -> Result<Vec<Job>> {
        let (r, s, _) = pts.dims3()?;
        let n_poses = pose.g.dim(0)?;
        let k = r / n_poses;
        let dev = pts.device();
        let pts_flat = pts.reshape((r * s, 3))?;
        let mut jobs = Vec::new();
        for p in 0..n_poses {
            let idx: Vec<u32> = (p * k * s..(p + 1) * k * s)
                .filter(|&i| fates[i] == SampleFate::Evaluate)
                .map(|i| i as u32)
                .collect();
            let far_p: Vec<usize> = far_rays
                .iter()
                .copied()
                .filter(|&ray| ray / k == p)
                .collect();
            if idx.is_empty() && far_p.is_empty() {
                continue;
            }
            let chunk = if inference {
                INFERENCE_POINT_CHUNK
            } else {
                idx.len().max(1)
            };
            let parts: Vec<&[u32]> = if idx.is_empty() {
                vec![&[]]
            } else {
                idx.chunks(chunk).collect()
            };
            let last = parts.len() - 1;
            for (c, part) in parts.iter().enumerate() {
                let len = part.len();
                let far = if c == last { far_p.clone() } else { Vec::new() };
                let mut rays_of: Vec<u32> = part.iter().map(|&i| i / s as u32).collect();
                let mut pts_c = Vec::new();
                if len > 0 {
                    let ids = Tensor::from_vec(part.to_vec(), len, dev)?;
                    pts_c.push(pts_flat.index_select(&ids, 0)?);
                }
                if !far.is_empty() {
                    let test = self.test.as_ref().ok_or_else(|| {
                        ModelError::Input("culling: constants need the window test".into())
                    })?;
                    let x = test.far_point(p)?;
                    let far_pts = Tensor::from_vec(x.repeat(far.len()), (far.len(), 3), dev)?;
                    pts_c.push(far_pts.to_dtype(pts.dtype())?);
                    rays_of.extend(far.iter().map(|&ray| ray as u32));
                }
                let rows = rays_of.len();
                let view_c = view.index_select(&Tensor::from_vec(rays_of, rows, dev)?, 0)?;
                jobs.push(Job {
                    p,
                    pts: Tensor::cat(&pts_c, 0)?,
                    view: view_c,
                    len,
                    far_rays: far,
                });
            }
        }
        Ok(jobs)
    }

    /// Run the jobs on the workers; keep the kept samples' rows in order and file the
    /// far-away rows under their rays. Returns (rgb rows, sigma rows, samples evaluated).
    fn evaluate(
        &mut self,
        avatar: &Avatar,
        pose: &PoseFeatures,
        jobs: Vec<Job>,
        inference: bool,
    ) -> Result<(Vec<Tensor>, Vec<Tensor>, usize)> {
        let workers = crate::parallel::workers_on(avatar.device());
        let outs = crate::parallel::map_ordered(workers, jobs.len(), |i| {
            crate::interrupt::check()?;
            let job = &jobs[i];
            let (rgb, sigma_raw) = avatar.eval_points(pose, job.p, &job.pts, &job.view, None)?;
            // In inference the chunk's graph goes at once (see `chunked`).
            Ok::<_, ModelError>(if inference {
                (rgb.detach(), sigma_raw.detach())
            } else {
                (rgb, sigma_raw)
            })
        })?;
        let (mut rgbs, mut sigmas) = (Vec::new(), Vec::new());
        let (mut evaluated, mut far_done) = (0usize, 0usize);
        for (job, (rgb, sigma_raw)) in jobs.into_iter().zip(outs) {
            if job.len > 0 {
                rgbs.push(rgb.narrow(0, 0, job.len)?);
                sigmas.push(sigma_raw.narrow(0, 0, job.len)?);
            }
            let far_len = job.far_rays.len();
            if far_len > 0 {
                let consts = &mut self.consts;
                for (i, &ray) in job.far_rays.iter().enumerate() {
                    consts.row_of_ray[ray] = (consts.rows + i) as u32;
                }
                consts.rows += far_len;
                consts.rgb.push(rgb.narrow(0, job.len, far_len)?);
                consts.sigma.push(sigma_raw.narrow(0, job.len, far_len)?);
                far_done += far_len;
            }
            evaluated += job.len;
        }
        avatar.count_points(evaluated + far_done);
        Ok((rgbs, sigmas, evaluated))
    }

    /// Every sample's row: its own evaluation, its ray's far-away constant, or a zero row.
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
                    next - 1
                }
                SampleFate::Outside if network_fill => {
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
        let rgb = Tensor::cat(&rgb_rows, 0)?.index_select(&idx, 0)?;
        let sigma_raw = Tensor::cat(&sigma_rows, 0)?.index_select(&idx, 0)?;
        Ok((rgb, sigma_raw, any_zero))
    }

    /// Inference without noise: the far-away density is one global constant (f^m and every
    /// windowed feature are 0 there). When it is ≤ 0 the colour of culled samples carries zero
    /// weight in every rendered output, so one evaluation (along ray `ray`) serves all rays;
    /// their raw colour is then the one seen along that ray. Decided once per forward pass.
    fn probe_shared_constant(
        &mut self,
        avatar: &Avatar,
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
        let (rgb, sigma) = avatar.eval_points(pose, p, &pts, &view_c, None)?;
        avatar.count_points(1);
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
