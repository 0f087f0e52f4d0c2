//! The Adam state of a reference checkpoint as a pma training state, so that
//! training can resume from a `.th` file.
//!
//! The file format ("pma-train-state" v1: `exp_avg.<param>` / `exp_avg_sq.<param>`
//! f32 tensors plus `global_iter`, `steps` and `param_groups` metadata) is
//! owned by the trainer and implemented once, in `pma_model::train::state`;
//! this module only maps torch's optimiser state onto it:
//!
//! * optimiser ids → parameter names by the reference's grouping
//!   (docs/reference.md, "Training schedule and Adam"): the parameters in `named_parameters()` order, split into group
//!   0 "freq" (names containing `graph_net`, `pose_extractor`, `win_fun`,
//!   `modulator`, `pts_enc_point`, `pts_enc_pose`) and group 1 "other"; torch
//!   numbers group 0 first;
//! * `lr` is the rate torch last set (the schedule's value for the next step);
//!   `initial_lr` is the reference's base rate of the group (1e-4 / 5e-4);
//! * a parameter torch holds no state for has never been stepped: it gets
//!   zero moments and step 0, exactly what Adam starts from, so the file is
//!   complete;
//! * AMSGrad and weight decay have no counterpart in pma's Adam and are refused.

use std::{collections::HashMap, path::Path};

use candle_core::{Device, Tensor};
use pma_model::{
    error::ModelError,
    network::checkpoint::{param_names, tensor_layout},
    train::{
        adam::reference_group,
        state::{fingerprint, TrainState},
        ParamGroup, ParamState, TrainConfig,
    },
    Config,
};
use safetensors::Dtype;

use crate::{
    error::{ConvertError, Result},
    torch::{ReferenceCheckpoint, TorchAdam, TorchAdamGroup},
};

pub use pma_model::train::state::{FORMAT, FORMAT_VERSION};

/// `dir/name.safetensors` → `dir/name.optim.safetensors`.
pub fn sidecar_path(checkpoint: &Path) -> std::path::PathBuf {
    let stem = checkpoint
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    checkpoint.with_file_name(format!("{stem}.optim.safetensors"))
}

/// The parameter names of each reference Adam group, in optimiser-id order.
pub fn reference_param_groups(cfg: &Config) -> [Vec<String>; 2] {
    let mut groups = [Vec::new(), Vec::new()];
    for n in param_names(cfg) {
        groups[reference_group(&n)].push(n);
    }
    groups
}

fn candle(e: candle_core::Error) -> ConvertError {
    ModelError::Candle(e).into()
}

/// Maps the torch Adam state of `ck` onto parameter names (see the module docs).
/// `model_file` is the pma checkpoint written from the same `.th`; its
/// fingerprint ties the two files together.
pub fn train_state_from_torch(
    ck: &ReferenceCheckpoint,
    cfg: &Config,
    model_file: Option<&[u8]>,
) -> Result<TrainState> {
    let path = &ck.path;
    let adam = ck.optimizer.as_ref().ok_or_else(|| {
        ConvertError::missing(path, "optimizer", " (needed for --with-optimizer)")
    })?;
    let global_iter = ck.global_iter.ok_or_else(|| {
        ConvertError::missing(path, "global_iter", " (needed for --with-optimizer)")
    })?;
    let global_iter = u64::try_from(global_iter).map_err(|_| {
        ConvertError::invalid(path, "global_iter", format!("negative value {global_iter}"))
    })?;

    let names = reference_param_groups(cfg);
    let (groups, id_to_name) = param_groups(path, adam, &names)?;
    let shapes: HashMap<String, Vec<usize>> = tensor_layout(cfg)
        .into_iter()
        .map(|t| (t.name, t.shape))
        .collect();
    let mut params = param_states(path, adam, &id_to_name, &shapes)?;
    add_unstepped(&mut params, &names, &shapes)?;
    Ok(TrainState {
        global_iter,
        groups,
        params,
        rng: None,
        sampler: None,
        progress: None,
        run_config: None,
        model_fingerprint: model_file.map(fingerprint),
        error_map: None,
        occupied: None,
        weights: Default::default(),
    })
}

