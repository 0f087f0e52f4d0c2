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
//!
//! All parameters go through one update: the gradients are concatenated into one flat
//! buffer, the moments are kept flat in state order, the update runs once over the whole
//! buffer and each parameter then gets its slice back (one copy each). The per-parameter
//! scalars (the rate of its group, the bias corrections of its step count) are expanded to
//! the elements by one gather. Step counts live on the device, so an update can be masked
//! there ([`Adam::step_masked`]: a skipped step decided on the device, with no read-back);
//! the bias corrections are read from tables computed on the host with the same f64
//! arithmetic as a per-parameter update, so the flat update gives its bits.

use candle_core::{DType, Device, Tensor, Var};

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

/// The reference's name of the pose side's group (rate `lr_freq`).
pub const FREQ_GROUP: &str = "freq";

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
    /// Where the parameter's elements start in the flat buffers.
    offset: usize,
    len: usize,
}

/// `1 − b1^t` and `sqrt(1 − b2^t)` for t = 0..len, in f64 on the device (index t).
struct BiasTables {
    len: usize,
    bias1: Tensor,
    bias2_sqrt: Tensor,
}

/// Adam over named candle `Var`s, split into groups with their own learning rates.
pub struct Adam {
    groups: Vec<ParamGroup>,
    /// Group-major (all of group 0, then group 1, ...), i.e. the reference's state ids.
    slots: Vec<Slot>,
    device: Device,
    /// Flat moments, [N] f32 in slot order.
    exp_avg: Tensor,
    exp_avg_sq: Tensor,
    /// Updates applied per slot: [slots] f64 (exact integers).
    steps: Tensor,
    /// The slot of every flat element: [N] u32.
    slot_of: Tensor,
    /// A bound on every slot's step count, known without reading `steps`: the largest count
    /// loaded plus the updates issued since (masked or not). Sizes the bias tables.
    max_step: u64,
    tables: Option<BiasTables>,
}

impl Adam {
    /// `vars` in model order; `group_of(name)` picks the index into `groups` (whose `params`
    /// lists are filled here, so pass them empty). The groups may differ in their rates only:
    /// one flat update serves them all, so betas and eps are shared.
    pub fn new(
        vars: &[(String, Var)],
        mut groups: Vec<ParamGroup>,
        group_of: impl Fn(&str) -> usize,
    ) -> Result<Self, TrainError> {
        for g in &mut groups {
            g.params.clear();
        }
        if let Some(first) = groups.first() {
            if let Some(g) = groups
                .iter()
                .find(|g| g.betas != first.betas || g.eps != first.eps)
            {
                return Err(TrainError::Config(format!(
                    "parameter group `{}` has betas {:?} and eps {}, group `{}` {:?} and {}: \
                     the groups may differ in their learning rates only",
                    g.name, g.betas, g.eps, first.name, first.betas, first.eps
                )));
            }
        }
        let device = vars
            .first()
            .map_or(Device::Cpu, |(_, v)| v.device().clone());
        let mut per_group: Vec<Vec<(String, Var)>> = groups.iter().map(|_| Vec::new()).collect();
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
            if !var.device().same_device(&device) {
                return Err(TrainError::Config(format!(
                    "parameter `{name}` is on another device than `{}`",
                    vars[0].0
                )));
            }
            groups[gi].params.push(name.clone());
            bucket.push((name.clone(), var.clone()));
        }
        let mut slots = Vec::new();
        let mut offset = 0;
        for (gi, bucket) in per_group.into_iter().enumerate() {
            for (name, var) in bucket {
                let len = var.elem_count();
                slots.push(Slot {
                    name,
                    var,
                    group: gi,
                    offset,
                    len,
                });
                offset += len;
            }
        }
        let lens: Vec<usize> = slots.iter().map(|s| s.len).collect();
        let zeros = Tensor::zeros(offset, DType::F32, &device)?;
        let mut adam = Self {
            groups,
            steps: Tensor::zeros(slots.len(), DType::F64, &device)?,
            slot_of: crate::compute::ops::adam::slot_index(&lens, &device)?,
            slots,
            exp_avg: zeros.clone(),
            exp_avg_sq: zeros,
            device,
            max_step: 0,
            tables: None,
        };
        // Built now, so steps upload nothing but their rates (until the tables grow).
        adam.ensure_tables(1)?;
        Ok(adam)
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
            vec![group(FREQ_GROUP, lr_freq), group("other", lr)],
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

