//! pma's training-state file: the Adam optimiser state that lets training
//! resume exactly, written next to a checkpoint.
//!
//! # Format (`format_version` 1)
//!
//! A safetensors file, by convention `<checkpoint stem>.optim.safetensors`
//! beside `<checkpoint stem>.safetensors` (see [`sidecar_path`]).
//!
//! Tensors, all F32, each with the shape of its parameter:
//! * `exp_avg.<param name>`: Adam's first moment m;
//! * `exp_avg_sq.<param name>`: Adam's second moment v.
//!
//! A parameter may have no moments (it has not been stepped yet); it then
//! starts from m = v = 0 and step 0, as in torch.
//!
//! Metadata (all values are strings, as safetensors requires):
//! * `format` = `"pma-train-state"`, `format_version` = `"1"`;
//! * `global_iter`: the iteration just completed, a decimal integer; training
//!   resumes at `global_iter + 1`;
//! * `steps`: JSON object, parameter name -> Adam step count (integer), one
//!   entry per parameter that has moments, and only those;
//! * `param_groups`: JSON array of `{"lr", "betas": [b1, b2], "eps",
//!   "weight_decay", "params": [names]}` in optimiser order. `lr` is the rate
//!   last set by the schedule. Every parameter with moments belongs to exactly
//!   one group.
//!
//! Parameter names are the checkpoint's tensor names (spec model.md §8.1).

use std::{
    collections::{BTreeMap, BTreeSet, HashMap},
    path::{Path, PathBuf},
};

use safetensors::{Dtype, SafeTensors};
use serde::{Deserialize, Serialize};

use crate::{
    error::{ConvertError, Result},
    raw::RawTensor,
};

pub const FORMAT: &str = "pma-train-state";
pub const FORMAT_VERSION: &str = "1";

/// One optimiser parameter group.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ParamGroup {
    pub lr: f64,
    pub betas: [f64; 2],
    pub eps: f64,
    #[serde(default)]
    pub weight_decay: f64,
    pub params: Vec<String>,
}

/// Adam's per-parameter state.
#[derive(Clone, Debug, PartialEq)]
pub struct Moments {
    pub step: u64,
    pub exp_avg: RawTensor,
    pub exp_avg_sq: RawTensor,
}

#[derive(Clone, Debug, PartialEq)]
pub struct TrainState {
    pub global_iter: u64,
    pub param_groups: Vec<ParamGroup>,
    /// Keyed by parameter name.
    pub moments: BTreeMap<String, Moments>,
}

/// `dir/name.safetensors` -> `dir/name.optim.safetensors`.
pub fn sidecar_path(checkpoint: &Path) -> PathBuf {
    let stem = checkpoint
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    checkpoint.with_file_name(format!("{stem}.optim.safetensors"))
}

impl TrainState {
    /// Checks the invariants of the format (see the module docs).
    pub fn check(&self, path: &Path) -> Result<()> {
        let mut owner: HashMap<&str, usize> = HashMap::new();
        for (g, group) in self.param_groups.iter().enumerate() {
            for p in &group.params {
                if let Some(prev) = owner.insert(p, g) {
                    return Err(ConvertError::invalid(
                        path,
                        "param_groups",
                        format!("parameter `{p}` is in groups {prev} and {g}"),
                    ));
                }
            }
            let finite = [
                group.lr,
                group.betas[0],
                group.betas[1],
                group.eps,
                group.weight_decay,
            ];
            if finite.iter().any(|x| !x.is_finite()) || group.lr < 0.0 || group.eps <= 0.0 {
                return Err(ConvertError::invalid(
                    path,
                    format!("param_groups[{g}]"),
                    format!(
                        "lr {}, betas {:?}, eps {} must be finite, lr >= 0, eps > 0",
                        group.lr, group.betas, group.eps
                    ),
                ));
            }
        }
        for (name, m) in &self.moments {
            if !owner.contains_key(name.as_str()) {
                return Err(ConvertError::invalid(
                    path,
                    name,
                    "has moments but is in no parameter group",
                ));
            }
            for (what, t) in [("exp_avg", &m.exp_avg), ("exp_avg_sq", &m.exp_avg_sq)] {
                if t.dtype != Dtype::F32 {
                    return Err(ConvertError::mismatch(
                        path,
                        format!("{what}.{name}"),
                        "F32",
                        format!("{:?}", t.dtype),
                    ));
                }
                if t.data.len() != t.numel() * 4 {
                    return Err(ConvertError::mismatch(
                        path,
                        format!("{what}.{name}"),
                        format!("{} bytes for shape {:?}", t.numel() * 4, t.shape),
                        format!("{} bytes", t.data.len()),
                    ));
                }
            }
            if m.exp_avg.shape != m.exp_avg_sq.shape {
                return Err(ConvertError::mismatch(
                    path,
                    format!("exp_avg_sq.{name}"),
                    format!("shape {:?} (that of exp_avg.{name})", m.exp_avg.shape),
                    format!("{:?}", m.exp_avg_sq.shape),
                ));
            }
        }
        Ok(())
    }

