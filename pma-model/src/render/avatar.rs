//! The avatar: the network ([`crate::network`]) behind a ray caster, rendered top-down.
//!
//! [`Avatar::forward`] reads in the order the model computes: per-pose work (6D rotations →
//! GNN → projected part features, box sizes) once per pose; ray casting; the coarse network
//! pass and render; importance sampling; the fine pass on the new samples only; merge and
//! the fine render. How the samples of a pass reach the network (densely, in chunks, or
//! culled) is [`crate::render::points`]'s business; what a pass may leave out is its
//! [`PassOptions`] argument, and what it did comes back in [`Outputs::stats`].

use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;

use candle_core::{DType, Device, Tensor, Var};
use pma_data::skeleton::Joints;

use crate::compute::host::host_f32;
use crate::error::{ModelError, Result};
use crate::network::config::Config;
use crate::network::occupancy::OccupancyGrid;
pub use crate::network::trace::Trace;
use crate::network::Network;
pub use crate::network::PoseFeatures;
pub use crate::render::batch::{Mode, NoiseFn, Outputs, Poses, Rays};
use crate::render::bones::BoneFrames;
use crate::render::cull::WindowTest;
use crate::render::occupancy::{RefreshOptions, RefreshStats};
pub use crate::render::options::{GridObservation, PassOptions, PassStats};
use crate::render::placement::coarse_in_occupied;
use crate::render::points::PointEval;
use crate::render::raycast::{merge_raw, CastInputs, CoarseSamples, RayCaster};
use crate::render::volume::raw2outputs;

/// A network, the ray caster of its bone boxes, and the optional occupancy grid saved with
/// it.
pub struct Avatar {
    net: Network,
    caster: RayCaster,
    /// Shared with the passes that consult it; the trainer's refresh writes it between steps.
    occupancy: Option<Arc<OccupancyGrid>>,
}

impl Avatar {
    /// Load a checkpoint (with its occupancy grid, if it has one) for inference or to
    /// continue training. Strict: see [`crate::network::checkpoint::load`].
    pub fn load(path: impl AsRef<Path>, device: &Device) -> Result<Self> {
        let ck = crate::network::checkpoint::load(path.as_ref(), device)?;
        let net = Network::from_tensors(ck.config, ck.tensors, device)?;
        Ok(Self::from_network(net)?.with_occupancy(ck.occupancy))
    }

    /// A freshly initialised avatar for `rest_pose` with the reference's initialisation,
    /// deterministic for `seed`.
    pub fn new(cfg: Config, rest_pose: &Joints, seed: u64, device: &Device) -> Result<Self> {
        Self::from_network(Network::new(cfg, rest_pose, seed, device)?)
    }

    /// Build from named tensors (the reference's state_dict names), checked against `cfg`.
    pub fn from_tensors(
        cfg: Config,
        tensors: HashMap<String, Tensor>,
        device: &Device,
    ) -> Result<Self> {
        Self::from_network(Network::from_tensors(cfg, tensors, device)?)
    }

    /// The avatar of `net`: its ray caster is derived from the network's box transforms.
    pub fn from_network(net: Network) -> Result<Self> {
        let caster = RayCaster::from_tensor(net.config(), net.raycast_align())?;
        Ok(Self {
            net,
            caster,
            occupancy: None,
        })
    }

    /// The same avatar computing with `numerics` (kernels, sine, TF32) in every later pass.
    pub fn with_numerics(self, numerics: crate::compute::numerics::Numerics) -> Self {
        Self {
            net: self.net.with_numerics(numerics),
            ..self
        }
    }

    /// Compute with `numerics` from the next pass on.
    pub fn set_numerics(&mut self, numerics: crate::compute::numerics::Numerics) {
        self.net.set_numerics(numerics);
    }

    /// How the avatar computes.
    pub fn numerics(&self) -> crate::compute::numerics::Numerics {
        self.net.numerics()
    }

    /// The same avatar with `grid` as its occupancy grid (`None`: without one).
    pub fn with_occupancy(mut self, grid: Option<OccupancyGrid>) -> Self {
        self.occupancy = grid.map(Arc::new);
        self
    }

