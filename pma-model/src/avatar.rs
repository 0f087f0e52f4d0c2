//! The whole PM-Avatar, wired top-down.
//!
//! [`Avatar::forward`] reads in the order the model computes: per-pose work (6D rotations →
//! GNN → projected part features, box sizes) once per pose; ray casting; the coarse network
//! pass and render; importance sampling; the fine pass on the new samples only; merge and
//! the fine render. [`Avatar::eval_points`] is the network on the points of one pose, in the
//! paper's order: bone-normalised points, the two-stage window, the pose-modulated sine
//! layers, the NeRF heads. How the samples of a pass reach it (densely, in chunks, or culled)
//! is [`crate::points`]'s business.

use std::collections::HashMap;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

use candle_core::{DType, Device, Tensor, Var, D};
use candle_nn::{VarBuilder, VarMap};
use pma_data::skeleton::{self, Joints, N_JOINTS};

pub use crate::batch::{Mode, NoiseFn, Outputs, PoseFeatures, Poses, Rays};
use crate::bones::BoneFrames;
use crate::checkpoint;
use crate::config::{Config, Culling};
use crate::encoders::{pose6d, spherical_harmonics, PointEnc};
use crate::error::{ModelError, Result};
use crate::field::{Field, FrameCodes};
use crate::gnn::GnnSine;
use crate::host::host_f32;
use crate::modulator::{Modulator, PoseExtractor};
use crate::params::{Init, Params, RestValue, RestValues, TensorKind, TensorSpec};
use crate::points::PointEval;
pub use crate::points::INFERENCE_POINT_CHUNK;
use crate::raycast::{merge_raw, RayCaster};
use crate::render::raw2outputs;
pub use crate::trace::Trace;
use crate::window::{aggregate, spatial_window, WinFun};

/// Every tensor of the model, registered in the reference's state_dict order (which is
/// also the order a fresh model draws its initial values in).
struct Network {
    rest_pose: Tensor,
    /// A_j for the network's bone-aligned frames (`pts_embedder.transforms`).
    align: Tensor,
    /// Point encoder of the feature window (absent without w^f).
    pts_enc_pose: Option<PointEnc>,
    /// Point encoder of the synthesis branch (absent in `only-gnn`).
    pts_enc_point: Option<PointEnc>,
    /// A_j for ray casting (`raycast.transforms`, equal to `align` in practice).
    raycast_align: Tensor,
    field: Field,
    framecodes: Option<FrameCodes>,
    gnn: GnnSine,
    /// The sine layers of the synthesis branch (absent in `only-gnn`).
    modulator: Option<Modulator>,
    /// The projection of the GNN features and the feature window (absent in `only-syn`).
    win_fun: Option<WinFun>,
    /// Frequencies and phases from f^m (present only in modulated variants).
    pose_extractor: Option<PoseExtractor>,
}

impl Network {
    fn new(p: &Params, cfg: &Config) -> Result<Self> {
        let (j, ce) = (cfg.n_joints, cfg.point_enc_dim);
        let rest_pose = p.buffer([j, 3], "rest_pose", Init::Rest(RestValue::Joints))?;
        let align_init = Init::Rest(RestValue::BoneAlign);
        let align = p.buffer([j, 4, 4], "pts_embedder.transforms", align_init.clone())?;
        let v = cfg.variant;
        let pts_enc_pose = v
            .feature_window()
            .then(|| PointEnc::new(p.pp("pts_enc_pose"), ce, cfg.sin_w0_pose))
            .transpose()?;
        let pts_enc_point = v
            .synthesis()
            .then(|| PointEnc::new(p.pp("pts_enc_point"), ce, cfg.sin_w0_point))
            .transpose()?;
        let raycast_align = p.buffer([j, 4, 4], "raycast.transforms", align_init)?;
        let field = Field::new(p.clone(), cfg)?;
        let framecodes = match cfg.use_framecodes {
            true => Some(FrameCodes::new(p.pp("framecodes"), cfg)?),
            false => None,
        };
        Ok(Self {
            rest_pose,
            align,
            pts_enc_pose,
            pts_enc_point,
            raycast_align,
            field,
            framecodes,
            gnn: GnnSine::new(p.pp("graph_net"), cfg)?,
            modulator: v
                .synthesis()
                .then(|| Modulator::new(p.pp("modulator"), cfg))
                .transpose()?,
            win_fun: v
                .gnn_features()
                .then(|| WinFun::new(p.pp("win_fun"), cfg))
                .transpose()?,
            pose_extractor: v
                .modulation()
                .then(|| PoseExtractor::new(p.pp("pose_extractor"), cfg))
                .transpose()?,
        })
    }
}

