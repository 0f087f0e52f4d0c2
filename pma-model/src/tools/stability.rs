//! Numerical-stability probes (docs/numerics.md): drive an avatar through the hard cases
//! and measure what comes out.
//!
//! Each probe returns [`ProbeRow`]s: the largest finite |output|, how many outputs or
//! gradient entries are not finite, the gradient norm, and how many invariants broke
//! (weights outside [0,1], far < near, unsorted importance samples, a ray whose bounds depend
//! on the rest of its batch). `pma check-stability` prints them; the `stability_*` tests
//! assert on them. Nothing here changes the avatar.
//!
//! The forward probes take the pass's [`PassOptions`] ([`ProbeOptions::pass`]), so a model with
//! an occupancy grid is probed on the route it renders and trains with. Such a pass cannot be
//! traced (the trace needs every sample's intermediates), so the hidden-value check then runs
//! on a separate parity forward of the same rays.

use std::collections::HashMap;

use candle_core::{DType, Tensor, Var};
use pma_data::skeleton::{self, Joints, N_JOINTS};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::compute::host::host_f32 as host32;
use crate::error::{ModelError, Result};
use crate::network::config::Config;
use crate::render::avatar::{Avatar, Mode, Outputs, PassOptions, Poses, Rays, Trace};
use crate::render::bones::BoneFrames;
use crate::render::raycast::RayCaster;
use crate::render::volume::raw2outputs;

/// One line of the stability table.
#[derive(Debug, Clone, PartialEq)]
pub struct ProbeRow {
    pub case: String,
    /// Largest |value| among the finite outputs of the case.
    pub max_abs: f64,
    /// Outputs and gradient entries that are NaN or ±inf.
    pub non_finite: usize,
    /// L2 norm of the gradient of a training-like loss over every parameter (finite entries
    /// only); `None` where the case takes no gradient.
    pub grad_norm: Option<f64>,
    /// Broken invariants (see the module docs).
    pub violations: usize,
    /// Samples of the probed forward pass (0 for probes without one).
    pub samples: u64,
    /// Samples the occupancy grid left out; `None` where the probe did not consult a grid.
    pub skipped_empty: Option<u64>,
}

/// All rows of a run.
#[derive(Debug, Clone, Default)]
pub struct Report {
    pub rows: Vec<ProbeRow>,
}

impl Report {
    /// Total non-finite values over all cases.
    pub fn non_finite(&self) -> usize {
        self.rows.iter().map(|r| r.non_finite).sum()
    }

    /// Total broken invariants over all cases.
    pub fn violations(&self) -> usize {
        self.rows.iter().map(|r| r.violations).sum()
    }

    /// The table as printed by `pma check-stability`.
    pub fn table(&self) -> String {
        let w = self
            .rows
            .iter()
            .map(|r| r.case.len())
            .max()
            .unwrap_or(4)
            .max(4);
        // The column only appears when some probe consulted a grid, so a parity run prints
        // the table it always printed.
        let grid = self.rows.iter().any(|r| r.skipped_empty.is_some());
        let mut s = format!(
            "{:<w$}  {:>12}  {:>10}  {:>12}  {:>10}",
            "case", "max |output|", "non-finite", "grad norm", "violations"
        );
        if grid {
            s += &format!("  {:>15}", "skipped (empty)");
        }
        s += "\n";
        for r in &self.rows {
            let g = r.grad_norm.map_or("-".to_string(), |g| format!("{g:.3e}"));
            s += &format!(
                "{:<w$}  {:>12.3e}  {:>10}  {:>12}  {:>10}",
                r.case, r.max_abs, r.non_finite, g, r.violations
            );
            if grid {
                let k = r
                    .skipped_empty
                    .map_or("-".to_string(), |k| format!("{k} / {}", r.samples));
                s += &format!("  {k:>15}");
            }
            s += "\n";
        }
        s
    }

    /// Probes whose forward pass consulted the occupancy grid, and all probes with a forward
    /// pass.
    pub fn grid_probes(&self) -> (usize, usize) {
        let forward = self.rows.iter().filter(|r| r.samples > 0);
        let on = forward
            .clone()
            .filter(|r| r.skipped_empty.is_some())
            .count();
        (on, forward.count())
    }

    /// Samples the grid left out and samples of the probes that consulted it.
    pub fn grid_skipped(&self) -> (u64, u64) {
        self.rows
            .iter()
            .filter_map(|r| r.skipped_empty.map(|k| (k, r.samples)))
            .fold((0, 0), |(a, b), (k, n)| (a + k, b + n))
    }

