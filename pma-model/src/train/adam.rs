//! Adam with parameter groups, the reference's learning-rate schedule and global-norm
//! gradient clipping (see `docs/reference.md`, "Training schedule and Adam").
//!
//! candle's `AdamW` has no parameter groups and keeps its moments private, so it can neither
//! reproduce the reference's two learning rates nor be checkpointed; this one holds its
//! moments as plain tensors (saved by [`super::state`]).
//!
//! The update follows torch's single-tensor `Adam` (`foreach=False`, the CPU default) in f32:
//!
//! ```text
//! m <- m + (g - m)(1 - b1)            (torch: exp_avg.lerp_(g, 1 - b1))
//! v <- v b2 + g² (1 - b2)
//! p <- p - lr / (1 - b1^t) * m / (sqrt(v) / sqrt(1 - b2^t) + eps)
//! ```

use candle_core::{DType, Tensor, Var};

use super::TrainError;

/// Substrings that put a parameter into the "freq" group (lr 1e-4, `model.lr_freq`); every
/// other parameter is in the "other" group (lr 5e-4).
pub const FREQ_GROUP_PATTERNS: [&str; 6] = [
    "graph_net",
    "pose_extractor",
    "win_fun",
    "modulator",
    "pts_enc_point",
    "pts_enc_pose",
];

/// Index of the reference group a parameter belongs to: 0 = "freq", 1 = "other".
pub fn reference_group(name: &str) -> usize {
    if FREQ_GROUP_PATTERNS.iter().any(|p| name.contains(p)) {
        0
    } else {
        1
    }
}

/// `lr(t) = max(lr0 * decay^(t / decay_steps), floor)`: the rate used for step `t + 1`
/// after `t` completed steps (continuous decay, not a staircase).
pub fn decayed_lr(lr0: f64, completed_steps: u64, decay: f64, decay_steps: f64, floor: f64) -> f64 {
    (lr0 * decay.powf(completed_steps as f64 / decay_steps)).max(floor)
}

/// Hyper-parameters and members of one parameter group.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ParamGroup {
    pub name: String,
    /// Rate at step 0; the schedule scales this one.
    pub initial_lr: f64,
    /// Rate of the next step.
    pub lr: f64,
    pub betas: [f64; 2],
    pub eps: f64,
    /// Parameter names, in the order of the model's `named_parameters()`.
    pub params: Vec<String>,
}

/// Adam moments of one parameter; `step` counts the updates applied to it.
#[derive(Debug, Clone)]
pub struct ParamState {
    pub step: u64,
    pub exp_avg: Tensor,
    pub exp_avg_sq: Tensor,
}

struct Slot {
    name: String,
    var: Var,
    group: usize,
    state: ParamState,
}

/// Adam over named candle `Var`s, split into groups with their own learning rates.
pub struct Adam {
    groups: Vec<ParamGroup>,
    /// Group-major (all of group 0, then group 1, ...), i.e. the reference's state ids.
    slots: Vec<Slot>,
}

impl Adam {
    /// `vars` in model order; `group_of(name)` picks the index into `groups` (whose `params`
    /// lists are filled here, so pass them empty).
    pub fn new(
        vars: &[(String, Var)],
        mut groups: Vec<ParamGroup>,
        group_of: impl Fn(&str) -> usize,
    ) -> Result<Self, TrainError> {
        for g in &mut groups {
            g.params.clear();
        }
        let mut per_group: Vec<Vec<Slot>> = groups.iter().map(|_| Vec::new()).collect();
        for (name, var) in vars {
            let gi = group_of(name);
            let Some(bucket) = per_group.get_mut(gi) else {
                return Err(TrainError::Config(format!(
                    "parameter `{name}` maps to group {gi}, but only {} groups exist",
                    groups.len()
                )));
            };
            if var.dtype() != DType::F32 {
                return Err(TrainError::Config(format!(
                    "parameter `{name}` is {:?}, expected f32",
                    var.dtype()
                )));
            }
            groups[gi].params.push(name.clone());
            let zeros = var.as_tensor().zeros_like()?;
            bucket.push(Slot {
                name: name.clone(),
                var: var.clone(),
                group: gi,
                state: ParamState {
                    step: 0,
                    exp_avg: zeros.clone(),
                    exp_avg_sq: zeros,
                },
            });
        }
        Ok(Self {
            groups,
            slots: per_group.into_iter().flatten().collect(),
        })
    }

