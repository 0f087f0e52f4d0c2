//! The official code's golden case (`fixtures/golden`: its CPU float32 outputs) run on a
//! device: the forward stage by stage, the gradients, and one Adam step.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{Device, Tensor};

use super::Check;
use crate::network::checkpoint;
use crate::render::avatar::{Avatar, Mode, Outputs, PassOptions, Poses, Rays, Trace};
use crate::train::batch::{FixedBatch, TrainBatch};
use crate::train::presets::{RunConfig, TrainConfig};
use crate::train::{Preset, Trainer};

/// Forward values: |a − b| ≤ 1e-4 · max(1, |b|) (the golden tests' bound).
pub const FORWARD_TOL: f64 = 1e-4;

/// Gradients, per array max |a − b| / max |b|. A few gradients are sums over all 4,608
/// samples with heavy cancellation (the σ head, the first GNN layer), whose f32 value moves
/// by up to ~1e-3 of its largest entry with the order of the sums (tests/model/grad.rs
/// measures that floor on the CPU); kernels that sum in blocks, as the GPU's do, move them
/// as much.
pub const GRADIENT_TOL: f64 = 2e-3;

/// The step's loss terms, relative.
pub const LOSS_TOL: f64 = 1e-5;

/// Parameters after the step and update norms, relative: Adam's first step is ±lr where
/// |g| ≫ eps but follows g where |g| is near eps, so there it inherits the gradient's
/// summation-order error (tests/model/train_parity.rs bounds it at 2e-4 on the CPU).
pub const STEP_TOL: f64 = 2e-4;

/// The golden arrays and the model, on `device`.
pub struct Golden {
    pub arrays: HashMap<String, Tensor>,
    pub step: HashMap<String, Tensor>,
    pub step_manifest: serde_json::Value,
    pub model: checkpoint::Checkpoint,
}

impl Golden {
    /// Read `dir` (a copy of `fixtures/golden`).
    pub fn load(dir: &Path, device: &Device) -> crate::error::Result<Self> {
        let read = |name: &str| -> crate::error::Result<HashMap<String, Tensor>> {
            Ok(candle_core::safetensors::load(dir.join(name), device)?)
        };
        let manifest_path = dir.join("train_step.json");
        let bad_manifest = |e: &dyn std::fmt::Display| {
            crate::error::ModelError::Input(format!("{}: {e}", manifest_path.display()))
        };
        let manifest = std::fs::read_to_string(&manifest_path).map_err(|e| bad_manifest(&e))?;
        Ok(Self {
            arrays: read("golden.safetensors")?,
            step: read("train_step.safetensors")?,
            step_manifest: serde_json::from_str(&manifest).map_err(|e| bad_manifest(&e))?,
            model: checkpoint::load(&dir.join("model.safetensors"), device)?,
        })
    }

    /// The reference's parameter names in its order (the step manifest's `param_names`).
    fn param_names(&self) -> Vec<String> {
        self.step_manifest["param_names"]
            .as_array()
            .map(|a| {
                a.iter()
                    .filter_map(|v| v.as_str().map(str::to_string))
                    .collect()
            })
            .unwrap_or_default()
    }

    fn t(&self, key: &str) -> crate::error::Result<&Tensor> {
        self.arrays.get(key).ok_or_else(|| {
            crate::error::ModelError::Input(format!("golden case: no array `{key}`"))
        })
    }

    /// The golden batch: per-ray copies of one pose, reduced to one pose (the reference's
    /// `N_unique = 1`).
    pub fn batch(&self) -> crate::error::Result<TrainBatch> {
        let bones = self.t("input/bones")?.get(0)?.to_vec2::<f32>()?;
        let mut joints = [[0f32; 3]; 24];
        for (d, s) in joints.iter_mut().zip(bones) {
            d.copy_from_slice(&s);
        }
        Ok(TrainBatch {
            rays: Rays {
                origins: self.t("input/rays_o")?.clone(),
                dirs: self.t("input/rays_d")?.clone(),
                bgs: Some(self.t("input/bgs")?.clone()),
                framecodes: self.t("input/cam_idxs")?.to_vec1::<i64>()?,
            },
            poses: Poses {
                bones: vec![joints],
                skts: self.t("input/skts")?.narrow(0, 0, 1)?.contiguous()?,
                cyls: self.t("input/cyls")?.narrow(0, 0, 1)?.contiguous()?,
            },
            target: self.t("input/target_s")?.clone(),
            pixels: None,
            weights: None,
        })
    }

    /// The golden model with its density noise off (the golden run's).
    fn avatar(&self, device: &Device) -> crate::error::Result<Avatar> {
        let mut cfg = self.model.config.clone();
        cfg.density_noise_std = 0.0;
        Avatar::from_tensors(cfg, self.model.tensors.clone(), device)
    }

