//! The network calls of a culled stage: planned over the samples to evaluate (all rows
//! gathered once), run on the workers, and their far-away rows filed under their rays.

use candle_core::{DType, Tensor};

use super::joints::{call_joints, chain_key, joint_calls};
use crate::compute::host::host_f32;
use crate::compute::ops::rows::select_rows;
use crate::error::{ModelError, Result};
use crate::network::{Network, PoseFeatures};
use crate::render::cull::{JointMask, SampleFate, WindowTest, ALL_JOINTS};
use pma_data::skeleton::N_JOINTS;

/// Network outputs at the far-away point, one row per ray that needed one (the coarse and
/// fine stages of a pass share them).
#[derive(Default)]
pub(super) struct ConstRows {
    /// Row of each ray (u32::MAX: not computed).
    pub row_of_ray: Vec<u32>,
    pub rgb: Vec<Tensor>,
    pub sigma: Vec<Tensor>,
    pub rows: usize,
    /// Row 0 serves every ray (inference, constant density 0).
    pub shared: bool,
    /// Whether the shared constant was tried in this forward pass.
    pub probed: bool,
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

/// What a plan reads besides the samples and their fates.
pub(super) struct Planner<'a> {
    /// The window test, which places each pose's far-away point.
    pub test: Option<&'a WindowTest>,
    /// With `cull_joints` on the CPU: the exact-zero window test that says which joints a
    /// sample needs (calls are grouped by it).
    pub joint_test: Option<&'a WindowTest>,
    /// The host copy of the samples [R·S·3] the fates were taken from, when the window
    /// test read one (the joint grouping reads them again).
    pub host_pts: &'a [f32],
    /// The network's numerics (its row gathers).
    pub numerics: crate::compute::numerics::Numerics,
}

/// The samples of a culled stage a plan covers: pts [R,S,3] of `n_poses` poses (R/P rays
/// each), the view features [R,V] of their rays, every sample's fate, the rays that still
/// need their far-away constant, and the points per call in inference (`None`: training).
#[derive(Clone, Copy)]
pub(super) struct Stage<'a> {
    pub n_poses: usize,
    pub pts: &'a Tensor,
    pub view: &'a Tensor,
    pub fates: &'a [SampleFate],
    pub far_rays: &'a [usize],
    pub chunk: Option<usize>,
}

/// What the calls of a plan returned: the rows of the kept samples (or of the whole padded
/// call) and the counts of the work done. The far-away rows are filed in the pass's
/// [`ConstRows`].
pub(super) struct Evaluated {
    pub rgbs: Vec<Tensor>,
    pub sigmas: Vec<Tensor>,
    /// Rows in `rgbs` and `sigmas`.
    pub rows: usize,
    /// Kept samples that ran the network.
    pub samples: usize,
    /// Points that went through the network (far-away points and padding included).
    pub points: usize,
    /// Σ over the calls of points × joints carried.
    pub joint_rows: usize,
}

/// The network calls of one culled stage: every row they read, gathered once per pass
/// (per pose, its kept samples in sample order, then in inference its far-away points), the
/// calls as ranges of those rows, and in training the far-away points' own call.
pub(super) struct Plan {
    /// [rows,3] points and the view features of their rays.
    pts: Tensor,
    view: Tensor,
    jobs: Vec<Job>,
    /// The evaluated samples in the order of the calls' rows, when that is not sample order
    /// (samples grouped by their joints).
    pub order: Option<Vec<usize>>,
    far: Option<FarCall>,
}

