//! The pma checkpoint: a safetensors file holding the reference's 71 tensors under the
//! reference's names (docs/reference.md, "Checkpoint and state_dict names"), plus metadata that makes the file
//! self-describing:
//!
//! | key | value |
//! | --- | --- |
//! | `format` | `"pma-checkpoint"` |
//! | `format_version` | `"1"` |
//! | `config` | the [`Config`] as JSON |
//! | `skeleton` | `{"names": [...], "parents": [...]}` |
//! | `rest_pose` | `[[x,y,z]; J]` (equals the `rest_pose` tensor) |
//! | `n_framecodes` | decimal string (equals `config.n_framecodes`) |
//! | `occupancy` | only with an occupancy grid: its [`OccupancyMeta`] as JSON |
//!
//! **Optional group.** A model with an occupancy grid ([`crate::network::occupancy`])
//! carries one more tensor, `occupancy.density` [24,R,R,R] f32, with the `occupancy` metadata
//! key; a model without one has neither, so its file is byte for byte what it was before
//! grids existed. The grid is checked like the rest: its shape against its metadata, every
//! value finite and >= 0; a tensor without the key (or the key without the tensor) is refused.
//!
//! A safetensors file without this metadata (e.g. one exported straight from a PyTorch
//! state_dict, like `fixtures/golden/model.safetensors`) is accepted too: its config is the
//! paper config with `n_framecodes` read from `framecodes.codes.weight`, and then checked
//! against every tensor like any other.
//!
//! Loading is strict. All problems (missing, unexpected, mis-shaped or non-f32 tensors, bad
//! metadata, NaN or infinite weights) are collected and reported together in one
//! [`ModelError::Checkpoint`] (its message is one line: the first problem and how many
//! more). The config in the metadata is checked against the size limits of
//! [`Config::validate`] before anything is sized from it, and the file is read up to its
//! real size and at most [`MAX_CHECKPOINT_BYTES`].

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use pma_data::skeleton::{self, JOINT_NAMES, N_JOINTS, PARENTS};

use crate::compute::host::host_f32;
use serde::{Deserialize, Serialize};

use crate::error::{ModelError, Result};
use crate::network::config::Config;
use crate::network::occupancy::{OccupancyGrid, OccupancyMeta};
use pma_data::FileError;

/// The optional occupancy group's tensor and metadata key (see the module docs).
pub const OCCUPANCY_TENSOR: &str = "occupancy.density";
pub const OCCUPANCY_KEY: &str = "occupancy";

pub const FORMAT: &str = "pma-checkpoint";
pub const FORMAT_VERSION: u32 = 1;

/// The largest checkpoint file read (8 GiB): above what a model within the limits of
/// [`Config::validate`] needs; a larger file is refused before it is read.
pub const MAX_CHECKPOINT_BYTES: u64 = 8 << 30;

/// How [`load_with`] treats a checkpoint.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LoadOptions {
    /// Accept NaN or infinite weights (to inspect a broken checkpoint); refused otherwise.
    pub allow_non_finite: bool,
}

pub use super::layers::tensor_layout;
pub use crate::network::params::{TensorKind, TensorSpec};

/// Names of the trainable tensors in reference order (`named_parameters()`).
pub fn param_names(cfg: &Config) -> Vec<String> {
    tensor_layout(cfg)
        .into_iter()
        .filter(|t| t.kind == TensorKind::Param)
        .map(|t| t.name)
        .collect()
}

/// Skeleton description stored in the metadata.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct SkeletonMeta {
    pub names: Vec<String>,
    pub parents: Vec<usize>,
}

impl SkeletonMeta {
    /// The SMPL 24-joint skeleton the model is built for.
    pub fn smpl() -> Self {
        Self {
            names: JOINT_NAMES.iter().map(|s| s.to_string()).collect(),
            parents: PARENTS.to_vec(),
        }
    }
}