    /// The state of parameter `name` (reads the step counts from the device).
    pub fn state(&self, name: &str) -> Result<Option<ParamState>, TrainError> {
        Ok(self
            .states()?
            .into_iter()
            .find(|(n, _)| *n == name)
            .map(|(_, s)| s))
    }

    /// `(name, state)` in state order; the moments are views of the flat buffers. Reads the
    /// step counts from the device (one copy).
    pub fn states(&self) -> Result<Vec<(&str, ParamState)>, TrainError> {
        let steps = self.steps.to_device(&Device::Cpu)?.to_vec1::<f64>()?;
        self.slots
            .iter()
            .zip(steps)
            .map(|(s, step)| {
                let view = |t: &Tensor| t.narrow(0, s.offset, s.len)?.reshape(s.var.shape());
                Ok((
                    s.name.as_str(),
                    ParamState {
                        step: step as u64,
                        exp_avg: view(&self.exp_avg)?,
                        exp_avg_sq: view(&self.exp_avg_sq)?,
                    },
                ))
            })
            .collect()
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

    /// Every group's rate set to `factor` × its initial rate, floored at `floor`.
    pub fn apply_factor(&mut self, factor: f64, floor: f64) {
        for g in &mut self.groups {
            g.lr = (g.initial_lr * factor).max(floor);
        }
    }

    /// The rate of group `name` (if there is one) multiplied by `by`.
    pub fn scale_group(&mut self, name: &str, by: f64) {
        for g in self.groups.iter_mut().filter(|g| g.name == name) {
            g.lr *= by;
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
        let (mut m, mut v, mut steps) = (Vec::new(), Vec::new(), Vec::new());
        for slot in &self.slots {
            let st = states.remove(&slot.name).expect("presence checked above");
            m.push(st.exp_avg.flatten_all()?.to_device(&self.device)?);
            v.push(st.exp_avg_sq.flatten_all()?.to_device(&self.device)?);
            steps.push(st.step as f64);
        }
        if !self.slots.is_empty() {
            self.exp_avg = Tensor::cat(&m, 0)?;
            self.exp_avg_sq = Tensor::cat(&v, 0)?;
        }
        self.max_step = steps.iter().fold(0f64, |a, &b| a.max(b)) as u64;
        self.ensure_tables(self.max_step as usize + 1)?;
        let n = steps.len();
        self.steps = Tensor::from_vec(steps, n, &self.device)?;
        for (g, &lr) in self.groups.iter_mut().zip(groups_lr) {
            g.lr = lr;
        }
        Ok(())
    }

    /// The gradients as one flat f32 buffer in state order (zeros for a `None` gradient),
    /// and which slots have one. `grads` is aligned with [`Self::param_names`].
    pub fn flatten(&self, grads: &[Option<Tensor>]) -> Result<(Tensor, Vec<bool>), TrainError> {
        if grads.len() != self.slots.len() {
            return Err(TrainError::Config(format!(
                "{} gradients given for {} parameters",
                grads.len(),
                self.slots.len()
            )));
        }
        let mut parts = Vec::with_capacity(grads.len());
        for (slot, g) in self.slots.iter().zip(grads) {
            parts.push(match g {
                Some(g) => {
                    if g.elem_count() != slot.len {
                        return Err(TrainError::Config(format!(
                            "gradient of `{}`: {:?}, the parameter is {:?}",
                            slot.name,
                            g.dims(),
                            slot.var.dims()
                        )));
                    }
                    g.detach().to_dtype(DType::F32)?.flatten_all()?
                }
                None => Tensor::zeros(slot.len, DType::F32, &self.device)?,
            });
        }
        let has = grads.iter().map(Option::is_some).collect();
        let flat = match parts.len() {
            0 => Tensor::zeros(0, DType::F32, &self.device)?,
            _ => Tensor::cat(&parts, 0)?,
        };
        Ok((flat, has))
    }

    /// One Adam update. `grads` is aligned with [`Self::param_names`]; a `None` gradient leaves
    /// that parameter and its state untouched (torch skips parameters whose `.grad` is `None`).
    pub fn step(&mut self, grads: &[Option<Tensor>]) -> Result<(), TrainError> {
        let (flat, has) = self.flatten(grads)?;
        self.step_masked(&flat, &has, None)
    }

    /// One Adam update on flat gradients `g` ([`Self::flatten`]'s) of the slots in `has`;
    /// with `apply` (a u8 scalar on the device) only where it is non-zero: otherwise
    /// nothing changes, moments and step counts included. Nothing is read back.
    pub fn step_masked(
        &mut self,
        g: &Tensor,
        has: &[bool],
        apply: Option<&Tensor>,
    ) -> Result<(), TrainError> {
        self.step_clipped(g, has, apply, None)
    }

    /// [`Self::step_masked`] of `g · coef` (`coef` an f32 scalar on the device: the
    /// global-norm clip factor): [`crate::compute::ops::adam`], one pass on the CPU, one
    /// kernel on a device, the same bits as the tensor ops.
    pub fn step_clipped(
        &mut self,
        g: &Tensor,
        has: &[bool],
        apply: Option<&Tensor>,
        coef: Option<&Tensor>,
    ) -> Result<(), TrainError> {
        let n_slots = self.slots.len();
        if n_slots == 0 || !has.iter().any(|&h| h) {
            return Ok(());
        }
        if has.len() != n_slots || g.dims() != self.exp_avg.dims() {
            return Err(TrainError::Config(format!(
                "flat gradient {:?} for {} parameters ({} elements)",
                g.dims(),
                n_slots,
                self.exp_avg.elem_count()
            )));
        }
        let dev = self.device.clone();
        let [b1, b2] = self.groups[0].betas;
        let eps = self.groups[0].eps;
        self.max_step += 1;
        self.ensure_tables(self.max_step as usize + 1)?;
        let tables = self.tables.as_ref().expect("tables just built");
        // Step number of this update per slot: the count so far plus one where it applies.
        let has_f: Vec<f64> = has.iter().map(|&h| h as u8 as f64).collect();
        let mut inc = Tensor::from_vec(has_f, n_slots, &dev)?;
        if let Some(a) = apply {
            inc = inc.broadcast_mul(&a.to_dtype(DType::F64)?)?;
        }
        let t = (&self.steps + &inc)?;
        let t_idx = t.to_dtype(DType::U32)?;
        let bias1 = tables.bias1.index_select(&t_idx, 0)?;
        let bias2_sqrt = tables.bias2_sqrt.index_select(&t_idx, 0)?;
        let lr: Vec<f64> = self.slots.iter().map(|s| self.groups[s.group].lr).collect();
        let step_size = Tensor::from_vec(lr, n_slots, &dev)?.div(&bias1)?;
        let params: Vec<Tensor> = self
            .slots
            .iter()
            .map(|s| s.var.as_tensor().detach())
            .collect();
        let (p, m, v) = crate::compute::ops::adam::update(&crate::compute::ops::adam::Update {
            g,
            params: &params,
            m: &self.exp_avg,
            v: &self.exp_avg_sq,
            slot_of: &self.slot_of,
            has,
            apply,
            coef,
            step_size: &step_size,
            bias2_sqrt: &bias2_sqrt,
            b1,
            b2,
            eps,
        })?;
        for slot in &self.slots {
            slot.var.set(
                &p.narrow(0, slot.offset, slot.len)?
                    .reshape(slot.var.shape())?,
            )?;
        }
        self.exp_avg = m;
        self.exp_avg_sq = v;
        self.steps = t;
        Ok(())
    }

    /// Bias-correction tables covering step counts 0..len (grown by doubling).
    fn ensure_tables(&mut self, len: usize) -> Result<(), TrainError> {
        let Some(group) = self.groups.first() else {
            return Ok(());
        };
        let [b1, b2] = group.betas;
        if self.tables.as_ref().is_some_and(|t| t.len >= len) {
            return Ok(());
        }
        let len = len.max(1024).next_power_of_two();
        // The same f64 expressions as a per-parameter update: 1 − b1^t, sqrt(1 − b2^t).
        let bias1: Vec<f64> = (0..len).map(|t| 1.0 - b1.powi(t as i32)).collect();
        let bias2: Vec<f64> = (0..len).map(|t| (1.0 - b2.powi(t as i32)).sqrt()).collect();
        self.tables = Some(BiasTables {
            len,
            bias1: Tensor::from_vec(bias1, len, &self.device)?,
            bias2_sqrt: Tensor::from_vec(bias2, len, &self.device)?,
        });
        Ok(())
    }
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
        assert_eq!(adam.state("w").unwrap().unwrap().step, 3);
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
        assert_eq!(adam.state("pts_linears.0.bias").unwrap().unwrap().step, 0);
        assert!(adam.step(&[]).is_err());
    }

    #[test]
    fn schedule_floors_and_decays_continuously() {
        assert_eq!(decayed_lr(5e-4, 0, 0.1, 500_000.0, 1e-5), 5e-4);
        let half = decayed_lr(5e-4, 250_000, 0.1, 500_000.0, 1e-5);
        assert!((half - 5e-4 * 0.1f64.sqrt()).abs() < 1e-15);
        assert_eq!(decayed_lr(1e-4, 10_000_000, 0.1, 500_000.0, 1e-5), 1e-5);
    }

    /// One flat update equals an update per parameter (the reference formula per tensor),
    /// bit for bit, with two groups, a parameter without a gradient on one step, and a masked
    /// step that changes nothing.
    /// Steps accounted as CUDA (clipped, masked, one parameter without a gradient) give the
    /// CPU route's bits and count the update as `adam.cu`'s one launch, with none of the
    /// plain update's element-wise ops.
    #[test]
    fn update_on_the_emulated_kernel_keeps_the_cpu_bits() {
        use crate::compute::account::{Account, Route};
        let dev = Device::Cpu;
        let shapes: [&[usize]; 3] = [&[3, 4], &[5], &[2, 2]];
        let names = ["graph_net.w", "pts_linears.0.weight", "pts_linears.0.bias"];
        let make = || -> Vec<(String, Var)> {
            names
                .iter()
                .zip(shapes)
                .enumerate()
                .map(|(k, (name, s))| {
                    let len: usize = s.iter().product();
                    let v: Vec<f32> = (0..len).map(|i| (i + k) as f32 * 0.37 - 1.1).collect();
                    let t = Tensor::from_vec(v, s, &dev).unwrap();
                    (name.to_string(), Var::from_tensor(&t).unwrap())
                })
                .collect()
        };
        let run = |accounted: bool| {
            let vars = make();
            let mut adam = Adam::reference(&vars, 1e-3, 5e-3, [0.9, 0.999], 1e-8).unwrap();
            let account = accounted.then(|| Account::start(&dev, Route::Cuda).unwrap());
            for step in 0..3usize {
                let grads: Vec<Option<Tensor>> = adam
                    .param_names()
                    .enumerate()
                    .map(|(k, _)| {
                        let shape = vars[k].1.shape().clone();
                        let len = shape.elem_count();
                        let g: Vec<f32> = (0..len)
                            .map(|i| ((i * 5 + k + step) % 7) as f32 * 0.3 - 0.8)
                            .collect();
                        (step != 1 || k != 2).then(|| Tensor::from_vec(g, shape, &dev).unwrap())
                    })
                    .collect();
                let (flat, has) = adam.flatten(&grads).unwrap();
                let coef = Tensor::new(0.75f32, &dev).unwrap();
                let ok = Tensor::new(u8::from(step != 2), &dev).unwrap();
                adam.step_clipped(&flat, &has, Some(&ok), Some(&coef))
                    .unwrap();
            }
            let report = account.map(Account::finish);
            let mut bits: Vec<Vec<u32>> = vars
                .iter()
                .map(|(_, v)| {
                    let x: Vec<f32> = v.flatten_all().unwrap().to_vec1().unwrap();
                    x.iter().map(|x| x.to_bits()).collect()
                })
                .collect();
            for t in [&adam.exp_avg, &adam.exp_avg_sq] {
                let x: Vec<f32> = t.to_vec1().unwrap();
                bits.push(x.iter().map(|x| x.to_bits()).collect());
            }
            (bits, report)
        };
        let (cpu, _) = run(false);
        let (counted, report) = run(true);
        let report = report.unwrap();
        assert_eq!(cpu, counted);
        let op = |name: &str| report.ops.get(name).copied().unwrap_or_default();
        assert_eq!((op("pma-adam").ops, op("pma-adam").launches), (3, 3));
        assert_eq!(op("pma-wrap").launches, 0);
        let n = 12 + 5 + 4;
        assert_eq!(op("pma-adam").bytes_written, 3 * 3 * 4 * n);
        for plain in ["sqrt", "sqr", "sub", "where"] {
            assert_eq!(
                op(plain).ops,
                0,
                "plain op `{plain}` in {:?}",
                report.ops.keys()
            );
        }
    }

    #[test]
    fn flat_update_equals_per_parameter_updates_and_masks() {
        let shapes: [&[usize]; 3] = [&[2, 3], &[4], &[1, 5]];
        let names = ["graph_net.w", "pts_linears.0.weight", "pts_linears.0.bias"];
        let init = |k: usize, n: usize| -> Vec<f32> {
            (0..n)
                .map(|i| ((i * 7 + k * 3) % 11) as f32 * 0.1 - 0.5)
                .collect()
        };
        let vars: Vec<(String, Var)> = names
            .iter()
            .zip(shapes)
            .enumerate()
            .map(|(k, (n, s))| {
                let len = s.iter().product();
                let t = Tensor::from_vec(init(k, len), s, &Device::Cpu).unwrap();
                (n.to_string(), Var::from_tensor(&t).unwrap())
            })
            .collect();
        let mut adam = Adam::reference(&vars, 1e-4, 5e-4, [0.9, 0.999], 1e-8).unwrap();
        // The per-parameter reference: the formula of the module docs on each tensor, with
        // the scalars as host f64 (what a per-tensor update multiplies by).
        let mut reference: Vec<(Tensor, Tensor, Tensor, u64)> = vars
            .iter()
            .map(|(_, v)| {
                let t = v.as_tensor().copy().unwrap();
                (
                    t.clone(),
                    t.zeros_like().unwrap(),
                    t.zeros_like().unwrap(),
                    0,
                )
            })
            .collect();
        let lr_of = |name: &str| {
            if reference_group(name) == 0 {
                1e-4
            } else {
                5e-4
            }
        };
        for step in 0..4 {
            // Optimizer order is group-major: graph_net first, then the others.
            let grads: Vec<Option<Tensor>> = adam
                .param_names()
                .map(|n| {
                    let k = names.iter().position(|m| *m == n).unwrap();
                    if step == 2 && k == 1 {
                        return None;
                    }
                    let len = shapes[k].iter().product();
                    let g: Vec<f32> = init(k + step + 1, len).iter().map(|v| v * 3.0).collect();
                    Some(Tensor::from_vec(g, shapes[k], &Device::Cpu).unwrap())
                })
                .collect();
            let order: Vec<usize> = adam
                .param_names()
                .map(|n| names.iter().position(|m| *m == n).unwrap())
                .collect();
            if step == 3 {
                // Masked off: nothing may change.
                let before: Vec<Vec<f32>> = vars
                    .iter()
                    .map(|(_, v)| v.flatten_all().unwrap().to_vec1().unwrap())
                    .collect();
                let (flat, has) = adam.flatten(&grads).unwrap();
                let off = Tensor::new(0u8, &Device::Cpu).unwrap();
                adam.step_masked(&flat, &has, Some(&off)).unwrap();
                for ((_, v), b) in vars.iter().zip(&before) {
                    assert_eq!(&v.flatten_all().unwrap().to_vec1::<f32>().unwrap(), b);
                }
                let steps: Vec<u64> = adam.states().unwrap().iter().map(|s| s.1.step).collect();
                assert_eq!(
                    steps,
                    vec![3, 2, 3],
                    "the parameter without a gradient on step 2 missed one"
                );
                break;
            }
            adam.step(&grads).unwrap();
            for (g, &k) in grads.iter().zip(&order) {
                let Some(g) = g else { continue };
                let (p, m, v, t) = &mut reference[k];
                *t += 1;
                let ti = *t as i32;
                let m1 = (&*m + ((g - &*m).unwrap() * (1.0 - 0.9)).unwrap()).unwrap();
                let v1 =
                    ((&*v * 0.999).unwrap() + (g.sqr().unwrap() * (1.0 - 0.999)).unwrap()).unwrap();
                let step_size = lr_of(names[k]) / (1.0 - 0.9f64.powi(ti));
                let bias2 = (1.0 - 0.999f64.powi(ti)).sqrt();
                let denom = ((v1.sqrt().unwrap() / bias2).unwrap() + 1e-8).unwrap();
                let upd = ((&m1 * step_size).unwrap() / denom).unwrap();
                *p = (&*p - upd).unwrap();
                (*m, *v) = (m1, v1);
            }
            for (k, (name, var)) in vars.iter().enumerate() {
                let bits = |t: &Tensor| -> Vec<u32> {
                    let v: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
                    v.iter().map(|x| x.to_bits()).collect()
                };
                assert_eq!(
                    bits(var.as_tensor()),
                    bits(&reference[k].0),
                    "{name} at step {step}"
                );
                let st = adam.state(name).unwrap().unwrap();
                assert_eq!(bits(&st.exp_avg), bits(&reference[k].1), "{name} m");
                assert_eq!(bits(&st.exp_avg_sq), bits(&reference[k].2), "{name} v");
                assert_eq!(st.step, reference[k].3, "{name} step");
            }
        }
    }
}