/// Training: the far-away points of the rays that still need their constant, as one call
/// ([`Network::eval_shared`]): one point per pose of the batch, so the call sees equal
/// blocks, the network once per pose and the colour head once per ray (in a `cpu-small`
/// step with culling about one point in ten was a ray's far-away point). Inference keeps
/// them as rows of the pose's last call, one per ray: there the constant is bit for bit what
/// parity computes at samples whose window is exactly 0 (a separate small call rounds
/// differently in the last bit), which is what makes culling at threshold 0 exact.
pub(super) struct FarCall {
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
pub(super) struct PaddedPlan {
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
pub(super) struct Job {
    p: usize,
    start: usize,
    len: usize,
    far_rays: Vec<usize>,
    /// The joints the call carries (`None`: all).
    joints: Option<Vec<u32>>,
}

impl Planner<'_> {
    /// The network calls of `stage`: per pose, the kept samples in chunks of its `chunk`; the
    /// far-away points of its `far_rays` at the back of the pose's last call. `None`:
    /// training (the graph is kept), one chunk per pose and the far-away points in a call of
    /// their own ([`FarCall`]).
    ///
    /// All rows are gathered at once and each call reads a range of them, but every call
    /// gets the rows, in the order and number, of a gather per call: a point's output can
    /// change in the last bits with its call's size and its place in it (gemm's
    /// matrix-vector path for the one-column σ head treats the rows past the last full
    /// vector apart), so regrouping the calls would change the outputs.
    pub fn plan(&self, stage: Stage) -> Result<Plan> {
        let Stage {
            n_poses,
            pts,
            view,
            fates,
            far_rays,
            chunk,
        } = stage;
        let (r, s, _) = pts.dims3()?;
        let k = r / n_poses;
        let n = r * s;
        // `run` and `march` plan the samples whose fates they just took: their host copy is
        // the one the window test read (a pass with joint grouping always has that test).
        let host = match &self.joint_test {
            Some(_) if self.host_pts.len() == n * 3 => {
                Some(std::borrow::Cow::Borrowed(self.host_pts))
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
                let test = self.test.ok_or_else(|| {
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

    /// [`PaddedPlan`] for `stage`, or `None` when no sample needs the network or the call
    /// would exceed its `chunk` points (then per-pose calls, [`Self::plan`]).
    pub fn plan_padded(&self, stage: Stage) -> Result<Option<PaddedPlan>> {
        let (n_poses, fates, far_rays) = (stage.n_poses, stage.fates, stage.far_rays);
        let (r, s, _) = stage.pts.dims3()?;
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
        if block == 0 || stage.chunk.is_some_and(|c| n_poses * block > c) {
            return Ok(None);
        }
        let far_point: Vec<[f32; 3]> = match far_rays.is_empty() {
            true => Vec::new(),
            false => {
                let test = self.test.ok_or_else(|| {
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
        let (pts, view) = self.gather(stage.pts, far_point.concat(), src, stage.view, rays_of)?;
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
}

/// Run a [`PaddedPlan`]'s call and file its far-away rows under their rays. Returns
/// what it evaluated (every row of the call) and the row of each evaluated sample.
pub(super) fn evaluate_padded(
    net: &Network,
    pose: &PoseFeatures,
    plan: PaddedPlan,
    inference: bool,
    consts: &mut ConstRows,
) -> Result<(Evaluated, Vec<u32>)> {
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
        for &(ray, row) in &plan.far {
            consts.row_of_ray[ray] = consts.rows as u32 + row;
        }
        consts.rows += rows;
        consts.rgb.push(rgb.clone());
        consts.sigma.push(sigma.clone());
    }
    let evaluated = Evaluated {
        rgbs: vec![rgb],
        sigmas: vec![sigma],
        rows,
        samples: plan.kept,
        points: rows,
        joint_rows: rows * N_JOINTS,
    };
    Ok((evaluated, plan.eval_row))
}

/// Run the jobs and the far-away call on the workers; keep the kept samples' rows in
/// order and file the far-away rows under their rays in `consts`.
pub(super) fn evaluate(
    net: &Network,
    pose: &PoseFeatures,
    plan: Plan,
    inference: bool,
    consts: &mut ConstRows,
) -> Result<Evaluated> {
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
    let mut joint_rows = 0;
    let far_out = far.as_ref().and_then(|_| outs.pop());
    if let (Some(f), Some((rgb, sigma_raw))) = (far, far_out) {
        consts.add(&f.rays, rgb, sigma_raw);
        far_points = f.n_poses;
        joint_rows += f.n_poses * N_JOINTS;
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
            consts.add(
                &job.far_rays,
                rgb.narrow(0, job.len, far_len)?,
                sigma_raw.narrow(0, job.len, far_len)?,
            );
            far_points += far_len;
        }
        evaluated += job.len;
        joint_rows += (job.len + far_len) * job.joints.as_ref().map_or(N_JOINTS, Vec::len);
    }
    Ok(Evaluated {
        rgbs,
        sigmas,
        rows: evaluated,
        samples: evaluated,
        points: evaluated + far_points,
        joint_rows,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::points::INFERENCE_POINT_CHUNK;
    use candle_core::Device;

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
        let ctx = Planner {
            test: Some(&test),
            joint_test: None,
            host_pts: &[],
            numerics: Default::default(),
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
        let stage = Stage {
            n_poses,
            pts: &pts,
            view: &view,
            fates: &fates,
            far_rays: &far_rays,
            chunk: Some(INFERENCE_POINT_CHUNK),
        };
        let plan = ctx.plan(stage).unwrap();
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
            .plan(Stage {
                chunk: None,
                ..stage
            })
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
}
