//! Everything but pixels of an `.h5`, with the layout's index semantics.

use std::path::Path;

use ndarray::{Array1, Array2, Array3};
use pma_data::{
    dataset::{Dataset, Warning},
    skeleton::Joints,
};

use super::{pixels::PixelPlan, Layout, MAX_SIDE};
use crate::{
    error::{ConvertError, Result},
    h5::H5File,
};

fn f32_array<D: ndarray::Dimension>(
    h5: &H5File,
    key: &str,
    rank: usize,
    what: &str,
) -> Result<ndarray::Array<f32, D>> {
    let (shape, v) = h5.read_f32(key)?;
    if shape.len() != rank {
        return Err(ConvertError::mismatch(
            h5.path(),
            key,
            format!("rank {rank} {what}"),
            format!("shape {shape:?}"),
        ));
    }
    ndarray::ArrayD::from_shape_vec(shape, v)
        .expect("hdf5 shape matches its element count")
        .into_dimensionality::<D>()
        .map_err(|_| ConvertError::mismatch(h5.path(), key, what, "another rank"))
}

fn opt<T>(
    h5: &H5File,
    keys: &[String],
    key: &str,
    f: impl FnOnce(&H5File) -> Result<T>,
) -> Result<Option<T>> {
    if keys.iter().any(|k| k == key) {
        f(h5).map(Some)
    } else {
        Ok(None)
    }
}

fn i64_vec(h5: &H5File, key: &str) -> Result<Array1<i64>> {
    let (shape, v) = h5.read_i64(key)?;
    if shape.len() != 1 {
        return Err(ConvertError::mismatch(
            h5.path(),
            key,
            "shape (N,)",
            format!("{shape:?}"),
        ));
    }
    Ok(Array1::from_vec(v))
}

fn scalar_f64(h5: &H5File, key: &str) -> Result<f64> {
    let (shape, v) = h5.read_f64(key)?;
    match v.as_slice() {
        [x] if shape.iter().product::<usize>() == 1 => Ok(*x),
        _ => Err(ConvertError::mismatch(
            h5.path(),
            key,
            "a scalar",
            format!("shape {shape:?}"),
        )),
    }
}

/// Keys the converter reads from an `.h5`; any other key is reported as dropped.
const KNOWN_KEYS: &[&str] = &[
    "img_shape",
    "imgs",
    "masks",
    "sampling_masks",
    "bkgds",
    "bkgd_idxs",
    "c2ws",
    "focals",
    "centers",
    "img_pose_indices",
    "kp_idxs",
    "kp3d",
    "bones",
    "skts",
    "cyls",
    "rest_pose",
    "betas",
    "gt_kp3d",
    "pose_scale",
    "ext_scale",
];

/// Reads everything but pixels from an `.h5` into a [`Dataset`], with the
/// layout's index semantics applied. Pixel keys are only checked for shape.
pub(super) fn read_h5_scene(h5: &H5File, layout: Layout) -> Result<(Dataset, PixelPlan)> {
    let keys = h5.keys()?;
    let bones: Array3<f32> = f32_array(h5, "bones", 3, "(P,24,3)")?;
    let mut ds = Dataset::from_bones(bones);
    ds.source = h5.path().display().to_string();
    ds.head_dir = layout.head_dir();

    read_pose_arrays(h5, &keys, &mut ds)?;
    read_cameras(h5, &keys, &mut ds)?;
    read_img_shape(h5, &keys, &mut ds)?;
    set_index_maps(h5, &keys, &mut ds, layout)?;
    warn_dropped_keys(&keys, &mut ds, layout);

    let plan = PixelPlan::new(h5, &keys, &ds, layout)?;
    Ok((ds, plan))
}

