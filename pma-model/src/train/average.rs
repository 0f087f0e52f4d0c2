//! Averaged weights: an exponential moving average of the parameters over the steps
//! (Polyak–Ruppert averaging in its exponential form; Polyak & Juditsky, "Acceleration of
//! stochastic approximation by averaging", 1992), kept beside the trained weights and used
//! wherever the run's model is used: the model file of each checkpoint, the held-out
//! evaluation during training and the bench's scores.
//!
//! Why: at the rates that learn fastest the weights of consecutive steps scatter around
//! where they are heading, and a model taken at one step scores tenths of a dB apart from
//! one taken a hundred steps later (docs/performance.md, "Time to quality"). Their average
//! sits nearer the middle. It costs two element-wise passes over the parameters per step
//! and no read-back.
//!
//! The trained weights stay the ones the optimizer moves; a checkpoint's train state keeps
//! them (`weights.<name>`), so a resumed run continues them and the average bit for bit.

use candle_core::{Tensor, Var};
use serde::{Deserialize, Serialize};

use super::TrainError;

/// `[train.average]`: the decay of the moving average.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AverageConfig {
    /// Each step keeps this share of the average and adds the rest of the new weights, once
    /// the warm-up of [`Self::decay_at`] has reached it (0.998: about the last 500 steps
    /// count; before step 4,500 about the last ninth of the steps done). Five-minute runs
    /// of the fast recipe at 0.99, 0.998 and 0.999 scored alike within the scatter of
    /// repeated runs (docs/performance.md, "Five minutes").
    pub decay: f64,
}

impl Default for AverageConfig {
    fn default() -> Self {
        Self { decay: 0.998 }
    }
}

impl AverageConfig {
    pub(crate) fn problems(&self) -> Vec<String> {
        match self.decay.is_finite() && (0.0..1.0).contains(&self.decay) {
            true => Vec::new(),
            false => vec![format!(
                "average.decay must be in [0, 1), found {}",
                self.decay
            )],
        }
    }

    /// The decay after `iter` completed iterations: it starts low, so the first steps'
    /// average is not held back by the initial weights (TensorFlow's
    /// `ExponentialMovingAverage` with `num_updates`).
    pub fn decay_at(&self, iter: u64) -> f64 {
        let t = iter as f64;
        self.decay.min((1.0 + t) / (10.0 + t))
    }
}

/// The running average of a list of parameters, flat in their order.
pub struct Average {
    cfg: AverageConfig,
    flat: Tensor,
}

impl Average {
    /// An average that starts at the parameters' current values.
    pub fn new(cfg: AverageConfig, params: &[Var]) -> Result<Self, TrainError> {
        Ok(Self {
            cfg,
            flat: flat(params)?,
        })
    }

    /// Take in the parameters after `iter` completed iterations.
    pub fn update(&mut self, params: &[Var], iter: u64) -> Result<(), TrainError> {
        let d = self.cfg.decay_at(iter);
        self.flat = (self.flat.affine(d, 0.0)? + flat(params)?.affine(1.0 - d, 0.0)?)?;
        Ok(())
    }

    /// Run `f` with the averaged values in `params`, then put their own values back (also
    /// when `f` fails).
    pub fn with_averaged<R, E: From<TrainError>>(
        &self,
        params: &[Var],
        f: impl FnOnce() -> Result<R, E>,
    ) -> Result<R, E> {
        let own = flat(params)?;
        set(params, &self.flat)?;
        let out = f();
        set(params, &own)?;
        out
    }
}

/// The parameters as one flat tensor (a copy). Detached: an op on a variable records its
/// inputs for the backward pass, and an average built from recorded ops would hold every
/// earlier average alive (memory growing with the steps).
pub(crate) fn flat(params: &[Var]) -> Result<Tensor, TrainError> {
    let parts = params
        .iter()
        .map(|p| p.as_tensor().detach().flatten_all())
        .collect::<candle_core::Result<Vec<_>>>()?;
    Ok(Tensor::cat(&parts, 0)?)
}

/// Write `flat` (as [`flat`] lays it out) into the parameters.
fn set(params: &[Var], flat: &Tensor) -> Result<(), TrainError> {
    let mut offset = 0;
    for p in params {
        let n = p.elem_count();
        p.set(&flat.narrow(0, offset, n)?.reshape(p.shape())?)?;
        offset += n;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    fn var(v: &[f32]) -> Var {
        Var::from_tensor(&Tensor::new(v, &Device::Cpu).unwrap()).unwrap()
    }

    #[test]
    fn the_average_follows_the_exponential_rule_and_gives_the_weights_back() {
        let params = vec![var(&[0.0, 1.0]), var(&[2.0])];
        let cfg = AverageConfig { decay: 0.5 };
        let mut avg = Average::new(cfg.clone(), &params).unwrap();
        params[0]
            .set(&Tensor::new(&[4.0f32, 5.0], &Device::Cpu).unwrap())
            .unwrap();
        params[1]
            .set(&Tensor::new(&[6.0f32], &Device::Cpu).unwrap())
            .unwrap();
        // At iteration 100 the decay is the configured 0.5.
        avg.update(&params, 100).unwrap();
        let seen = avg
            .with_averaged::<_, TrainError>(&params, || {
                Ok((
                    params[0].to_vec1::<f32>().unwrap(),
                    params[1].to_vec1::<f32>().unwrap(),
                ))
            })
            .unwrap();
        assert_eq!(seen, (vec![2.0, 3.0], vec![4.0]));
        assert_eq!(params[0].to_vec1::<f32>().unwrap(), vec![4.0, 5.0]);
        assert_eq!(params[1].to_vec1::<f32>().unwrap(), vec![6.0]);
        // Nothing of the average records ops, so no step keeps an earlier one alive.
        assert!(!avg.flat.track_op());
        // The weights come back when the closure fails too.
        let r: Result<(), TrainError> =
            avg.with_averaged(&params, || Err(TrainError::Config("boom".into())));
        assert!(r.is_err());
        assert_eq!(params[1].to_vec1::<f32>().unwrap(), vec![6.0]);
    }

    #[test]
    fn the_decay_starts_low_and_reaches_the_configured_value() {
        let cfg = AverageConfig { decay: 0.99 };
        assert!((cfg.decay_at(0) - 0.1).abs() < 1e-12);
        assert!(cfg.decay_at(10) < cfg.decay_at(100));
        assert_eq!(cfg.decay_at(1_000_000), 0.99);
        assert!(AverageConfig { decay: 1.0 }.problems().len() == 1);
        assert!(AverageConfig { decay: f64::NAN }.problems().len() == 1);
        assert!(AverageConfig::default().problems().is_empty());
    }
}