    /// One line on how the forward probes ran: parity, or with the grid and what it skipped.
    pub fn pass_summary(&self) -> String {
        let (on, forward) = self.grid_probes();
        if on == 0 {
            return format!("occupancy grid: off ({forward} forward probes at parity)");
        }
        let (skipped, samples) = self.grid_skipped();
        format!(
            "occupancy grid: on in {on} of {forward} forward probes; {skipped} of {samples} \
             samples skipped as empty (hidden values checked on a parity pass of the same rays)"
        )
    }
}

/// Largest finite |x| and the count of non-finite values over `ts`.
pub fn tensor_stats(ts: &[&Tensor]) -> Result<(f64, usize)> {
    let mut max_abs = 0f64;
    let mut bad = 0usize;
    for t in ts {
        for v in t.flatten_all()?.to_dtype(DType::F64)?.to_vec1::<f64>()? {
            if v.is_finite() {
                max_abs = max_abs.max(v.abs());
            } else {
                bad += 1;
            }
        }
    }
    Ok((max_abs, bad))
}

/// Named extreme poses: exact and near-π rotations of every joint, axis-angle vectors near 0
/// and near 2π, the head turned backwards, interpenetrating limbs, random angles up to π, and
/// the most extreme frames of the AIST++ dance (embedded in pma-data).
pub fn extreme_poses() -> Result<Vec<(String, Joints)>> {
    use std::f32::consts::PI;
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let unit = |rng: &mut ChaCha8Rng| -> [f32; 3] {
        loop {
            let v: [f32; 3] = [
                rng.gen_range(-1.0..1.0),
                rng.gen_range(-1.0..1.0),
                rng.gen_range(-1.0..1.0),
            ];
            let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            if n > 0.1 && n <= 1.0 {
                return [v[0] / n, v[1] / n, v[2] / n];
            }
        }
    };
    let scaled = |a: [f32; 3], s: f32| [a[0] * s, a[1] * s, a[2] * s];
    let mut out: Vec<(String, Joints)> =
        vec![("rest (zero rotations)".into(), [[0.0; 3]; N_JOINTS])];
    out.push(("every joint pi about x".into(), [[PI, 0.0, 0.0]; N_JOINTS]));
    let d = PI / 3f32.sqrt();
    out.push(("every joint pi about (1,1,1)".into(), [[d, d, d]; N_JOINTS]));
    let mut pose = [[0.0; 3]; N_JOINTS];
    for w in pose.iter_mut() {
        *w = scaled(unit(&mut rng), PI * (1.0 - 1e-7));
    }
    out.push(("every joint pi-1e-7, random axes".into(), pose));
    for (name, angle) in [
        ("axis-angle 1e-9", 1e-9f32),
        ("axis-angle 2pi-1e-6", 2.0 * PI - 1e-6),
        ("axis-angle 2pi", 2.0 * PI),
    ] {
        let mut pose = [[0.0; 3]; N_JOINTS];
        for w in pose.iter_mut() {
            *w = scaled(unit(&mut rng), angle);
        }
        out.push((name.into(), pose));
    }
    for k in 0..2 {
        let mut pose = [[0.0; 3]; N_JOINTS];
        for w in pose.iter_mut() {
            let a = rng.gen_range(0.0..=PI);
            *w = scaled(unit(&mut rng), a);
        }
        out.push((format!("random angles up to pi #{k}"), pose));
    }
    let mut head = [[0.0; 3]; N_JOINTS];
    head[12] = [0.0, PI, 0.0];
    out.push(("head turned backwards".into(), head));
    let mut tangle = [[0.0; 3]; N_JOINTS];
    // Legs crossed through each other, knees and elbows folded past their range, arms swung
    // through the torso.
    tangle[1] = [0.0, 0.0, 0.6];
    tangle[2] = [0.0, 0.0, -0.6];
    tangle[4] = [2.9, 0.0, 0.0];
    tangle[5] = [2.9, 0.0, 0.0];
    tangle[16] = [0.0, 2.6, 0.0];
    tangle[17] = [0.0, -2.6, 0.0];
    tangle[18] = [0.0, 2.9, 0.0];
    tangle[19] = [0.0, -2.9, 0.0];
    out.push(("limbs interpenetrating".into(), tangle));
    out.extend(aist_extremes(3)?);
    Ok(out)
}

