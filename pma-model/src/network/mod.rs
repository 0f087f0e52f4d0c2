//! The PM-Avatar network on points: everything that has weights.
//!
//! [`Network::pose_features`] is the per-pose work (6D rotations → GNN → projected part
//! features, box sizes), once per pose. [`Network::eval_points`] is the network on the points
//! of one pose, in the paper's order: bone-normalised points, the two-stage window
//! ([`window`]), the pose-modulated sine layers ([`modulator`]), the NeRF heads ([`field`]).
//! Rays, samples and compositing are [`crate::render`]'s business; the layers here see
//! points only.
//!
//! | module | what |
//! | --- | --- |
//! | [`config`], [`presets`] | the architecture's sizes and switches; named sizes |
//! | [`params`], [`checkpoint`] | tensor registration and initialisation; the file format |
//! | [`occupancy`] | per joint, which cells of its box frame hold density (optional, saved with the model) |
//! | [`run_dir`] | a training run's directory: its complete checkpoints, the newest model |
//! | [`nn`] | linear and sine layers |
//! | [`encoders`] | 6D joint rotations, per-joint point encoders, spherical harmonics |
//! | [`gnn`] | the pose graph network over the 24 joints, box half-extents |
//! | [`window`] | spatial window w^p, feature window w^f, the max-pool over joints |
//! | [`modulator`] | pose-predicted frequencies/phases, modulated sine layers |
//! | [`field`] | NeRF density/colour heads, frame codes |
//! | [`trace`] | named intermediates for the golden comparisons |

pub mod checkpoint;
pub mod config;
pub mod encoders;
pub mod field;
pub mod gnn;
mod layers;
pub mod modulator;
pub mod nn;
pub mod occupancy;
pub mod params;
pub mod presets;
pub mod run_dir;
pub mod trace;
pub mod window;

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor, Var, D};
use candle_nn::{VarBuilder, VarMap};
use pma_data::skeleton::{self, Joints, N_JOINTS};

use crate::compute::host::host_f32;
use crate::compute::numerics::Numerics;
use crate::error::{ModelError, Result};
use config::Config;
use encoders::{pose6d, spherical_harmonics};
pub use layers::tensor_layout;
use layers::Layers;
use params::{Params, RestValues, TensorKind};
use trace::Trace;
use window::{aggregate, spatial_window};

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

/// The view features the colour head of a network call sees.
enum Heads<'a> {
    /// One row per point.
    PerPoint(&'a Tensor),
    /// One row per ray, with the point of each ray (`rows`).
    Gathered { view: &'a Tensor, rows: &'a Tensor },
    /// No colour head: the call wants the density alone.
    None,
}

/// The network's tensors and what every pass derives from them once.
pub struct Network {
    cfg: Config,
    device: Device,
    /// The dtype of every tensor (f32 unless built by [`Network::with_dtype`]).
    dtype: DType,
    varmap: VarMap,
    rest_pose: Joints,
    layers: Layers,
    /// Rotation of A_j, transposed: [24,3,3].
    align_rot_t: Tensor,
    /// Translation of A_j: [24,3].
    align_trans: Tensor,
    /// A_j on the host, [24,4,4] row-major: the culling test runs there.
    align_host: Vec<f32>,
    /// How every pass computes ([`Self::with_numerics`]).
    numerics: Numerics,
}

impl Network {
    /// Load a checkpoint for inference (or to continue training). Strict: see
    /// [`checkpoint::load`].
    pub fn load(path: impl AsRef<Path>, device: &Device) -> Result<Self> {
        let ck = checkpoint::load(path.as_ref(), device)?;
        Self::from_tensors(ck.config, ck.tensors, device)
    }