/// Every tensor of the model for `cfg`, in the reference's state_dict order, as the layers
/// register them. Filtering to [`TensorKind::Param`] gives `named_parameters()` order.
pub fn tensor_layout(cfg: &Config) -> Vec<TensorSpec> {
    let p = Params::record();
    // Recording only hands out zero tensors on the host, which cannot fail.
    Network::new(&p, cfg).expect("recording the tensor layout");
    p.specs()
}

pub struct Avatar {
    cfg: Config,
    device: Device,
    /// The dtype of every tensor (f32 unless built by [`Avatar::with_dtype`]).
    dtype: DType,
    varmap: VarMap,
    rest_pose: Joints,
    net: Network,
    /// Rotation of A_j, transposed: [24,3,3].
    align_rot_t: Tensor,
    /// Translation of A_j: [24,3].
    align_trans: Tensor,
    /// A_j on the host, [24,4,4] row-major: the culling test runs there.
    align_host: Vec<f32>,
    caster: RayCaster,
    /// Points that went through the network since construction (bench counters).
    points_evaluated: AtomicU64,
}

impl Avatar {
    /// Load a checkpoint for inference (or to continue training). Strict: see
    /// [`checkpoint::load`].
    pub fn load(path: impl AsRef<Path>, device: &Device) -> Result<Self> {
        let ck = checkpoint::load(path.as_ref(), device)?;
        Self::from_tensors(ck.config, ck.tensors, device)
    }

    /// A freshly initialised avatar for `rest_pose` with the reference's initialisation,
    /// deterministic for `seed`.
    pub fn new(cfg: Config, rest_pose: &Joints, seed: u64, device: &Device) -> Result<Self> {
        cfg.validate()?;
        let base = skeleton::check_model_rest_pose(rest_pose)?;
        let align = skeleton::bone_align(rest_pose)?;
        let rest = RestValues {
            joints: rest_pose.iter().flatten().copied().collect(),
            bone_align: align
                .transforms
                .iter()
                .flatten()
                .flatten()
                .copied()
                .collect(),
            half_extents: base.iter().flatten().copied().collect(),
        };
        let varmap = VarMap::new();
        let p = Params::init(seed, rest, varmap.clone(), device);
        let net = Network::new(&p, &cfg)?;
        checkpoint::check_buffers(&varmap_tensors(&varmap))?;
        Self::assemble(cfg, net, varmap, DType::F32, device)
    }

    /// Build from named tensors (the reference's state_dict names), checked against `cfg`.
    pub fn from_tensors(
        cfg: Config,
        tensors: HashMap<String, Tensor>,
        device: &Device,
    ) -> Result<Self> {
        cfg.validate()?;
        // The network runs in the dtype of its tensors (f32 from checkpoints; f16/bf16/f64 via
        // [`Self::with_dtype`]), so the layout check only asks for one common float dtype.
        let dtype = tensors.get("rest_pose").map_or(DType::F32, |t| t.dtype());
        let as_f32 = |t: &Tensor| match t.dtype() == dtype && dtype.is_float() {
            true => DType::F32,
            false => t.dtype(),
        };
        let problems = checkpoint::check_tensors(
            &cfg,
            tensors
                .iter()
                .map(|(n, t)| (n.as_str(), t.dims(), as_f32(t))),
        );
        if !problems.is_empty() {
            return Err(checkpoint::tensors_error(problems));
        }
        checkpoint::check_buffers(&tensors)?;
        let varmap = VarMap::new();
        {
            let mut data = varmap.data().lock().expect("fresh VarMap lock");
            for (name, t) in &tensors {
                data.insert(name.clone(), Var::from_tensor(&t.to_device(device)?)?);
            }
        }
        let vb = VarBuilder::from_varmap(&varmap, dtype, device);
        let net = Network::new(&Params::from(vb), &cfg)?;
        Self::assemble(cfg, net, varmap, dtype, device)
    }