/// The `n` AIST++ dance frames with the largest single non-root joint rotation.
pub fn aist_extremes(n: usize) -> Result<Vec<(String, Joints)>> {
    let motion =
        pma_data::synth::dance_motion().map_err(|e| ModelError::Input(format!("AIST++: {e}")))?;
    let angle = |w: &[f32; 3]| (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt();
    let mut frames: Vec<(f32, usize)> = motion
        .bones
        .iter()
        .enumerate()
        .map(|(f, b)| (b[1..].iter().map(angle).fold(0.0, f32::max), f))
        .collect();
    frames.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    Ok(frames
        .into_iter()
        .take(n)
        .map(|(a, f)| {
            (
                format!("AIST++ frame {f} (max joint {:.0} deg)", a.to_degrees()),
                motion.bones[f],
            )
        })
        .collect())
}

/// Probe rays of one posed body: rays aimed at several joints from axis-aligned, vertical and
/// diagonal directions, a ray from inside the pelvis, a ray that misses everything and one
/// pointing away from the body. Returns host (origins, dirs), [R,3] each.
pub fn probe_rays(kp3d: &Joints) -> (Vec<f32>, Vec<f32>) {
    let dirs: [[f32; 3]; 8] = [
        [0.0, 0.0, -1.0],
        [-1.0, 0.0, 0.0],
        [0.0, -1.0, 0.0],
        [0.0, 1.0, 0.0],
        [-0.577_350_26, -0.577_350_26, -0.577_350_26],
        [0.6, 0.0, -0.8],
        [0.0, 0.8, 0.6],
        [1.0, 0.0, 0.0],
    ];
    let targets = [0usize, 4, 7, 12, 15, 18, 20, 22];
    let mut o = Vec::new();
    let mut d = Vec::new();
    for (&j, dir) in targets.iter().zip(&dirs) {
        let p = kp3d[j];
        o.extend((0..3).map(|k| p[k] - 2.5 * dir[k]));
        d.extend_from_slice(dir);
    }
    // Inside the body, looking forward.
    o.extend_from_slice(&kp3d[0]);
    d.extend_from_slice(&[0.0, 0.0, 1.0]);
    // Far away, looking further away: misses the cylinder and every box.
    o.extend_from_slice(&[kp3d[0][0] + 20.0, kp3d[0][1], kp3d[0][2] + 20.0]);
    d.extend_from_slice(&[0.707_106_77, 0.0, 0.707_106_77]);
    // Outside the cylinder, facing away from it: the circle lies behind the camera.
    o.extend_from_slice(&[kp3d[0][0], kp3d[0][1], kp3d[0][2] + 3.0]);
    d.extend_from_slice(&[0.0, 0.0, 1.0]);
    // Grazing along the body's vertical axis.
    o.extend_from_slice(&[kp3d[0][0], kp3d[0][1] - 3.0, kp3d[0][2]]);
    d.extend_from_slice(&[0.0, 1.0, 0.0]);
    (o, d)
}

/// A training-like forward and backward on the probe rays of `bones` (root at the origin):
/// training mode without noise, loss = L1 of both renders against grey + 1e-3·Σ box volumes.
pub fn probe_pose(avatar: &Avatar, case: &str, bones: &Joints) -> Result<ProbeRow> {
    probe_pose_with(avatar, case, bones, &PassOptions::parity())
}

/// [`probe_pose`] with the forward pass run under `pass` (e.g. with the occupancy grid on).
pub fn probe_pose_with(
    avatar: &Avatar,
    case: &str,
    bones: &Joints,
    pass: &PassOptions,
) -> Result<ProbeRow> {
    let (poses, kp3d) = avatar.pose_from_bones(bones, [0.0; 3])?;
    let (o, d) = probe_rays(&kp3d);
    forward_backward_with(avatar, case, &poses, &o, &d, pass)
}

/// [`probe_pose`] on given host rays: origins, dirs [R,3].
pub fn forward_backward(
    avatar: &Avatar,
    case: &str,
    poses: &Poses,
    origins: &[f32],
    dirs: &[f32],
) -> Result<ProbeRow> {
    forward_backward_with(avatar, case, poses, origins, dirs, &PassOptions::parity())
}

/// [`forward_backward`] with the pass run under `pass`.
pub fn forward_backward_with(
    avatar: &Avatar,
    case: &str,
    poses: &Poses,
    origins: &[f32],
    dirs: &[f32],
    pass: &PassOptions,
) -> Result<ProbeRow> {
    pass.validate(avatar.config())?;
    let dev = avatar.device();
    let r = origins.len() / 3;
    let rays = Rays {
        origins: Tensor::from_vec(origins.to_vec(), (r, 3), dev)?,
        dirs: Tensor::from_vec(dirs.to_vec(), (r, 3), dev)?,
        bgs: None,
        framecodes: vec![0; r],
    };
    // Every intermediate is traced and counted: candle's ReLU maps NaN to 0, so a NaN density
    // head would otherwise render as empty space without a trace in the outputs.
    let mut trace = Trace::default();
    let out = if pass.is_parity() {
        avatar.forward(&rays, poses, &mut Mode::Train(None), pass, Some(&mut trace))?
    } else {
        // A traced pass takes every sample, so it cannot show the pass under test; trace a
        // parity pass of the same rays for the hidden values and probe the real one.
        let parity = PassOptions::parity();
        avatar.forward(
            &rays,
            poses,
            &mut Mode::Train(None),
            &parity,
            Some(&mut trace),
        )?;
        avatar.forward(&rays, poses, &mut Mode::Train(None), pass, None)?
    };
    let loss = training_like_loss(&out)?;
    let grads = loss.backward()?;
    let (grad_norm, grad_bad) = grad_norm(avatar, &grads)?;
    let fine = &out.fine;
    let (_, hidden) = tensor_stats(&trace.tensors.values().collect::<Vec<_>>())?;
    let (max_abs, bad) = tensor_stats(&[
        &fine.rgb,
        &fine.acc,
        &fine.disp,
        &fine.weights,
        &out.coarse.rgb,
        &out.raw,
        &loss,
    ])?;
    let mut violations = weight_violations(&fine.weights, &fine.acc)?
        + weight_violations(&out.coarse.weights, &out.coarse.acc)?;
    let (skts, scales) = (host32(&poses.skts)?, host32(&out.vol_scale)?);
    // Rays cast on a GPU have no host bounds: cast them again on the host.
    let bounds = match &out.bounds {
        Some(b) => b.clone(),
        None => {
            let cyls = host32(&poses.cyls)?;
            avatar
                .ray_caster()
                .near_far(origins, dirs, &cyls, &skts, &scales)?
        }
    };
    violations += bound_violations(avatar, origins, dirs, &bounds, &skts, &scales);
    Ok(ProbeRow {
        case: case.to_string(),
        max_abs,
        non_finite: bad + grad_bad + hidden,
        grad_norm: Some(grad_norm),
        violations,
        samples: out.stats.samples,
        skipped_empty: pass.occupancy.then_some(out.stats.skipped_empty),
    })
}

fn training_like_loss(out: &Outputs) -> Result<Tensor> {
    let fine = out.fine.rgb.affine(1.0, -0.5)?.abs()?.mean_all()?;
    let coarse = out.coarse.rgb.affine(1.0, -0.5)?.abs()?.mean_all()?;
    let s = &out.vol_scale;
    let volume = ((s.narrow(1, 0, 1)? * s.narrow(1, 1, 1)?)? * s.narrow(1, 2, 1)?)?.sum_all()?;
    let loss = ((fine + coarse)? + (volume * 1e-3)?)?;
    Ok(loss.to_dtype(DType::F32)?)
}

/// L2 norm over the finite gradient entries of every parameter, and the count of the others.
pub fn grad_norm(
    avatar: &Avatar,
    grads: &candle_core::backprop::GradStore,
) -> Result<(f64, usize)> {
    let mut sq = 0f64;
    let mut bad = 0usize;
    for (_, v) in avatar.trainable() {
        if let Some(g) = grads.get(v.as_tensor()) {
            for x in g.flatten_all()?.to_dtype(DType::F64)?.to_vec1::<f64>()? {
                if x.is_finite() {
                    sq += x * x;
                } else {
                    bad += 1;
                }
            }
        }
    }
    Ok((sq.sqrt(), bad))
}

/// Weights or accumulated opacity outside [0, 1] (beyond rounding).
fn weight_violations(weights: &Tensor, acc: &Tensor) -> Result<usize> {
    let tol = 1e-5;
    let (w, a) = (host64(weights)?, host64(acc)?);
    Ok(w.iter()
        .chain(&a)
        .filter(|&&x| x.is_finite() && !(-tol..=1.0 + tol).contains(&x))
        .count())
}

fn host64(t: &Tensor) -> Result<Vec<f64>> {
    Ok(t.flatten_all()?.to_dtype(DType::F64)?.to_vec1::<f64>()?)
}

/// The avatar's tensors with the pose extractor's frequency head replaced by constants, so
/// every modulated layer runs at frequency `gamma` (its weights zeroed, its bias set).
pub fn with_constant_gamma(avatar: &Avatar, gamma: f64) -> Result<Avatar> {
    let cfg = avatar.config().clone();
    let mut tensors = avatar.tensors();
    let head = format!("pose_extractor.sin_lin{}.layer", cfg.pose_extractor_depth);
    let n_freq = cfg.n_pm * cfg.freq_dim;
    let w0 = cfg.sin_w0_point;
    // Invert the modulator's γ(Θ) map (15Θ + 30 for ω > 15, ωΘ + 2ω otherwise).
    let theta = if w0 > 15.0 {
        (gamma - 30.0) / 15.0
    } else {
        (gamma - 2.0 * w0) / w0
    };
    let w = tensors[&format!("{head}.weight")].to_dtype(DType::F32)?;
    let mut wv = w.flatten_all()?.to_vec1::<f32>()?;
    let fan_in = w.dim(1)?;
    wv[..n_freq * fan_in].iter_mut().for_each(|x| *x = 0.0);
    let b = tensors[&format!("{head}.bias")].to_dtype(DType::F32)?;
    let mut bv = b.to_vec1::<f32>()?;
    bv[..n_freq].iter_mut().for_each(|x| *x = theta as f32);
    let (dev, dt) = (avatar.device(), avatar.dtype());
    tensors.insert(
        format!("{head}.weight"),
        Tensor::from_vec(wv, w.shape(), dev)?.to_dtype(dt)?,
    );
    tensors.insert(
        format!("{head}.bias"),
        Tensor::from_vec(bv, b.shape(), dev)?.to_dtype(dt)?,
    );
    Ok(Avatar::from_tensors(cfg, tensors, dev)?.with_occupancy(avatar.occupancy().cloned()))
}

/// The avatar with the raw axis-scale parameter set to `factor × base_scale` (0 or negative
/// values put every box at the straight-through floor).
pub fn with_axis_scale(avatar: &Avatar, factor: f64) -> Result<Avatar> {
    let mut tensors = avatar.tensors();
    let base = tensors["graph_net.base_scale"].clone();
    tensors.insert("graph_net.axis_scale".into(), (base * factor)?);
    Ok(
        Avatar::from_tensors(avatar.config().clone(), tensors, avatar.device())?
            .with_occupancy(avatar.occupancy().cloned()),
    )
}

/// Volume rendering on stiff inputs: for every interval length δ in 1e-7..1e10, rays with
/// densities 0..1e6 (one ray per density), plus rays with all weight on one sample and rays
/// with no density at all. Checks weights and opacity in [0,1], monotone transmittance,
/// finite gradients w.r.t. the raw outputs, and sorted in-range importance samples.
pub fn probe_compositing(cfg: &Config) -> Result<Vec<ProbeRow>> {
    let m = cfg.n_samples;
    let caster = RayCaster::new(cfg, &identity_transforms())?;
    let sigmas = [0.0f32, 1e-6, 1e-2, 1.0, 1e3, 1e6];
    let mut rows = Vec::new();
    let mut cases: Vec<(String, Vec<f32>, Vec<f32>)> = Vec::new();
    for delta in [1e-7f32, 1e-3, 1.0, 1e3, 1e10] {
        let z: Vec<f32> = (0..m).map(|k| 1.0 + delta * k as f32).collect();
        let mut raw = Vec::new();
        for &s in &sigmas {
            for k in 0..m {
                raw.extend_from_slice(&[0.2, 0.5, 0.9 * (k % 2) as f32, s]);
            }
        }
        let zs = z.repeat(sigmas.len());
        cases.push((
            format!("composite delta {delta:.0e}, sigma 0..1e6"),
            raw,
            zs,
        ));
    }
    let z: Vec<f32> = (0..m).map(|k| 2.0 + 0.05 * k as f32).collect();
    let mut one_hot = Vec::new();
    for hot in 0..m {
        for k in 0..m {
            let s = if k == hot { 1e6 } else { 0.0 };
            one_hot.extend_from_slice(&[1.0, 0.0, 0.5, s]);
        }
    }
    cases.push((
        "composite all weight on one sample".into(),
        one_hot,
        z.repeat(m),
    ));
    let zero: Vec<f32> = (0..m).flat_map(|_| [0.3, 0.3, 0.3, 0.0]).collect();
    cases.push(("composite all-zero density".into(), zero, z.clone()));

    for (case, raw, z) in cases {
        let r = z.len() / m;
        let raw_v = Var::from_tensor(&Tensor::from_vec(
            raw,
            (r, m, 4),
            &candle_core::Device::Cpu,
        )?)?;
        let z_t = Tensor::from_vec(z.clone(), (r, m), &candle_core::Device::Cpu)?;
        let d_t = Tensor::from_vec(
            [0.0f32, 0.0, 1.0].repeat(r),
            (r, 3),
            &candle_core::Device::Cpu,
        )?;
        let bg = Tensor::full(0.5f32, (r, 3), &candle_core::Device::Cpu)?;
        let out = raw2outputs(raw_v.as_tensor(), &z_t, &d_t, Some(&bg))?;
        let loss = ((out.rgb.sum_all()? + out.acc.sum_all()?)? + out.weights.sum_all()?)?;
        let grads = loss.backward()?;
        let g = grads
            .get(raw_v.as_tensor())
            .cloned()
            .unwrap_or(raw_v.as_tensor().zeros_like()?);
        let (g_max, g_bad) = tensor_stats(&[&g])?;
        let _ = g_max;
        let gn = host64(&g)?
            .iter()
            .filter(|x| x.is_finite())
            .map(|x| x * x)
            .sum::<f64>()
            .sqrt();
        let (max_abs, bad) = tensor_stats(&[&out.rgb, &out.acc, &out.weights, &out.transmittance])?;
        let mut violations = weight_violations(&out.weights, &out.acc)?;
        let rgb = host64(&out.rgb)?;
        violations += rgb
            .iter()
            .filter(|&&x| !(-0.001 - 1e-5..=1.001 + 1e-5).contains(&x))
            .count();
        let t = host64(&out.transmittance)?;
        for row in t.chunks_exact(m) {
            violations += row
                .windows(2)
                .filter(|w| w[1] > w[0] * (1.0 + 1e-6) + 1e-30)
                .count();
            violations += row
                .iter()
                .filter(|&&x| !(0.0..=1.0 + 1e-6).contains(&x))
                .count();
        }
        // Importance sampling on these weights: sorted, inside the coarse span, finite.
        let w = out.weights.flatten_all()?.to_vec1::<f32>()?;
        let zi = caster.importance_z(&z, &w, None)?;
        let sf = caster.n_importance();
        let mut is_bad = 0usize;
        for (zr, zc) in zi.chunks_exact(sf).zip(z.chunks_exact(m)) {
            let (lo, hi) = (zc[0], zc[m - 1]);
            is_bad += zr
                .iter()
                .filter(|&&x| !(x.is_finite() && x >= lo && x <= hi))
                .count();
            is_bad += zr.windows(2).filter(|p| p[1] < p[0]).count();
        }
        rows.push(ProbeRow {
            case,
            max_abs,
            non_finite: bad + g_bad,
            grad_norm: Some(gn),
            violations: violations + is_bad,
            samples: 0,
            skipped_empty: None,
        });
    }
    Ok(rows)
}

fn identity_transforms() -> Vec<f32> {
    let mut t = vec![0f32; N_JOINTS * 16];
    for j in 0..N_JOINTS {
        for k in 0..4 {
            t[j * 16 + 5 * k] = 1.0;
        }
    }
    t
}

/// Hard rays for the ray caster on one posed body: rays parallel to a box's faces (lying in a
/// face plane), along a box edge, through a box corner, starting at a box centre, vertical
/// rays, rays missing everything and rays facing away from the cylinder. Returns host
/// (origins, dirs) [R,3].
pub fn geometry_rays(
    avatar: &Avatar,
    kp3d: &Joints,
    skts: &[f32],
    scales: &[f32],
) -> (Vec<f32>, Vec<f32>) {
    let a = avatar.ray_caster().bone_align();
    let bound = avatar.config().box_bound as f32;
    let mut o = Vec::new();
    let mut d = Vec::new();
    let mut push = |oo: [f32; 3], dd: [f32; 3]| {
        o.extend_from_slice(&oo);
        d.extend_from_slice(&dd);
    };
    for j in [0usize, 4, 9, 15, 18] {
        // World → box: M = A_j·skt_j (rigid), box point b = R·x + t, x = Rᵀ(b − t).
        let m = crate::render::bones::mat4_mul(&a[j * 16..j * 16 + 16], &skts[j * 16..j * 16 + 16]);
        let r = |i: usize, k: usize| m[4 * i + k];
        let to_world = |b: [f32; 3]| -> [f32; 3] {
            let c = [b[0] - m[3], b[1] - m[7], b[2] - m[11]];
            [0, 1, 2].map(|k| r(0, k) * c[0] + r(1, k) * c[1] + r(2, k) * c[2])
        };
        let axis = |i: usize| [r(i, 0), r(i, 1), r(i, 2)];
        let s = [scales[3 * j], scales[3 * j + 1], scales[3 * j + 2]];
        let f = [bound * s[0], bound * s[1], bound * s[2]];
        // In a face plane (x = +face), running along z.
        push(to_world([f[0], 0.0, -3.0 * f[2]]), axis(2));
        // Along an edge (x = +face, y = +face).
        push(to_world([f[0], f[1], -3.0 * f[2]]), axis(2));
        // Through two opposite corners.
        let diag = {
            let v = [2.0 * f[0], 2.0 * f[1], 2.0 * f[2]];
            let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            let b = [v[0] / n, v[1] / n, v[2] / n];
            let w = to_world([0.0; 3]);
            let e = to_world(b);
            [e[0] - w[0], e[1] - w[1], e[2] - w[2]]
        };
        push(to_world([-2.0 * f[0], -2.0 * f[1], -2.0 * f[2]]), diag);
        // Starting at the box centre.
        push(to_world([0.0; 3]), [0.0, 0.0, 1.0]);
    }
    let c = kp3d[0];
    push([c[0], c[1] + 3.0, c[2]], [0.0, -1.0, 0.0]);
    push([c[0] + 0.05, c[1] - 3.0, c[2]], [0.0, 1.0, 0.0]);
    push([c[0] + 30.0, c[1], c[2]], [1.0, 0.0, 0.0]);
    push([c[0], c[1], c[2] + 3.0], [0.0, 0.0, 1.0]);
    push([c[0] + 2.0, c[1], c[2] - 3.0], [0.0, 0.6, 0.8]);
    (o, d)
}

/// Ray bounds on [`geometry_rays`]: near ≤ far and finite for every ray, and each ray's bounds
/// the same alone as in the batch (the reference's batch-mean fallback for cylinder misses
/// breaks the latter; `quirks.per_ray_cylinder_fallback` fixes it).
pub fn probe_geometry(avatar: &Avatar, bones: &Joints) -> Result<ProbeRow> {
    let (poses, kp3d) = avatar.pose_from_bones(bones, [0.0; 3])?;
    let skts = host32(&poses.skts)?;
    let cyls = host32(&poses.cyls)?;
    let scales = host32(&avatar.axis_scale()?)?;
    let (o, d) = geometry_rays(avatar, &kp3d, &skts, &scales);
    let caster = avatar.ray_caster();
    let all = caster.near_far(&o, &d, &cyls, &skts, &scales)?;
    let mut violations = bound_violations(avatar, &o, &d, &all, &skts, &scales);
    let mut bad = 0;
    let mut max_abs = 0f64;
    for (n, f) in all.near.iter().zip(&all.far) {
        if !(n.is_finite() && f.is_finite()) {
            bad += 1;
        } else {
            max_abs = max_abs.max(n.abs().max(f.abs()) as f64);
        }
    }
    for r in 0..all.near.len() {
        let alone = caster.near_far(
            &o[3 * r..3 * r + 3],
            &d[3 * r..3 * r + 3],
            &cyls,
            &skts,
            &scales,
        )?;
        let same = |a: f32, b: f32| a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan());
        if !(same(alone.near[0], all.near[r]) && same(alone.far[0], all.far[r])) {
            violations += 1;
        }
    }
    Ok(ProbeRow {
        case: "ray bounds: faces, edges, corners, inside, vertical, misses".into(),
        max_abs,
        non_finite: bad,
        grad_norm: None,
        violations,
        samples: 0,
        skipped_empty: None,
    })
}

