//! What the reference trainer saves: the model's state_dict, the Adam
//! `state_dict()` and the iteration count (docs/reference.md, "Checkpoint and
//! state_dict names" and "Training schedule and Adam").

use std::{
    collections::BTreeMap,
    path::{Path, PathBuf},
};

use safetensors::Dtype;

use super::{Heap, TorchArchive, Value};
use crate::{
    error::{ConvertError, Result},
    raw::RawTensor,
};

/// The Adam state of one parameter, as torch saves it.
#[derive(Clone, Debug, PartialEq)]
pub struct TorchAdamParam {
    /// Steps taken; torch stores a float, an int or a 0-d tensor depending on its version.
    pub step: f64,
    pub exp_avg: RawTensor,
    pub exp_avg_sq: RawTensor,
}

/// One Adam parameter group (`param_groups[g]`).
#[derive(Clone, Debug, PartialEq)]
pub struct TorchAdamGroup {
    pub lr: f64,
    pub betas: (f64, f64),
    pub eps: f64,
    pub weight_decay: f64,
    pub amsgrad: bool,
    /// Optimiser ids of the group's parameters, in order.
    pub params: Vec<usize>,
}

/// `optimizer.state_dict()` of a torch Adam.
#[derive(Clone, Debug, PartialEq)]
pub struct TorchAdam {
    pub state: BTreeMap<usize, TorchAdamParam>,
    pub param_groups: Vec<TorchAdamGroup>,
}
/// What the reference trainer saves.
#[derive(Clone, Debug)]
pub struct ReferenceCheckpoint {
    pub path: PathBuf,
    /// The state_dict in its saved (module registration) order.
    pub model: Vec<(String, RawTensor)>,
    pub optimizer: Option<TorchAdam>,
    pub global_iter: Option<i64>,
}

/// Reads `{'model', 'optimizer', 'global_iter'}` from a reference `.th` file.
/// `optimizer` and `global_iter` are optional here; callers that need them say so.
pub fn read_reference_checkpoint(path: &Path) -> Result<ReferenceCheckpoint> {
    let mut ar = TorchArchive::open(path)?;
    let g = ar.graph().clone();
    if g.heap.items(&g.root).is_none() {
        return Err(ConvertError::mismatch(
            path,
            "<top level>",
            "a dict",
            g.root.kind(),
        ));
    }
    let model_v = g.heap.get(&g.root, "model").ok_or_else(|| {
        ConvertError::missing(
            path,
            "model",
            " (the checkpoint's top-level dict must hold the state_dict under `model`)",
        )
    })?;
    let model = read_tensor_dict(&mut ar, &g.heap, model_v, "model")?;

    let global_iter = match g.heap.get(&g.root, "global_iter") {
        None => None,
        Some(Value::Int(i)) => Some(*i),
        Some(other) => {
            return Err(ConvertError::mismatch(
                path,
                "global_iter",
                "an int",
                other.kind(),
            ))
        }
    };
    let optimizer = match g.heap.get(&g.root, "optimizer") {
        None | Some(Value::None) => None,
        Some(v) => Some(read_adam(&mut ar, &g.heap, v)?),
    };
    Ok(ReferenceCheckpoint {
        path: path.to_path_buf(),
        model,
        optimizer,
        global_iter,
    })
}

fn read_tensor_dict(
    ar: &mut TorchArchive,
    heap: &Heap,
    v: &Value,
    key: &str,
) -> Result<Vec<(String, RawTensor)>> {
    let path = ar.path().to_path_buf();
    let items = heap
        .items(v)
        .ok_or_else(|| ConvertError::mismatch(&path, key, "a dict of tensors", v.kind()))?;
    let mut out: Vec<(String, RawTensor)> = Vec::with_capacity(items.len());
    for (k, t) in items {
        let Value::Str(name) = k else {
            return Err(ConvertError::mismatch(&path, key, "string keys", k.kind()));
        };
        let full = format!("{key}.{name}");
        let Some(tr) = t.as_tensor() else {
            return Err(ConvertError::mismatch(&path, full, "a tensor", t.kind()));
        };
        if out.iter().any(|(n, _)| n == &**name) {
            return Err(ConvertError::invalid(&path, full, "duplicate key"));
        }
        let raw = ar.read_tensor(tr, &full)?;
        out.push((name.to_string(), raw));
    }
    Ok(out)
}

