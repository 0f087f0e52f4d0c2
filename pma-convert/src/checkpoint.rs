//! Reference `.th` checkpoint → pma checkpoint (+ optional training state).
//!
//! The model tensors are copied byte for byte under their reference names
//! (spec model.md §8.1). The [`Config`] is inferred from the tensor shapes
//! ([`infer_config`]) and then every tensor is checked against the layout that
//! config implies, so a checkpoint of another architecture fails with the list
//! of tensors that do not fit instead of loading garbage. `n_framecodes` and
//! `rest_pose` come from the `framecodes.codes.weight` and `rest_pose` tensors.
//!
//! With the optimiser, the torch Adam state is written as a pma training state
//! (see [`crate::train_state`]): optimiser ids are mapped to parameter names by
//! the reference's grouping (model.md §6, §8.2): the parameters are taken in
//! `named_parameters()` order and split into group 0 (name contains
//! `graph_net`, `pose_extractor`, `win_fun`, `modulator`, `pts_enc_point` or
//! `pts_enc_pose`) and group 1 (the rest); torch numbers group 0 first.

use std::{
    collections::{BTreeMap, HashMap},
    path::{Path, PathBuf},
};

use candle_core::{Device, Tensor};
use pma_model::{
    checkpoint::{check_tensors, param_names, save, tensor_layout},
    error::ModelError,
    Config,
};
use safetensors::Dtype;

use crate::{
    error::{ConvertError, Result},
    raw::RawTensor,
    torch::{read_reference_checkpoint, ReferenceCheckpoint},
    train_state::{sidecar_path, Moments, ParamGroup, TrainState},
};

/// Name substrings that put a parameter in the reference's group 0 ("freq", lr 1e-4).
pub const FREQ_GROUP_KEYS: [&str; 6] = [
    "graph_net",
    "pose_extractor",
    "win_fun",
    "modulator",
    "pts_enc_point",
    "pts_enc_pose",
];

/// The reference's parameter group of a parameter name (0 = freq, 1 = other).
pub fn reference_param_group(name: &str) -> usize {
    if FREQ_GROUP_KEYS.iter().any(|k| name.contains(k)) {
        0
    } else {
        1
    }
}

/// The parameter names of each reference Adam group, in optimiser-id order.
pub fn reference_param_groups(cfg: &Config) -> [Vec<String>; 2] {
    let mut groups = [Vec::new(), Vec::new()];
    for n in param_names(cfg) {
        groups[reference_param_group(&n)].push(n);
    }
    groups
}

/// Options of [`convert_checkpoint`].
#[derive(Clone, Debug, Default)]
pub struct CheckpointOptions {
    /// Also export the Adam state to [`sidecar_path`]`(output)`.
    pub with_optimizer: bool,
}

/// What a conversion produced.
#[derive(Clone, Debug)]
pub struct CheckpointReport {
    pub config: Config,
    pub n_tensors: usize,
    pub n_parameters: usize,
    pub global_iter: Option<i64>,
    /// The training-state file, when written.
    pub train_state: Option<PathBuf>,
    /// Parameters that had Adam moments.
    pub n_moments: usize,
}

fn shape_of<'a>(model: &'a [(String, RawTensor)], name: &str) -> Option<&'a [usize]> {
    model
        .iter()
        .find(|(n, _)| n == name)
        .map(|(_, t)| t.shape.as_slice())
}

fn count(model: &[(String, RawTensor)], f: impl Fn(usize) -> String) -> usize {
    (0..)
        .take_while(|&i| shape_of(model, &f(i)).is_some())
        .count()
}