    /// The same avatar with every tensor converted to `dtype` (f16/bf16 inference, f64
    /// checks); the occupancy grid is kept. Inputs are converted at the forward entry points,
    /// and the ray caster keeps working in f32.
    pub fn with_dtype(&self, dtype: DType) -> Result<Self> {
        let mut a = Self::from_network(self.net.with_dtype(dtype)?)?;
        a.occupancy = self.occupancy.clone();
        Ok(a)
    }

    // ---- forward pass -------------------------------------------------------------------

    /// Render a ray batch: the full coarse + fine forward pass, leaving out what `opts` says.
    pub fn forward(
        &self,
        rays: &Rays,
        poses: &Poses,
        mode: &mut Mode,
        opts: &PassOptions,
        mut trace: Option<&mut Trace>,
    ) -> Result<Outputs> {
        crate::render::batch::check_batch(rays, poses)?;
        let cast = crate::render::batch::cast_batch(rays, poses, self.dtype())?;
        let (rays, poses) = cast.as_ref().map_or((rays, poses), |(r, p)| (r, p));
        // 1. Per-pose work.
        let mut pose_trace = trace.as_ref().map(|_| Trace::default());
        let pose = self.pose_features(poses, pose_trace.as_mut())?;
        crate::compute::profile::mark("pose features", self.device());
        let out = self.forward_inner(rays, poses, &pose, mode, opts, trace.as_deref_mut())?;
        if let (Some(t), Some(pt)) = (trace, pose_trace) {
            for stage in ["coarse", "fine"] {
                for (k, v) in &pt.tensors {
                    t.put(format!("{stage}/{k}"), v);
                }
            }
        }
        Ok(out)
    }

    /// [`Self::forward`] with the per-pose work already done (`pose` from
    /// [`Self::pose_features`] of the same `poses`), so callers that split a pose's rays into
    /// chunks run the GNN once per pose, not once per chunk.
    pub fn forward_with_pose(
        &self,
        rays: &Rays,
        poses: &Poses,
        pose: &PoseFeatures,
        mode: &mut Mode,
        opts: &PassOptions,
    ) -> Result<Outputs> {
        crate::render::batch::check_batch(rays, poses)?;
        let cast = crate::render::batch::cast_batch(rays, poses, self.dtype())?;
        let (rays, poses) = cast.as_ref().map_or((rays, poses), |(r, p)| (r, p));
        self.forward_inner(rays, poses, pose, mode, opts, None)
    }

    /// Step 2, ray casting (no gradient) with the current, detached box sizes: on the host
    /// when the rays are on the CPU or the pass leaves work out (culling and the occupancy
    /// grid need the host bounds and samples), as tensor ops on the rays' device otherwise
    /// ([`crate::render::raycast::device`]).
    pub fn cast(
        &self,
        rays: &Rays,
        poses: &Poses,
        pose: &PoseFeatures,
        opts: &PassOptions,
    ) -> Result<CoarseSamples> {
        self.cast_on(
            rays,
            poses,
            pose,
            opts,
            self.casts_on_host(&rays.origins, opts),
        )
    }

    /// [`Self::cast`] on the host or not, as decided for the pass. With
    /// `opts.coarse_from_grid` and a built grid the coarse samples are placed in the
    /// intervals the grid marks occupied ([`crate::render::placement`]), from the host copies
    /// the cast makes anyway.
    fn cast_on(
        &self,
        rays: &Rays,
        poses: &Poses,
        pose: &PoseFeatures,
        opts: &PassOptions,
        on_host: bool,
    ) -> Result<CoarseSamples> {
        check_pose_count(poses, pose)?;
        let args = (
            &rays.origins,
            &rays.dirs,
            &poses.cyls,
            &poses.skts,
            &pose.scales.detach(),
        );
        let grid = self
            .occupancy
            .as_deref()
            .filter(|g| opts.coarse_from_grid && g.is_built());
        let jitter = opts.jitter;
        if let (true, Some(grid)) = (on_host, grid) {
            let cfg = self.config();
            let threshold = opts.window_threshold().unwrap_or(0.0);
            let place = |inputs: &CastInputs, even: Vec<f32>| -> Result<Vec<f32>> {
                let test = WindowTest::new(
                    self.bone_align(),
                    inputs.skts,
                    inputs.scales,
                    cfg.window_alpha,
                    cfg.window_beta,
                    threshold,
                )?;
                coarse_in_occupied(&test, grid, inputs, even, cfg.n_samples)
            };
            self.caster
                .cast_placed(args.0, args.1, args.2, args.3, args.4, Some(&place), jitter)
        } else if on_host {
            self.caster
                .cast_placed(args.0, args.1, args.2, args.3, args.4, None, jitter)
        } else {
            self.caster
                .cast_tensors(args.0, args.1, args.2, args.3, args.4, jitter)
        }
    }