    /// [`Golden::avatar`]'s training-mode pass over the golden batch in parity mode;
    /// `trace` collects the network's stages.
    fn forward(
        &self,
        device: &Device,
        trace: Option<&mut Trace>,
    ) -> crate::error::Result<(Avatar, TrainBatch, Outputs)> {
        let avatar = self.avatar(device)?;
        let batch = self.batch()?;
        let out = avatar.forward(
            &batch.rays,
            &batch.poses,
            &mut Mode::Train(None),
            &PassOptions::parity(),
            trace,
        )?;
        Ok((avatar, batch, out))
    }
}

/// √Σ v².
fn l2(values: impl Iterator<Item = f64>) -> f64 {
    values.map(|v| v * v).sum::<f64>().sqrt()
}

/// max |a − b| / max(1, |b|) element-wise, NaN-safe (a NaN anywhere is infinite).
fn scaled_error(a: &Tensor, b: &Tensor) -> crate::error::Result<f64> {
    let (a, b) = (flat(a)?, flat(b)?);
    if a.len() != b.len() {
        return Ok(f64::INFINITY);
    }
    Ok(a.iter().zip(&b).fold(0f64, |m, (x, y)| {
        let d = (x - y).abs() / y.abs().max(1.0);
        if d.is_nan() {
            f64::INFINITY
        } else {
            m.max(d)
        }
    }))
}

/// max |a − b| / max |b|.
fn relative_error(a: &[f64], b: &[f64]) -> f64 {
    if a.len() != b.len() {
        return f64::INFINITY;
    }
    let scale = b.iter().fold(0f64, |m, v| m.max(v.abs())).max(1e-30);
    let d = a.iter().zip(b).fold(0f64, |m, (x, y)| m.max((x - y).abs()));
    if d.is_nan() {
        f64::INFINITY
    } else {
        d / scale
    }
}

fn flat(t: &Tensor) -> crate::error::Result<Vec<f64>> {
    Ok(t.flatten_all()?
        .to_dtype(candle_core::DType::F64)?
        .to_vec1::<f64>()?)
}

fn row(section: &'static str, what: String, err: f64, tol: f64) -> Check {
    Check {
        section,
        what,
        max_err: Some(err),
        tol: Some(tol),
        passed: err <= tol,
        note: String::new(),
    }
}

/// The forward stage by stage: the ray caster's coarse depths, the network's stages, the
/// renders (`section` names the route).
pub fn forward(
    g: &Golden,
    device: &Device,
    section: &'static str,
) -> crate::error::Result<Vec<Check>> {
    let mut trace = Trace::default();
    let (_, _, out) = g.forward(device, Some(&mut trace))?;
    let mut rows = Vec::new();
    let mut cmp = |what: &str, ours: &Tensor, key: &str| -> crate::error::Result<()> {
        rows.push(row(
            section,
            format!("forward {what}"),
            scaled_error(ours, g.t(key)?)?,
            FORWARD_TOL,
        ));
        Ok(())
    };
    cmp(
        "ray casting: coarse depths",
        &out.z_coarse,
        "raycast/z_vals_coarse",
    )?;
    cmp(
        "ray casting: merged depths",
        &out.z_vals,
        "raycast/z_vals_merged",
    )?;
    for stage in ["coarse", "fine"] {
        for k in ["gnn_feat", "axis_scale", "sigma_raw", "rgb_logits"] {
            if let Some(t) = trace.tensors.get(&format!("{stage}/{k}")) {
                cmp(&format!("{stage} {k}"), t, &format!("{stage}/{k}"))?;
            }
        }
    }
    cmp("coarse rgb", &out.coarse.rgb, "out/rgb0")?;
    cmp("coarse acc", &out.coarse.acc, "out/acc0")?;
    cmp("fine rgb", &out.fine.rgb, "out/rgb_map")?;
    cmp("fine acc", &out.fine.acc, "out/acc_map")?;
    cmp("fine disp", &out.fine.disp, "out/disp_map")?;
    cmp("fine weights", &out.fine.weights, "out/T_i")?;
    Ok(rows)
}

