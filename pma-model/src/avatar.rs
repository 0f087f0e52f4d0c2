//! The whole PM-Avatar, wired top-down (spec model.md §4).
//!
//! `Avatar::forward` reads in the order the model computes:
//! per-pose work (6D → GNN → projected pose features, box scales) once per pose;
//! ray casting; the coarse network pass; coarse rendering; importance sampling; the fine
//! pass on the new samples only; merge and fine rendering.
//!
//! The network is evaluated through [`Avatar::eval_points`], which takes the points of one
//! pose explicitly, so a caller can evaluate any subset of points (e.g. only those inside a
//! bone volume) and place the results back itself.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

use candle_core::{DType, Device, Tensor, Var, D};
use candle_nn::{VarBuilder, VarMap};
use pma_data::skeleton::{self, Joints, N_JOINTS, PARENTS};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::checkpoint::{self, TensorKind};
use crate::config::{Config, Culling, SampleFill};
use crate::cull::{ray_fates, SampleFate, WindowTest};
use crate::encoders::{pose6d, spherical_harmonics, PointEnc};
use crate::error::{ModelError, Result};
use crate::field::{Field, FrameCodes};
use crate::gnn::GnnSine;
use crate::modulator::{Modulator, PoseExtractor};
use crate::raycast::{merge_raw, RayBounds, RayCaster};
use crate::render::{raw2outputs, RenderOutputs};
use crate::window::{aggregate, spatial_window, WinFun};

/// Named intermediate tensors recorded during a forward pass (parity tests, debugging).
/// Keys follow the golden manifest (`coarse/gnn_feat`, `fine/w_p`, ...).
#[derive(Debug, Default, Clone)]
pub struct Trace {
    pub tensors: BTreeMap<String, Tensor>,
}

impl Trace {
    fn put(&mut self, key: String, t: &Tensor) {
        self.tensors.insert(key, t.clone());
    }
}

/// Per-pose data of a ray batch: P distinct poses. Rays are grouped by pose in P equal,
/// contiguous blocks (rays `[p·R/P, (p+1)·R/P)` belong to pose p).
#[derive(Debug, Clone)]
pub struct Poses {
    /// bones: [P][24][3] axis-angle per joint.
    pub bones: Vec<Joints>,
    /// skts: [P,24,4,4] world→joint transforms.
    pub skts: Tensor,
    /// cyls: [P,5] bounding cylinders (centre_x, centre_z, radius, top, bottom).
    pub cyls: Tensor,
}

/// A batch of rays.
#[derive(Debug, Clone)]
pub struct Rays {
    /// origins: [R,3]
    pub origins: Tensor,
    /// dirs: [R,3] (unit for training rays; any length at render time)
    pub dirs: Tensor,
    /// bgs: [R,3] background colours, or `None` for black.
    pub bgs: Option<Tensor>,
    /// Frame-code index per ray: [R] (training image index; −1 everywhere = mean code).
    pub framecodes: Vec<i64>,
}

/// Standard-normal noise source for the density noise: `n` → [n] tensor. Supplied by the
/// trainer from its own seeded RNG so runs resume bit-exactly.
pub type NoiseFn<'a> = &'a mut dyn FnMut(usize) -> Result<Tensor>;

/// How a forward pass runs.
#[derive(Default)]
pub struct ForwardOptions<'a> {
    /// Training mode: frame codes are looked up directly, and density noise is added when
    /// `noise` is given.
    pub training: bool,
    pub noise: Option<NoiseFn<'a>>,
    /// Inference: no gradient is needed, so the network runs on bounded chunks of points
    /// whose outputs are detached (their intermediates are freed at once). Memory then no
    /// longer grows with the number of rays.
    pub inference: bool,
}

/// Points per network call in inference: the largest per-point tensors are [n,24,128] f32,
/// 4,096 × 24 × 128 × 4 B = 48 MiB each, a handful alive per worker. Larger chunks were no
/// faster (throughput example, one thread: 6,585 samples/s at 4,096 vs 6,052 at 16,384),
/// and many chunks keep the workers balanced.
pub const INFERENCE_POINT_CHUNK: usize = 4_096;

/// Everything a forward pass returns.
#[derive(Debug, Clone)]
pub struct Outputs {
    /// Fine render (coarse + importance samples merged): rgb [R,3], acc [R], disp [R],
    /// weights (T_i) and alpha [R,Sc+Sf].
    pub fine: RenderOutputs,
    /// Coarse render: rgb0, acc0, disp0, weights, alpha [R,Sc].
    pub coarse: RenderOutputs,
    /// z_coarse: [R,Sc]
    pub z_coarse: Tensor,
    /// z_vals: [R,Sc+Sf] merged and sorted.
    pub z_vals: Tensor,
    /// raw_coarse: [R,Sc,4] (rgb, density) of the coarse samples.
    pub raw_coarse: Tensor,
    /// raw: [R,Sc+Sf,4] merged.
    pub raw: Tensor,
    /// vol_scale: [24,3] effective box half-extents (differentiable).
    pub vol_scale: Tensor,
    /// Host-side ray bounds (near/far, box hits).
    pub bounds: RayBounds,
}

/// Pose-only work, computed once per pose of the batch.
#[derive(Debug, Clone)]
pub struct PoseFeatures {
    /// g: [P,24,H] projected GNN features `layer_pose(G)`.
    pub g: Tensor,
    /// skts: [P,24,4,4] world → joint transforms.
    pub skts: Tensor,
    /// s: [24,3] effective half-extents.
    pub scales: Tensor,
}