    /// Steps 3–5 of the forward pass on samples cast by [`Self::cast`] (of these rays, or of
    /// a batch these rays are rows of: casting depends on the whole batch only through the
    /// fallback bounds of rays that miss the bounding cylinder).
    pub fn forward_cast(
        &self,
        rays: &Rays,
        poses: &Poses,
        pose: &PoseFeatures,
        coarse: CoarseSamples,
        mode: &mut Mode,
        opts: &PassOptions,
    ) -> Result<Outputs> {
        crate::render::batch::check_batch(rays, poses)?;
        check_pose_count(poses, pose)?;
        if rays.dirs.dtype() != self.dtype() || poses.skts.dtype() != self.dtype() {
            return Err(ModelError::Input(format!(
                "forward_cast: rays and poses must be {:?} like the network",
                self.dtype()
            )));
        }
        let on_host = self.casts_on_host(&rays.origins, opts);
        self.render(rays, poses, pose, coarse, mode, opts, on_host, None)
    }

    /// Steps 2–5 of the forward pass.
    fn forward_inner(
        &self,
        rays: &Rays,
        poses: &Poses,
        pose: &PoseFeatures,
        mode: &mut Mode,
        opts: &PassOptions,
        trace: Option<&mut Trace>,
    ) -> Result<Outputs> {
        let on_host = self.casts_on_host(&rays.origins, opts);
        let coarse = self.cast_on(rays, poses, pose, opts, on_host)?;
        crate::compute::profile::mark("cast", self.device());
        self.render(rays, poses, pose, coarse, mode, opts, on_host, trace)
    }

    /// Whether ray casting and importance sampling run on the host for rays like `t`.
    fn casts_on_host(&self, t: &Tensor, opts: &PassOptions) -> bool {
        crate::compute::account::cpu_route(t.device()) || opts.leaves_out_work()
    }