/// `optimizer.state_dict()`: `{'state': {id: {...}}, 'param_groups': [{...}]}`.
fn read_adam(ar: &mut TorchArchive, heap: &Heap, v: &Value) -> Result<TorchAdam> {
    let path = ar.path().to_path_buf();
    if heap.items(v).is_none() {
        return Err(ConvertError::mismatch(
            &path,
            "optimizer",
            "a dict",
            v.kind(),
        ));
    }
    let state_v = heap
        .get(v, "state")
        .ok_or_else(|| ConvertError::missing(&path, "optimizer.state", ""))?;
    let groups_v = heap
        .get(v, "param_groups")
        .ok_or_else(|| ConvertError::missing(&path, "optimizer.param_groups", ""))?;

    let groups = match groups_v {
        Value::List(_) => heap.seq(groups_v).unwrap_or_default(),
        other => {
            return Err(ConvertError::mismatch(
                &path,
                "optimizer.param_groups",
                "a list",
                other.kind(),
            ))
        }
    };
    let param_groups = groups
        .iter()
        .enumerate()
        .map(|(g, gv)| read_param_group(&path, heap, g, gv))
        .collect::<Result<Vec<_>>>()?;

    let entries = heap.items(state_v).ok_or_else(|| {
        ConvertError::mismatch(&path, "optimizer.state", "a dict", state_v.kind())
    })?;
    let mut state = BTreeMap::new();
    for (k, sv) in entries {
        let id = state_id(&path, k)?;
        state.insert(id, read_param_state(ar, heap, id, sv)?);
    }
    Ok(TorchAdam {
        state,
        param_groups,
    })
}

/// `param_groups[g]`.
fn read_param_group(path: &Path, heap: &Heap, g: usize, gv: &Value) -> Result<TorchAdamGroup> {
    let key = |k: &str| format!("optimizer.param_groups[{g}].{k}");
    if heap.items(gv).is_none() {
        return Err(ConvertError::mismatch(
            path,
            format!("optimizer.param_groups[{g}]"),
            "a dict",
            gv.kind(),
        ));
    }
    let num = |k: &str| -> Result<f64> {
        let x = heap
            .get(gv, k)
            .ok_or_else(|| ConvertError::missing(path, key(k), ""))?;
        x.as_f64()
            .ok_or_else(|| ConvertError::mismatch(path, key(k), "a number", x.kind()))
    };
    let betas = read_betas(path, heap, heap.get(gv, "betas"), &key("betas"))?;
    let amsgrad = match heap.get(gv, "amsgrad") {
        None | Some(Value::Bool(false)) => false,
        Some(Value::Bool(true)) => true,
        Some(other) => {
            return Err(ConvertError::mismatch(
                path,
                key("amsgrad"),
                "a bool",
                other.kind(),
            ))
        }
    };
    let params = read_param_ids(path, heap, heap.get(gv, "params"), &key("params"))?;
    let weight_decay = match heap.get(gv, "weight_decay") {
        None => 0.0,
        Some(_) => num("weight_decay")?,
    };
    Ok(TorchAdamGroup {
        lr: num("lr")?,
        betas,
        eps: num("eps")?,
        weight_decay,
        amsgrad,
        params,
    })
}

/// `betas`: a 2-tuple of numbers.
fn read_betas(path: &Path, heap: &Heap, v: Option<&Value>, key: &str) -> Result<(f64, f64)> {
    match v {
        Some(t @ Value::Tuple(_)) => match heap.seq(t).unwrap_or_default() {
            [a, b] => match (a.as_f64(), b.as_f64()) {
                (Some(a), Some(b)) => Ok((a, b)),
                _ => Err(ConvertError::mismatch(
                    path,
                    key,
                    "two numbers",
                    "other values",
                )),
            },
            other => Err(ConvertError::mismatch(
                path,
                key,
                "a 2-tuple",
                format!("{} items", other.len()),
            )),
        },
        Some(other) => Err(ConvertError::mismatch(path, key, "a 2-tuple", other.kind())),
        None => Err(ConvertError::missing(path, key, "")),
    }
}

