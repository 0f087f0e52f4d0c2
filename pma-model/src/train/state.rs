//! The train-state file ("pma-train-state" v1): everything besides the model weights that a
//! run needs to continue exactly where it stopped.
//!
//! A safetensors file with one pair of f32 tensors per trainable parameter,
//! `exp_avg.<param>` and `exp_avg_sq.<param>` (torch Adam's names), and this metadata:
//!
//! | key | value |
//! | --- | --- |
//! | `format` | `"pma-train-state"` |
//! | `format_version` | `"1"` |
//! | `global_iter` | completed iterations (decimal); a resumed run starts at `global_iter + 1` |
//! | `steps` | JSON `{param: adam_step}` |
//! | `param_groups` | JSON `[{name, lr, initial_lr, betas, eps, weight_decay, params}]` |
//! | `rng` | JSON [`RngState`] of the trainer's noise generator (optional) |
//! | `sampler` | JSON state of the ray sampler (optional, opaque here) |
//! | `progress` | JSON [`Progress`] (optional) |
//! | `run_config` | JSON of the run's model + training config (optional) |
//! | `model_fingerprint` | FNV-1a 64 of the model file written with this state (optional) |
//!
//! The first five keys are the format shared with `pma-convert` (which writes them from a
//! reference `.th` checkpoint); the optional ones are what an exact resume needs beyond them.
//! A run whose sampler keeps an error map (`pma_data::error_map`) saves it as one more f32
//! tensor, `sampler.error_map` [images, cells_y, cells_x]. A run whose model file holds the
//! average of its weights ([`crate::train::average`]) saves the trained weights as
//! `weights.<param>`; a run with an occupancy grid saves its marked cells as
//! `occupancy.occupied` (u8).

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::adam::{ParamGroup, ParamState};
use super::{write_atomic, TrainError};

pub const FORMAT: &str = "pma-train-state";
pub const FORMAT_VERSION: u32 = 1;

/// Position of a ChaCha8 stream, enough to rebuild the generator bit for bit.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct RngState {
    /// 32-byte seed as hex.
    pub seed: String,
    pub stream: u64,
    /// Word position (u128) as a decimal string: JSON numbers cannot hold it.
    pub word_pos: String,
}

impl RngState {
    pub fn capture(rng: &ChaCha8Rng) -> Self {
        Self {
            seed: rng.get_seed().iter().map(|b| format!("{b:02x}")).collect(),
            stream: rng.get_stream(),
            word_pos: rng.get_word_pos().to_string(),
        }
    }

    pub fn restore(&self) -> Result<ChaCha8Rng, TrainError> {
        use rand::SeedableRng;
        let bad = |what: &str| TrainError::State(vec![format!("rng state: invalid {what}")]);
        if self.seed.len() != 64 {
            return Err(bad("seed (expected 64 hex digits)"));
        }
        let mut seed = [0u8; 32];
        for (i, b) in seed.iter_mut().enumerate() {
            *b = u8::from_str_radix(&self.seed[2 * i..2 * i + 2], 16).map_err(|_| bad("seed"))?;
        }
        let pos: u128 = self.word_pos.parse().map_err(|_| bad("word_pos"))?;
        let mut rng = ChaCha8Rng::from_seed(seed);
        rng.set_stream(self.stream);
        rng.set_word_pos(pos);
        Ok(rng)
    }
}

/// Run statistics carried across a resume.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Progress {
    /// Wall-clock seconds spent in the run so far (all sessions together).
    pub wall_s: f64,
    /// Steps skipped because the loss or the gradient norm was not finite.
    pub skipped: u64,
    /// Of those, the ones at the end of the run without a good step since.
    pub consecutive_skipped: u64,
}

/// In-memory form of a train-state file.
#[derive(Debug, Clone)]
pub struct TrainState {
    pub global_iter: u64,
    pub groups: Vec<ParamGroup>,
    pub params: HashMap<String, ParamState>,
    pub rng: Option<RngState>,
    pub sampler: Option<serde_json::Value>,
    pub progress: Option<Progress>,
    pub run_config: Option<serde_json::Value>,
    pub model_fingerprint: Option<String>,
    /// The sampler's error map, [images, cells_y, cells_x] (optional).
    pub error_map: Option<Tensor>,
    /// The occupancy grid's cells as the run last marked them (u8 0/1, the grid's layout):
    /// between refreshes they differ from what the model file's values give.
    pub occupied: Option<Tensor>,
    /// The trained weights of a run whose model file holds their average
    /// ([`crate::train::average`]), by parameter name; empty otherwise.
    pub weights: HashMap<String, Tensor>,
}

