//! Reference `.th` checkpoint → pma checkpoint (+ optional training state).
//!
//! The model tensors are copied byte for byte under their reference names
//! (docs/reference.md, "Checkpoint and state_dict names"). The [`Config`] is inferred from the tensor shapes
//! ([`infer_config`]) and then every tensor is checked against the layout that
//! config implies, so a checkpoint of another architecture fails with the list
//! of tensors that do not fit instead of loading garbage. `n_framecodes` and
//! `rest_pose` come from the `framecodes.codes.weight` and `rest_pose` tensors.
//!
//! With the optimiser, the torch Adam state is written as a pma training state
//! beside the checkpoint (see [`crate::train_state`]).

use std::{
    collections::HashMap,
    io::Write,
    path::{Path, PathBuf},
};

use pma_data::fsio::{commit_all, AtomicFile};

use candle_core::{Device, Tensor};
use pma_model::{
    error::ModelError,
    network::checkpoint::{check_tensors, param_names, to_bytes},
    train::state::fingerprint,
    Config,
};
use safetensors::Dtype;

use crate::{
    error::{ConvertError, Result},
    raw::RawTensor,
    torch::read_reference_checkpoint,
    train_state::{sidecar_path, train_state_from_torch},
};

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
    /// Parameters that had Adam state in the `.th` (the others start from zero).
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

/// `pma convert checkpoint`: reads `input` (`.th`), writes a pma checkpoint to
/// `output` and, with `opts.with_optimizer`, the training state beside it.
/// Nothing is written if any check fails; the pair is committed together
/// (`pma_data::fsio::commit_all`): both files are complete and synced before
/// either is renamed into place, the model last, so a failed write (a full disk)
/// leaves neither. The train state carries the model's fingerprint, which
/// catches a pair split by a crash between the two renames.
pub fn convert_checkpoint(
    input: &Path,
    output: &Path,
    opts: &CheckpointOptions,
) -> Result<CheckpointReport> {
    let ck = read_reference_checkpoint(input)?;
    let cfg = checked_config(input, &ck.model)?;
    // Checked before anything is written; the fingerprint of the written model is added below.
    let state = if opts.with_optimizer {
        Some(train_state_from_torch(&ck, &cfg, None)?)
    } else {
        None
    };

    let mut tensors: HashMap<String, Tensor> = HashMap::with_capacity(ck.model.len());
    for (name, t) in &ck.model {
        let tensor = t.to_candle(&Device::Cpu).map_err(ModelError::Candle)?;
        tensors.insert(name.clone(), tensor);
    }
    let model_bytes = to_bytes(output, &tensors, &cfg)?;
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
    let mut files = Vec::new();
    if let Some(mut state) = state {
        state.model_fingerprint = Some(fingerprint(&model_bytes));
        let side = sidecar_path(output);
        files.push(staged(&side, &state.to_bytes(&side)?)?);
        report.n_moments = ck.optimizer.as_ref().map_or(0, |o| o.state.len());
        report.train_state = Some(side);
    }
    files.push(staged(output, &model_bytes)?);
    commit_all(files).map_err(|e| ConvertError::write(output, e))?;
    Ok(report)
}

/// `bytes` in a temporary file beside `path`, to be committed with the others.
fn staged(path: &Path, bytes: &[u8]) -> Result<AtomicFile> {
    let f = AtomicFile::create(path).map_err(|e| ConvertError::write(path, e))?;
    f.writer()
        .write_all(bytes)
        .map_err(|e| ConvertError::write(path, e))?;
    Ok(f)
}