    /// The host-side pieces every pass needs, derived once from the network's buffers.
    fn assemble(
        cfg: Config,
        net: Network,
        varmap: VarMap,
        dtype: DType,
        device: &Device,
    ) -> Result<Self> {
        let mut rest_pose = [[0f32; 3]; N_JOINTS];
        for (d, s) in rest_pose
            .iter_mut()
            .zip(host_f32(&net.rest_pose)?.chunks_exact(3))
        {
            d.copy_from_slice(s);
        }
        let caster = RayCaster::from_tensor(&cfg, &net.raycast_align)?;
        let a = &net.align;
        Ok(Self {
            align_rot_t: a
                .narrow(1, 0, 3)?
                .narrow(2, 0, 3)?
                .transpose(1, 2)?
                .contiguous()?,
            align_trans: a.narrow(1, 0, 3)?.narrow(2, 3, 1)?.reshape((N_JOINTS, 3))?,
            align_host: host_f32(a)?,
            caster,
            points_evaluated: AtomicU64::new(0),
            rest_pose,
            net,
            varmap,
            device: device.clone(),
            dtype,
            cfg,
        })
    }

    /// The same avatar with every tensor converted to `dtype` (f16/bf16 inference, f64
    /// checks). Inputs are converted at the forward entry points, and the ray caster keeps
    /// working in f32 on the host.
    pub fn with_dtype(&self, dtype: DType) -> Result<Self> {
        let tensors = self
            .tensors()
            .into_iter()
            .map(|(k, t)| Ok((k, t.to_dtype(dtype)?)))
            .collect::<Result<HashMap<_, _>>>()?;
        Self::from_tensors(self.cfg.clone(), tensors, &self.device)
    }

    // ---- forward pass -------------------------------------------------------------------

    /// Render a ray batch: the full coarse + fine forward pass.
    pub fn forward(
        &self,
        rays: &Rays,
        poses: &Poses,
        mode: &mut Mode,
        mut trace: Option<&mut Trace>,
    ) -> Result<Outputs> {
        crate::batch::check_batch(rays, poses)?;
        let cast = crate::batch::cast_batch(rays, poses, self.dtype)?;
        let (rays, poses) = cast.as_ref().map_or((rays, poses), |(r, p)| (r, p));
        // 1. Per-pose work.
        let mut pose_trace = trace.as_ref().map(|_| Trace::default());
        let pose = self.pose_features(poses, pose_trace.as_mut())?;
        let out = self.forward_inner(rays, poses, &pose, mode, trace.as_deref_mut())?;
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
    ) -> Result<Outputs> {
        crate::batch::check_batch(rays, poses)?;
        let cast = crate::batch::cast_batch(rays, poses, self.dtype)?;
        let (rays, poses) = cast.as_ref().map_or((rays, poses), |(r, p)| (r, p));
        if pose.g.dim(0)? != poses.bones.len() {
            return Err(ModelError::shape(
                "pose features",
                [poses.bones.len()],
                [pose.g.dim(0)?],
            ));
        }
        self.forward_inner(rays, poses, pose, mode, None)
    }

    /// Steps 2–5 of the forward pass.
    fn forward_inner(
        &self,
        rays: &Rays,
        poses: &Poses,
        pose: &PoseFeatures,
        mode: &mut Mode,
        mut trace: Option<&mut Trace>,
    ) -> Result<Outputs> {
        // 2. Ray casting (no gradient) with the current, detached box sizes.
        let coarse = self.caster.cast(
            &rays.origins,
            &rays.dirs,
            &poses.cyls,
            &poses.skts,
            &pose.scales.detach(),
        )?;
        let prof = crate::profile::mark;
        prof("cast", &self.device);
        let (view, d_root) = self.ray_view_features(rays, poses, mode.is_training())?;
        let mut points = PointEval::new(self, mode, poses, pose, &coarse.bounds, trace.is_some())?;
        // 3. Coarse pass and render.
        let tr = trace.as_deref_mut();
        let raw_coarse = points.run(self, pose, &coarse.pts, &view, mode, "coarse", tr)?;
        prof("coarse network", &self.device);
        let render_coarse = raw2outputs(&raw_coarse, &coarse.z, &rays.dirs, rays.bgs.as_ref())?;
        prof("coarse render", &self.device);
        // 4. Importance samples from the coarse weights, then the fine pass on those only.
        let weights = render_coarse.weights.detach();
        let fine = self
            .caster
            .resample(&rays.origins, &rays.dirs, &coarse.z, &weights)?;
        prof("resample", &self.device);
        let tr = trace.as_deref_mut();
        let raw_fine = points.run(self, pose, &fine.pts, &view, mode, "fine", tr)?;
        prof("fine network", &self.device);
        // 5. Merge with the coarse outputs (reused, noise included) and render again.
        let raw = merge_raw(&raw_coarse, &raw_fine, &fine.perm)?;
        let render_fine = raw2outputs(&raw, &fine.z_all, &rays.dirs, rays.bgs.as_ref())?;
        prof("merge + fine render", &self.device);
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
        Ok(Outputs {
            vol_scale: pose.scales.clone(),
            bounds: coarse.bounds,
            z_coarse: coarse.z,
            z_vals: fine.z_all,
            raw_coarse,
            raw,
            coarse: render_coarse,
            fine: render_fine,
        })
    }

