//! A non-finite gradient or loss skips the step: nothing reaches the weights or the optimizer,
//! the skip is counted, training continues, and a streak of them stops the run.
#![cfg(feature = "train")]

use crate::train_support::*;
use candle_core::{Device, Tensor};
use pma_model::train::{SkipReason, TrainBatch, TrainError, Trainer};

/// Hook that overwrites the first element of the first parameter's gradient.
fn poison(value: f32) -> impl FnMut(&mut [Option<Tensor>]) {
    move |grads: &mut [Option<Tensor>]| {
        let g = grads[0].as_ref().expect("every parameter has a gradient");
        let mut v = g.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        v[0] = value;
        grads[0] = Some(Tensor::from_vec(v, g.shape(), &Device::Cpu).unwrap());
    }
}

#[test]
fn non_finite_gradient_is_skipped_and_counted() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"));
    let mut t = tiny_trainer(&data);
    t.step_read().unwrap();
    let (params, adam) = (param_bits(&t), adam_bits(&t));

    for (i, bad) in [f32::NAN, f32::INFINITY].into_iter().enumerate() {
        let mut hook = poison(bad);
        let s = t.step_hooked(&mut hook).unwrap();
        assert_eq!(s.skipped, Some(SkipReason::NonFiniteGradNorm), "{bad}");
        assert!(!s.grad_norm.is_finite());
        assert_eq!(t.progress().skipped, i as u64 + 1);
        assert!(
            param_bits(&t) == params,
            "a skipped step changed the weights"
        );
        assert!(
            adam_bits(&t) == adam,
            "a skipped step changed the optimizer state"
        );
    }
    assert_eq!(
        t.iteration(),
        3,
        "skipped iterations still count as iterations"
    );

    // Training goes on, and every weight stays finite.
    let s = t.step_read().unwrap();
    assert_eq!(s.skipped, None);
    assert_eq!(t.progress().consecutive_skipped, 0);
    assert!(param_bits(&t) != params);
    for (name, v) in t.avatar().trainable() {
        let vals = v.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert!(vals.iter().all(|x| x.is_finite()), "{name} is not finite");
    }
}

#[test]
fn non_finite_loss_is_skipped_without_backward() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"));
    let mut t = tiny_trainer(&data);
    let mut src =
        pma_model::train::DatasetSource::new(data.clone(), 64, 2, true, 1, &Device::Cpu).unwrap();
    use pma_model::train::BatchSource;
    let good = src.next_batch().unwrap();
    let nan_target = (good.target.clone() * f64::NAN).unwrap();
    let bad = TrainBatch {
        target: nan_target,
        ..good
    };
    let params = param_bits(&t);
    let s = t.step_on(&bad, None).unwrap();
    assert_eq!(s.skipped, Some(SkipReason::NonFiniteLoss));
    assert!(param_bits(&t) == params);
    assert_eq!(t.optimizer().states().unwrap()[0].1.step, 0);
}

#[test]
fn a_streak_of_non_finite_steps_stops_the_run() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"));
    let mut run = tiny_run();
    run.train.max_consecutive_skips = 2;
    let mut t = Trainer::new(run, data, &Device::Cpu).unwrap();
    let mut hook = poison(f32::NAN);
    t.step_hooked(&mut hook).unwrap();
    let err = t.step_hooked(&mut hook).unwrap_err();
    assert!(
        matches!(err, TrainError::Diverged { count: 2, iter: 2 }),
        "{err}"
    );
}