/// What a checkpoint says about itself besides its tensors.
#[derive(Debug, Clone, PartialEq)]
pub struct CheckpointMeta {
    /// `Some(1)` for a pma checkpoint, `None` for a plain safetensors state_dict.
    pub format_version: Option<u32>,
    pub skeleton: SkeletonMeta,
    /// `[J]` joint positions of the rest pose (from the metadata, or from the tensor).
    pub rest_pose: Vec<[f32; 3]>,
    /// `true` when the config was inferred from tensor shapes (no pma metadata).
    pub config_inferred: bool,
}

/// A loaded, validated checkpoint: every tensor of [`tensor_layout`] is present with the
/// right shape and dtype f32, and nothing else is.
#[derive(Debug, Clone)]
pub struct Checkpoint {
    pub config: Config,
    pub tensors: HashMap<String, Tensor>,
    pub meta: CheckpointMeta,
    /// The optional occupancy grid (not among `tensors`).
    pub occupancy: Option<OccupancyGrid>,
}

/// Compare `(name, shape, dtype)` triples against the layout of `cfg`; one line per problem.
pub fn check_tensors<'a>(
    cfg: &Config,
    found: impl IntoIterator<Item = (&'a str, &'a [usize], DType)>,
) -> Vec<String> {
    let layout = tensor_layout(cfg);
    let mut found: HashMap<&str, (&[usize], DType)> =
        found.into_iter().map(|(n, s, d)| (n, (s, d))).collect();
    let mut problems = Vec::new();
    for spec in &layout {
        match found.remove(spec.name.as_str()) {
            None => problems.push(format!(
                "missing tensor `{}` (expected shape {:?})",
                spec.name, spec.shape
            )),
            Some((shape, dtype)) => {
                if shape != spec.shape.as_slice() {
                    problems.push(format!(
                        "tensor `{}`: expected shape {:?}, found {:?}",
                        spec.name, spec.shape, shape
                    ));
                }
                if dtype != DType::F32 {
                    problems.push(format!(
                        "tensor `{}`: expected dtype f32, found {dtype:?}",
                        spec.name
                    ));
                }
            }
        }
    }
    let mut unexpected: Vec<_> = found.into_iter().collect();
    unexpected.sort_by(|a, b| a.0.cmp(b.0));
    for (name, (shape, _)) in unexpected {
        problems.push(format!("unexpected tensor `{name}` (shape {shape:?})"));
    }
    problems
}

/// Write a checkpoint atomically (temporary file in the target directory, then rename).
///
/// `tensors` must be exactly the tensors of [`tensor_layout`]`(cfg)`, f32. The `rest_pose`
/// metadata is taken from the `rest_pose` tensor so the two cannot disagree.
pub fn save(path: &Path, tensors: &HashMap<String, Tensor>, cfg: &Config) -> Result<()> {
    save_with(path, tensors, cfg, None)
}

/// [`save`] with the optional occupancy grid.
pub fn save_with(
    path: &Path,
    tensors: &HashMap<String, Tensor>,
    cfg: &Config,
    occupancy: Option<&OccupancyGrid>,
) -> Result<()> {
    let bytes = to_bytes_with(path, tensors, cfg, occupancy)?;
    pma_data::fsio::write_atomic(path, &bytes).map_err(|e| FileError::write(path, e).into())
}

/// The bytes [`save`] writes (`path` names the file in errors), for writers that commit
/// several files together.
pub fn to_bytes(path: &Path, tensors: &HashMap<String, Tensor>, cfg: &Config) -> Result<Vec<u8>> {
    to_bytes_with(path, tensors, cfg, None)
}