    /// Step 1, the pose-only work for every pose of the batch: 6D rotations, the GNN, its
    /// projection `layer_pose(G)`, and the effective box half-extents.
    pub fn pose_features(&self, poses: &Poses, trace: Option<&mut Trace>) -> Result<PoseFeatures> {
        let p = poses.bones.len();
        if poses.skts.dims() != [p, N_JOINTS, 4, 4] {
            return Err(ModelError::shape(
                "skts",
                [p, N_JOINTS, 4, 4],
                poses.skts.dims(),
            ));
        }
        let theta = pose6d(&poses.bones, &self.device)?.to_dtype(self.dtype)?;
        let scales = self.net.gnn.axis_scale()?;
        let Some(win_fun) = &self.net.win_fun else {
            // No GNN features (`only-syn`): an empty feature per joint keeps the pose count.
            let g = Tensor::zeros((p, N_JOINTS, 0), self.dtype, &self.device)?;
            let skts = poses.skts.to_dtype(self.dtype)?;
            return Ok(PoseFeatures { g, skts, scales });
        };
        let mut layers = Vec::new();
        let g_feat = self
            .net
            .gnn
            .forward(&theta, trace.is_some().then_some(&mut layers))?;
        let g = win_fun.project_pose(&g_feat)?;
        if let Some(t) = trace {
            t.put("pose6d", &theta);
            for (l, pre) in layers.iter().enumerate() {
                t.put(format!("gnn_layer{l}_pre_sin"), pre);
            }
            t.put("gnn_feat", &g_feat);
            let flat = g.reshape(((), g.dim(D::Minus1)?))?;
            t.put("win_layer_pose", &flat);
            t.put("axis_scale", &scales);
        }
        Ok(PoseFeatures {
            g,
            skts: poses.skts.to_dtype(self.dtype)?,
            scales,
        })
    }