/// Reads the architecture off the tensor shapes. Dimensions that cannot be
/// read (a tensor is missing) keep the paper value; the result is only a
/// hypothesis until [`check_tensors`] confirms every shape. Non-shape
/// hyper-parameters (sine frequencies, sampling counts, quirks) are not stored
/// in a reference checkpoint and are the paper's.
pub fn infer_config(model: &[(String, RawTensor)]) -> Config {
    let mut c = Config::paper();
    let dim = |name: &str, axis: usize| shape_of(model, name).and_then(|s| s.get(axis).copied());
    if let Some(j) = dim("rest_pose", 0) {
        c.n_joints = j;
    }
    let depth = count(model, |i| format!("pts_linears.{i}.weight"));
    if depth > 0 {
        c.trunk_depth = depth;
    }
    if let Some(w) = dim("pts_linears.0.weight", 0) {
        c.trunk_width = w;
    }
    let n_pm = count(model, |k| format!("modulator.sin_lin{k}.layer.weight"));
    if n_pm > 0 {
        c.n_pm = n_pm;
    }
    if let Some(f) = dim("modulator.sin_lin0.layer.weight", 0) {
        c.freq_dim = f;
    }
    if let Some(ce) = dim("pts_enc_pose.sin_lin0.layer.weight", 0) {
        c.point_enc_dim = ce;
    }
    // A skip layer takes the trunk width plus the modulator output again.
    let s_dim = c.n_pm * c.freq_dim;
    c.skips = (0..c.trunk_depth.saturating_sub(1))
        .filter(|&i| {
            dim(&format!("pts_linears.{}.weight", i + 1), 1) == Some(c.trunk_width + s_dim)
        })
        .collect();
    if let Some(v) = dim("views_linears.0.weight", 0) {
        c.view_width = v;
    }
    match shape_of(model, "framecodes.codes.weight") {
        Some([n, ch]) => {
            c.use_framecodes = true;
            c.n_framecodes = *n;
            c.framecode_ch = *ch;
        }
        Some(_) => {}
        None => c.use_framecodes = false,
    }
    if let Some(view_in) = dim("views_linears.0.weight", 1) {
        let codes = if c.use_framecodes { c.framecode_ch } else { 0 };
        let sh2 = view_in.saturating_sub(c.trunk_width + codes);
        let sh = (sh2 as f64).sqrt().round() as usize;
        if sh * sh == sh2 {
            c.sh_degree = sh;
        }
    }
    if let Some(g) = dim("graph_net.layers.0.bias", 0) {
        c.gnn_width = g;
    }
    let graph = count(model, |l| format!("graph_net.layers.{l}.adj_w"));
    if graph > 0 {
        c.gnn_graph_layers = graph;
        c.gnn_fc_layers = count(model, |l| format!("graph_net.layers.{}.weight", l + graph));
    }
    if let Some(h) = dim("win_fun.layer_pose.layer.weight", 0) {
        c.win_hidden = h;
    }
    if let Some(h) = dim("pose_extractor.sin_lin0.layer.weight", 0) {
        c.pose_extractor_hidden = h;
    }
    let pe = count(model, |l| format!("pose_extractor.sin_lin{l}.layer.weight"));
    if pe > 0 {
        c.pose_extractor_depth = pe - 1;
    }
    c
}

/// Infers the config and checks every tensor against it.
pub fn checked_config(path: &Path, model: &[(String, RawTensor)]) -> Result<Config> {
    let cfg = infer_config(model);
    let mut problems: Vec<String> = Vec::new();
    if let Err(e) = cfg.validate() {
        problems.push(e.to_string());
    }
    let dtype_of = |d: Dtype| match d {
        Dtype::F32 => candle_core::DType::F32,
        Dtype::F64 => candle_core::DType::F64,
        Dtype::F16 => candle_core::DType::F16,
        Dtype::BF16 => candle_core::DType::BF16,
        Dtype::I64 => candle_core::DType::I64,
        // Reported as a dtype problem through this stand-in.
        _ => candle_core::DType::U8,
    };
    problems.extend(check_tensors(
        &cfg,
        model
            .iter()
            .map(|(n, t)| (n.as_str(), t.shape.as_slice(), dtype_of(t.dtype))),
    ));
    if !problems.is_empty() {
        problems.push(format!(
            "(checked against the config inferred from the tensor shapes: trunk {}x{} skips {:?}, n_pm {}, freq_dim {}, \
             gnn {}+{} layers of width {}, n_framecodes {}; the reference architecture is the paper config)",
            cfg.trunk_depth,
            cfg.trunk_width,
            cfg.skips,
            cfg.n_pm,
            cfg.freq_dim,
            cfg.gnn_graph_layers,
            cfg.gnn_fc_layers,
            cfg.gnn_width,
            cfg.n_framecodes
        ));
        return Err(ModelError::Checkpoint {
            path: path.to_path_buf(),
            problems,
        }
        .into());
    }
    Ok(cfg)
}