/// The tensor name of the sampler's error map.
const ERROR_MAP_TENSOR: &str = "sampler.error_map";

/// The tensor name of the occupancy grid's marked cells.
const OCCUPIED_TENSOR: &str = "occupancy.occupied";

/// The prefix of the trained weights' tensors (see [`TrainState::weights`]).
const WEIGHTS_PREFIX: &str = "weights.";

#[derive(Serialize, Deserialize)]
struct GroupMeta {
    name: String,
    lr: f64,
    initial_lr: f64,
    betas: [f64; 2],
    eps: f64,
    #[serde(default)]
    weight_decay: f64,
    params: Vec<String>,
}

impl TrainState {
    /// Write atomically (temporary file beside `path`, then rename).
    pub fn save(&self, path: &Path) -> Result<(), TrainError> {
        write_atomic(path, &self.to_bytes(path)?)
    }

    /// The bytes [`Self::save`] writes (`path` names the file in errors).
    pub fn to_bytes(&self, path: &Path) -> Result<Vec<u8>, TrainError> {
        let mut meta = HashMap::new();
        meta.insert("format".to_string(), FORMAT.to_string());
        meta.insert("format_version".to_string(), FORMAT_VERSION.to_string());
        meta.insert("global_iter".to_string(), self.global_iter.to_string());
        let steps: BTreeMap<&str, u64> = self
            .params
            .iter()
            .map(|(n, s)| (n.as_str(), s.step))
            .collect();
        meta.insert("steps".to_string(), json(&steps)?);
        let groups: Vec<GroupMeta> = self
            .groups
            .iter()
            .map(|g| GroupMeta {
                name: g.name.clone(),
                lr: g.lr,
                initial_lr: g.initial_lr,
                betas: g.betas,
                eps: g.eps,
                weight_decay: 0.0,
                params: g.params.clone(),
            })
            .collect();
        meta.insert("param_groups".to_string(), json(&groups)?);
        if let Some(r) = &self.rng {
            meta.insert("rng".to_string(), json(r)?);
        }
        if let Some(s) = &self.sampler {
            meta.insert("sampler".to_string(), json(s)?);
        }
        if let Some(p) = &self.progress {
            meta.insert("progress".to_string(), json(p)?);
        }
        if let Some(c) = &self.run_config {
            meta.insert("run_config".to_string(), json(c)?);
        }
        if let Some(f) = &self.model_fingerprint {
            meta.insert("model_fingerprint".to_string(), f.clone());
        }

        let mut tensors: Vec<(String, Tensor)> = Vec::with_capacity(2 * self.params.len());
        for (name, st) in &self.params {
            tensors.push((format!("exp_avg.{name}"), st.exp_avg.to_dtype(DType::F32)?));
            tensors.push((
                format!("exp_avg_sq.{name}"),
                st.exp_avg_sq.to_dtype(DType::F32)?,
            ));
        }
        if let Some(m) = &self.error_map {
            tensors.push((ERROR_MAP_TENSOR.to_string(), m.to_dtype(DType::F32)?));
        }
        if let Some(o) = &self.occupied {
            tensors.push((OCCUPIED_TENSOR.to_string(), o.to_dtype(DType::U8)?));
        }
        for (name, w) in &self.weights {
            tensors.push((format!("{WEIGHTS_PREFIX}{name}"), w.to_dtype(DType::F32)?));
        }
        tensors.sort_by(|a, b| a.0.cmp(&b.0));
        safetensors::serialize(tensors.iter().map(|(n, t)| (n.as_str(), t)), Some(meta)).map_err(
            |e| TrainError::StateFile {
                path: path.to_path_buf(),
                problems: vec![e.to_string()],
            },
        )
    }