    /// The network on the points of pose p: pts: [n,3] world points, view: [n,V] view
    /// features ([`Self::view_features`]). Returns (rgb [n,3], sigma_raw [n,1]).
    pub fn eval_points(
        &self,
        pose: &PoseFeatures,
        p: usize,
        pts: &Tensor,
        view: &Tensor,
        trace: Option<(&mut Trace, &str)>,
    ) -> Result<(Tensor, Tensor)> {
        let n = pts.dim(0)?;
        let j = N_JOINTS;
        let net = &self.net;
        // World → joint frames of every joint at once (one [n,3]x[3,72] product), then into
        // the bone-aligned frames. Two steps, in the reference's order: folding A_j into
        // skt_j first changes the rounding enough to cost ~1e-4 after the ω=16 encoder.
        let skt = pose.skts.get(p)?;
        let rot = skt.narrow(1, 0, 3)?.narrow(2, 0, 3)?.reshape((3 * j, 3))?;
        let trans = skt.narrow(1, 0, 3)?.narrow(2, 3, 1)?.reshape((j, 3))?;
        let x_jt = pts
            .matmul(&rot.t()?)?
            .reshape((n, j, 3))?
            .broadcast_add(&trans)?;
        // `contiguous`: CUDA's batched gemm needs packed rows (the CPU gemm takes any
        // strides), and the transposed [j,n,3] view has a row stride of 3j.
        let x_hat = x_jt
            .transpose(0, 1)?
            .contiguous()?
            .matmul(&self.align_rot_t)?
            .transpose(0, 1)?
            .broadcast_add(&self.align_trans)?;
        // Bone-normalised points x̄ and the spatial window w^p (Eq. 4).
        let x_bar = x_hat.broadcast_div(&pose.scales)?;
        let v = self.cfg.variant;
        let w_p = match v.spatial_window() {
            true => spatial_window(&x_bar, self.cfg.window_alpha, self.cfg.window_beta)?,
            false => Tensor::ones((n, j), x_bar.dtype(), x_bar.device())?,
        };
        // Feature window w^f and w = w^p·w^f (Eqs. 5–6), then f^m = Σ_j w_j g_j.
        let g = pose.g.get(p)?;
        let (win, e) = match (&net.win_fun, &net.pts_enc_pose) {
            (Some(win_fun), Some(enc)) if v.feature_window() => {
                let e = enc.forward(&x_bar)?;
                (Some(win_fun.forward(&g, &e, &w_p)?), Some(e))
            }
            _ => (None, None),
        };
        let w = match &win {
            Some(win) => win.w.clone(),
            None => w_p.clone(),
        };
        let f_m = match v.gnn_features() {
            true => Some(aggregate(&w, &g)?),
            false => None,
        };
        // Frequencies and phases from f^m drive the sine layers (Eqs. 7–8); `only-gnn` feeds
        // f^m to the NeRF trunk instead, `only-syn` runs the layers unmodulated.
        let modulation = match (&net.pose_extractor, &f_m) {
            (Some(ext), Some(f_m)) => Some(ext.forward(f_m)?),
            _ => None,
        };
        let (s, z) = match (&net.modulator, &net.pts_enc_point) {
            (Some(modulator), Some(enc)) => {
                let z = enc.forward(&x_bar)?;
                let x_tilde = z
                    .broadcast_mul(&w.unsqueeze(D::Minus1)?)?
                    .reshape((n, j * self.cfg.point_enc_dim))?;
                let s = match &modulation {
                    Some(m) => modulator.forward(&x_tilde, m)?,
                    None => modulator.forward_fixed(&x_tilde)?,
                };
                (s, Some(z))
            }
            _ => (
                f_m.clone()
                    .ok_or_else(|| ModelError::Config("no trunk input".into()))?,
                None,
            ),
        };
        // NeRF density and colour heads.
        let out = net.field.forward(&s, view)?;
        if let Some((tr, stage)) = trace {
            // Θ mapped to the frequencies γ the layers use, stacked per layer like Φ.
            let gp = match (&modulation, &net.modulator) {
                (Some(m), Some(md)) => {
                    let g: Vec<_> = m.freq.iter().map(|f| md.gamma(f)).collect::<Result<_>>()?;
                    Some((Tensor::stack(&g, 0)?, Tensor::stack(&m.phase, 0)?))
                }
                _ => None,
            };
            let items: Vec<(&str, &Tensor)> = [
                Some(("pts_jt", &x_jt)),
                Some(("pts_t", &x_hat)),
                Some(("x_bar", &x_bar)),
                Some(("w_p", &w_p)),
                Some(("w", &w)),
                e.as_ref().map(|e| ("pts_enc_pose", e)),
                win.as_ref().map(|w| ("win_maxpool", &w.pooled)),
                win.as_ref().map(|w| ("win_logits", &w.logits)),
                win.as_ref().map(|w| ("w_f", &w.w_f)),
                f_m.as_ref().map(|f| ("f_m", f)),
                z.as_ref().map(|z| ("pts_enc_point", z)),
                gp.as_ref().map(|g| ("mod_freq", &g.0)),
                gp.as_ref().map(|g| ("mod_phase", &g.1)),
                Some(("modulator_out", &s)),
                Some(("density_l0_pre_relu", &out.l0_pre)),
                Some(("density_feat", &out.feature)),
                Some(("sigma_raw", &out.sigma_raw)),
                Some(("feature_linear", &out.feature_linear)),
                Some(("view_l0_pre_relu", &out.view_pre)),
                Some(("rgb_logits", &out.rgb_logits)),
            ]
            .into_iter()
            .flatten()
            .collect();
            tr.put_stage(stage, &items);
        }
        Ok((out.rgb, out.sigma_raw))
    }

