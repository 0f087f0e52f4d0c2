//! The ray-batch file of `pma forward` (the parity hook for outside tools): an npz of the
//! golden `input/*` arrays without the prefix, i.e. per-ray copies of the pose data as the
//! reference's data loader delivers them, and the npz of outputs under the reference's
//! names.
//!
//! | key | shape | what |
//! | --- | --- | --- |
//! | `rays_o`, `rays_d` | `[R,3]` | ray origins and directions |
//! | `kp3d` | `[R,24,3]` | posed joints (not read: the model derives its own) |
//! | `skts` | `[R,24,4,4]` | world → joint transforms |
//! | `bones` | `[R,24,3]` | axis-angle joint rotations |
//! | `cyls` | `[R,5]` | bounding cylinder |
//! | `cam_idxs` | `[R]` | frame-code indices |
//! | `bgs` | `[R,3]` | background colours |
//! | `rest_pose` | `[24,3]` | the skeleton the batch was made for |
//! | `N_unique` (optional) | `[1]` or `[]` | poses in the batch: `R` splits into that many equal per-pose blocks |
//!
//! Float arrays may be float32 or float64 (read as float32) and must be finite; integer
//! arrays int64 or int32.

use std::collections::HashMap;
use std::io::{BufWriter, Write as _};
use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
use pma_data::dataset::npz::{MemberData, NpyData, NpzReader, NpzWriter};
use pma_data::fsio::AtomicFile;

use crate::error::ModelError;
use crate::network::checkpoint;
use crate::render::avatar::Avatar;
use crate::render::batch::{Outputs, Poses, Rays};

/// What is wrong with a ray batch, its model, or writing the outputs. Every message names
/// the file and the key or tensor.
#[derive(Debug, thiserror::Error)]
pub enum BatchFileError {
    #[error("{file}: missing key `{key}`")]
    MissingKey { file: String, key: String },

    #[error("{file}: key `{key}`: expected shape [{expected}], found {found:?}")]
    Shape {
        file: String,
        key: String,
        expected: String,
        found: Vec<usize>,
    },

    #[error("{file}: key `{key}`: expected {expected}, found {found}")]
    Dtype {
        file: String,
        key: String,
        expected: &'static str,
        found: String,
    },

    #[error("{file}: key `{key}`: non-finite value at flat index {index}")]
    NonFinite {
        file: String,
        key: String,
        index: usize,
    },

    #[error(
        "{file}: {rays} rays cannot be split into N_unique = {n_unique} equal per-pose blocks"
    )]
    PoseBlocks {
        file: String,
        rays: usize,
        n_unique: usize,
    },

    #[error("{file}: key `rest_pose` differs from the model's rest pose by {error:.2e} (the batch was made for another subject)")]
    RestPose { file: String, error: f32 },

    /// A tensor of the override file that the model lacks or has in another shape.
    #[error("{}: tensor `{name}`: {problem}", path.display())]
    Override {
        path: PathBuf,
        name: String,
        problem: String,
    },

    #[error("reading {}: {source}", path.display())]
    OverrideFile {
        path: PathBuf,
        #[source]
        source: Box<candle_core::Error>,
    },

    #[error(transparent)]
    File(#[from] pma_data::FileError),

    // Boxed: the wrapped errors are large.
    #[error(transparent)]
    Data(Box<pma_data::DataError>),

    #[error(transparent)]
    Model(Box<ModelError>),

    #[error(transparent)]
    Candle(Box<candle_core::Error>),
}

crate::error::boxed_from!(
    BatchFileError:
    Data(pma_data::DataError),
    Model(ModelError),
    Candle(candle_core::Error),
);

impl pma_data::ExitKind for BatchFileError {
    fn kind(&self) -> pma_data::ErrorKind {
        use pma_data::ErrorKind;
        match self {
            Self::Candle(_) => ErrorKind::Failure,
            Self::File(e) => e.kind(),
            Self::Data(e) => e.kind(),
            Self::Model(e) => e.kind(),
            _ => ErrorKind::Refused,
        }
    }
}

pub type Result<T> = std::result::Result<T, BatchFileError>;

/// A ray-batch file's arrays, checked as they are taken out.
pub struct RayBatchFile {
    file: String,
    arrays: HashMap<String, (Vec<usize>, NpyData)>,
}

