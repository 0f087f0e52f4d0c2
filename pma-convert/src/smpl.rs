//! The user's SMPL body model (never shipped): what the capture importer needs
//! of it, which is the shape space and the joint regressor.
//!
//! Joints do not depend on the pose-corrective blend shapes or the skinning
//! weights: SMPL regresses its joints from the shaped template, and posed
//! joints follow by kinematics (docs/conventions.md, "ZJU-MoCap capture").
//!
//! Accepted files:
//! * `.pkl` as distributed: a pickled dict of numpy arrays, a scipy sparse
//!   `J_regressor`, chumpy `Ch` objects (their `x` array is used); read with
//!   the restricted pickle machine, nothing executes;
//! * `.npz`: `v_template (V,3)`, `shapedirs (V,3,B)`, `kintree_table (2,24)`
//!   and either a dense `J_regressor (24,V)` or its compressed-sparse-column
//!   parts `J_regressor_data`, `J_regressor_indices`, `J_regressor_indptr`
//!   (`J_regressor_shape` optional). Other members (`weights`, `posedirs`, `f`)
//!   are ignored.

use std::{collections::BTreeMap, path::Path};

use pma_data::skeleton::{N_JOINTS, PARENTS};

use crate::{
    capture::npy::{read_npy_bytes, NpyContent},
    error::{ConvertError, Result},
    pickle::{
        self,
        numpy::{dense, NumpyData},
        Value,
    },
};

/// A dense array: shape and row-major elements.
pub type Dense = (Vec<usize>, Vec<f64>);

/// The parts of an SMPL model the joints need.
#[derive(Clone, Debug)]
pub struct SmplModel {
    /// `(V,3)` row-major.
    pub v_template: Vec<f64>,
    /// `(V,3,B)` row-major.
    pub shapedirs: Vec<f64>,
    pub n_betas: usize,
    /// `(24,V)` row-major.
    pub j_regressor: Vec<f64>,
    pub n_verts: usize,
}

impl SmplModel {
    /// Reads and checks a `.pkl` or `.npz` model.
    pub fn read(path: &Path) -> Result<SmplModel> {
        let arrays = match crate::extension(path).as_str() {
            "pkl" => read_pkl(path)?,
            "npz" => read_npz(path)?,
            _ => {
                return Err(ConvertError::Usage(format!(
                    "{}: unknown SMPL model type; expected a .pkl or .npz file",
                    path.display()
                )))
            }
        };
        Self::from_arrays(path, &arrays)
    }

    /// Builds the model from named arrays, checking every shape.
    pub fn from_arrays(path: &Path, a: &BTreeMap<String, Dense>) -> Result<SmplModel> {
        let get = |k: &str| {
            a.get(k).ok_or_else(|| {
                ConvertError::missing(
                    path,
                    k,
                    " (an SMPL model needs v_template, shapedirs, J_regressor and kintree_table)",
                )
            })
        };
        let (vs, v_template) = get("v_template")?;
        let n_verts = match vs[..] {
            [v, 3] if v > 0 => v,
            _ => {
                return Err(ConvertError::mismatch(
                    path,
                    "v_template",
                    "shape (V,3)",
                    format!("{vs:?}"),
                ))
            }
        };
        let (ss, shapedirs) = get("shapedirs")?;
        let n_betas = match ss[..] {
            [v, 3, b] if v == n_verts && b > 0 => b,
            _ => {
                return Err(ConvertError::mismatch(
                    path,
                    "shapedirs",
                    format!("shape ({n_verts},3,B)"),
                    format!("{ss:?}"),
                ))
            }
        };
        let j_regressor = match (a.get("J_regressor"), a.get("J_regressor_data")) {
            (Some((js, j)), _) => {
                if js[..] != [N_JOINTS, n_verts] {
                    return Err(ConvertError::mismatch(
                        path,
                        "J_regressor",
                        format!("shape ({N_JOINTS},{n_verts})"),
                        format!("{js:?}"),
                    ));
                }
                j.clone()
            }
            (None, Some((_, data))) => {
                let (_, indices) = get("J_regressor_indices")?;
                let (_, indptr) = get("J_regressor_indptr")?;
                if let Some((_, sh)) = a.get("J_regressor_shape") {
                    if sh[..] != [N_JOINTS as f64, n_verts as f64] {
                        return Err(ConvertError::mismatch(
                            path,
                            "J_regressor_shape",
                            format!("[{N_JOINTS}, {n_verts}]"),
                            format!("{sh:?}"),
                        ));
                    }
                }
                pickle::numpy::sparse_to_dense(data, indices, indptr, [N_JOINTS, n_verts], false)
                    .map_err(|m| ConvertError::invalid(path, "J_regressor", m))?
            }
            (None, None) => get("J_regressor")?.1.clone(),
        };
        let (ks, kin) = get("kintree_table")?;
        if ks[..] != [2, N_JOINTS] {
            return Err(ConvertError::mismatch(
                path,
                "kintree_table",
                format!("shape (2,{N_JOINTS})"),
                format!("{ks:?}"),
            ));
        }
        // SMPL's tree must be the one pma's skeleton uses (the root's parent
        // is stored as -1 or 2^32-1).
        for j in 1..N_JOINTS {
            if kin[N_JOINTS + j] != j as f64 || kin[j] != PARENTS[j] as f64 {
                return Err(ConvertError::mismatch(
                    path,
                    "kintree_table",
                    format!("SMPL's joint tree (joint {j} has parent {})", PARENTS[j]),
                    format!("parent {} of joint {}", kin[j], kin[N_JOINTS + j]),
                ));
            }
        }
        for (k, v) in [
            ("v_template", &v_template[..]),
            ("shapedirs", &shapedirs[..]),
            ("J_regressor", &j_regressor[..]),
        ] {
            if let Some(i) = v.iter().position(|x| !x.is_finite()) {
                return Err(ConvertError::invalid(
                    path,
                    k,
                    format!("element {i} is not finite"),
                ));
            }
        }
        Ok(SmplModel {
            v_template: v_template.clone(),
            shapedirs: shapedirs.clone(),
            n_betas,
            j_regressor,
            n_verts,
        })
    }