/// The pose-side arrays besides `bones`, as stored.
fn read_pose_arrays(h5: &H5File, keys: &[String], ds: &mut Dataset) -> Result<()> {
    if let Some(rest) = opt(h5, keys, "rest_pose", |h| h.read_f32("rest_pose"))? {
        ds.rest_pose = Some(joints(h5.path(), "rest_pose", &rest.0, &rest.1)?);
    }
    ds.kp3d = opt(h5, keys, "kp3d", |h| f32_array(h, "kp3d", 3, "(P,24,3)"))?;
    ds.skts = opt(h5, keys, "skts", |h| {
        f32_array::<ndarray::Ix4>(h, "skts", 4, "(P,24,4,4)")
    })?;
    ds.cyls = opt(h5, keys, "cyls", |h| f32_array(h, "cyls", 2, "(P,5)"))?;
    ds.betas = opt(h5, keys, "betas", |h| {
        f32_array(h, "betas", 2, "(P,10) or (1,10)")
    })?;
    ds.gt_kp3d = opt(h5, keys, "gt_kp3d", |h| {
        f32_array(h, "gt_kp3d", 3, "(P,J',3)")
    })?;
    Ok(())
}

/// Camera arrays and scales; `focals (C,)` becomes `(C,2)`.
fn read_cameras(h5: &H5File, keys: &[String], ds: &mut Dataset) -> Result<()> {
    let has = |k: &str| keys.iter().any(|x| x == k);
    ds.c2ws = opt(h5, keys, "c2ws", |h| f32_array(h, "c2ws", 3, "(C,4,4)"))?;
    if has("focals") {
        let (shape, v) = h5.read_f32("focals")?;
        ds.focals = Some(match shape.as_slice() {
            [c] => Array2::from_shape_fn((*c, 2), |(i, _)| v[i]),
            [c, 2] => Array2::from_shape_vec((*c, 2), v).expect("shape matches"),
            _ => {
                return Err(ConvertError::mismatch(
                    h5.path(),
                    "focals",
                    "shape (C,) or (C,2)",
                    format!("{shape:?}"),
                ))
            }
        });
        if shape.len() == 1 {
            ds.derived.push("focals (C,) expanded to (C,2)".into());
        }
    }
    ds.centers = opt(h5, keys, "centers", |h| f32_array(h, "centers", 2, "(C,2)"))?;
    if has("pose_scale") {
        ds.pose_scale = scalar_f64(h5, "pose_scale")? as f32;
    }
    ds.ext_scale = opt(h5, keys, "ext_scale", |h| scalar_f64(h, "ext_scale"))?;
    Ok(())
}

/// `img_shape`, `(N, H, W, 3)` with sides up to [`MAX_SIDE`].
fn read_img_shape(h5: &H5File, keys: &[String], ds: &mut Dataset) -> Result<()> {
    if !keys.iter().any(|k| k == "img_shape") {
        return Ok(());
    }
    let (shape, v) = h5.read_i64("img_shape")?;
    let side = 1..=MAX_SIDE as i64;
    match v.as_slice() {
        [n, hh, ww, 3] if shape == [4] && *n >= 0 && side.contains(hh) && side.contains(ww) => {
            ds.img_shape = Some([*n as usize, *hh as usize, *ww as usize, 3]);
            Ok(())
        }
        _ => Err(ConvertError::mismatch(
            h5.path(),
            "img_shape",
            format!("4 entries (N, H, W, 3) with 1 <= H, W <= {MAX_SIDE}"),
            format!("{v:?}"),
        )),
    }
}