/// What a ray-batch file holds, as model input.
pub struct BatchInput {
    pub rays: Rays,
    pub poses: Poses,
    /// The rest pose the batch was made for (`[24·3]`).
    pub rest: Vec<f32>,
}

impl RayBatchFile {
    pub fn read(path: &Path) -> Result<Self> {
        let mut reader = NpzReader::open(path)?;
        let mut arrays = HashMap::new();
        for key in reader.keys() {
            let a = reader.read(&key)?;
            arrays.insert(key, (a.shape, a.data));
        }
        Ok(Self {
            file: path.display().to_string(),
            arrays,
        })
    }

    /// The file's name as messages give it.
    pub fn file(&self) -> &str {
        &self.file
    }

    fn get(&self, key: &str, shape: &[Option<usize>]) -> Result<&NpyData> {
        let (s, d) = self
            .arrays
            .get(key)
            .ok_or_else(|| BatchFileError::MissingKey {
                file: self.file.clone(),
                key: key.into(),
            })?;
        check_shape(&self.file, key, s, shape)?;
        Ok(d)
    }

    fn f32(&self, key: &str, shape: &[Option<usize>]) -> Result<Vec<f32>> {
        let v = match self.get(key, shape)? {
            NpyData::F32(v) => v.clone(),
            NpyData::F64(v) => v.iter().map(|x| *x as f32).collect(),
            other => return Err(self.dtype(key, "float32", other)),
        };
        if let Some(index) = v.iter().position(|x| !x.is_finite()) {
            return Err(BatchFileError::NonFinite {
                file: self.file.clone(),
                key: key.into(),
                index,
            });
        }
        Ok(v)
    }

    fn i64(&self, key: &str, shape: &[Option<usize>]) -> Result<Vec<i64>> {
        Ok(match self.get(key, shape)? {
            NpyData::I64(v) => v.clone(),
            NpyData::I32(v) => v.iter().map(|x| *x as i64).collect(),
            other => return Err(self.dtype(key, "an integer array", other)),
        })
    }

    fn dtype(&self, key: &str, expected: &'static str, found: &NpyData) -> BatchFileError {
        BatchFileError::Dtype {
            file: self.file.clone(),
            key: key.into(),
            expected,
            found: format!("{:?}", found.elem()),
        }
    }

    /// The batch as model input on `dev`: the rays, and one pose per `N_unique` block (its
    /// first ray's, as the reference strides them).
    pub fn input(&self, dev: &Device) -> Result<BatchInput> {
        let rays_o = self.f32("rays_o", &[None, Some(3)])?;
        let r = rays_o.len() / 3;
        let n = Some(r);
        let rays_d = self.f32("rays_d", &[n, Some(3)])?;
        let bones = self.f32("bones", &[n, Some(24), Some(3)])?;
        let skts = self.f32("skts", &[n, Some(24), Some(4), Some(4)])?;
        let cyls = self.f32("cyls", &[n, Some(5)])?;
        let bgs = self.f32("bgs", &[n, Some(3)])?;
        let cam_idxs = self.i64("cam_idxs", &[n])?;
        let rest = self.f32("rest_pose", &[Some(24), Some(3)])?;
        let n_unique = match self.arrays.get("N_unique") {
            Some(_) => self
                .i64("N_unique", &[Some(1)])
                .or_else(|_| self.i64("N_unique", &[]))?[0] as usize,
            None => 1,
        };
        if r == 0 || n_unique == 0 || r % n_unique != 0 {
            return Err(BatchFileError::PoseBlocks {
                file: self.file.clone(),
                rays: r,
                n_unique,
            });
        }
        let stride = r / n_unique;
        let pick = |v: &[f32], per: usize| -> Vec<f32> {
            (0..n_unique)
                .flat_map(|p| v[p * stride * per..(p * stride + 1) * per].to_vec())
                .collect()
        };
        let pose_bones = (0..n_unique)
            .map(|p| {
                let mut j = [[0f32; 3]; 24];
                for (k, row) in j.iter_mut().enumerate() {
                    let at = (p * stride * 24 + k) * 3;
                    row.copy_from_slice(&bones[at..at + 3]);
                }
                j
            })
            .collect();
        Ok(BatchInput {
            poses: Poses {
                bones: pose_bones,
                skts: Tensor::from_vec(pick(&skts, 24 * 16), (n_unique, 24, 4, 4), dev)?,
                cyls: Tensor::from_vec(pick(&cyls, 5), (n_unique, 5), dev)?,
            },
            rays: Rays {
                origins: Tensor::from_vec(rays_o, (r, 3), dev)?,
                dirs: Tensor::from_vec(rays_d, (r, 3), dev)?,
                bgs: Some(Tensor::from_vec(bgs, (r, 3), dev)?),
                framecodes: cam_idxs,
            },
            rest,
        })
    }
}