    /// Steps 3–5, one way: the coarse samples through the network and rendered; importance
    /// samples from that render; the fine samples through the network; the merged render.
    /// What is decided before the pass runs: where sampling runs (`on_host`, as for the
    /// cast: [`Self::casts_on_host`]), how the samples reach the network ([`PointEval`]'s
    /// route) and where the fine samples come from. With `occupancy_fine` the grid places
    /// them (inference): the coarse samples then wait and go through the network with the
    /// fine ones in one round.
    #[allow(clippy::too_many_arguments)]
    fn render(
        &self,
        rays: &Rays,
        poses: &Poses,
        pose: &PoseFeatures,
        coarse: CoarseSamples,
        mode: &mut Mode,
        opts: &PassOptions,
        on_host: bool,
        mut trace: Option<&mut Trace>,
    ) -> Result<Outputs> {
        let prof = |stage| crate::compute::profile::mark(stage, self.device());
        let fine_from_grid = opts.occupancy_fine && trace.is_none();
        let composite =
            |raw: &Tensor, z: &Tensor| raw2outputs(raw, z, &rays.dirs, rays.bgs.as_ref());
        let (view, d_root) = self.ray_view_features(rays, poses, mode.is_training())?;
        let mut points = PointEval::new(
            &self.net,
            pose,
            &view,
            mode,
            poses,
            coarse.bounds.as_ref(),
            trace.is_some(),
            opts,
            self.occupancy.as_ref(),
        )?;
        // 3. The coarse samples through the network and rendered (unless they wait for the
        //    fine samples).
        let coarse_done = match fine_from_grid {
            true => None,
            false => {
                let raw = points.coarse(&coarse, &rays.dirs, mode, trace.as_deref_mut())?;
                prof("coarse network");
                let render = composite(&raw, &coarse.z)?;
                prof("coarse render");
                Some((raw, render))
            }
        };
        // 4. Importance samples from the coarse render's weights, or from the grid's.
        let weights = match &coarse_done {
            Some((_, render)) => render.weights.detach(),
            None => points.grid_weights(&coarse, &rays.dirs)?,
        };
        let resample = match on_host {
            true => RayCaster::resample,
            false => RayCaster::resample_tensors,
        };
        let fine = resample(
            &self.caster,
            &rays.origins,
            &rays.dirs,
            &coarse.z,
            &weights,
            coarse.fine_u.as_deref(),
        )?;
        prof("resample");
        // 5. The fine samples through the network (with the coarse ones that waited).
        let (raw_coarse, render_coarse, raw_fine) = match coarse_done {
            Some((raw, render)) => {
                let raw_fine = points.fine(&fine, mode, trace.as_deref_mut())?;
                prof("fine network");
                (raw, render, raw_fine)
            }
            None => {
                let (raw, raw_fine) = points.coarse_and_fine(&coarse, &fine, mode)?;
                prof("coarse + fine network");
                let render = composite(&raw, &coarse.z)?;
                prof("coarse render");
                (raw, render, raw_fine)
            }
        };
        if let Some(t) = trace {
            let r = rays.origins.dim(0)?;
            for (stage, samples) in [("coarse", coarse.z.dim(1)?), ("fine", fine.z.dim(1)?)] {
                let dr = d_root.unsqueeze(1)?.broadcast_as((r, samples, 3))?;
                t.put(format!("{stage}/view_dir_root"), &dr);
            }
            t.put("raycast/pts_coarse", &coarse.pts);
            t.put("raycast/z_vals_coarse", &coarse.z);
            t.put("raycast/pts_is", &fine.pts);
            t.put("raycast/z_vals_merged", &fine.z_all);
            t.put("raycast/sorted_idxs", &fine.perm);
            t.put("view_features", &view);
        }
        // 6. Merge the fine outputs into the coarse ones (reused, noise included) and render
        //    again.
        let raw = merge_raw(&raw_coarse, &raw_fine, &fine.perm, self.net.numerics())?;
        let render_fine = composite(&raw, &fine.z_all)?;
        prof("merge + fine render");
        let (stats, observed) = points.finish(raw.dim(0)? * raw.dim(1)?);
        Ok(Outputs {
            vol_scale: pose.scales.clone(),
            bounds: coarse.bounds,
            z_coarse: coarse.z,
            z_vals: fine.z_all,
            raw_coarse,
            raw,
            coarse: render_coarse,
            fine: render_fine,
            stats,
            observed,
        })
    }

    /// View features of a ray batch: the directions in each pose's root frame, then
    /// [`Network::view_features`]. Returns ([R,V], d_root [R,3]).
    fn ray_view_features(
        &self,
        rays: &Rays,
        poses: &Poses,
        training: bool,
    ) -> Result<(Tensor, Tensor)> {
        let r = rays.dirs.dim(0)?;
        let p = poses.bones.len();
        // Only the root's rotation: directions are expressed in the pelvis frame.
        let r0 = poses
            .skts
            .narrow(1, 0, 1)?
            .squeeze(1)?
            .narrow(1, 0, 3)?
            .narrow(2, 0, 3)?
            // A 3×3 window of the 4×4 matrices: CUDA's gemm rejects its row stride of 4.
            .contiguous()?;
        let d = rays
            .dirs
            .reshape((p, r / p, 3))?
            .matmul(&r0.transpose(1, 2)?)?
            .reshape((r, 3))?;
        Ok((self.net.view_features(&d, &rays.framecodes, training)?, d))
    }

    /// Step 1 of [`Self::forward`] for every pose of `poses` ([`Network::pose_features`]).
    pub fn pose_features(&self, poses: &Poses, trace: Option<&mut Trace>) -> Result<PoseFeatures> {
        self.net.pose_features(&poses.bones, &poses.skts, trace)
    }

    // ---- accessors ----------------------------------------------------------------------

    pub fn network(&self) -> &Network {
        &self.net
    }

    pub fn config(&self) -> &Config {
        self.net.config()
    }

    pub fn device(&self) -> &Device {
        self.net.device()
    }

    /// The dtype the network computes in (that of its tensors).
    pub fn dtype(&self) -> DType {
        self.net.dtype()
    }

    pub fn rest_pose(&self) -> &Joints {
        self.net.rest_pose()
    }

    pub fn ray_caster(&self) -> &RayCaster {
        &self.caster
    }