    /// A freshly initialised network for `rest_pose` with the reference's initialisation,
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
        let layers = Layers::new(&p, &cfg)?;
        checkpoint::check_buffers(&varmap_tensors(&varmap))?;
        Self::assemble(cfg, layers, varmap, DType::F32, device)
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
        let layers = Layers::new(&Params::from(vb), &cfg)?;
        Self::assemble(cfg, layers, varmap, dtype, device)
    }

    /// The host-side pieces every pass needs, derived once from the network's buffers.
    fn assemble(
        cfg: Config,
        layers: Layers,
        varmap: VarMap,
        dtype: DType,
        device: &Device,
    ) -> Result<Self> {
        let mut rest_pose = [[0f32; 3]; N_JOINTS];
        for (d, s) in rest_pose
            .iter_mut()
            .zip(host_f32(&layers.rest_pose)?.chunks_exact(3))
        {
            d.copy_from_slice(s);
        }
        let a = &layers.align;
        Ok(Self {
            align_rot_t: a
                .narrow(1, 0, 3)?
                .narrow(2, 0, 3)?
                .transpose(1, 2)?
                .contiguous()?,
            align_trans: a.narrow(1, 0, 3)?.narrow(2, 3, 1)?.reshape((N_JOINTS, 3))?,
            align_host: host_f32(a)?,
            rest_pose,
            layers,
            varmap,
            device: device.clone(),
            dtype,
            cfg,
            numerics: Numerics::default(),
        })
    }

    /// The same network computing with `numerics` (kernels, sine, TF32) in every later pass.
    pub fn with_numerics(mut self, numerics: Numerics) -> Self {
        self.numerics = numerics;
        self
    }

    /// Compute with `numerics` from the next pass on.
    pub fn set_numerics(&mut self, numerics: Numerics) {
        self.numerics = numerics;
    }

    /// The same network with every tensor converted to `dtype` (f16/bf16 inference, f64
    /// checks).
    pub fn with_dtype(&self, dtype: DType) -> Result<Self> {
        let tensors = self
            .tensors()
            .into_iter()
            .map(|(k, t)| Ok((k, t.to_dtype(dtype)?)))
            .collect::<Result<HashMap<_, _>>>()?;
        Ok(Self::from_tensors(self.cfg.clone(), tensors, &self.device)?
            .with_numerics(self.numerics))
    }

    /// Step 1, the pose-only work for every pose of the batch: 6D rotations, the GNN, its
    /// projection `layer_pose(G)`, and the effective box half-extents.
    pub fn pose_features(
        &self,
        bones: &[Joints],
        skts: &Tensor,
        trace: Option<&mut Trace>,
    ) -> Result<PoseFeatures> {
        let p = bones.len();
        if skts.dims() != [p, N_JOINTS, 4, 4] {
            return Err(ModelError::shape("skts", [p, N_JOINTS, 4, 4], skts.dims()));
        }
        let theta = pose6d(bones, &self.device)?.to_dtype(self.dtype)?;
        let scales = self.layers.gnn.axis_scale()?;
        let Some(win_fun) = &self.layers.win_fun else {
            // No GNN features (`only-syn`): an empty feature per joint keeps the pose count.
            let g = Tensor::zeros((p, N_JOINTS, 0), self.dtype, &self.device)?;
            let skts = skts.to_dtype(self.dtype)?;
            return Ok(PoseFeatures { g, skts, scales });
        };
        let mut layers = Vec::new();
        let g_feat = self
            .layers
            .gnn
            .forward(&theta, trace.is_some().then_some(&mut layers))?;
        let g = win_fun.project_pose(&g_feat, self.numerics)?;
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
            skts: skts.to_dtype(self.dtype)?,
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
        self.eval_poses(pose, p..p + 1, pts, view, trace)
    }

    /// The network on the points of the poses `poses` in one call: pts: [m·n,3] grouped by
    /// pose in equal blocks (rows `[i·n, (i+1)·n)` belong to pose `poses.start + i`), view:
    /// [m·n,V]. The per-pose pieces (world → joint transform, the GNN features g) apply to
    /// their block as batched products and broadcasts; everything else is per point. For one
    /// pose this is [`Self::eval_points`], op for op.
    pub fn eval_poses(
        &self,
        pose: &PoseFeatures,
        poses: std::ops::Range<usize>,
        pts: &Tensor,
        view: &Tensor,
        trace: Option<(&mut Trace, &str)>,
    ) -> Result<(Tensor, Tensor)> {
        self.eval_joints(pose, poses, pts, view, None, trace)
    }

    /// [`Self::eval_poses`] carrying only the joints `joints` (ascending, fewer than 24; `None`
    /// = all) through the per-joint work. Exact when every other joint's spatial window is 0
    /// at every point of the call: such a joint's windowed features are 0, so it adds nothing
    /// to f^m or to the first modulated layer, and a 0 in the max-pool, which is put back
    /// with a max against 0. The sums then skip exact zeros, so outputs may differ from
    /// [`Self::eval_poses`] in the last bits (float summation order).
    pub fn eval_joints(
        &self,
        pose: &PoseFeatures,
        poses: std::ops::Range<usize>,
        pts: &Tensor,
        view: &Tensor,
        joints: Option<&[u32]>,
        trace: Option<(&mut Trace, &str)>,
    ) -> Result<(Tensor, Tensor)> {
        self.eval_with(pose, poses, pts, Heads::PerPoint(view), joints, trace)
    }

    /// The network at one point per pose of `poses` (pts: [m,3], in pose order) seen along R
    /// rays: view: [R,V], rows: [R] (u32, the point of each ray). Everything but the colour
    /// layers runs once per point, so R rays that share a point (the culled route's far-away
    /// point of a pose) cost one point and R colour heads. Returns (rgb [R,3], sigma_raw
    /// [R,1]): what [`Self::eval_poses`] gives for each ray's point with its view.
    pub fn eval_shared(
        &self,
        pose: &PoseFeatures,
        poses: std::ops::Range<usize>,
        pts: &Tensor,
        view: &Tensor,
        rows: &Tensor,
    ) -> Result<(Tensor, Tensor)> {
        self.eval_with(pose, poses, pts, Heads::Gathered { view, rows }, None, None)
    }

    /// The density alone at the points of pose p (pts: [n,3] world points): sigma_raw [n,1],
    /// the bits [`Self::eval_points`] gives, without the colour layers (which are the cost
    /// that density does not depend on: the occupancy grid's refreshes ask for σ only).
    pub fn eval_density(&self, pose: &PoseFeatures, p: usize, pts: &Tensor) -> Result<Tensor> {
        self.eval_density_joints(pose, p, pts, None)
    }

    /// [`Self::eval_density`] carrying only the joints `joints` (see [`Self::eval_joints`]:
    /// exact up to float summation order when every other joint's window is 0 at every
    /// point).
    pub fn eval_density_joints(
        &self,
        pose: &PoseFeatures,
        p: usize,
        pts: &Tensor,
        joints: Option<&[u32]>,
    ) -> Result<Tensor> {
        Ok(self
            .eval_with(pose, p..p + 1, pts, Heads::None, joints, None)?
            .1)
    }

    /// The network at pts; returns (rgb, sigma_raw), with `Heads::None` (σ, σ).
    fn eval_with(
        &self,
        pose: &PoseFeatures,
        poses: std::ops::Range<usize>,
        pts: &Tensor,
        heads: Heads,
        joints: Option<&[u32]>,
        trace: Option<(&mut Trace, &str)>,
    ) -> Result<(Tensor, Tensor)> {
        let n = pts.dim(0)?;
        let m = poses.len();
        let sub = match joints {
            Some(js) if js.len() < N_JOINTS => {
                if js.is_empty()
                    || js.windows(2).any(|w| w[0] >= w[1])
                    || js[js.len() - 1] as usize >= N_JOINTS
                {
                    return Err(ModelError::Input(format!(
                        "network: joint subset {js:?} is not ascending, non-empty and below {N_JOINTS}"
                    )));
                }
                if trace.is_some() {
                    return Err(ModelError::Input(
                        "network: a traced call carries every joint".into(),
                    ));
                }
                Some(Tensor::from_vec(js.to_vec(), js.len(), &self.device)?)
            }
            _ => None,
        };
        let j = sub.as_ref().map_or(Ok(N_JOINTS), |s| s.dim(0))?;
        // The per-joint tensors of the joints the call carries.
        let sel = |t: &Tensor, dim: usize| -> Result<Tensor> {
            Ok(match &sub {
                Some(s) => t.index_select(s, dim)?,
                None => t.clone(),
            })
        };
        let net = &self.layers;
        let k = self.numerics;
        if m == 0 || n % m != 0 || poses.end > pose.g.dim(0)? {
            return Err(ModelError::Input(format!(
                "network: {n} points cannot be split into equal blocks of poses {poses:?} \
                 (the batch has {} poses)",
                pose.g.dim(0)?
            )));
        }
        let per_pose = n / m;
        // World → joint frames of every joint at once (one [n,3]x[3,72] product per pose),
        // then into the bone-aligned frames. Two steps, in the reference's order: folding A_j
        // into skt_j first changes the rounding enough to cost ~1e-4 after the ω=16 encoder.
        let skt = sel(&pose.skts.narrow(0, poses.start, m)?, 1)?;
        let rot = skt
            .narrow(2, 0, 3)?
            .narrow(3, 0, 3)?
            .reshape((m, 3 * j, 3))?;
        let trans = skt
            .narrow(2, 0, 3)?
            .narrow(3, 3, 1)?
            .reshape((m, 1, j, 3))?;
        let x_jt = pts
            .reshape((m, per_pose, 3))?
            .matmul(&rot.transpose(1, 2)?)?
            .reshape((m, per_pose, j, 3))?
            .broadcast_add(&trans)?
            .reshape((n, j, 3))?;
        // `contiguous`: CUDA's batched gemm needs packed rows (the CPU gemm takes any
        // strides), and the transposed [j,n,3] view has a row stride of 3j.
        let x_hat = x_jt
            .transpose(0, 1)?
            .contiguous()?
            .matmul(&sel(&self.align_rot_t, 0)?)?
            .transpose(0, 1)?
            .broadcast_add(&sel(&self.align_trans, 0)?)?;
        // Bone-normalised points x̄ and the spatial window w^p (Eq. 4).
        let x_bar = x_hat.broadcast_div(&sel(&pose.scales, 0)?)?;
        let v = self.cfg.variant;
        let w_p = match v.spatial_window() {
            true => spatial_window(&x_bar, self.cfg.window_alpha, self.cfg.window_beta)?,
            false => Tensor::ones((n, j), x_bar.dtype(), x_bar.device())?,
        };
        // Feature window w^f and w = w^p·w^f (Eqs. 5–6), then f^m = Σ_j w_j g_j, with each
        // pose's g ([m,24,H]) applied to its block of points.
        let g = sel(&pose.g.narrow(0, poses.start, m)?, 1)?;
        let (win, e) = match (&net.win_fun, &net.pts_enc_pose) {
            (Some(win_fun), Some(enc)) if v.feature_window() => {
                let e = enc.forward(&x_bar, k)?;
                (
                    Some(win_fun.forward(&g, &e, &w_p, sub.as_ref(), k)?),
                    Some(e),
                )
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
            (Some(ext), Some(f_m)) => Some(ext.forward(f_m, k)?),
            _ => None,
        };
        let (s, z) = match (&net.modulator, &net.pts_enc_point) {
            (Some(modulator), Some(enc)) => {
                // A trace keeps z; otherwise the weighting is part of the encoder's op.
                let (z, x_tilde) = match trace.is_some() {
                    true => {
                        let z = enc.forward(&x_bar, k)?;
                        let x_tilde = z.broadcast_mul(&w.unsqueeze(D::Minus1)?)?;
                        (Some(z), x_tilde)
                    }
                    false => (None, enc.forward_weighted(&x_bar, &w, k)?),
                };
                let x_tilde = x_tilde.reshape((n, j * self.cfg.point_enc_dim))?;
                let s = match &modulation {
                    Some(m) => modulator.forward(&x_tilde, m, sub.as_ref(), k)?,
                    None => modulator.forward_fixed(&x_tilde, sub.as_ref(), k)?,
                };
                (s, z)
            }
            _ => (
                f_m.clone()
                    .ok_or_else(|| ModelError::Config("no trunk input".into()))?,
                None,
            ),
        };
        // NeRF density and colour heads.
        let view = match heads {
            Heads::PerPoint(view) => view,
            Heads::Gathered { view, rows } => {
                return net.field.forward_gathered(&s, view, rows, k);
            }
            Heads::None => {
                let sigma = net.field.density(&s, k)?;
                return Ok((sigma.clone(), sigma));
            }
        };
        let out = net.field.forward(&s, view, k, trace.is_some())?;
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
                out.l0_pre.as_ref().map(|t| ("density_l0_pre_relu", t)),
                Some(("density_feat", &out.feature)),
                Some(("sigma_raw", &out.sigma_raw)),
                Some(("feature_linear", &out.feature_linear)),
                out.view_pre.as_ref().map(|t| ("view_l0_pre_relu", t)),
                Some(("rgb_logits", &out.rgb_logits)),
            ]
            .into_iter()
            .flatten()
            .collect();
            tr.put_stage(stage, &items);
        }
        Ok((out.rgb, out.sigma_raw))
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
        Ok(match &self.layers.framecodes {
            Some(codes) => {
                let code = codes.lookup(framecodes, training, self.numerics)?;
                Tensor::cat(&[&sh, &code], 1)?
            }
            None => sh,
        })
    }

    // ---- accessors ----------------------------------------------------------------------

    pub fn config(&self) -> &Config {
        &self.cfg
    }

    /// How the network computes.
    pub fn numerics(&self) -> Numerics {
        self.numerics
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

    /// A_j of the network's bone-aligned frames on the host, [24,4,4] row-major.
    pub fn bone_align(&self) -> &[f32] {
        &self.align_host
    }

    /// Effective box half-extents s: [24,3].
    pub fn axis_scale(&self) -> Result<Tensor> {
        self.layers.gnn.axis_scale()
    }

    /// A_j of the ray caster's boxes (`raycast.transforms`): [24,4,4].
    pub fn raycast_align(&self) -> &Tensor {
        &self.layers.raycast_align
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

impl std::fmt::Debug for Network {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Network")
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

/// The tensors of a fresh network ([`Network::new`]) by name.
pub fn init_tensors(
    cfg: &Config,
    rest: &Joints,
    seed: u64,
    device: &Device,
) -> Result<HashMap<String, Tensor>> {
    Ok(Network::new(cfg.clone(), rest, seed, device)?.tensors())
}