    /// The reference's two groups ("freq" 1e-4, "other" 5e-4) over `vars`.
    pub fn reference(
        vars: &[(String, Var)],
        lr_freq: f64,
        lr: f64,
        betas: [f64; 2],
        eps: f64,
    ) -> Result<Self, TrainError> {
        let group = |name: &str, lr0: f64| ParamGroup {
            name: name.to_string(),
            initial_lr: lr0,
            lr: lr0,
            betas,
            eps,
            params: Vec::new(),
        };
        Self::new(
            vars,
            vec![group("freq", lr_freq), group("other", lr)],
            reference_group,
        )
    }

    pub fn groups(&self) -> &[ParamGroup] {
        &self.groups
    }

    /// Parameter names in state order (group-major).
    pub fn param_names(&self) -> impl Iterator<Item = &str> {
        self.slots.iter().map(|s| s.name.as_str())
    }

    pub fn state(&self, name: &str) -> Option<&ParamState> {
        self.slots.iter().find(|s| s.name == name).map(|s| &s.state)
    }

    /// Iterate `(name, state)` in state order.
    pub fn states(&self) -> impl Iterator<Item = (&str, &ParamState)> {
        self.slots.iter().map(|s| (s.name.as_str(), &s.state))
    }

    pub fn set_lr(&mut self, group: usize, lr: f64) {
        self.groups[group].lr = lr;
    }

    /// Set every group's rate from its initial rate for the step after `completed_steps`.
    pub fn apply_schedule(
        &mut self,
        completed_steps: u64,
        decay: f64,
        decay_steps: f64,
        floor: f64,
    ) {
        for g in &mut self.groups {
            g.lr = decayed_lr(g.initial_lr, completed_steps, decay, decay_steps, floor);
        }
    }

    /// Replace the moments, step counts and current group rates (from a train-state file).
    /// Every parameter must be given, with its own shape; on error nothing is changed.
    pub fn load_states(
        &mut self,
        mut states: std::collections::HashMap<String, ParamState>,
        groups_lr: &[f64],
    ) -> Result<(), TrainError> {
        let mut problems = Vec::new();
        if groups_lr.len() != self.groups.len() {
            problems.push(format!(
                "{} group rates given, {} groups exist",
                groups_lr.len(),
                self.groups.len()
            ));
        }
        for slot in &self.slots {
            match states.get(&slot.name) {
                None => problems.push(format!("no optimizer state for `{}`", slot.name)),
                Some(st) => {
                    for (what, t) in [("exp_avg", &st.exp_avg), ("exp_avg_sq", &st.exp_avg_sq)] {
                        if t.dims() != slot.var.dims() || t.dtype() != DType::F32 {
                            problems.push(format!(
                                "{what}.{}: expected f32 {:?}, found {:?} {:?}",
                                slot.name,
                                slot.var.dims(),
                                t.dtype(),
                                t.dims()
                            ));
                        }
                    }
                }
            }
        }
        let known: std::collections::HashSet<&str> =
            self.slots.iter().map(|s| s.name.as_str()).collect();
        let mut extra: Vec<_> = states
            .keys()
            .filter(|k| !known.contains(k.as_str()))
            .cloned()
            .collect();
        extra.sort();
        for name in extra {
            problems.push(format!("optimizer state for unknown parameter `{name}`"));
        }
        if !problems.is_empty() {
            return Err(TrainError::State(problems));
        }
        for slot in &mut self.slots {
            let st = states.remove(&slot.name).expect("presence checked above");
            let device = slot.var.device();
            slot.state = ParamState {
                step: st.step,
                exp_avg: st.exp_avg.to_device(device)?,
                exp_avg_sq: st.exp_avg_sq.to_device(device)?,
            };
        }
        for (g, &lr) in self.groups.iter_mut().zip(groups_lr) {
            g.lr = lr;
        }
        Ok(())
    }