/// The gradients of the fine L1 loss: the full gradients of the selected parameters and
/// the norm of every parameter's gradient.
pub fn gradients(
    g: &Golden,
    device: &Device,
    section: &'static str,
) -> crate::error::Result<Vec<Check>> {
    let (avatar, batch, out) = g.forward(device, None)?;
    let loss = crate::train::loss::l1(&out.fine.rgb, &batch.target)?;
    let store = loss.backward()?;
    let grads: HashMap<String, Tensor> = avatar
        .trainable()
        .into_iter()
        .filter_map(|(n, v)| store.get(v.as_tensor()).map(|t| (n, t.clone())))
        .collect();
    let mut rows = vec![row(
        section,
        "gradients: the loss".into(),
        relative_error(&flat(&loss)?, &flat(g.t("grad_l1fine/loss")?)?),
        FORWARD_TOL,
    )];
    let mut keys: Vec<&String> = g
        .arrays
        .keys()
        .filter(|k| k.starts_with("grad_l1fine/grad/"))
        .collect();
    keys.sort();
    for key in keys {
        let name = &key["grad_l1fine/grad/".len()..];
        let (base, rows_of) = match name.strip_suffix("[0:3]") {
            Some(b) => (b, Some(3)),
            None => (name, None),
        };
        let ours = match (grads.get(base), rows_of) {
            (Some(t), Some(k)) => flat(&t.narrow(0, 0, k)?)?,
            (Some(t), None) => flat(t)?,
            (None, _) => Vec::new(),
        };
        rows.push(row(
            section,
            format!("gradient of {name}"),
            relative_error(&ours, &flat(&g.arrays[key])?),
            GRADIENT_TOL,
        ));
    }
    let names = g.param_names();
    let norms = flat(g.t("grad_l1fine/grad_norms")?)?;
    let ours: Vec<f64> = names
        .iter()
        .map(|n| {
            grads.get(n).map_or(Ok(0.0), |t| {
                Ok::<_, crate::error::ModelError>(l2(flat(t)?.into_iter()))
            })
        })
        .collect::<crate::error::Result<_>>()?;
    let worst = ours
        .iter()
        .zip(&norms)
        .map(|(a, b)| {
            if *b == 0.0 {
                a.abs()
            } else {
                (a - b).abs() / b
            }
        })
        .fold(0f64, f64::max);
    rows.push(row(
        section,
        format!("gradient norms of all {} parameters", names.len()),
        worst,
        GRADIENT_TOL,
    ));
    Ok(rows)
}

/// One training step of the reference on the golden batch (loss, backward, clip, Adam,
/// schedule): the loss terms, the selected parameters after it, and every update's norm.
pub fn adam_step(
    g: &Golden,
    device: &Device,
    section: &'static str,
) -> crate::error::Result<Vec<Check>> {
    let avatar = g.avatar(device)?;
    let run = RunConfig {
        preset: Preset::Paper,
        model: avatar.config().clone(),
        train: TrainConfig::paper(),
        numerics: Default::default(),
    };
    let mut trainer = Trainer::with_source(run, avatar, Box::new(FixedBatch(g.batch()?)))
        .map_err(|e| crate::error::ModelError::Input(e.to_string()))?;
    let snapshot = |t: &Trainer| -> crate::error::Result<HashMap<String, Vec<f64>>> {
        t.avatar()
            .trainable()
            .into_iter()
            .map(|(n, v)| Ok((n, flat(v.as_tensor())?)))
            .collect()
    };
    let before = snapshot(&trainer)?;
    let stats = trainer
        .step_read()
        .map_err(|e| crate::error::ModelError::Input(e.to_string()))?;
    let after = snapshot(&trainer)?;
    let scalar = |k: &str| -> crate::error::Result<f64> {
        let t = g
            .step
            .get(k)
            .ok_or_else(|| crate::error::ModelError::Input(format!("golden step: no `{k}`")))?;
        Ok(flat(t)?[0])
    };
    let rel = |a: f64, b: f64| (a - b).abs() / b.abs().max(1e-30);
    let mut rows = Vec::new();
    for (what, ours, key) in [
        ("fine loss", stats.loss.fine, "train_step/loss_fine"),
        ("coarse loss", stats.loss.coarse, "train_step/loss_coarse"),
        ("total loss", stats.loss.total, "train_step/total_loss"),
    ] {
        rows.push(row(
            section,
            format!("Adam step: {what}"),
            rel(ours, scalar(key)?),
            LOSS_TOL,
        ));
    }
    let mut worst_param = 0f64;
    for (key, t) in &g.step {
        let Some(name) = key.strip_prefix("train_step/param_after/") else {
            continue;
        };
        let base = name.strip_suffix("[0:3]").unwrap_or(name);
        let reference = flat(t)?;
        let ours = after
            .get(base)
            .map(|v| v[..reference.len().min(v.len())].to_vec())
            .unwrap_or_default();
        let num = l2(ours.iter().zip(&reference).map(|(a, b)| a - b));
        let den = l2(reference.iter().copied());
        worst_param = worst_param.max(if ours.len() == reference.len() {
            num / den.max(1e-30)
        } else {
            f64::INFINITY
        });
    }
    rows.push(row(
        section,
        "Adam step: selected parameters after it".into(),
        worst_param,
        STEP_TOL,
    ));
    let names = g.param_names();
    let norms =
        flat(g.step.get("train_step/param_delta_norms").ok_or_else(|| {
            crate::error::ModelError::Input("golden step: no update norms".into())
        })?)?;
    let mut worst = 0f64;
    for (name, reference) in names.iter().zip(&norms) {
        let (Some(a), Some(b)) = (after.get(name), before.get(name)) else {
            worst = f64::INFINITY;
            continue;
        };
        let delta = l2(a.iter().zip(b).map(|(x, y)| x - y));
        worst = worst.max(rel(delta, *reference));
    }
    rows.push(row(
        section,
        format!("Adam step: update norms of all {} parameters", names.len()),
        worst,
        STEP_TOL,
    ));
    Ok(rows)
}