/// Rays whose bounds are unusable: non-finite, near > far, near < 0, or (for rays that cross
/// the body) a near or far point that lies on no box. The last catches the reference's
/// unsigned crossings, which mirror a box behind the camera to the front.
pub fn bound_violations(
    avatar: &Avatar,
    origins: &[f32],
    dirs: &[f32],
    b: &crate::render::raycast::RayBounds,
    skts: &[f32],
    scales: &[f32],
) -> usize {
    let Ok(frames) = BoneFrames::new(avatar.ray_caster().bone_align(), skts) else {
        // No pose to test against: every ray that claims to cross the body is wrong.
        return b.ray_hits_body.iter().filter(|&&h| h).count();
    };
    let bound = avatar.config().box_bound as f32;
    let n_rays = b.near.len();
    let per_pose = (n_rays / frames.n_poses()).max(1);
    let on_a_box = |p: [f32; 3], pose: usize| {
        (0..N_JOINTS).any(|j| {
            let m = frames.world_to_box(pose, j);
            (0..3).all(|i| {
                let x = m[4 * i] * p[0] + m[4 * i + 1] * p[1] + m[4 * i + 2] * p[2] + m[4 * i + 3];
                (x / scales[3 * j + i]).abs() <= bound * 1.001 + 1e-4
            })
        })
    };
    (0..n_rays)
        .filter(|&r| {
            let (n, f) = (b.near[r], b.far[r]);
            if !(n.is_finite() && f.is_finite() && n <= f && n >= 0.0) {
                return true;
            }
            if !b.ray_hits_body[r] {
                return false;
            }
            let at = |t: f32| [0, 1, 2].map(|k| origins[3 * r + k] + t * dirs[3 * r + k]);
            !(on_a_box(at(n), r / per_pose) && on_a_box(at(f), r / per_pose))
        })
        .count()
}