    /// View features of a ray batch: the directions in each pose's root frame, then
    /// [`Self::view_features`]. Returns ([R,V], d_root [R,3]).
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
        Ok((self.view_features(&d, &rays.framecodes, training)?, d))
    }

    /// View features `[SH(d_root); frame code]`: [R,V] for directions d_root: [R,3] already in
    /// the root joint's frame and one frame-code index per row (all −1 outside training:
    /// the mean code).
    pub fn view_features(
        &self,
        d_root: &Tensor,
        framecodes: &[i64],
        training: bool,
    ) -> Result<Tensor> {
        let d = if self.cfg.quirks.normalize_view_dirs {
            let norm = d_root.sqr()?.sum_keepdim(1)?.sqrt()?;
            d_root.broadcast_div(&norm.clamp(1e-12, f64::INFINITY)?)?
        } else {
            d_root.clone()
        };
        let sh = spherical_harmonics(&d, self.cfg.sh_degree)?;
        Ok(match &self.net.framecodes {
            Some(codes) => Tensor::cat(&[&sh, &codes.lookup(framecodes, training)?], 1)?,
            None => sh,
        })
    }

    // ---- accessors ----------------------------------------------------------------------

    pub fn config(&self) -> &Config {
        &self.cfg
    }

    pub fn device(&self) -> &Device {
        &self.device
    }

    /// The dtype the network computes in (that of its tensors).
    pub fn dtype(&self) -> DType {
        self.dtype
    }

    pub fn rest_pose(&self) -> &Joints {
        &self.rest_pose
    }

    pub fn ray_caster(&self) -> &RayCaster {
        &self.caster
    }

    /// A_j of the network's bone-aligned frames on the host, [24,4,4] row-major.
    pub fn bone_align(&self) -> &[f32] {
        &self.align_host
    }

    /// The bone boxes the ray caster clips against, for poses with skts: [P,24,4,4].
    pub fn bone_frames(&self, skts: &Tensor) -> Result<BoneFrames> {
        BoneFrames::new(self.caster.bone_align(), &host_f32(skts)?)
    }

    /// Effective box half-extents s: [24,3].
    pub fn axis_scale(&self) -> Result<Tensor> {
        self.net.gnn.axis_scale()
    }

    /// Switch culling (leaving work out, [`crate::cull`]) on or off for later passes.
    pub fn set_culling(&mut self, culling: Culling) -> Result<()> {
        let mut cfg = self.cfg.clone();
        cfg.culling = culling;
        cfg.validate()?;
        self.cfg = cfg;
        Ok(())
    }

    /// Pin the (near, far) that rays missing the bounding cylinder get in later passes
    /// ([`RayCaster::with_miss_fill`]; `None` unpins): chunked training casts every chunk
    /// with its whole batch's values.
    pub fn pin_miss_fill(&mut self, fill: Option<(f32, f32)>) {
        self.caster = self.caster.with_miss_fill(fill);
    }

    /// Points evaluated by the network (far-away constants included) since construction.
    pub fn points_evaluated(&self) -> u64 {
        self.points_evaluated.load(Ordering::Relaxed)
    }

    pub(crate) fn count_points(&self, n: usize) {
        self.points_evaluated.fetch_add(n as u64, Ordering::Relaxed);
    }

    /// All tensors (parameters and buffers) by reference name, for saving.
    pub fn tensors(&self) -> HashMap<String, Tensor> {
        varmap_tensors(&self.varmap)
    }

    /// The trainable parameters in the reference's `named_parameters()` order.
    pub fn trainable(&self) -> Vec<(String, Var)> {
        let data = self.varmap.data().lock().expect("VarMap lock");
        tensor_layout(&self.cfg)
            .into_iter()
            .filter(|s| s.kind == TensorKind::Param)
            .map(|s| {
                let v = data[&s.name].clone();
                (s.name, v)
            })
            .collect()
    }

    /// Save as a pma checkpoint (atomic).
    pub fn save(&self, path: impl AsRef<Path>) -> Result<()> {
        checkpoint::save(path.as_ref(), &self.tensors(), &self.cfg)
    }
}

impl std::fmt::Debug for Avatar {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Avatar")
            .field("cfg", &self.cfg)
            .field("device", &self.device)
            .finish_non_exhaustive()
    }
}

fn varmap_tensors(varmap: &VarMap) -> HashMap<String, Tensor> {
    let data = varmap.data().lock().expect("VarMap lock");
    data.iter()
        .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
        .collect()
}

/// The tensors of a fresh avatar ([`Avatar::new`]) by name.
pub fn init_tensors(
    cfg: &Config,
    rest: &Joints,
    seed: u64,
    device: &Device,
) -> Result<HashMap<String, Tensor>> {
    Ok(Avatar::new(cfg.clone(), rest, seed, device)?.tensors())
}