/// Maps the torch Adam state onto parameter names (see the module docs).
pub fn train_state_from_torch(ck: &ReferenceCheckpoint, cfg: &Config) -> Result<TrainState> {
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
    if adam.param_groups.len() != names.len() {
        return Err(ConvertError::mismatch(
            path,
            "optimizer.param_groups",
            format!("{} groups (freq, other)", names.len()),
            format!("{} groups", adam.param_groups.len()),
        ));
    }
    let shapes: HashMap<String, Vec<usize>> = tensor_layout(cfg)
        .into_iter()
        .map(|t| (t.name, t.shape))
        .collect();
    let mut id_to_name: HashMap<usize, &str> = HashMap::new();
    let mut param_groups = Vec::new();
    for (g, (group, names)) in adam.param_groups.iter().zip(&names).enumerate() {
        if group.params.len() != names.len() {
            return Err(ConvertError::mismatch(
                path,
                format!("optimizer.param_groups[{g}].params"),
                format!("{} parameters ({}…)", names.len(), names[0]),
                format!("{} ids", group.params.len()),
            ));
        }
        if group.amsgrad {
            return Err(ConvertError::invalid(
                path,
                format!("optimizer.param_groups[{g}].amsgrad"),
                "AMSGrad state (max_exp_avg_sq) is not supported by pma's Adam",
            ));
        }
        for (&id, name) in group.params.iter().zip(names) {
            if id_to_name.insert(id, name).is_some() {
                return Err(ConvertError::invalid(
                    path,
                    "optimizer.param_groups",
                    format!("optimiser id {id} is listed twice"),
                ));
            }
        }
        param_groups.push(ParamGroup {
            lr: group.lr,
            betas: [group.betas.0, group.betas.1],
            eps: group.eps,
            weight_decay: group.weight_decay,
            params: names.clone(),
        });
    }

    let mut moments = BTreeMap::new();
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
        moments.insert(
            name.to_string(),
            Moments {
                step: st.step as u64,
                exp_avg: st.exp_avg.clone(),
                exp_avg_sq: st.exp_avg_sq.clone(),
            },
        );
    }
    Ok(TrainState {
        global_iter,
        param_groups,
        moments,
    })
}

/// `pma convert checkpoint`: reads `input` (`.th`), writes a pma checkpoint to
/// `output` and, with `opts.with_optimizer`, the training state beside it.
/// Both files are written atomically; nothing is written if any check fails.
pub fn convert_checkpoint(
    input: &Path,
    output: &Path,
    opts: &CheckpointOptions,
) -> Result<CheckpointReport> {
    let ck = read_reference_checkpoint(input)?;
    let cfg = checked_config(input, &ck.model)?;
    let state = if opts.with_optimizer {
        Some(train_state_from_torch(&ck, &cfg)?)
    } else {
        None
    };

    let mut tensors: HashMap<String, Tensor> = HashMap::with_capacity(ck.model.len());
    for (name, t) in &ck.model {
        let tensor = t.to_candle(&Device::Cpu).map_err(ModelError::Candle)?;
        tensors.insert(name.clone(), tensor);
    }
    save(output, &tensors, &cfg)?;
    crate::set_readable(output)?;
    let n_parameters = param_names(&cfg)
        .iter()
        .map(|n| tensors[n].elem_count())
        .sum();

    let mut report = CheckpointReport {
        config: cfg,
        n_tensors: ck.model.len(),
        n_parameters,
        global_iter: ck.global_iter,
        train_state: None,
        n_moments: 0,
    };
    if let Some(state) = state {
        let side = sidecar_path(output);
        state.write(&side)?;
        report.n_moments = state.moments.len();
        report.train_state = Some(side);
    }
    Ok(report)
}