fn check_shape(file: &str, key: &str, found: &[usize], shape: &[Option<usize>]) -> Result<()> {
    let ok = found.len() == shape.len()
        && found
            .iter()
            .zip(shape)
            .all(|(a, b)| b.is_none_or(|b| *a == b));
    if ok {
        return Ok(());
    }
    let expected: Vec<String> = shape
        .iter()
        .map(|d| d.map_or("*".into(), |v| v.to_string()))
        .collect();
    Err(BatchFileError::Shape {
        file: file.into(),
        key: key.into(),
        expected: expected.join(","),
        found: found.to_vec(),
    })
}

/// Rays in a ray-batch file (the first dimension of its `rays_o`), without reading the rest.
pub fn count_rays(path: &Path) -> Result<usize> {
    let a = NpzReader::open(path)?.read("rays_o")?;
    let file = path.display().to_string();
    check_shape(&file, "rays_o", &a.shape, &[None, Some(3)])?;
    Ok(a.shape[0])
}

/// How [`load_model`] loads the model a batch runs on.
#[derive(Debug, Clone, Default)]
pub struct ModelOptions {
    /// Accept NaN or infinite weights (refused otherwise), to see what they compute.
    pub allow_non_finite: bool,
    /// A safetensors file whose tensors replace the model's (e.g. the golden `dense` case's
    /// sigma head); each must be a model tensor of the same shape.
    pub overrides: Option<PathBuf>,
}

/// The model at `path` for `batch`: its rest pose must be the batch's (within 1e-5), and
/// the tensors of `opts.overrides` replace its own.
pub fn load_model(
    path: &Path,
    batch: &RayBatchFile,
    rest: &[f32],
    opts: &ModelOptions,
    dev: &Device,
) -> Result<Avatar> {
    let ck = checkpoint::load_with(
        path,
        dev,
        &checkpoint::LoadOptions {
            allow_non_finite: opts.allow_non_finite,
        },
    )?;
    let model_rest = ck.meta.rest_pose.iter().flatten();
    let error = model_rest
        .zip(rest)
        .fold(0f32, |m, (a, b)| m.max((a - b).abs()));
    if error > 1e-5 {
        return Err(BatchFileError::RestPose {
            file: batch.file.clone(),
            error,
        });
    }
    let mut tensors = ck.tensors;
    if let Some(path) = &opts.overrides {
        let replacing = candle_core::safetensors::load(path, dev).map_err(|source| {
            BatchFileError::OverrideFile {
                path: path.clone(),
                source: Box::new(source),
            }
        })?;
        for (name, v) in replacing {
            let problem = match tensors.get(&name) {
                Some(old) if old.dims() == v.dims() => {
                    tensors.insert(name, v);
                    continue;
                }
                Some(old) => format!("expected shape {:?}, found {:?}", old.dims(), v.dims()),
                None => "is not a model tensor".to_string(),
            };
            return Err(BatchFileError::Override {
                path: path.clone(),
                name,
                problem,
            });
        }
    }
    Ok(Avatar::from_tensors(ck.config, tensors, dev)?)
}