pub struct Avatar {
    cfg: Config,
    device: Device,
    /// The dtype of every tensor (f32 unless built by [`Avatar::with_dtype`]).
    dtype: DType,
    varmap: VarMap,
    rest_pose: Joints,
    /// Rotation of A_j (`pts_embedder.transforms`), transposed: [24,3,3].
    align_rot_t: Tensor,
    /// Translation of A_j: [24,3].
    align_trans: Tensor,
    /// A_j on the host, [24,4,4] row-major: the culling test runs there.
    align_host: Vec<f32>,
    /// Points that went through the network since construction (bench counters).
    points_evaluated: AtomicU64,
    caster: RayCaster,
    gnn: GnnSine,
    pts_enc_pose: PointEnc,
    pts_enc_point: PointEnc,
    win_fun: WinFun,
    pose_extractor: PoseExtractor,
    modulator: Modulator,
    field: Field,
    framecodes: Option<FrameCodes>,
}

impl Avatar {
    /// Load a checkpoint for inference (or to continue training). Strict: see
    /// [`checkpoint::load`].
    pub fn load(path: impl AsRef<Path>, device: &Device) -> Result<Self> {
        let ck = checkpoint::load(path.as_ref(), device)?;
        Self::from_tensors(ck.config, ck.tensors, device)
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
        let mut problems = checkpoint::check_tensors(
            &cfg,
            tensors.iter().map(|(n, t)| {
                let dt = if t.dtype() == dtype && dtype.is_float() {
                    DType::F32
                } else {
                    t.dtype()
                };
                (n.as_str(), t.dims(), dt)
            }),
        );
        if problems.is_empty() {
            problems.extend(check_buffers(&tensors)?);
        }
        if !problems.is_empty() {
            return Err(ModelError::Checkpoint {
                path: "<tensors>".into(),
                problems,
            });
        }
        let varmap = VarMap::new();
        {
            let mut data = varmap.data().lock().expect("fresh VarMap lock");
            for (name, t) in &tensors {
                data.insert(name.clone(), Var::from_tensor(&t.to_device(device)?)?);
            }
        }
        let vb = VarBuilder::from_varmap(&varmap, dtype, device);
        let rest = vb
            .get((N_JOINTS, 3), "rest_pose")?
            .to_dtype(DType::F32)?
            .to_vec2::<f32>()?;
        let mut rest_pose = [[0f32; 3]; N_JOINTS];
        for (d, s) in rest_pose.iter_mut().zip(rest) {
            d.copy_from_slice(&s);
        }
        let align = vb
            .get((N_JOINTS, 4, 4), "pts_embedder.transforms")?
            .detach();
        let caster =
            RayCaster::from_tensor(&cfg, &vb.get((N_JOINTS, 4, 4), "raycast.transforms")?)?;
        let ce = cfg.point_enc_dim;
        Ok(Self {
            gnn: GnnSine::load(vb.pp("graph_net"), &cfg)?,
            pts_enc_pose: PointEnc::load(vb.pp("pts_enc_pose"), ce, cfg.sin_w0_pose)?,
            pts_enc_point: PointEnc::load(vb.pp("pts_enc_point"), ce, cfg.sin_w0_point)?,
            win_fun: WinFun::load(vb.pp("win_fun"), &cfg)?,
            pose_extractor: PoseExtractor::load(vb.pp("pose_extractor"), &cfg)?,
            modulator: Modulator::load(vb.pp("modulator"), &cfg)?,
            field: Field::load(vb.clone(), &cfg)?,
            framecodes: if cfg.use_framecodes {
                Some(FrameCodes::load(vb.pp("framecodes"), &cfg)?)
            } else {
                None
            },
            caster,
            align_rot_t: align
                .narrow(1, 0, 3)?
                .narrow(2, 0, 3)?
                .transpose(1, 2)?
                .contiguous()?,
            align_trans: align
                .narrow(1, 0, 3)?
                .narrow(2, 3, 1)?
                .reshape((N_JOINTS, 3))?,
            align_host: align
                .flatten_all()?
                .to_dtype(DType::F32)?
                .to_device(&Device::Cpu)?
                .to_vec1::<f32>()?,
            points_evaluated: AtomicU64::new(0),
            rest_pose,
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

    /// The dtype the network computes in (that of its tensors).
    pub fn dtype(&self) -> DType {
        self.dtype
    }

    /// Rays and poses converted to the network's dtype (a no-op for f32 inputs of an f32
    /// avatar, the only case training and parity use).
    fn cast_batch(&self, rays: &Rays, poses: &Poses) -> Result<Option<(Rays, Poses)>> {
        if rays.dirs.dtype() == self.dtype
            && rays.origins.dtype() == self.dtype
            && poses.skts.dtype() == self.dtype
        {
            return Ok(None);
        }
        let rays = Rays {
            origins: rays.origins.to_dtype(self.dtype)?,
            dirs: rays.dirs.to_dtype(self.dtype)?,
            bgs: rays
                .bgs
                .as_ref()
                .map(|b| b.to_dtype(self.dtype))
                .transpose()?,
            framecodes: rays.framecodes.clone(),
        };
        let poses = Poses {
            bones: poses.bones.clone(),
            skts: poses.skts.to_dtype(self.dtype)?,
            cyls: poses.cyls.to_dtype(self.dtype)?,
        };
        Ok(Some((rays, poses)))
    }

    /// A freshly initialised avatar for `rest_pose` with the reference's initialisation
    /// (model.md §7), deterministic for `seed`.
    pub fn new(cfg: Config, rest_pose: &Joints, seed: u64, device: &Device) -> Result<Self> {
        let tensors = init_tensors(&cfg, rest_pose, seed, device)?;
        Self::from_tensors(cfg, tensors, device)
    }

    pub fn config(&self) -> &Config {
        &self.cfg
    }

    /// Switch culling (leaving work out, [`crate::cull`]) on or off for later passes.
    pub fn set_culling(&mut self, culling: Culling) -> Result<()> {
        let mut cfg = self.cfg.clone();
        cfg.culling = culling;
        cfg.validate()?;
        self.cfg = cfg;
        Ok(())
    }

    /// Points evaluated by the network (far-away constants included) since construction.
    pub fn points_evaluated(&self) -> u64 {
        self.points_evaluated.load(Ordering::Relaxed)
    }

    pub fn device(&self) -> &Device {
        &self.device
    }

    pub fn rest_pose(&self) -> &Joints {
        &self.rest_pose
    }

    pub fn ray_caster(&self) -> &RayCaster {
        &self.caster
    }

    /// Pin the (near, far) that rays missing the bounding cylinder get in later passes
    /// ([`RayCaster::with_miss_fill`]; `None` unpins): chunked training casts every chunk
    /// with its whole batch's values.
    pub fn pin_miss_fill(&mut self, fill: Option<(f32, f32)>) {
        self.caster = self.caster.with_miss_fill(fill);
    }

    /// All tensors (parameters and buffers) by reference name, for saving.
    pub fn tensors(&self) -> HashMap<String, Tensor> {
        let data = self.varmap.data().lock().expect("VarMap lock");
        data.iter()
            .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
            .collect()
    }

    /// The trainable parameters in the reference's `named_parameters()` order.
    pub fn trainable(&self) -> Vec<(String, Var)> {
        let data = self.varmap.data().lock().expect("VarMap lock");
        checkpoint::tensor_layout(&self.cfg)
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

    /// Effective box half-extents s: [24,3].
    pub fn axis_scale(&self) -> Result<Tensor> {
        self.gnn.axis_scale()
    }

    /// Pose-only work for every pose of the batch.
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
        let mut layers = Vec::new();
        let g_feat = self
            .gnn
            .forward(&theta, trace.is_some().then_some(&mut layers))?;
        let g = self.win_fun.project_pose(&g_feat)?;
        let scales = self.gnn.axis_scale()?;
        if let Some(t) = trace {
            t.put("pose6d".into(), &theta);
            for (l, pre) in layers.iter().enumerate() {
                t.put(format!("gnn_layer{l}_pre_sin"), pre);
            }
            t.put("gnn_feat".into(), &g_feat);
            t.put(
                "win_layer_pose".into(),
                &g.reshape(((), g.dim(D::Minus1)?))?,
            );
            t.put("axis_scale".into(), &scales);
        }
        Ok(PoseFeatures {
            g,
            skts: poses.skts.to_dtype(self.dtype)?,
            scales,
        })
    }

    /// The network on the points of one pose: pts: [n,3] world points, view: [n,V] view
    /// features (SH of the root-frame direction, then the frame code).
    /// Returns (rgb [n,3], sigma_raw [n,1]).
    pub fn eval_points(
        &self,
        pose: &PoseFeatures,
        p: usize,
        pts: &Tensor,
        view: &Tensor,
        mut trace: Option<(&mut Trace, &str)>,
    ) -> Result<(Tensor, Tensor)> {
        let n = pts.dim(0)?;
        let j = N_JOINTS;
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
        let x_bar = x_hat.broadcast_div(&pose.scales)?;
        let w_p = spatial_window(&x_bar, self.cfg.window_alpha, self.cfg.window_beta)?;
        let e = self.pts_enc_pose.forward(&x_bar)?;
        let g = pose.g.get(p)?;
        let win = self.win_fun.forward(&g, &e, &w_p)?;
        let f_m = aggregate(&win.w, &g)?;
        let modulation = self.pose_extractor.forward(&f_m)?;
        let z = self.pts_enc_point.forward(&x_bar)?;
        let x_tilde = z
            .broadcast_mul(&win.w.unsqueeze(D::Minus1)?)?
            .reshape((n, j * self.cfg.point_enc_dim))?;
        let s = self.modulator.forward(&x_tilde, &modulation)?;
        let out = self.field.forward(&s, view)?;
        if let Some((tr, stage)) = trace.as_mut() {
            let k = |name: &str| format!("{stage}/{name}");
            tr.put(k("pts_jt"), &x_jt);
            tr.put(k("pts_t"), &x_hat);
            tr.put(k("x_bar"), &x_bar);
            tr.put(k("w_p"), &w_p);
            tr.put(k("pts_enc_pose"), &e);
            tr.put(k("win_maxpool"), &win.pooled);
            tr.put(k("win_logits"), &win.logits);
            tr.put(k("w_f"), &win.w_f);
            tr.put(k("w"), &win.w);
            tr.put(k("f_m"), &f_m);
            tr.put(k("pts_enc_point"), &z);
            let gammas = modulation
                .freq
                .iter()
                .map(|f| self.modulator.gamma(f))
                .collect::<Result<Vec<_>>>()?;
            tr.put(k("mod_freq"), &Tensor::stack(&gammas, 0)?);
            tr.put(k("mod_phase"), &Tensor::stack(&modulation.phase, 0)?);
            tr.put(k("modulator_out"), &s);
            tr.put(k("density_l0_pre_relu"), &out.l0_pre);
            tr.put(k("density_feat"), &out.feature);
            tr.put(k("sigma_raw"), &out.sigma_raw);
            tr.put(k("feature_linear"), &out.feature_linear);
            tr.put(k("view_l0_pre_relu"), &out.view_pre);
            tr.put(k("rgb_logits"), &out.rgb_logits);
        }
        Ok((out.rgb, out.sigma_raw))
    }

    /// View features per ray: [SH(d_root); frame code] -> [R,V]. Also returns d_root [R,3].
    fn view_features(
        &self,
        rays: &Rays,
        poses: &Poses,
        training: bool,
    ) -> Result<(Tensor, Tensor)> {
        let r = rays.dirs.dim(0)?;
        let p = poses.bones.len();
        let k = r / p;
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
            .reshape((p, k, 3))?
            .matmul(&r0.transpose(1, 2)?)?
            .reshape((r, 3))?;
        let d = if self.cfg.quirks.normalize_view_dirs {
            d.broadcast_div(
                &d.sqr()?
                    .sum_keepdim(1)?
                    .sqrt()?
                    .clamp(1e-12, f64::INFINITY)?,
            )?
        } else {
            d
        };
        let sh = spherical_harmonics(&d, self.cfg.sh_degree)?;
        let view = match &self.framecodes {
            Some(codes) => Tensor::cat(&[&sh, &codes.lookup(&rays.framecodes, training)?], 1)?,
            None => sh,
        };
        Ok((view, d))
    }

    /// Network pass on samples pts: [R,S,3] of all rays -> raw [R,S,4] (rgb, density).
    fn network_pass(
        &self,
        pose: &PoseFeatures,
        pts: &Tensor,
        view: &Tensor,
        opts: &mut ForwardOptions,
        stage: &str,
        trace: Option<&mut Trace>,
    ) -> Result<Tensor> {
        let (r, s, _) = pts.dims3()?;
        self.points_evaluated
            .fetch_add((r * s) as u64, Ordering::Relaxed);
        let n_poses = pose.g.dim(0)?;
        let k = r / n_poses;
        let vdim = view.dim(1)?;
        let mut rgbs = Vec::with_capacity(n_poses);
        let mut sigmas = Vec::with_capacity(n_poses);
        let mut traces = Vec::new();
        if opts.inference {
            // Every (pose, chunk) pair is one job for the workers; outputs stay in ray order.
            let n = k * s;
            let chunk = INFERENCE_POINT_CHUNK;
            let per_pose = n.div_ceil(chunk);
            let mut inputs = Vec::with_capacity(n_poses);
            for p in 0..n_poses {
                let pts_p = pts.narrow(0, p * k, k)?.reshape((n, 3))?;
                let view_p = view
                    .narrow(0, p * k, k)?
                    .unsqueeze(1)?
                    .broadcast_as((k, s, vdim))?
                    .reshape((n, vdim))?;
                inputs.push((pts_p, view_p));
            }
            let workers = crate::parallel::workers_on(pts.device());
            let outs = crate::parallel::map_ordered(workers, n_poses * per_pose, |i| {
                let (p, c) = (i / per_pose, i % per_pose);
                let (start, len) = (c * chunk, chunk.min(n - c * chunk));
                let (pts_p, view_p) = &inputs[p];
                let (rgb, sigma_raw) = self.eval_points(
                    pose,
                    p,
                    &pts_p.narrow(0, start, len)?,
                    &view_p.narrow(0, start, len)?,
                    None,
                )?;
                // Detached at once: the weights are variables, so the outputs would otherwise
                // keep the chunk's whole graph alive until every chunk is done.
                Ok::<_, ModelError>((rgb.detach(), sigma_raw.detach()))
            })?;
            for (rgb, sigma_raw) in outs {
                rgbs.push(rgb);
                sigmas.push(sigma_raw);
            }
        }
        for p in (0..n_poses).filter(|_| !opts.inference) {
            let pts_p = pts.narrow(0, p * k, k)?.reshape((k * s, 3))?;
            let view_p = view
                .narrow(0, p * k, k)?
                .unsqueeze(1)?
                .broadcast_as((k, s, vdim))?
                .reshape((k * s, vdim))?;
            let mut tp = Trace::default();
            let (rgb, sigma_raw) = self.eval_points(
                pose,
                p,
                &pts_p,
                &view_p,
                trace.is_some().then_some((&mut tp, stage)),
            )?;
            traces.push(tp);
            rgbs.push(rgb);
            sigmas.push(sigma_raw);
        }
        let rgb = Tensor::cat(&rgbs, 0)?;
        let sigma_raw = Tensor::cat(&sigmas, 0)?;
        if let Some(t) = trace {
            // Per-pose traces are concatenated in ray order (poses are contiguous blocks).
            let keys: Vec<String> = traces
                .first()
                .map(|t| t.tensors.keys().cloned().collect())
                .unwrap_or_default();
            for key in keys {
                let parts: Vec<Tensor> = traces.iter().map(|t| t.tensors[&key].clone()).collect();
                let cat_dim = if key.ends_with("mod_freq") || key.ends_with("mod_phase") {
                    1
                } else {
                    0
                };
                t.put(key, &Tensor::cat(&parts, cat_dim)?);
            }
        }
        let sigma_in = match (opts.training, opts.noise.as_mut()) {
            (true, Some(noise)) if self.cfg.density_noise_std > 0.0 => {
                let eps = noise(r * s)?.reshape((r * s, 1))?;
                (&sigma_raw + (eps * self.cfg.density_noise_std)?)?
            }
            _ => sigma_raw,
        };
        let density = sigma_in.relu()?;
        Ok(Tensor::cat(&[rgb, density], 1)?.reshape((r, s, 4))?)
    }

    /// The culling state of one forward pass, or `None` when culling is off.
    fn cull_context(
        &self,
        pose: &PoseFeatures,
        poses: &Poses,
        bounds: &RayBounds,
    ) -> Result<Option<CullCtx>> {
        let c = &self.cfg.culling;
        if c.is_off() {
            return Ok(None);
        }
        let test = match c.sample_threshold {
            Some(t) => Some(WindowTest::new(
                &self.align_host,
                &host_vec(&poses.skts)?,
                &host_vec(&pose.scales)?,
                self.cfg.window_alpha,
                self.cfg.window_beta,
                t,
            )?),
            None => None,
        };
        Ok(Some(CullCtx {
            test,
            ray_alive: c.rays.then(|| bounds.ray_hits_body.clone()),
            fill: c.sample_fill,
            consts: ConstRows::default(),
        }))
    }

    /// [`Self::network_pass`] with culling: only samples with [`SampleFate::Evaluate`] go
    /// through the network; the rest are filled from the far-away constants or with zeros.
    /// Gradients reach the evaluated samples and the constants (an `index_select` gathers
    /// them), so training with culling at threshold 0 matches parity mode as well.
    ///
    /// The far-away points ride in the same network call as the evaluated samples: gemm's
    /// result for a row depends (by an ulp) on the size of the call, not on the row's place
    /// in it, and parity mode evaluates culled samples inside large calls.
    fn network_pass_culled(
        &self,
        pose: &PoseFeatures,
        pts: &Tensor,
        view: &Tensor,
        opts: &mut ForwardOptions,
        cull: &mut CullCtx,
    ) -> Result<Tensor> {
        let (r, s, _) = pts.dims3()?;
        let n = r * s;
        let n_poses = pose.g.dim(0)?;
        let k = r / n_poses;
        let dev = pts.device();
        let fates = match (&cull.test, &cull.ray_alive) {
            (Some(t), alive) => t.fates(&host_vec(pts)?, r, s, alive.as_deref())?,
            (None, Some(alive)) => ray_fates(r, s, alive)?,
            (None, None) => vec![SampleFate::Evaluate; n],
        };
        let network_fill = cull.fill == SampleFill::Network;
        let noisy = opts.training && opts.noise.is_some() && self.cfg.density_noise_std > 0.0;
        let need: Vec<usize> = if network_fill {
            (0..r)
                .filter(|&ray| fates[ray * s..(ray + 1) * s].contains(&SampleFate::Outside))
                .collect()
        } else {
            Vec::new()
        };
        if cull.consts.row_of_ray.len() != r {
            cull.consts.row_of_ray = vec![u32::MAX; r];
        }
        if !need.is_empty() && opts.inference && !noisy && !cull.consts.probed {
            self.probe_shared_constant(pose, view, need[0], cull)?;
        }
        let far_rays: Vec<usize> = if cull.consts.shared {
            Vec::new()
        } else {
            need.iter()
                .copied()
                .filter(|&ray| cull.consts.row_of_ray[ray] == u32::MAX)
                .collect()
        };
        let pts_flat = pts.reshape((n, 3))?;
        let mut rgbs = Vec::new();
        let mut sigmas = Vec::new();
        let mut evaluated = 0usize;
        let mut far_done = 0usize;
        let mut jobs = Vec::new();
        let mut far_of_pose: Vec<Vec<usize>> = Vec::new();
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
            let chunk = if opts.inference {
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
            // Inputs of every chunk first, then the network on the workers, then the
            // bookkeeping in chunk order.
            let mut inputs = Vec::with_capacity(parts.len());
            for (c, part) in parts.iter().enumerate() {
                let len = part.len();
                let far_len = if c == last { far_p.len() } else { 0 };
                let mut rays_of: Vec<u32> = part.iter().map(|&i| i / s as u32).collect();
                let mut pts_c = Vec::new();
                if len > 0 {
                    pts_c.push(
                        pts_flat.index_select(&Tensor::from_vec(part.to_vec(), len, dev)?, 0)?,
                    );
                }
                if far_len > 0 {
                    let test = cull.test.as_ref().ok_or_else(|| {
                        ModelError::Input("culling: constants need the window test".into())
                    })?;
                    let far = test.far_point(p)?;
                    pts_c.push(
                        Tensor::from_vec(far.repeat(far_len), (far_len, 3), dev)?
                            .to_dtype(pts.dtype())?,
                    );
                    rays_of.extend(far_p.iter().map(|&ray| ray as u32));
                }
                let pts_c = Tensor::cat(&pts_c, 0)?;
                let view_c =
                    view.index_select(&Tensor::from_vec(rays_of, len + far_len, dev)?, 0)?;
                inputs.push((pts_c, view_c, len, far_len));
            }
            jobs.extend(
                inputs
                    .into_iter()
                    .map(|(pts_c, view_c, len, far_len)| (p, pts_c, view_c, len, far_len)),
            );
            far_of_pose.push(far_p);
        }
        // The network on the workers for every (pose, chunk) job, then the bookkeeping in
        // order.
        let workers = crate::parallel::workers_on(dev);
        let outs = crate::parallel::map_ordered(workers, jobs.len(), |i| {
            let (p, pts_c, view_c, _, _) = &jobs[i];
            let (rgb, sigma_raw) = self.eval_points(pose, *p, pts_c, view_c, None)?;
            // In inference the chunk's graph goes at once (see `network_pass`).
            Ok::<_, ModelError>(if opts.inference {
                (rgb.detach(), sigma_raw.detach())
            } else {
                (rgb, sigma_raw)
            })
        })?;
        for ((p, _, _, len, far_len), (rgb, sigma_raw)) in jobs.into_iter().zip(outs) {
            let far_p = far_of_pose
                .iter()
                .find(|f| f.first().is_some_and(|&ray| ray / k == p))
                .map_or(&[][..], |f| f.as_slice());
            if len > 0 {
                rgbs.push(rgb.narrow(0, 0, len)?);
                sigmas.push(sigma_raw.narrow(0, 0, len)?);
            }
            if far_len > 0 {
                let consts = &mut cull.consts;
                for (i, &ray) in far_p.iter().enumerate() {
                    consts.row_of_ray[ray] = (consts.rows + i) as u32;
                }
                consts.rows += far_len;
                consts.rgb.push(rgb.narrow(0, len, far_len)?);
                consts.sigma.push(sigma_raw.narrow(0, len, far_len)?);
                far_done += far_len;
            }
            evaluated += len;
        }
        self.points_evaluated
            .fetch_add((evaluated + far_done) as u64, Ordering::Relaxed);
        let consts = &cull.consts;
        let zero_row = (evaluated + consts.rows) as u32;
        let mut next = 0u32;
        let mut any_zero = false;
        let idx: Vec<u32> = (0..n)
            .map(|i| match fates[i] {
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
        let idx = Tensor::from_vec(idx, n, dev)?;
        let rgb = Tensor::cat(&rgb_rows, 0)?.index_select(&idx, 0)?;
        let sigma_raw = Tensor::cat(&sigma_rows, 0)?.index_select(&idx, 0)?;
        let sigma_in = match (opts.training, opts.noise.as_mut()) {
            (true, Some(noise)) if self.cfg.density_noise_std > 0.0 => {
                // Drawn for every sample, culled or not, so the noise stream stays aligned
                // with parity mode.
                let eps = noise(n)?.reshape((n, 1))?;
                (&sigma_raw + (eps * self.cfg.density_noise_std)?)?
            }
            _ => sigma_raw,
        };
        let mut density = sigma_in.relu()?;
        if noisy && any_zero {
            // Zero-filled samples have no density even where noise would have given some.
            let alive: Vec<f32> = fates
                .iter()
                .map(|f| match f {
                    SampleFate::Evaluate => 1.0,
                    SampleFate::Outside if network_fill => 1.0,
                    _ => 0.0,
                })
                .collect();
            let alive = Tensor::from_vec(alive, (n, 1), dev)?.to_dtype(density.dtype())?;
            density = density.broadcast_mul(&alive)?;
        }
        Ok(Tensor::cat(&[rgb, density], 1)?.reshape((r, s, 4))?)
    }

    /// Inference without noise: the far-away density is one global constant (f^m and every
    /// windowed feature are 0 there). When it is ≤ 0 the colour of culled samples carries zero
    /// weight in every rendered output, so one evaluation (along ray `ray`) serves all rays;
    /// their raw colour is then the one seen along that ray. Decided once per forward pass.
    fn probe_shared_constant(
        &self,
        pose: &PoseFeatures,
        view: &Tensor,
        ray: usize,
        cull: &mut CullCtx,
    ) -> Result<()> {
        let consts = &mut cull.consts;
        consts.probed = true;
        let Some(test) = cull.test.as_ref() else {
            return Ok(());
        };
        let rays_per_pose = view.dim(0)? / pose.g.dim(0)?;
        let p = ray / rays_per_pose;
        let dev = view.device();
        let far = test.far_point(p)?;
        let pts = Tensor::from_vec(far.to_vec(), (1, 3), dev)?;
        let view_c = view.narrow(0, ray, 1)?;
        let (rgb, sigma) = self.eval_points(pose, p, &pts, &view_c, None)?;
        self.points_evaluated.fetch_add(1, Ordering::Relaxed);
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

    /// Render a ray batch: the full coarse + fine forward pass (training or inference).
    pub fn forward(
        &self,
        rays: &Rays,
        poses: &Poses,
        opts: &mut ForwardOptions,
        mut trace: Option<&mut Trace>,
    ) -> Result<Outputs> {
        check_batch(rays, poses)?;
        let cast = self.cast_batch(rays, poses)?;
        let (rays, poses) = cast.as_ref().map_or((rays, poses), |(r, p)| (r, p));
        let stage_trace = |t: &mut Option<&mut Trace>, prefix: &str| -> Option<Trace> {
            t.as_ref().map(|_| {
                let _ = prefix;
                Trace::default()
            })
        };

        // 1. Per-pose work.
        let mut pose_trace = stage_trace(&mut trace, "pose");
        let pose = self.pose_features(poses, pose_trace.as_mut())?;
        self.forward_inner(rays, poses, &pose, opts, trace, pose_trace)
    }

    /// [`Self::forward`] with the per-pose work already done (`pose` from
    /// [`Self::pose_features`] of the same `poses`), so callers that split a pose's rays into
    /// chunks run the GNN once per pose, not once per chunk.
    pub fn forward_with_pose(
        &self,
        rays: &Rays,
        poses: &Poses,
        pose: &PoseFeatures,
        opts: &mut ForwardOptions,
    ) -> Result<Outputs> {
        check_batch(rays, poses)?;
        let cast = self.cast_batch(rays, poses)?;
        let (rays, poses) = cast.as_ref().map_or((rays, poses), |(r, p)| (r, p));
        if pose.g.dim(0)? != poses.bones.len() {
            return Err(ModelError::shape(
                "pose features",
                [poses.bones.len()],
                [pose.g.dim(0)?],
            ));
        }
        self.forward_inner(rays, poses, pose, opts, None, None)
    }

    fn forward_inner(
        &self,
        rays: &Rays,
        poses: &Poses,
        pose: &PoseFeatures,
        opts: &mut ForwardOptions,
        mut trace: Option<&mut Trace>,
        pose_trace: Option<Trace>,
    ) -> Result<Outputs> {
        let r = rays.origins.dim(0)?;
        let n_poses = poses.bones.len();
        // 2. Ray casting (no gradient) with the current, detached box sizes.
        let coarse = self.caster.cast(
            &rays.origins,
            &rays.dirs,
            &poses.cyls,
            &poses.skts,
            &pose.scales.detach(),
        )?;
        let (view, d_root) = self.view_features(rays, poses, opts.training)?;
        // Culling needs per-point traces of every sample, so a traced pass never culls.
        let mut cull = match trace {
            None => self.cull_context(pose, poses, &coarse.bounds)?,
            Some(_) => None,
        };
        // 3. Coarse pass and render.
        let raw_coarse = match cull.as_mut() {
            Some(c) => self.network_pass_culled(pose, &coarse.pts, &view, opts, c)?,
            None => self.network_pass(
                pose,
                &coarse.pts,
                &view,
                opts,
                "coarse",
                trace.as_deref_mut(),
            )?,
        };
        let render_coarse = raw2outputs(&raw_coarse, &coarse.z, &rays.dirs, rays.bgs.as_ref())?;
        // 4. Importance samples from the coarse weights, then the fine pass on those only.
        let fine = self.caster.resample(
            &rays.origins,
            &rays.dirs,
            &coarse.z,
            &render_coarse.weights.detach(),
        )?;
        let raw_fine = match cull.as_mut() {
            Some(c) => self.network_pass_culled(pose, &fine.pts, &view, opts, c)?,
            None => {
                self.network_pass(pose, &fine.pts, &view, opts, "fine", trace.as_deref_mut())?
            }
        };
        // 5. Merge with the coarse outputs (reused, noise included) and render again.
        let raw = merge_raw(&raw_coarse, &raw_fine, &fine.perm)?;
        let render_fine = raw2outputs(&raw, &fine.z_all, &rays.dirs, rays.bgs.as_ref())?;

        if let Some(t) = trace {
            if let Some(pt) = pose_trace {
                for stage in ["coarse", "fine"] {
                    for (k, v) in &pt.tensors {
                        t.put(format!("{stage}/{k}"), v);
                    }
                }
            }
            for (stage, samples) in [("coarse", coarse.z.dim(1)?), ("fine", fine.z.dim(1)?)] {
                let dr = d_root.unsqueeze(1)?.broadcast_as((r, samples, 3))?;
                t.put(format!("{stage}/view_dir_root"), &dr);
            }
            t.put("raycast/pts_coarse".into(), &coarse.pts);
            t.put("raycast/z_vals_coarse".into(), &coarse.z);
            t.put("raycast/pts_is".into(), &fine.pts);
            t.put("raycast/z_vals_merged".into(), &fine.z_all);
            t.put("raycast/sorted_idxs".into(), &fine.perm);
            t.put("view_features".into(), &view);
            let _ = n_poses;
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

    /// Inference: render rays (eval mode, no noise, no gradient, bounded memory).
    pub fn render_rays(&self, rays: &Rays, poses: &Poses) -> Result<Outputs> {
        let mut opts = ForwardOptions {
            inference: true,
            ..Default::default()
        };
        self.forward(rays, poses, &mut opts, None)
    }

    /// Render a whole image of one pose (eval mode, mean frame code, black or given
    /// background), in chunks of rays inside the body's 2-D box: memory stays bounded at any
    /// resolution. `kp3d` are the pose's joint positions (for the box).
    pub fn render_image(
        &self,
        poses: &Poses,
        kp3d: &Joints,
        cam: &pma_data::camera::Camera,
        background: Option<&[f32]>,
        opts: &crate::image::ImageOptions,
    ) -> Result<crate::image::RenderedImage> {
        if poses.bones.len() != 1 {
            return Err(ModelError::Input(format!(
                "render_image takes one pose, found {}",
                poses.bones.len()
            )));
        }
        // The GNN and every other per-pose term once per image, not once per chunk.
        let pose = self.pose_features(poses, None)?;
        let mut renderer =
            |o: &Tensor, d: &Tensor, bg: &Tensor| -> Result<crate::image::ChunkRender> {
                let rays = Rays {
                    origins: o.clone(),
                    dirs: d.clone(),
                    bgs: Some(bg.clone()),
                    framecodes: vec![-1; o.dim(0)?],
                };
                let mut opts = ForwardOptions {
                    inference: true,
                    ..Default::default()
                };
                let out = self.forward_with_pose(&rays, poses, &pose, &mut opts)?;
                Ok(crate::image::ChunkRender {
                    rgb: out.fine.rgb,
                    acc: out.fine.acc,
                    disp: out.fine.disp,
                })
            };
        crate::image::render_image(&mut renderer, cam, kp3d, background, opts)
    }

    /// Per-pose data for one pose given only its bones and root location: FK with the
    /// avatar's own rest pose (what retargeting needs).
    pub fn pose_from_bones(&self, bones: &Joints, root: [f32; 3]) -> Result<(Poses, Joints)> {
        let posed = skeleton::forward_kinematics(&self.rest_pose, bones, root);
        let skts: Vec<f32> = posed.skts.iter().flatten().flatten().copied().collect();
        let cyl = pma_data::cylinder::cylinder_from_joints(
            &posed.kp3d,
            &pma_data::cylinder::CylinderParams::training(pma_data::cylinder::HeadDir::NegY),
        );
        Ok((
            Poses {
                bones: vec![*bones],
                skts: Tensor::from_vec(skts, (1, N_JOINTS, 4, 4), &self.device)?,
                cyls: Tensor::from_vec(cyl.to_vec(), (1, 5), &self.device)?,
            },
            posed.kp3d,
        ))
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

/// Culling state of one forward pass (coarse and fine share the far-away constants).
struct CullCtx {
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

fn host_vec(t: &Tensor) -> Result<Vec<f32>> {
    Ok(t.flatten_all()?
        .to_dtype(DType::F32)?
        .to_device(&Device::Cpu)?
        .to_vec1::<f32>()?)
}

/// Buffers a checkpoint may carry that would only fail much later, as NaN: a degenerate
/// rest pose and zero or non-finite box sizes (the floor is a fraction of `base_scale`, so a
/// zero there divides by zero in x̄ = x̂ / s). One line per problem.
fn check_buffers(tensors: &HashMap<String, Tensor>) -> Result<Vec<String>> {
    let mut problems = Vec::new();
    let host = |k: &str| -> Result<Vec<f32>> { host_vec(&tensors[k]) };
    let rest = host("rest_pose")?;
    let mut joints = [[0f32; 3]; N_JOINTS];
    for (d, s) in joints.iter_mut().zip(rest.chunks_exact(3)) {
        d.copy_from_slice(s);
    }
    if let Err(e) = skeleton::check_rest_pose(&joints) {
        problems.push(format!("tensor `rest_pose`: {e}"));
    }
    let base = host("graph_net.base_scale")?;
    let mut s = [[0f32; 3]; N_JOINTS];
    for (d, v) in s.iter_mut().zip(base.chunks_exact(3)) {
        d.copy_from_slice(v);
    }
    if let Err(e) = skeleton::check_half_extents(
        "tensor `graph_net.base_scale`",
        &s,
        skeleton::rest_pose_scale(&joints),
    ) {
        problems.push(e.to_string());
    }
    for k in ["pts_embedder.transforms", "raycast.transforms"] {
        if let Some(i) = host(k)?.iter().position(|v| !v.is_finite()) {
            problems.push(format!("tensor `{k}`: value {i} is not finite"));
        }
    }
    Ok(problems)
}

fn check_batch(rays: &Rays, poses: &Poses) -> Result<()> {
    let r = rays.origins.dim(0)?;
    let p = poses.bones.len();
    if p == 0 || r == 0 || r % p != 0 {
        return Err(ModelError::Input(format!(
            "{r} rays cannot be split into {p} equal, contiguous per-pose blocks"
        )));
    }
    if rays.origins.dims() != [r, 3] || rays.dirs.dims() != [r, 3] {
        return Err(ModelError::shape("rays_o/rays_d", [r, 3], rays.dirs.dims()));
    }
    if poses.cyls.dims() != [p, 5] {
        return Err(ModelError::shape("cyls", [p, 5], poses.cyls.dims()));
    }
    if rays.framecodes.len() != r {
        return Err(ModelError::shape(
            "framecodes",
            [r],
            [rays.framecodes.len()],
        ));
    }
    Ok(())
}

/// Reference initialisation (model.md §7) of every tensor, deterministic for `seed`.
pub fn init_tensors(
    cfg: &Config,
    rest: &Joints,
    seed: u64,
    device: &Device,
) -> Result<HashMap<String, Tensor>> {
    cfg.validate()?;
    let base = skeleton::check_model_rest_pose(rest)?;
    let align = skeleton::bone_align(rest)?;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut out = HashMap::new();
    let j = cfg.n_joints;
    let mut adj = vec![0f32; j * j];
    for i in 0..j {
        adj[i * j + i] = 1.0;
        if i > 0 {
            adj[i * j + PARENTS[i]] = 1.0;
            adj[PARENTS[i] * j + i] = 1.0;
        }
    }
    for spec in checkpoint::tensor_layout(cfg) {
        let n: usize = spec.shape.iter().product();
        let name = spec.name.as_str();
        let uniform = |rng: &mut ChaCha8Rng, a: f64| -> Vec<f32> {
            (0..n).map(|_| rng.gen_range(-a..=a) as f32).collect()
        };
        let fan_in = |s: &[usize]| s.last().copied().unwrap_or(1) as f64;
        let default_bound = |s: &[usize]| 1.0 / fan_in(s).sqrt();
        let data: Vec<f32> = match name {
            "rest_pose" => rest.iter().flatten().copied().collect(),
            "pts_embedder.transforms" | "raycast.transforms" => align
                .transforms
                .iter()
                .flatten()
                .flatten()
                .copied()
                .collect(),
            "graph_net.axis_scale" | "graph_net.base_scale" => {
                base.iter().flatten().copied().collect()
            }
            "graph_net.mask" => (0..j)
                .map(|i| if i == 0 && cfg.mask_root { 0.0 } else { 1.0 })
                .collect(),
            _ if name.ends_with(".adj") => adj.clone(),
            _ if name.ends_with(".adj_w") => (0..j * j)
                .map(|i| {
                    let u: f64 = rng.gen();
                    if i / j == i % j {
                        1.0
                    } else {
                        adj[i] * (0.05 + 0.1 * (u - 0.5)).clamp(0.01, 1.0) as f32
                    }
                })
                .collect(),
            "framecodes.codes.weight" => {
                let std = (2.0 / (spec.shape[0] + spec.shape[1]) as f64).sqrt();
                (0..n)
                    .map(|_| (std * standard_normal(&mut rng)) as f32)
                    .collect()
            }
            _ if name.starts_with("graph_net.layers.") && name.ends_with("bias") => vec![0.0; n],
            _ if name.starts_with("graph_net.layers.0.") => {
                uniform(&mut rng, 1.0 / spec.shape[2] as f64)
            }
            _ if name.starts_with("graph_net.layers.") => {
                // The reference's SIREN init reads the last dim as fan-in: for the [J,in,out]
                // layout that is the fan-out (a quirk kept for parity).
                uniform(
                    &mut rng,
                    (6.0 / spec.shape[2] as f64).sqrt() / cfg.sin_w0_pose,
                )
            }
            _ if name.starts_with("pts_enc_") && name.ends_with("weight") => {
                uniform(&mut rng, 1.0 / 3.0)
            }
            _ if (name.starts_with("win_fun.") || name.starts_with("pose_extractor."))
                && name.ends_with("weight") =>
            {
                uniform(
                    &mut rng,
                    (6.0 / fan_in(&spec.shape)).sqrt() / cfg.sin_w0_pose,
                )
            }
            _ if name.starts_with("modulator.") && name.ends_with("weight") => uniform(
                &mut rng,
                (6.0 / fan_in(&spec.shape)).sqrt() / cfg.sin_w0_point,
            ),
            _ if name.ends_with("bias") => {
                // torch's default bias bound 1/sqrt(fan_in), fan_in from the matching weight.
                let w = checkpoint::tensor_layout(cfg)
                    .into_iter()
                    .find(|s| s.name == name.replace("bias", "weight"))
                    .map(|s| s.shape)
                    .unwrap_or_else(|| spec.shape.clone());
                uniform(&mut rng, default_bound(&w))
            }
            _ => uniform(&mut rng, default_bound(&spec.shape)),
        };
        out.insert(
            spec.name.clone(),
            Tensor::from_vec(data, spec.shape.clone(), device)?,
        );
    }
    Ok(out)
}

/// Box–Muller; keeps `rand_distr` (a training-only dependency) out of inference builds.
fn standard_normal(rng: &mut ChaCha8Rng) -> f64 {
    let u1: f64 = rng.gen_range(f64::EPSILON..1.0);
    let u2: f64 = rng.gen();
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}