    /// Read and check a train-state file: metadata present and well-formed, every group
    /// member has both moments and a step, and no tensor is left over.
    pub fn load(path: &Path, device: &Device) -> Result<Self, TrainError> {
        // Moments are twice the model's parameters.
        let limit = 2 * crate::network::checkpoint::MAX_CHECKPOINT_BYTES;
        let bytes =
            pma_data::fsio::read_input(path, limit).map_err(super::error::read_err(path))?;
        Self::from_bytes(&bytes, device).map_err(|e| match e {
            TrainError::State(problems) => TrainError::StateFile {
                path: path.to_path_buf(),
                problems,
            },
            other => other,
        })
    }

    fn from_bytes(bytes: &[u8], device: &Device) -> Result<Self, TrainError> {
        let fail = |p: String| TrainError::State(vec![p]);
        let (_, header) = safetensors::SafeTensors::read_metadata(bytes)
            .map_err(|e| fail(format!("not a safetensors file: {e}")))?;
        let meta = header.metadata().clone().unwrap_or_default();
        match meta.get("format").map(String::as_str) {
            Some(FORMAT) => {}
            other => {
                return Err(fail(format!(
                    "metadata `format`: expected {FORMAT:?}, found {other:?}"
                )))
            }
        }
        match meta.get("format_version") {
            Some(v) if *v == FORMAT_VERSION.to_string() => {}
            other => {
                return Err(fail(format!(
                    "metadata `format_version`: expected \"{FORMAT_VERSION}\", found {other:?}"
                )))
            }
        }
        let mut problems = Vec::new();
        let required = |key: &str, problems: &mut Vec<String>| -> Option<String> {
            let v = meta.get(key).cloned();
            if v.is_none() {
                problems.push(format!("metadata key `{key}` is missing"));
            }
            v
        };
        let global_iter = required("global_iter", &mut problems).and_then(|s| {
            s.parse::<u64>()
                .map_err(|_| problems.push(format!("`global_iter` = {s:?} is not an integer")))
                .ok()
        });
        let steps: Option<BTreeMap<String, u64>> = required("steps", &mut problems).and_then(|s| {
            serde_json::from_str(&s)
                .map_err(|e| problems.push(format!("`steps`: {e}")))
                .ok()
        });
        let groups: Option<Vec<GroupMeta>> =
            required("param_groups", &mut problems).and_then(|s| {
                serde_json::from_str(&s)
                    .map_err(|e| problems.push(format!("`param_groups`: {e}")))
                    .ok()
            });
        fn optional<T: serde::de::DeserializeOwned>(
            meta: &HashMap<String, String>,
            key: &str,
            problems: &mut Vec<String>,
        ) -> Option<T> {
            meta.get(key).and_then(|s| {
                serde_json::from_str(s)
                    .map_err(|e| problems.push(format!("`{key}`: {e}")))
                    .ok()
            })
        }
        let rng: Option<RngState> = optional(&meta, "rng", &mut problems);
        let sampler: Option<serde_json::Value> = optional(&meta, "sampler", &mut problems);
        let progress: Option<Progress> = optional(&meta, "progress", &mut problems);
        let run_config: Option<serde_json::Value> = optional(&meta, "run_config", &mut problems);
        let model_fingerprint = meta.get("model_fingerprint").cloned();
        let (Some(global_iter), Some(steps), Some(groups)) = (global_iter, steps, groups) else {
            return Err(TrainError::State(problems));
        };

        let st = safetensors::SafeTensors::deserialize(bytes).map_err(|e| fail(e.to_string()))?;
        let mut tensors: HashMap<String, Tensor> = HashMap::new();
        let mut occupied = None;
        for (name, view) in st.tensors() {
            if name == OCCUPIED_TENSOR && view.dtype() == safetensors::Dtype::U8 {
                occupied = Some(candle_core::safetensors::Load::load(&view, device)?);
                continue;
            }
            if view.dtype() != safetensors::Dtype::F32 {
                problems.push(format!(
                    "tensor `{name}`: expected f32, found {:?}",
                    view.dtype()
                ));
                continue;
            }
            tensors.insert(name, candle_core::safetensors::Load::load(&view, device)?);
        }
        let error_map = tensors.remove(ERROR_MAP_TENSOR);
        let weight_names: Vec<String> = tensors
            .keys()
            .filter(|n| n.starts_with(WEIGHTS_PREFIX))
            .cloned()
            .collect();
        let weights = weight_names
            .into_iter()
            .filter_map(|n| {
                let t = tensors.remove(&n)?;
                Some((n[WEIGHTS_PREFIX.len()..].to_string(), t))
            })
            .collect();
        let params = param_states(&groups, &steps, tensors, &mut problems);
        if !problems.is_empty() {
            return Err(TrainError::State(problems));
        }
        let groups = groups
            .into_iter()
            .map(|g| ParamGroup {
                name: g.name,
                initial_lr: g.initial_lr,
                lr: g.lr,
                betas: g.betas,
                eps: g.eps,
                params: g.params,
            })
            .collect();
        Ok(Self {
            global_iter,
            groups,
            params,
            rng,
            sampler,
            progress,
            run_config,
            model_fingerprint,
            error_map,
            occupied,
            weights,
        })
    }
}