    /// One Adam update. `grads` is aligned with [`Self::param_names`]; a `None` gradient leaves
    /// that parameter and its state untouched (torch skips parameters whose `.grad` is `None`).
    pub fn step(&mut self, grads: &[Option<Tensor>]) -> Result<(), TrainError> {
        if grads.len() != self.slots.len() {
            return Err(TrainError::Config(format!(
                "{} gradients given for {} parameters",
                grads.len(),
                self.slots.len()
            )));
        }
        for (slot, grad) in self.slots.iter_mut().zip(grads) {
            let Some(g) = grad else { continue };
            let group = &self.groups[slot.group];
            let [b1, b2] = group.betas;
            let st = &mut slot.state;
            let t = st.step + 1;
            let g = g.detach();
            // lerp form of torch's exp_avg.lerp_(g, 1 - b1) (weight < 0.5 branch).
            let m = (&st.exp_avg + ((&g - &st.exp_avg)? * (1.0 - b1))?)?;
            let v = ((&st.exp_avg_sq * b2)? + (g.sqr()? * (1.0 - b2))?)?;
            let bias1 = 1.0 - b1.powi(t as i32);
            let bias2_sqrt = (1.0 - b2.powi(t as i32)).sqrt();
            let step_size = group.lr / bias1;
            let denom = ((v.sqrt()? / bias2_sqrt)? + group.eps)?;
            let update = ((&m * step_size)? / denom)?;
            let p = (slot.var.as_tensor().detach() - update)?;
            slot.var.set(&p)?;
            *st = ParamState {
                step: t,
                exp_avg: m,
                exp_avg_sq: v,
            };
        }
        Ok(())
    }
}

/// Global L2 norm of all gradients together, accumulated in f64. Non-finite if any
/// gradient element is non-finite.
pub fn global_norm(grads: &[Option<Tensor>]) -> Result<f64, TrainError> {
    let sums = grads
        .iter()
        .flatten()
        .map(|g| g.to_dtype(DType::F64)?.sqr()?.sum_all())
        .collect::<candle_core::Result<Vec<_>>>()?;
    if sums.is_empty() {
        return Ok(0.0);
    }
    // One read-back for all tensors (one device sync on a GPU, not one per tensor), then
    // the same sum in the same order as reading them one by one.
    let host = Tensor::stack(&sums, 0)?
        .to_device(&candle_core::Device::Cpu)?
        .to_vec1::<f64>()?;
    let sum = host.iter().fold(0.0f64, |a, v| a + v);
    Ok(sum.sqrt())
}