/// Which probes [`run_all`] runs.
#[derive(Debug, Clone)]
pub struct ProbeOptions {
    /// Frequencies γ forced onto every modulated layer.
    pub gammas: Vec<f64>,
    /// Raw axis-scale factors (× base scale) for the floor probes.
    pub scale_factors: Vec<f64>,
    /// Options of every probed forward pass (parity by default; `occupancy` for a model with
    /// a grid, so the probes see the samples it leaves out).
    pub pass: PassOptions,
}

impl Default for ProbeOptions {
    fn default() -> Self {
        Self {
            gammas: vec![-1e4, 0.0, 1e2, 1e3, 1e4],
            scale_factors: vec![0.0, -1e-3, 1e-30],
            pass: PassOptions::parity(),
        }
    }
}

/// Number of rows [`run_all`] produces with `opts` (for progress bars).
pub fn case_count(opts: &ProbeOptions) -> Result<usize> {
    Ok(extreme_poses()?.len() + opts.gammas.len() + opts.scale_factors.len() + 7 + 2)
}

/// Every probe on `avatar`: extreme poses, large frequencies, scales at the floor, stiff
/// compositing and ray geometry. `progress` is called after each case.
pub fn run_all(
    avatar: &Avatar,
    opts: &ProbeOptions,
    progress: &mut dyn FnMut(&ProbeRow),
) -> Result<Report> {
    opts.pass.validate(avatar.config())?;
    if opts.pass.occupancy && avatar.occupancy().is_none() {
        return Err(ModelError::Input(
            "occupancy: the model has no occupancy grid (train with `--occupancy` or build one \
             with `pma occupancy build`)"
                .into(),
        ));
    }
    let mut report = Report::default();
    let mut add = |row: ProbeRow, report: &mut Report| {
        progress(&row);
        report.rows.push(row);
    };
    let poses = extreme_poses()?;
    for (name, bones) in &poses {
        add(
            probe_pose_with(avatar, &format!("pose: {name}"), bones, &opts.pass)?,
            &mut report,
        );
    }
    let hard = &poses[1].1;
    for &g in &opts.gammas {
        let a = with_constant_gamma(avatar, g)?;
        add(
            probe_pose_with(
                &a,
                &format!("gamma {g:.0e}, every joint pi"),
                hard,
                &opts.pass,
            )?,
            &mut report,
        );
    }
    for &f in &opts.scale_factors {
        let a = with_axis_scale(avatar, f)?;
        add(
            probe_pose_with(
                &a,
                &format!("axis scale {f:e} x base (floor)"),
                hard,
                &opts.pass,
            )?,
            &mut report,
        );
    }
    for row in probe_compositing(avatar.config())? {
        add(row, &mut report);
    }
    for (name, bones) in [&poses[0], &poses[1]] {
        let mut row = probe_geometry(avatar, bones)?;
        row.case = format!("{} ({name})", row.case);
        add(row, &mut report);
    }
    Ok(report)
}