    /// Rest joints for shape `betas`: `J_regressor · (v_template + shapedirs·β)`.
    /// Betas beyond the model's shape space are ignored.
    pub fn rest_joints(&self, betas: &[f64]) -> [[f64; 3]; N_JOINTS] {
        let b = betas.len().min(self.n_betas);
        let mut v = self.v_template.clone();
        for (i, vi) in v.iter_mut().enumerate() {
            let dirs = &self.shapedirs[i * self.n_betas..i * self.n_betas + b];
            *vi += dirs.iter().zip(betas).map(|(d, x)| d * x).sum::<f64>();
        }
        let mut j = [[0.0; 3]; N_JOINTS];
        for (r, row) in j.iter_mut().enumerate() {
            let w = &self.j_regressor[r * self.n_verts..(r + 1) * self.n_verts];
            for (k, x) in row.iter_mut().enumerate() {
                *x = w
                    .iter()
                    .enumerate()
                    .map(|(i, wi)| wi * v[3 * i + k])
                    .sum::<f64>();
            }
        }
        j
    }
}

const MODEL_KEYS: [&str; 8] = [
    "v_template",
    "shapedirs",
    "J_regressor",
    "kintree_table",
    "J_regressor_data",
    "J_regressor_indices",
    "J_regressor_indptr",
    "J_regressor_shape",
];

fn read_pkl(path: &Path) -> Result<BTreeMap<String, Dense>> {
    let bytes = pma_data::fsio::read_input(path, crate::MAX_INPUT_BYTES)
        .map_err(|e| ConvertError::io(path, e))?;
    let name = path
        .file_name()
        .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
    let tree = pickle::parse(&bytes, &NumpyData, path, &name)?;
    let items = tree.heap.items(&tree.root).ok_or_else(|| {
        ConvertError::format(
            path,
            format!("the pickle holds a {}, expected a dict", tree.root.kind()),
        )
    })?;
    let mut out = BTreeMap::new();
    for (k, v) in items {
        let Value::Str(k) = k else { continue };
        if !MODEL_KEYS.contains(&&**k) {
            continue;
        }
        let d = dense(&tree.heap, v).map_err(|m| ConvertError::invalid(path, &**k, m))?;
        out.insert(k.to_string(), d);
    }
    Ok(out)
}

fn read_npz(path: &Path) -> Result<BTreeMap<String, Dense>> {
    let f = pma_data::fsio::open_input(path).map_err(|e| ConvertError::io(path, e))?;
    let mut zip = zip::ZipArchive::new(f).map_err(|cause| ConvertError::Zip {
        path: path.to_path_buf(),
        cause,
    })?;
    let mut out = BTreeMap::new();
    for i in 0..zip.len() {
        let mut m = zip.by_index(i).map_err(|cause| ConvertError::Zip {
            path: path.to_path_buf(),
            cause,
        })?;
        let name = m.name().map(|n| n.to_string()).unwrap_or_default();
        let Some(key) = name.strip_suffix(".npy").map(str::to_string) else {
            continue;
        };
        if !MODEL_KEYS.contains(&key.as_str()) {
            continue;
        }
        let mut b = Vec::new();
        std::io::Read::read_to_end(&mut m, &mut b).map_err(|e| ConvertError::io(path, e))?;
        let d = match read_npy_bytes(&b, path, &key)? {
            NpyContent::Array(a) => (
                a.shape.clone(),
                a.to_f64()
                    .map_err(|m| ConvertError::invalid(path, &key, m))?,
            ),
            NpyContent::Pickled(_) => {
                return Err(ConvertError::invalid(
                    path,
                    &key,
                    "an object array; SMPL .npz members must be numeric",
                ))
            }
        };
        out.insert(key, d);
    }
    Ok(out)
}