/// [`to_bytes`] with the optional occupancy grid.
pub fn to_bytes_with(
    path: &Path,
    tensors: &HashMap<String, Tensor>,
    cfg: &Config,
    occupancy: Option<&OccupancyGrid>,
) -> Result<Vec<u8>> {
    cfg.validate()?;
    let problems = check_tensors(
        cfg,
        tensors
            .iter()
            .map(|(n, t)| (n.as_str(), t.dims(), t.dtype())),
    );
    if !problems.is_empty() {
        return Err(ModelError::Checkpoint {
            path: path.to_path_buf(),
            problems,
        });
    }
    let rest_pose: Vec<[f32; 3]> = tensors["rest_pose"]
        .to_vec2::<f32>()?
        .into_iter()
        .map(|r| [r[0], r[1], r[2]])
        .collect();
    let mut meta = HashMap::new();
    meta.insert("format".to_string(), FORMAT.to_string());
    meta.insert("format_version".to_string(), FORMAT_VERSION.to_string());
    meta.insert("config".to_string(), to_json(cfg)?);
    meta.insert("skeleton".to_string(), to_json(&SkeletonMeta::smpl())?);
    meta.insert("rest_pose".to_string(), to_json(&rest_pose)?);
    meta.insert("n_framecodes".to_string(), cfg.n_framecodes.to_string());
    let grid = match occupancy {
        Some(g) => {
            meta.insert(OCCUPANCY_KEY.to_string(), to_json(&g.meta())?);
            Some(Tensor::from_slice(
                g.density(),
                g.shape().to_vec(),
                &Device::Cpu,
            )?)
        }
        None => None,
    };

    // safetensors views need contiguous CPU-readable data; candle's `View` impl copies as needed.
    let all = tensors
        .iter()
        .map(|(n, t)| (n.as_str(), t))
        .chain(grid.iter().map(|t| (OCCUPANCY_TENSOR, t)));
    let bytes =
        safetensors::serialize(all, Some(meta)).map_err(|source| ModelError::Safetensors {
            path: path.to_path_buf(),
            source,
        })?;
    Ok(sorted_header(bytes))
}

/// The same safetensors bytes with the JSON header's keys in sorted order. safetensors
/// writes its metadata from a `HashMap`, whose order changes from one process to the next;
/// sorted, the same tensors and config give the same file, byte for byte. The header keeps
/// its length (trailing spaces are safetensors' alignment padding), so data offsets hold.
pub fn sorted_header(mut bytes: Vec<u8>) -> Vec<u8> {
    let Some(len) = bytes
        .get(..8)
        .map(|b| u64::from_le_bytes(b.try_into().expect("8 bytes")))
    else {
        return bytes;
    };
    let end = 8usize.saturating_add(len as usize);
    let Some(header) = bytes.get(8..end) else {
        return bytes;
    };
    // serde_json's map is a BTreeMap: parsing and printing sorts every object's keys.
    let Ok(value) = serde_json::from_slice::<serde_json::Value>(header) else {
        return bytes;
    };
    let Ok(mut sorted) = serde_json::to_vec(&value) else {
        return bytes;
    };
    if sorted.len() > header.len() {
        return bytes;
    }
    sorted.resize(header.len(), b' ');
    bytes[8..end].copy_from_slice(&sorted);
    bytes
}

/// Read and validate a checkpoint (see the module docs for what is checked).
pub fn load(path: &Path, device: &Device) -> Result<Checkpoint> {
    load_with(path, device, &LoadOptions::default())
}