/// Tensors of a fresh avatar cast to `dtype` (helper for the f64 gradient checks).
pub fn cast_tensors(
    tensors: &HashMap<String, Tensor>,
    dtype: DType,
) -> Result<HashMap<String, Tensor>> {
    tensors
        .iter()
        .map(|(k, t)| Ok((k.clone(), t.to_dtype(dtype)?)))
        .collect()
}

/// `skeleton::forward_kinematics` round trip: rotations orthonormal with det 1, `skt·l2w = I`,
/// and axis-angle → matrix → axis-angle → matrix reproducing the matrix. Returns the largest
/// deviation over all joints.
pub fn kinematics_error(rest: &Joints, bones: &Joints) -> f64 {
    let posed = skeleton::forward_kinematics(rest, bones, [0.1, -0.2, 0.3]);
    let mut err = 0f64;
    for (j, w) in bones.iter().enumerate() {
        let l = skeleton::mat4_from_rows(&posed.l2ws[j]);
        let s = skeleton::mat4_from_rows(&posed.skts[j]);
        let prod = s * l;
        err = err.max(mat4_identity_err(&prod));
        let m =
            skeleton::axis_angle_to_matrix(glam::DVec3::new(w[0] as f64, w[1] as f64, w[2] as f64));
        let rt = m.transpose() * m;
        err = err.max(mat3_dist(&rt, &glam::DMat3::IDENTITY));
        err = err.max((m.determinant() - 1.0).abs());
        let back = skeleton::axis_angle_to_matrix(skeleton::matrix_to_axis_angle(m));
        err = err.max(mat3_dist(&back, &m));
    }
    err
}

fn mat3_dist(a: &glam::DMat3, b: &glam::DMat3) -> f64 {
    (a.to_cols_array().iter().zip(b.to_cols_array()))
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

/// Largest |entry − I| of a 4×4 matrix.
fn mat4_identity_err(m: &glam::DMat4) -> f64 {
    (m.to_cols_array()
        .iter()
        .zip(glam::DMat4::IDENTITY.to_cols_array()))
    .map(|(x, y)| (x - y).abs())
    .fold(0.0, f64::max)
}