/// The Adam state of every parameter of `groups` from the moment tensors and step counts;
/// every missing, duplicated or left-over entry goes to `problems`.
fn param_states(
    groups: &[GroupMeta],
    steps: &BTreeMap<String, u64>,
    mut tensors: HashMap<String, Tensor>,
    problems: &mut Vec<String>,
) -> HashMap<String, ParamState> {
    let mut params = HashMap::new();
    let mut seen = std::collections::HashSet::new();
    for g in groups {
        for name in &g.params {
            if !seen.insert(name.clone()) {
                problems.push(format!(
                    "parameter `{name}` is listed in more than one group"
                ));
                continue;
            }
            let m = tensors.remove(&format!("exp_avg.{name}"));
            let v = tensors.remove(&format!("exp_avg_sq.{name}"));
            let step = steps.get(name).copied();
            match (m, v, step) {
                (Some(m), Some(v), Some(step)) => {
                    if m.dims() != v.dims() {
                        problems.push(format!(
                            "`{name}`: exp_avg {:?} and exp_avg_sq {:?} differ in shape",
                            m.dims(),
                            v.dims()
                        ));
                    }
                    params.insert(
                        name.clone(),
                        ParamState {
                            step,
                            exp_avg: m,
                            exp_avg_sq: v,
                        },
                    );
                }
                (m, v, step) => {
                    for (what, missing) in [
                        ("tensor exp_avg", m.is_none()),
                        ("tensor exp_avg_sq", v.is_none()),
                        ("steps entry", step.is_none()),
                    ] {
                        if missing {
                            problems.push(format!("`{name}`: {what} is missing"));
                        }
                    }
                }
            }
        }
    }
    let mut left: Vec<_> = tensors.into_keys().collect();
    left.sort();
    for name in left {
        problems.push(format!("tensor `{name}` belongs to no parameter group"));
    }
    for name in steps.keys().filter(|n| !seen.contains(*n)) {
        problems.push(format!(
            "`steps` names `{name}`, which is in no parameter group"
        ));
    }
    params
}

/// FNV-1a (64 bit) of a file's bytes, as hex: ties a train state to the model file written
/// with it, so a crash between the two writes is detected on resume.
pub fn fingerprint(bytes: &[u8]) -> String {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    format!("{h:016x}")
}