/// [`load`] with options (e.g. to inspect a checkpoint with non-finite weights).
pub fn load_with(path: &Path, device: &Device, opts: &LoadOptions) -> Result<Checkpoint> {
    let bytes = read_checkpoint_file(path)?;
    let st_err = |source| ModelError::Safetensors {
        path: path.to_path_buf(),
        source,
    };
    let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).map_err(st_err)?;
    let st = safetensors::SafeTensors::deserialize(&bytes).map_err(st_err)?;
    let fail = |problems: Vec<String>| ModelError::Checkpoint {
        path: path.to_path_buf(),
        problems,
    };

    let mut problems = Vec::new();
    let meta_map = header.metadata().clone().unwrap_or_default();
    let (grid_views, views): (Vec<_>, Vec<_>) = st
        .tensors()
        .into_iter()
        .partition(|(n, _)| n == OCCUPANCY_TENSOR);
    let found: Vec<(&str, &[usize], DType)> = views
        .iter()
        .map(|(n, v)| (n.as_str(), v.shape(), dtype_of(v.dtype())))
        .collect();

    let (config, format_version, skeleton, meta_rest) =
        match meta_map.get("format").map(String::as_str) {
            Some(FORMAT) => {
                let (c, s, r) = read_pma_meta(&meta_map).map_err(fail)?;
                (c, Some(FORMAT_VERSION), s, Some(r))
            }
            Some(other) if meta_map.contains_key("format_version") => {
                return Err(fail(vec![format!(
                    "metadata `format`: expected \"{FORMAT}\", found {other:?}"
                )]));
            }
            _ => {
                let mut cfg = Config::paper();
                // A state_dict sizes nothing but the frame codes from its shapes; they are
                // bounded like any config's before the layout is built.
                match found
                    .iter()
                    .find(|(n, _, _)| *n == "framecodes.codes.weight")
                {
                    Some((_, [n, _], _)) => cfg.n_framecodes = *n,
                    Some((_, shape, _)) => problems.push(format!(
                    "tensor `framecodes.codes.weight`: expected shape [n, 128], found {shape:?}"
                )),
                    None => {} // reported as missing below
                }
                (cfg, None, SkeletonMeta::smpl(), None)
            }
        };

    if let Err(e) = config.validate() {
        // Nothing is sized from a config outside the limits.
        problems.push(e.to_string());
        return Err(fail(problems));
    }
    problems.extend(check_tensors(&config, found.iter().copied()));
    if problems.is_empty() && !opts.allow_non_finite {
        problems.extend(non_finite(&views));
    }
    let occupancy = match read_occupancy(&meta_map, grid_views.first().map(|(_, v)| v)) {
        Ok(g) => g,
        Err(p) => {
            problems.push(p);
            None
        }
    };
    if !problems.is_empty() {
        if format_version.is_some() {
            problems.push(format!(
                "(shapes are checked against the config stored in the file: n_joints {}, n_framecodes {})",
                config.n_joints, config.n_framecodes
            ));
        }
        return Err(fail(problems));
    }

    let mut tensors = HashMap::with_capacity(views.len());
    for (name, view) in &views {
        let t = candle_core::safetensors::Load::load(view, device)?;
        tensors.insert(name.clone(), t);
    }
    let rest_pose: Vec<[f32; 3]> = tensors["rest_pose"]
        .to_vec2::<f32>()?
        .into_iter()
        .map(|r| [r[0], r[1], r[2]])
        .collect();
    if let Some(meta_rest) = meta_rest {
        if meta_rest != rest_pose {
            return Err(fail(vec![
                "metadata `rest_pose` differs from the `rest_pose` tensor".to_string(),
            ]));
        }
    }
    Ok(Checkpoint {
        config,
        tensors,
        meta: CheckpointMeta {
            format_version,
            skeleton,
            rest_pose,
            config_inferred: format_version.is_none(),
        },
        occupancy,
    })
}

/// The optional occupancy group: both the tensor and its metadata key, or neither.
fn read_occupancy(
    meta_map: &HashMap<String, String>,
    view: Option<&safetensors::tensor::TensorView<'_>>,
) -> std::result::Result<Option<OccupancyGrid>, String> {
    let (json, view) = match (meta_map.get(OCCUPANCY_KEY), view) {
        (None, None) => return Ok(None),
        (Some(_), None) => {
            return Err(format!(
                "metadata `{OCCUPANCY_KEY}` without the tensor `{OCCUPANCY_TENSOR}`"
            ))
        }
        (None, Some(_)) => {
            return Err(format!(
                "tensor `{OCCUPANCY_TENSOR}` without the metadata key `{OCCUPANCY_KEY}`"
            ))
        }
        (Some(j), Some(v)) => (j, v),
    };
    let meta: OccupancyMeta = serde_json::from_str(json)
        .map_err(|e| format!("metadata `{OCCUPANCY_KEY}` is not a valid grid description: {e}"))?;
    meta.config
        .validate(&format!("metadata `{OCCUPANCY_KEY}`"))
        .map_err(|e| e.to_string())?;
    let r = meta.config.resolution;
    let want = [N_JOINTS, r, r, r];
    if view.shape() != want || view.dtype() != safetensors::Dtype::F32 {
        return Err(format!(
            "tensor `{OCCUPANCY_TENSOR}`: expected f32 of shape {want:?} (resolution {r} in its \
             metadata), found {:?} of shape {:?}",
            view.dtype(),
            view.shape()
        ));
    }
    let values: Vec<f32> = view
        .data()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    OccupancyGrid::from_parts(meta, values)
        .map(Some)
        .map_err(|e| format!("tensor `{OCCUPANCY_TENSOR}`: {e}"))
}