    /// A_j of the network's bone-aligned frames on the host, [24,4,4] row-major.
    pub fn bone_align(&self) -> &[f32] {
        self.net.bone_align()
    }

    /// The bone boxes the ray caster clips against, for poses with skts: [P,24,4,4].
    pub fn bone_frames(&self, skts: &Tensor) -> Result<BoneFrames> {
        BoneFrames::new(self.caster.bone_align(), &host_f32(skts)?)
    }

    /// Effective box half-extents s: [24,3].
    pub fn axis_scale(&self) -> Result<Tensor> {
        self.net.axis_scale()
    }

    /// The occupancy grid saved with the model, if it has one.
    pub fn occupancy(&self) -> Option<&OccupancyGrid> {
        self.occupancy.as_deref()
    }

    /// The occupancy grid, shared (to lend it to another avatar).
    pub fn occupancy_shared(&self) -> Option<Arc<OccupancyGrid>> {
        self.occupancy.clone()
    }

    /// Replace the occupancy grid with a shared one (`None`: without one).
    pub fn set_occupancy(&mut self, grid: Option<Arc<OccupancyGrid>>) {
        self.occupancy = grid;
    }

    /// Refresh the occupancy grid from the network's density for `poses` (whose pose
    /// features are `pose`): see [`crate::render::occupancy::refresh`]. The avatar must have a
    /// grid.
    pub fn refresh_occupancy<R: rand::Rng>(
        &mut self,
        poses: &Poses,
        pose: &PoseFeatures,
        opts: RefreshOptions,
        rng: &mut R,
    ) -> Result<RefreshStats> {
        let grid = self.occupancy.as_mut().ok_or_else(|| {
            ModelError::Input("occupancy: the model has no occupancy grid to refresh".into())
        })?;
        // Copied first only if a pass still holds the grid.
        let grid = Arc::make_mut(grid);
        crate::render::occupancy::refresh(&self.net, grid, poses, pose, opts, rng)
    }

    /// Restore the occupancy of every cell of the grid (a resumed training run; see
    /// [`OccupancyGrid::occupied_cells`]).
    pub fn set_occupied_cells(&mut self, occupied: Vec<bool>) -> Result<()> {
        let grid = self.occupancy.as_mut().ok_or_else(|| {
            ModelError::Input("occupancy: the model has no occupancy grid to restore".into())
        })?;
        Arc::make_mut(grid).set_occupied(occupied)
    }

    /// Take what a training step's evaluated samples saw ([`Outputs::observed`]) into the
    /// occupancy grid: `cell = max(cell, σ)`. Their occupancy follows at the next refresh.
    pub fn observe_occupancy(&mut self, seen: &[GridObservation]) -> Result<()> {
        if seen.is_empty() {
            return Ok(());
        }
        let grid = self.occupancy.as_mut().ok_or_else(|| {
            ModelError::Input("occupancy: the model has no occupancy grid to feed".into())
        })?;
        let grid = Arc::make_mut(grid);
        for o in seen {
            grid.update_max(o.joint as usize, o.cell as usize, o.sigma)?;
        }
        Ok(())
    }

    /// All tensors (parameters and buffers) by reference name, for saving.
    pub fn tensors(&self) -> HashMap<String, Tensor> {
        self.net.tensors()
    }

    /// The trainable parameters in the reference's `named_parameters()` order.
    pub fn trainable(&self) -> Vec<(String, Var)> {
        self.net.trainable()
    }

    /// Save as a pma checkpoint (atomic), with the occupancy grid if there is one.
    pub fn save(&self, path: impl AsRef<Path>) -> Result<()> {
        crate::network::checkpoint::save_with(
            path.as_ref(),
            &self.tensors(),
            self.config(),
            self.occupancy(),
        )
    }
}

/// `pose` must hold the features of every pose of `poses`.
fn check_pose_count(poses: &Poses, pose: &PoseFeatures) -> Result<()> {
    if pose.g.dim(0)? != poses.bones.len() {
        return Err(ModelError::shape(
            "pose features",
            [poses.bones.len()],
            [pose.g.dim(0)?],
        ));
    }
    Ok(())
}

impl std::fmt::Debug for Avatar {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Avatar")
            .field("cfg", self.config())
            .field("device", self.device())
            .finish_non_exhaustive()
    }
}