/// `params`: the optimiser ids of a group, a list of non-negative ints.
fn read_param_ids(path: &Path, heap: &Heap, v: Option<&Value>, key: &str) -> Result<Vec<usize>> {
    match v {
        Some(l @ Value::List(_)) => heap
            .seq(l)
            .unwrap_or_default()
            .iter()
            .map(|x| match x {
                Value::Int(i) if *i >= 0 => Ok(*i as usize),
                other => Err(ConvertError::mismatch(
                    path,
                    key,
                    "non-negative ints",
                    other.kind(),
                )),
            })
            .collect(),
        Some(other) => Err(ConvertError::mismatch(path, key, "a list", other.kind())),
        None => Err(ConvertError::missing(path, key, "")),
    }
}

/// A key of `state`: a parameter's optimiser id.
fn state_id(path: &Path, k: &Value) -> Result<usize> {
    match k {
        Value::Int(id) if *id >= 0 => Ok(*id as usize),
        Value::Int(id) => Err(ConvertError::invalid(
            path,
            "optimizer.state",
            format!("negative parameter id {id}"),
        )),
        other => Err(ConvertError::mismatch(
            path,
            "optimizer.state",
            "int keys",
            other.kind(),
        )),
    }
}

/// `state[id]`: `{'step', 'exp_avg', 'exp_avg_sq'}`.
fn read_param_state(
    ar: &mut TorchArchive,
    heap: &Heap,
    id: usize,
    sv: &Value,
) -> Result<TorchAdamParam> {
    let path = ar.path().to_path_buf();
    let key = |k: &str| format!("optimizer.state[{id}].{k}");
    if heap.items(sv).is_none() {
        return Err(ConvertError::mismatch(
            &path,
            format!("optimizer.state[{id}]"),
            "a dict",
            sv.kind(),
        ));
    }
    let mut tensor = |k: &str| -> Result<RawTensor> {
        match heap.get(sv, k) {
            Some(v) => match v.as_tensor() {
                Some(t) => ar.read_tensor(t, &key(k)),
                None => Err(ConvertError::mismatch(&path, key(k), "a tensor", v.kind())),
            },
            None => Err(ConvertError::missing(&path, key(k), "")),
        }
    };
    let exp_avg = tensor("exp_avg")?;
    let exp_avg_sq = tensor("exp_avg_sq")?;
    let step = read_step(ar, heap.get(sv, "step"), &key("step"))?;
    Ok(TorchAdamParam {
        step,
        exp_avg,
        exp_avg_sq,
    })
}

/// `step`: a number, or a one-element tensor in newer torch versions.
fn read_step(ar: &mut TorchArchive, v: Option<&Value>, key: &str) -> Result<f64> {
    let path = ar.path().to_path_buf();
    let Some(v) = v else {
        return Err(ConvertError::missing(&path, key, ""));
    };
    if let Some(t) = v.as_tensor() {
        let raw = ar.read_tensor(t, key)?;
        return scalar_of(&raw).ok_or_else(|| {
            ConvertError::mismatch(
                &path,
                key,
                "a one-element float or int tensor",
                format!("{:?} of shape {:?}", raw.dtype, raw.shape),
            )
        });
    }
    v.as_f64()
        .ok_or_else(|| ConvertError::mismatch(&path, key, "a number", v.kind()))
}

fn scalar_of(t: &RawTensor) -> Option<f64> {
    if t.numel() != 1 {
        return None;
    }
    let b = &t.data;
    Some(match t.dtype {
        Dtype::F32 => f32::from_le_bytes(b.get(..4)?.try_into().ok()?) as f64,
        Dtype::F64 => f64::from_le_bytes(b.get(..8)?.try_into().ok()?),
        Dtype::I64 => i64::from_le_bytes(b.get(..8)?.try_into().ok()?) as f64,
        Dtype::I32 => i32::from_le_bytes(b.get(..4)?.try_into().ok()?) as f64,
        _ => return None,
    })
}