/// A checkpoint file's bytes: a regular file of at most [`MAX_CHECKPOINT_BYTES`], read up
/// to its real size.
fn read_checkpoint_file(path: &Path) -> Result<Vec<u8>> {
    pma_data::fsio::read_input(path, MAX_CHECKPOINT_BYTES)
        .map_err(|e| FileError::read(path, e).into())
}

/// One problem per tensor that holds NaN or infinite values (f32 tensors; the layout check
/// has already refused any other dtype).
fn non_finite(views: &[(String, safetensors::tensor::TensorView<'_>)]) -> Vec<String> {
    let mut problems = Vec::new();
    let mut sorted: Vec<_> = views.iter().collect();
    sorted.sort_by(|a, b| a.0.cmp(&b.0));
    for (name, v) in sorted {
        if v.dtype() != safetensors::Dtype::F32 {
            continue;
        }
        let mut first = None;
        let mut count = 0usize;
        for (i, b) in v.data().chunks_exact(4).enumerate() {
            let x = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            if !x.is_finite() {
                count += 1;
                first.get_or_insert((i, x));
            }
        }
        if let Some((i, x)) = first {
            problems.push(format!(
                "tensor `{name}` holds {count} non-finite value(s), the first {x} at flat index {i} \
                 (a diverged or corrupt model; `pma inspect` shows such a file)"
            ));
        }
    }
    problems
}

/// Config, skeleton and rest pose from a pma checkpoint's metadata.
type PmaMeta = (Config, SkeletonMeta, Vec<[f32; 3]>);

/// The metadata of a pma checkpoint, or every problem found.
fn read_pma_meta(meta_map: &HashMap<String, String>) -> std::result::Result<PmaMeta, Vec<String>> {
    let mut problems = Vec::new();
    let mut get = |key: &str| -> Option<String> {
        let v = meta_map.get(key).cloned();
        if v.is_none() {
            problems.push(format!("metadata key `{key}` is missing"));
        }
        v
    };
    let version = get("format_version");
    let config = get("config");
    let skeleton = get("skeleton");
    let rest = get("rest_pose");
    let n_codes = get("n_framecodes");
    if !problems.is_empty() {
        return Err(problems);
    }
    let (version, config, skeleton, rest, n_codes) = (
        version.unwrap(),
        config.unwrap(),
        skeleton.unwrap(),
        rest.unwrap(),
        n_codes.unwrap(),
    );
    if version != FORMAT_VERSION.to_string() {
        problems.push(format!(
            "metadata `format_version`: expected \"{FORMAT_VERSION}\", found {version:?}"
        ));
    }
    let config: Option<Config> = serde_json::from_str(&config)
        .map_err(|e| problems.push(format!("metadata `config` is not a valid config: {e}")))
        .ok();
    let skeleton: Option<SkeletonMeta> = serde_json::from_str(&skeleton)
        .map_err(|e| {
            problems.push(format!(
                "metadata `skeleton` is not {{names, parents}}: {e}"
            ))
        })
        .ok();
    let rest: Option<Vec<[f32; 3]>> = serde_json::from_str(&rest)
        .map_err(|e| problems.push(format!("metadata `rest_pose` is not [[x,y,z],...]: {e}")))
        .ok();
    if let Some(cfg) = &config {
        if n_codes != cfg.n_framecodes.to_string() {
            problems.push(format!(
                "metadata `n_framecodes` = {n_codes:?} disagrees with config.n_framecodes = {}",
                cfg.n_framecodes
            ));
        }
        if let Err(e) = cfg.validate() {
            problems.push(format!("metadata `config`: {e}"));
        }
    }
    if let Some(sk) = &skeleton {
        if *sk != SkeletonMeta::smpl() {
            problems.push(format!(
                "metadata `skeleton`: expected the SMPL 24-joint skeleton, found {} joints {:?}",
                sk.names.len(),
                sk.names
            ));
        }
    }
    match (config, skeleton, rest) {
        (Some(c), Some(s), Some(r)) if problems.is_empty() => Ok((c, s, r)),
        _ => Err(problems),
    }
}

/// candle's dtype for a safetensors dtype; any dtype a checkpoint cannot hold is reported
/// as a dtype problem through the stand-in u8.
fn dtype_of(d: safetensors::Dtype) -> DType {
    match d {
        safetensors::Dtype::F32 => DType::F32,
        safetensors::Dtype::F64 => DType::F64,
        safetensors::Dtype::F16 => DType::F16,
        safetensors::Dtype::BF16 => DType::BF16,
        safetensors::Dtype::I64 => DType::I64,
        safetensors::Dtype::U32 => DType::U32,
        _ => DType::U8,
    }
}

/// Read tensors from a plain safetensors file (no checks): e.g. a partial override such as
/// `sigma_override.safetensors`.
pub fn load_tensors(path: &Path, device: &Device) -> Result<HashMap<String, Tensor>> {
    let bytes = read_checkpoint_file(path)?;
    candle_core::safetensors::load_buffer(&bytes, device).map_err(|e| ModelError::Checkpoint {
        path: PathBuf::from(path),
        problems: vec![e.to_string()],
    })
}

fn to_json<T: Serialize>(v: &T) -> Result<String> {
    serde_json::to_string(v)
        .map_err(|e| ModelError::Config(format!("cannot serialise checkpoint metadata: {e}")))
}

pub(crate) fn tensors_error(problems: Vec<String>) -> ModelError {
    ModelError::Checkpoint {
        path: "<tensors>".into(),
        problems,
    }
}

/// Buffers a checkpoint may carry that would only fail much later, as NaN: a degenerate
/// rest pose and zero or non-finite box sizes (the floor is a fraction of `base_scale`, so a
/// zero there divides by zero in x̄ = x̂ / s).
pub(crate) fn check_buffers(tensors: &HashMap<String, Tensor>) -> Result<()> {
    let mut problems = Vec::new();
    let host = |k: &str| -> Result<Vec<f32>> { host_f32(&tensors[k]) };
    let mut joints = [[0f32; 3]; N_JOINTS];
    for (d, s) in joints.iter_mut().zip(host("rest_pose")?.chunks_exact(3)) {
        d.copy_from_slice(s);
    }
    if let Err(e) = skeleton::check_rest_pose(&joints) {
        problems.push(format!("tensor `rest_pose`: {e}"));
    }
    let mut s = [[0f32; 3]; N_JOINTS];
    for (d, v) in s
        .iter_mut()
        .zip(host("graph_net.base_scale")?.chunks_exact(3))
    {
        d.copy_from_slice(v);
    }
    if let Err(e) = skeleton::check_half_extents(
        "tensor `graph_net.base_scale`",
        &s,
        skeleton::rest_pose_scale(&joints),
    ) {
        problems.push(e.to_string());
    }
    for k in ["pts_embedder.transforms", "raycast.transforms"] {
        if let Some(i) = host(k)?.iter().position(|v| !v.is_finite()) {
            problems.push(format!("tensor `{k}`: value {i} is not finite"));
        }
    }
    match problems.is_empty() {
        true => Ok(()),
        false => Err(tensors_error(problems)),
    }
}