/// The two groups with their rates, and which parameter each optimiser id is.
fn param_groups<'a>(
    path: &Path,
    adam: &TorchAdam,
    names: &'a [Vec<String>; 2],
) -> Result<(Vec<ParamGroup>, HashMap<usize, &'a str>)> {
    if adam.param_groups.len() != names.len() {
        return Err(ConvertError::mismatch(
            path,
            "optimizer.param_groups",
            format!("{} groups (freq, other)", names.len()),
            format!("{} groups", adam.param_groups.len()),
        ));
    }
    let paper = TrainConfig::paper();
    let mut id_to_name: HashMap<usize, &str> = HashMap::new();
    let mut groups = Vec::new();
    for (g, (group, names)) in adam.param_groups.iter().zip(names).enumerate() {
        check_group(path, g, group, names)?;
        for (&id, name) in group.params.iter().zip(names) {
            if id_to_name.insert(id, name).is_some() {
                return Err(ConvertError::invalid(
                    path,
                    "optimizer.param_groups",
                    format!("optimiser id {id} is listed twice"),
                ));
            }
        }
        let (name, initial_lr) = if g == 0 {
            ("freq", paper.lr_freq)
        } else {
            ("other", paper.lr)
        };
        groups.push(ParamGroup {
            name: name.to_string(),
            initial_lr,
            lr: group.lr,
            betas: [group.betas.0, group.betas.1],
            eps: group.eps,
            params: names.clone(),
        });
    }
    Ok((groups, id_to_name))
}

/// A group has one id per parameter and no option pma's Adam lacks.
fn check_group(path: &Path, g: usize, group: &TorchAdamGroup, names: &[String]) -> Result<()> {
    let key = |k: &str| format!("optimizer.param_groups[{g}].{k}");
    if group.params.len() != names.len() {
        return Err(ConvertError::mismatch(
            path,
            key("params"),
            format!("{} parameters ({}, ...)", names.len(), names[0]),
            format!("{} ids", group.params.len()),
        ));
    }
    if group.amsgrad {
        return Err(ConvertError::invalid(
            path,
            key("amsgrad"),
            "AMSGrad is not supported by pma's Adam",
        ));
    }
    if group.weight_decay != 0.0 {
        return Err(ConvertError::invalid(
            path,
            key("weight_decay"),
            format!(
                "{} is not supported by pma's Adam (the reference uses 0)",
                group.weight_decay
            ),
        ));
    }
    Ok(())
}

/// The moments and step count of every parameter torch holds state for.
fn param_states(
    path: &Path,
    adam: &TorchAdam,
    id_to_name: &HashMap<usize, &str>,
    shapes: &HashMap<String, Vec<usize>>,
) -> Result<HashMap<String, ParamState>> {
    let mut params: HashMap<String, ParamState> = HashMap::new();
    for (id, st) in &adam.state {
        let key = format!("optimizer.state[{id}]");
        let name = *id_to_name.get(id).ok_or_else(|| {
            ConvertError::invalid(path, &key, "optimiser id is in no parameter group")
        })?;
        let shape = &shapes[name];
        for (what, t) in [("exp_avg", &st.exp_avg), ("exp_avg_sq", &st.exp_avg_sq)] {
            if &t.shape != shape || t.dtype != Dtype::F32 {
                return Err(ConvertError::mismatch(
                    path,
                    format!("{key}.{what} (parameter `{name}`)"),
                    format!("F32 of shape {shape:?}"),
                    format!("{:?} of shape {:?}", t.dtype, t.shape),
                ));
            }
        }
        if !(st.step >= 0.0 && st.step.fract() == 0.0 && st.step < 9.0e15) {
            return Err(ConvertError::invalid(
                path,
                format!("{key}.step"),
                format!("{} is not a step count", st.step),
            ));
        }
        let state = ParamState {
            step: st.step as u64,
            exp_avg: st.exp_avg.to_candle(&Device::Cpu).map_err(candle)?,
            exp_avg_sq: st.exp_avg_sq.to_candle(&Device::Cpu).map_err(candle)?,
        };
        params.insert(name.to_string(), state);
    }
    Ok(params)
}

/// Zero moments and step 0 for the parameters torch never stepped.
fn add_unstepped(
    params: &mut HashMap<String, ParamState>,
    names: &[Vec<String>; 2],
    shapes: &HashMap<String, Vec<usize>>,
) -> Result<()> {
    for name in names.iter().flatten() {
        if !params.contains_key(name) {
            let zeros = Tensor::zeros(
                shapes[name].as_slice(),
                candle_core::DType::F32,
                &Device::Cpu,
            )
            .map_err(candle)?;
            params.insert(
                name.clone(),
                ParamState {
                    step: 0,
                    exp_avg: zeros.clone(),
                    exp_avg_sq: zeros,
                },
            );
        }
    }
    Ok(())
}