/// The per-image index maps with the layout's semantics (docs/conventions.md,
/// "A-NeRF/DANBO .h5"): stored for H36M-ZJU and AIST, built for the others.
fn set_index_maps(h5: &H5File, keys: &[String], ds: &mut Dataset, layout: Layout) -> Result<()> {
    let path = h5.path();
    let has = |k: &str| keys.iter().any(|x| x == k);
    let n = ds.n_images();
    let p = ds.n_poses();
    // These layouts have per-image poses or cameras, so their index maps are
    // built from N; a corrupt N must not size them.
    let cams = ds.c2ws.as_ref().map_or(0, |c| c.shape()[0]);
    if layout != Layout::H36mZju && layout != Layout::Aist && n > p.max(cams) {
        return Err(ConvertError::mismatch(
            path,
            "img_shape",
            format!(
                "at most {} images ({p} poses, {cams} cameras in the file)",
                p.max(cams)
            ),
            format!("N = {n}"),
        ));
    }
    let identity = || Array1::from_iter(0..n as i64);

    match layout {
        Layout::H36mZju | Layout::Aist => {
            ds.kp_idxs = opt(h5, keys, "kp_idxs", |h| i64_vec(h, "kp_idxs"))?;
            ds.img_pose_indices = opt(h5, keys, "img_pose_indices", |h| {
                i64_vec(h, "img_pose_indices")
            })?;
            ds.bkgd_idxs = opt(h5, keys, "bkgd_idxs", |h| i64_vec(h, "bkgd_idxs"))?;
        }
        Layout::PerfCap => {
            ds.kp_idxs = Some(identity());
            ds.img_pose_indices = Some(identity());
            if has("bkgd_idxs") && i64_vec(h5, "bkgd_idxs")?.iter().any(|&b| b != 0) {
                ds.warnings.push(warn(
                    "bkgd_idxs",
                    "PerfCap images all use background plate 0; the stored values are replaced",
                ));
            }
            ds.bkgd_idxs = Some(Array1::zeros(n));
            ds.derived.push(
                "kp_idxs, img_pose_indices (identity), bkgd_idxs (zeros): PerfCap semantics".into(),
            );
        }
        Layout::Surreal => {
            if p == 0 || n % p != 0 {
                return Err(ConvertError::invalid(
                    path,
                    "bones",
                    format!("SURREAL images are camera-major over the poses, so N = {n} must be a multiple of P = {p}"),
                ));
            }
            ds.kp_idxs = Some(Array1::from_iter((0..n).map(|i| (i % p) as i64)));
            ds.img_pose_indices = Some(identity());
            ds.bkgd_idxs = Some(Array1::zeros(n));
            ds.derived.push("kp_idxs (n mod P), img_pose_indices (identity), bkgd_idxs (zeros): SURREAL semantics".into());
        }
        Layout::Mixamo => {
            ds.kp_idxs = Some(identity());
            ds.img_pose_indices = Some(identity());
            ds.bkgd_idxs = Some(Array1::zeros(n));
            ds.derived.push(
                "kp_idxs, img_pose_indices (identity; the stored kp_idxs are frame numbers), bkgd_idxs (zeros): Mixamo semantics"
                    .into(),
            );
        }
    }
    Ok(())
}

/// Warns about keys outside the schema and stored values the layout replaces.
fn warn_dropped_keys(keys: &[String], ds: &mut Dataset, layout: Layout) {
    for k in keys {
        if !KNOWN_KEYS.contains(&k.as_str()) {
            ds.warnings
                .push(warn(k, "not part of the pma-npz schema; dropped"));
        } else if k == "kp_idxs" && layout == Layout::Mixamo {
            ds.warnings.push(warn(
                k,
                "Mixamo frame numbers, not pose rows; replaced by the image index",
            ));
        } else if k == "bkgds" && layout == Layout::Mixamo {
            ds.warnings.push(warn(
                k,
                "Mixamo images are composited on white; replaced by one white plate",
            ));
        }
    }
}

fn warn(key: &str, message: &str) -> Warning {
    Warning {
        key: key.to_string(),
        message: message.to_string(),
    }
}

/// `(24,3)` or `(1,24,3)` → joints.
pub(crate) fn joints(path: &Path, key: &str, shape: &[usize], v: &[f32]) -> Result<Joints> {
    if !(shape == [24, 3] || shape == [1, 24, 3]) {
        return Err(ConvertError::mismatch(
            path,
            key,
            "shape (24,3) or (1,24,3)",
            format!("{shape:?}"),
        ));
    }
    let mut j = [[0.0f32; 3]; 24];
    for (i, row) in j.iter_mut().enumerate() {
        row.copy_from_slice(&v[3 * i..3 * i + 3]);
    }
    Ok(j)
}