    /// Writes the file atomically (temporary file in the target directory, then rename).
    pub fn write(&self, path: &Path) -> Result<()> {
        self.check(path)?;
        let steps: BTreeMap<&str, u64> = self
            .moments
            .iter()
            .map(|(n, m)| (n.as_str(), m.step))
            .collect();
        let metadata: HashMap<String, String> = [
            ("format", FORMAT.to_string()),
            ("format_version", FORMAT_VERSION.to_string()),
            ("global_iter", self.global_iter.to_string()),
            (
                "steps",
                serde_json::to_string(&steps).expect("map of integers serialises"),
            ),
            (
                "param_groups",
                serde_json::to_string(&self.param_groups).expect("plain struct serialises"),
            ),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
        let mut tensors: Vec<(String, &RawTensor)> = Vec::with_capacity(2 * self.moments.len());
        for (name, m) in &self.moments {
            tensors.push((format!("exp_avg.{name}"), &m.exp_avg));
            tensors.push((format!("exp_avg_sq.{name}"), &m.exp_avg_sq));
        }
        let bytes = safetensors::serialize(tensors, Some(metadata)).map_err(|source| {
            ConvertError::Safetensors {
                path: path.to_path_buf(),
                cause: source,
            }
        })?;
        crate::write_atomic(path, &bytes)
    }

    pub fn read(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|e| ConvertError::io(path, e))?;
        let (_, header) =
            SafeTensors::read_metadata(&bytes).map_err(|source| ConvertError::Safetensors {
                path: path.to_path_buf(),
                cause: source,
            })?;
        let meta = header.metadata().clone().unwrap_or_default();
        let field = |k: &str| -> Result<&String> {
            meta.get(k).ok_or_else(|| {
                ConvertError::missing(path, k, " (safetensors metadata of a pma training state)")
            })
        };
        let format = field("format")?;
        if format != FORMAT {
            return Err(ConvertError::mismatch(path, "format", FORMAT, format));
        }
        let version = field("format_version")?;
        if version != FORMAT_VERSION {
            return Err(ConvertError::mismatch(
                path,
                "format_version",
                FORMAT_VERSION,
                version,
            ));
        }
        let global_iter = field("global_iter")?.parse::<u64>().map_err(|e| {
            ConvertError::invalid(
                path,
                "global_iter",
                format!("not a non-negative integer: {e}"),
            )
        })?;
        let steps: BTreeMap<String, u64> = serde_json::from_str(field("steps")?).map_err(|e| {
            ConvertError::invalid(
                path,
                "steps",
                format!("not a JSON map of name -> integer: {e}"),
            )
        })?;
        let param_groups: Vec<ParamGroup> = serde_json::from_str(field("param_groups")?)
            .map_err(|e| ConvertError::invalid(path, "param_groups", format!("bad JSON: {e}")))?;

        let st = SafeTensors::deserialize(&bytes).map_err(|source| ConvertError::Safetensors {
            path: path.to_path_buf(),
            cause: source,
        })?;
        let mut avg: BTreeMap<String, RawTensor> = BTreeMap::new();
        let mut avg_sq: BTreeMap<String, RawTensor> = BTreeMap::new();
        for (name, view) in st.tensors() {
            let raw = RawTensor {
                dtype: view.dtype(),
                shape: view.shape().to_vec(),
                data: view.data().to_vec(),
            };
            if let Some(p) = name.strip_prefix("exp_avg_sq.") {
                avg_sq.insert(p.to_string(), raw);
            } else if let Some(p) = name.strip_prefix("exp_avg.") {
                avg.insert(p.to_string(), raw);
            } else {
                return Err(ConvertError::invalid(
                    path,
                    name,
                    "unexpected tensor; expected exp_avg.<param> or exp_avg_sq.<param>",
                ));
            }
        }
        let names: BTreeSet<&String> = avg
            .keys()
            .chain(avg_sq.keys())
            .chain(steps.keys())
            .collect();
        let mut moments = BTreeMap::new();
        for name in names {
            let get = |m: &BTreeMap<String, RawTensor>, what: &str| {
                m.get(name)
                    .cloned()
                    .ok_or_else(|| ConvertError::missing(path, format!("{what}.{name}"), ""))
            };
            let step = *steps
                .get(name)
                .ok_or_else(|| ConvertError::missing(path, format!("steps[{name}]"), ""))?;
            moments.insert(
                name.clone(),
                Moments {
                    step,
                    exp_avg: get(&avg, "exp_avg")?,
                    exp_avg_sq: get(&avg_sq, "exp_avg_sq")?,
                },
            );
        }
        let state = Self {
            global_iter,
            param_groups,
            moments,
        };
        state.check(path)?;
        Ok(state)
    }
}