/// Write `out` under the reference's names as one npz, replacing `path` atomically.
pub fn write_outputs(out: &Outputs, path: &Path) -> Result<()> {
    let outputs: [(&str, &Tensor); 14] = [
        ("rgb_map", &out.fine.rgb),
        ("acc_map", &out.fine.acc),
        ("disp_map", &out.fine.disp),
        ("weights", &out.fine.weights),
        ("alpha", &out.fine.alpha),
        ("rgb0", &out.coarse.rgb),
        ("acc0", &out.coarse.acc),
        ("disp0", &out.coarse.disp),
        ("alpha0", &out.coarse.alpha),
        ("z_vals", &out.z_vals),
        ("z_vals_coarse", &out.z_coarse),
        ("raw", &out.raw_coarse),
        ("raw_merged", &out.raw),
        ("vol_scale", &out.vol_scale),
    ];
    let write = |source| BatchFileError::from(pma_data::FileError::write(path, source));
    let file = AtomicFile::create(path).map_err(write)?;
    let mut w = NpzWriter::new(
        BufWriter::new(file.owned_writer().map_err(write)?),
        false,
        path.display().to_string(),
    );
    for (name, t) in outputs {
        let data = t.flatten_all()?.to_vec1::<f32>()?;
        w.add(name, t.dims(), MemberData::F32(&data))?;
    }
    w.finish()?.flush().map_err(write)?;
    file.commit().map_err(write)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// (key, shape, data) of the float members.
    type Members = Vec<(&'static str, Vec<usize>, Vec<f32>)>;

    /// A batch of `rays` rays in `poses` blocks; `tweak` edits the members before writing.
    fn write_batch(path: &Path, rays: usize, poses: i64, tweak: impl FnOnce(&mut Members)) {
        let mut members: Members = vec![
            ("rays_o", vec![rays, 3], vec![0.0; rays * 3]),
            ("rays_d", vec![rays, 3], vec![1.0; rays * 3]),
            ("bones", vec![rays, 24, 3], vec![0.0; rays * 72]),
            ("skts", vec![rays, 24, 4, 4], vec![0.0; rays * 384]),
            ("cyls", vec![rays, 5], vec![0.0; rays * 5]),
            ("bgs", vec![rays, 3], vec![0.0; rays * 3]),
            ("rest_pose", vec![24, 3], vec![0.0; 72]),
        ];
        tweak(&mut members);
        let file = std::fs::File::create(path).unwrap();
        let mut w = NpzWriter::new(file, false, path.display().to_string());
        for (key, shape, data) in &members {
            w.add(key, shape, MemberData::F32(data)).unwrap();
        }
        let codes: Vec<i64> = (0..rays as i64).collect();
        w.add("cam_idxs", &[rays], MemberData::I64(&codes)).unwrap();
        w.add("N_unique", &[1], MemberData::I64(&[poses])).unwrap();
        w.finish().unwrap();
    }

    #[test]
    fn a_batch_gives_one_pose_per_block() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("b.npz");
        write_batch(&path, 6, 2, |m| {
            // Ray 3 starts the second block: its bones are that pose's.
            m[2].2[3 * 72] = 0.5;
        });
        assert_eq!(count_rays(&path).unwrap(), 6);
        let input = RayBatchFile::read(&path)
            .unwrap()
            .input(&Device::Cpu)
            .unwrap();
        assert_eq!(input.rays.framecodes, [0, 1, 2, 3, 4, 5]);
        assert_eq!(input.poses.bones.len(), 2);
        assert_eq!(input.poses.bones[1][0][0], 0.5);
        assert_eq!(input.poses.skts.dims(), [2, 24, 4, 4]);
        assert_eq!(input.rest.len(), 72);
    }

    #[test]
    fn bad_batches_name_the_file_and_the_key() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("b.npz");
        let err = |rays, poses, tweak: fn(&mut Members)| {
            write_batch(&path, rays, poses, tweak);
            let e = RayBatchFile::read(&path)
                .and_then(|b| b.input(&Device::Cpu).map(|_| ()))
                .unwrap_err();
            assert!(
                e.to_string().starts_with(&path.display().to_string()),
                "{e}"
            );
            assert_eq!(
                pma_data::ExitKind::kind(&e),
                pma_data::ErrorKind::Refused,
                "{e}"
            );
            e.to_string()
        };
        let e = err(4, 1, |m| {
            m.retain(|(k, _, _)| *k != "skts");
        });
        assert!(e.ends_with("missing key `skts`"), "{e}");
        let e = err(4, 1, |m| m[4].1 = vec![2, 10]);
        assert!(
            e.contains("key `cyls`: expected shape [4,5], found [2, 10]"),
            "{e}"
        );
        let e = err(4, 1, |m| m[1].2[5] = f32::NAN);
        assert!(
            e.contains("key `rays_d`: non-finite value at flat index 5"),
            "{e}"
        );
        let e = err(4, 3, |_| {});
        assert!(
            e.contains("4 rays cannot be split into N_unique = 3"),
            "{e}"
        );
    }
}