/// Scale gradients so their global norm is at most `max_norm` (torch `clip_grad_norm_`:
/// coefficient `max_norm / (norm + 1e-6)`, applied only when it is below 1).
/// Returns the coefficient used (1 when nothing was scaled).
pub fn clip_grad_norm(
    grads: &mut [Option<Tensor>],
    max_norm: f64,
    total_norm: f64,
) -> Result<f64, TrainError> {
    let coef = max_norm / (total_norm + 1e-6);
    if coef >= 1.0 {
        return Ok(1.0);
    }
    for g in grads.iter_mut().flatten() {
        *g = (&*g * coef)?;
    }
    Ok(coef)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    fn var(v: &[f32]) -> Var {
        Var::from_tensor(&Tensor::new(v, &Device::Cpu).unwrap()).unwrap()
    }

    /// Reference values from a plain f64 transcription of torch's Adam.
    fn adam_ref(p: &mut [f64], grads: &[Vec<f64>], lr: f64, b1: f64, b2: f64, eps: f64) {
        let mut m = vec![0.0; p.len()];
        let mut v = vec![0.0; p.len()];
        for (t, g) in grads.iter().enumerate() {
            let t = t as i32 + 1;
            for i in 0..p.len() {
                m[i] = b1 * m[i] + (1.0 - b1) * g[i];
                v[i] = b2 * v[i] + (1.0 - b2) * g[i] * g[i];
                let denom = (v[i] / (1.0 - b2.powi(t))).sqrt() + eps;
                p[i] -= lr / (1.0 - b1.powi(t)) * m[i] / denom;
            }
        }
    }

    #[test]
    fn adam_matches_reference_formula_over_several_steps() {
        let x = var(&[0.5, -1.0, 2.0, 1e-3]);
        let mut adam = Adam::new(
            &[("w".to_string(), x.clone())],
            vec![ParamGroup {
                name: "g".into(),
                initial_lr: 0.01,
                lr: 0.01,
                betas: [0.9, 0.999],
                eps: 1e-8,
                params: vec![],
            }],
            |_| 0,
        )
        .unwrap();
        let grads: Vec<Vec<f64>> = vec![
            vec![0.1, -0.2, 3.0, 1e-9],
            vec![-0.3, 0.2, 1.0, 0.0],
            vec![0.05, 0.0, -2.0, 5e-9],
        ];
        for g in &grads {
            let gt = Tensor::new(
                g.iter().map(|&x| x as f32).collect::<Vec<_>>(),
                &Device::Cpu,
            )
            .unwrap();
            adam.step(&[Some(gt)]).unwrap();
        }
        let mut want = vec![0.5, -1.0, 2.0, 1e-3];
        adam_ref(&mut want, &grads, 0.01, 0.9, 0.999, 1e-8);
        let got = x.to_vec1::<f32>().unwrap();
        for (g, w) in got.iter().zip(&want) {
            assert!(
                (*g as f64 - w).abs() < 1e-6 * w.abs().max(1e-3),
                "{got:?} vs {want:?}"
            );
        }
        assert_eq!(adam.state("w").unwrap().step, 3);
    }

    #[test]
    fn groups_follow_reference_patterns_and_rates() {
        let vars = vec![
            (
                "pts_enc_pose.sin_lin0.layer.weight".to_string(),
                var(&[1.0]),
            ),
            ("pts_linears.0.weight".to_string(), var(&[1.0])),
            ("graph_net.axis_scale".to_string(), var(&[1.0])),
            ("framecodes.codes.weight".to_string(), var(&[1.0])),
        ];
        let mut adam = Adam::reference(&vars, 1e-4, 5e-4, [0.9, 0.999], 1e-8).unwrap();
        let names: Vec<_> = adam.param_names().collect();
        assert_eq!(
            names,
            [
                "pts_enc_pose.sin_lin0.layer.weight",
                "graph_net.axis_scale",
                "pts_linears.0.weight",
                "framecodes.codes.weight"
            ]
        );
        // First Adam step moves every element by ~lr (sign of the gradient).
        let g = |v: f32| Some(Tensor::new(&[v], &Device::Cpu).unwrap());
        adam.step(&[g(1.0), g(-1.0), g(1.0), g(1.0)]).unwrap();
        let val = |i: usize| vars[i].1.to_vec1::<f32>().unwrap()[0] as f64;
        assert!((val(0) - (1.0 - 1e-4)).abs() < 1e-7);
        assert!((val(2) - (1.0 + 1e-4)).abs() < 1e-7);
        assert!((val(1) - (1.0 - 5e-4)).abs() < 1e-7);
        adam.apply_schedule(1, 0.1, 500_000.0, 1e-5);
        assert!((adam.groups()[1].lr - 0.0004999976974202089).abs() < 1e-15);
        assert!((adam.groups()[0].lr - 9.999953948404178e-05).abs() < 1e-15);
    }

    #[test]
    fn none_gradient_leaves_param_and_state_alone() {
        let x = var(&[1.0, 2.0]);
        let mut adam = Adam::reference(
            &[("pts_linears.0.bias".into(), x.clone())],
            1e-4,
            5e-4,
            [0.9, 0.999],
            1e-8,
        )
        .unwrap();
        adam.step(&[None]).unwrap();
        assert_eq!(x.to_vec1::<f32>().unwrap(), vec![1.0, 2.0]);
        assert_eq!(adam.state("pts_linears.0.bias").unwrap().step, 0);
        assert!(adam.step(&[]).is_err());
    }

    #[test]
    fn schedule_floors_and_decays_continuously() {
        assert_eq!(decayed_lr(5e-4, 0, 0.1, 500_000.0, 1e-5), 5e-4);
        let half = decayed_lr(5e-4, 250_000, 0.1, 500_000.0, 1e-5);
        assert!((half - 5e-4 * 0.1f64.sqrt()).abs() < 1e-15);
        assert_eq!(decayed_lr(1e-4, 10_000_000, 0.1, 500_000.0, 1e-5), 1e-5);
    }

    #[test]
    fn clipping_scales_to_max_norm_and_reports_coefficient() {
        let t = |v: &[f32]| Some(Tensor::new(v, &Device::Cpu).unwrap());
        let mut grads = vec![t(&[3.0, 0.0]), None, t(&[4.0])];
        let n = global_norm(&grads).unwrap();
        assert!((n - 5.0).abs() < 1e-12);
        let coef = clip_grad_norm(&mut grads, 1.0, n).unwrap();
        assert!((coef - 1.0 / (5.0 + 1e-6)).abs() < 1e-12);
        assert!((global_norm(&grads).unwrap() - 1.0).abs() < 1e-6);
        // Below the threshold nothing changes.
        let before = grads[0].as_ref().unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(clip_grad_norm(&mut grads, 10.0, 1.0).unwrap(), 1.0);
        assert_eq!(grads[0].as_ref().unwrap().to_vec1::<f32>().unwrap(), before);
        // A NaN anywhere makes the norm non-finite.
        let bad = vec![t(&[1.0]), t(&[f32::NAN])];
        assert!(!global_norm(&bad).unwrap().is_finite());
    }
}