fn json<T: Serialize + ?Sized>(v: &T) -> Result<String, TrainError> {
    serde_json::to_string(v)
        .map_err(|e| TrainError::Config(format!("cannot serialise train state: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngCore, SeedableRng};

    fn sample_state() -> TrainState {
        let dev = Device::Cpu;
        let t = |v: &[f32]| Tensor::new(v, &dev).unwrap();
        let mut params = HashMap::new();
        params.insert(
            "a.weight".to_string(),
            ParamState {
                step: 3,
                exp_avg: t(&[0.1, 0.2]),
                exp_avg_sq: t(&[1e-3, 2e-3]),
            },
        );
        params.insert(
            "b.bias".to_string(),
            ParamState {
                step: 3,
                exp_avg: t(&[-0.5]),
                exp_avg_sq: t(&[4e-6]),
            },
        );
        let group = |name: &str, lr: f64, p: &str| ParamGroup {
            name: name.into(),
            initial_lr: lr,
            lr: lr * 0.9,
            betas: [0.9, 0.999],
            eps: 1e-8,
            params: vec![p.into()],
        };
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        rng.next_u64();
        TrainState {
            global_iter: 3,
            groups: vec![
                group("freq", 1e-4, "a.weight"),
                group("other", 5e-4, "b.bias"),
            ],
            params,
            rng: Some(RngState::capture(&rng)),
            sampler: Some(serde_json::json!({"cursor": 5})),
            progress: Some(Progress {
                wall_s: 1.5,
                skipped: 1,
                consecutive_skipped: 0,
            }),
            run_config: None,
            model_fingerprint: Some(fingerprint(b"model")),
            error_map: None,
            occupied: None,
            weights: HashMap::new(),
        }
    }

    #[test]
    fn roundtrip_is_exact() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("state.safetensors");
        let s = sample_state();
        s.save(&path).unwrap();
        let l = TrainState::load(&path, &Device::Cpu).unwrap();
        assert_eq!(l.global_iter, 3);
        // serde_json's float parsing may be 1 ulp off; the trainer recomputes rates from the
        // schedule on resume, so the stored ones only need to be close.
        for (a, b) in l.groups.iter().zip(&s.groups) {
            assert_eq!(
                (&a.name, &a.params, a.betas, a.eps),
                (&b.name, &b.params, b.betas, b.eps)
            );
            assert!((a.lr - b.lr).abs() <= 1e-15 * b.lr && a.initial_lr == b.initial_lr);
        }
        assert_eq!(l.rng, s.rng);
        assert_eq!(l.sampler, s.sampler);
        assert_eq!(l.progress, s.progress);
        assert_eq!(l.model_fingerprint, s.model_fingerprint);
        for (n, p) in &s.params {
            let q = &l.params[n];
            assert_eq!(q.step, p.step);
            assert_eq!(
                q.exp_avg.to_vec1::<f32>().unwrap(),
                p.exp_avg.to_vec1::<f32>().unwrap()
            );
            assert_eq!(
                q.exp_avg_sq.to_vec1::<f32>().unwrap(),
                p.exp_avg_sq.to_vec1::<f32>().unwrap()
            );
        }
    }

    #[test]
    fn rng_state_restores_the_same_stream() {
        let mut a = ChaCha8Rng::seed_from_u64(42);
        for _ in 0..13 {
            a.next_u32();
        }
        let mut b = RngState::capture(&a).restore().unwrap();
        for _ in 0..100 {
            assert_eq!(a.next_u64(), b.next_u64());
        }
        let bad = RngState {
            seed: "zz".into(),
            stream: 0,
            word_pos: "0".into(),
        };
        assert!(bad.restore().is_err());
    }

    #[test]
    fn incomplete_or_foreign_files_are_rejected_with_all_problems() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("state.safetensors");
        let mut s = sample_state();
        // A group member without moments, and moments for a name in no group.
        s.groups[0].params.push("ghost".into());
        s.params.insert(
            "stray".into(),
            ParamState {
                step: 1,
                exp_avg: Tensor::new(&[0f32], &Device::Cpu).unwrap(),
                exp_avg_sq: Tensor::new(&[0f32], &Device::Cpu).unwrap(),
            },
        );
        s.save(&path).unwrap();
        let e = TrainState::load(&path, &Device::Cpu).unwrap_err();
        // The message is one line (the first problem and how many more); the error lists all.
        let err = e.to_string();
        assert_eq!(err.lines().count(), 1, "{err}");
        assert!(err.contains(path.to_str().unwrap()), "{err}");
        let TrainError::StateFile { problems, .. } = e else {
            panic!("expected StateFile, got {err}");
        };
        let err = problems.join("\n");
        assert!(err.contains("`ghost`: tensor exp_avg is missing"), "{err}");
        assert!(
            err.contains("tensor `exp_avg.stray` belongs to no parameter group"),
            "{err}"
        );

        // A model checkpoint is not a train state.
        let other = dir.path().join("model.safetensors");
        let t = Tensor::new(&[1f32], &Device::Cpu).unwrap();
        safetensors::serialize_to_file([("x", &t)], None, &other).unwrap();
        let err = TrainState::load(&other, &Device::Cpu)
            .unwrap_err()
            .to_string();
        assert!(err.contains("metadata `format`"), "{err}");
    }

    #[test]
    fn fingerprint_changes_with_content() {
        assert_ne!(fingerprint(b"abc"), fingerprint(b"abd"));
        assert_eq!(fingerprint(b""), "cbf29ce484222325");
    }
}
