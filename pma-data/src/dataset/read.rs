//! npz → [`Dataset`]: dtype and shape normalisation of every known key
//! (docs/conventions.md, "pma-npz v1"). Counts across keys are
//! checked later by validation.

use std::path::Path;

use ndarray::{Array1, Array2, Array3, Array4};

use super::npz::{NpyArray, NpyData, NpzReader};
use super::{frames_path_for, Dataset, ReadOptions, Warning};
use crate::error::{DataError, Result};
use crate::skeleton::{matrix_from_rot6d, matrix_to_axis_angle, Joints, N_JOINTS};

/// Keys that live in the frames file of a split scene.
pub(crate) const PIXEL_KEYS: [&str; 4] = ["imgs", "masks", "sampling_masks", "bkgds"];

/// Keys read by the loader; anything else is ignored with a warning.
const KNOWN_KEYS: [&str; 25] = [
    "schema_version",
    "rest_pose",
    "bones",
    "kp3d",
    "root_locs",
    "skts",
    "cyls",
    "betas",
    "gt_kp3d",
    "c2ws",
    "focals",
    "centers",
    "img_shape",
    "kp_idxs",
    "img_pose_indices",
    "bkgd_idxs",
    "imgs",
    "masks",
    "sampling_masks",
    "bkgds",
    "pose_scale",
    "ext_scale",
    "head_dir",
    "eval_tag",
    "frame_ids",
];

struct Ctx<'a> {
    file: String,
    opts: &'a ReadOptions,
    warnings: Vec<Warning>,
    derived: Vec<String>,
}

impl Ctx<'_> {
    fn shape_err(&self, key: &str, expected: &str, found: &[usize]) -> DataError {
        DataError::Shape {
            file: self.file.clone(),
            key: key.into(),
            expected: expected.into(),
            found: found.to_vec(),
        }
    }

    fn dtype_err(&self, key: &str, expected: &str, found: &NpyData) -> DataError {
        DataError::Dtype {
            file: self.file.clone(),
            key: key.into(),
            expected: expected.into(),
            found: found.elem().descr().into(),
        }
    }

    fn warn(&mut self, key: &str, msg: impl Into<String>) {
        self.warnings.push(Warning {
            key: key.into(),
            message: msg.into(),
        });
    }

    /// Float payload as f32; `<f8` arrays are accepted with a warning.
    fn f32s(&mut self, key: &str, a: NpyArray) -> Result<(Vec<usize>, Vec<f32>)> {
        match a.data {
            NpyData::F32(v) => Ok((a.shape, v)),
            NpyData::F64(v) => {
                self.warn(key, "stored as float64; converted to float32");
                Ok((a.shape, v.into_iter().map(|x| x as f32).collect()))
            }
            other => Err(self.dtype_err(key, "<f4", &other)),
        }
    }

    /// Integer payload; float payloads only when `allow_integral_float` and
    /// every value is integral (the PerfCap `bkgd_idxs` case).
    fn i64s(
        &mut self,
        key: &str,
        a: NpyArray,
        allow_integral_float: bool,
    ) -> Result<(Vec<usize>, Vec<i64>)> {
        let shape = a.shape;
        let v = match a.data {
            NpyData::I64(v) => v,
            NpyData::I32(v) => v.into_iter().map(i64::from).collect(),
            NpyData::I8(v) => v.into_iter().map(i64::from).collect(),
            NpyData::U8(v) => v.into_iter().map(i64::from).collect(),
            NpyData::F32(v) if allow_integral_float => {
                self.integral(key, v.into_iter().map(f64::from).collect())?
            }
            NpyData::F64(v) if allow_integral_float => self.integral(key, v)?,
            other => return Err(self.dtype_err(key, "<i8 (or <i4)", &other)),
        };
        Ok((shape, v))
    }

    fn integral(&mut self, key: &str, v: Vec<f64>) -> Result<Vec<i64>> {
        if let Some((i, x)) = v
            .iter()
            .enumerate()
            .find(|(_, x)| !x.is_finite() || x.fract() != 0.0)
        {
            return Err(DataError::Value {
                file: self.file.clone(),
                key: key.into(),
                problem: format!("non-integral index at position {i}"),
                expected: "integral values".into(),
                found: x.to_string(),
            });
        }
        self.warn(key, "stored as float; cast to int64");
        Ok(v.into_iter().map(|x| x as i64).collect())
    }

    fn u8s(&self, key: &str, a: NpyArray) -> Result<(Vec<usize>, Vec<u8>)> {
        match a.data {
            NpyData::U8(v) => Ok((a.shape, v)),
            other => Err(self.dtype_err(key, "|u1 (uint8 pixels)", &other)),
        }
    }

    fn scalar_f64(&mut self, key: &str, a: NpyArray) -> Result<f64> {
        if a.shape.iter().product::<usize>() != 1 || a.shape.len() > 1 {
            return Err(self.shape_err(key, "() (a 0-d scalar)", &a.shape));
        }
        match a.data {
            NpyData::F32(v) => Ok(v[0] as f64),
            NpyData::F64(v) => Ok(v[0]),
            other => Err(self.dtype_err(key, "<f4 or <f8", &other)),
        }
    }
}

fn arr2(shape: [usize; 2], v: Vec<f32>) -> Array2<f32> {
    Array2::from_shape_vec(shape, v).expect("shape checked")
}
/// A `(rows, cols)` float array; `expected` names the shape in the error.
fn rows(
    ctx: &mut Ctx<'_>,
    key: &str,
    a: NpyArray,
    cols: usize,
    expected: &str,
) -> Result<Array2<f32>> {
    let (s, v) = ctx.f32s(key, a)?;
    if s.len() != 2 || s[1] != cols {
        return Err(ctx.shape_err(key, expected, &s));
    }
    Ok(arr2([s[0], cols], v))
}
fn arr3<T>(shape: [usize; 3], v: Vec<T>) -> Array3<T> {
    Array3::from_shape_vec(shape, v).expect("shape checked")
}

/// `(P,24,3)` with a joint-count check.
fn pose_array(ctx: &Ctx<'_>, key: &str, shape: &[usize], last: usize) -> Result<[usize; 3]> {
    if shape.len() != 3 || shape[1] != N_JOINTS || shape[2] != last {
        let what = if shape.len() == 3 && shape[1] != N_JOINTS {
            format!("(P,24,{last}) - only the 24-joint SMPL skeleton is supported")
        } else {
            format!("(P,24,{last})")
        };
        return Err(ctx.shape_err(key, &what, shape));
    }
    Ok([shape[0], shape[1], shape[2]])
}

/// Convert 6D bones `(P,24,6)` to axis-angle; degenerate columns are an error
/// naming the pose and joint.
fn bones_from_6d(ctx: &Ctx<'_>, p: usize, v: &[f32]) -> Result<Vec<f32>> {
    let mut out = Vec::with_capacity(p * N_JOINTS * 3);
    for (i, x) in v.chunks_exact(6).enumerate() {
        let x6 = [0, 1, 2, 3, 4, 5].map(|k| x[k] as f64);
        let m = matrix_from_rot6d(x6).map_err(|e| DataError::Value {
            file: ctx.file.clone(),
            key: "bones".into(),
            problem: format!(
                "6D rotation of pose {} joint {}",
                i / N_JOINTS,
                i % N_JOINTS
            ),
            expected: "two linearly independent columns (|a1| >= 1e-6, |u| >= 1e-6)".into(),
            found: e.to_string(),
        })?;
        let w = matrix_to_axis_angle(m);
        out.extend([w.x as f32, w.y as f32, w.z as f32]);
    }
    Ok(out)
}

/// Pixel array `(n, H·W, ch)`, also accepting `(n, H, W, ch)` and, for
/// single-channel masks, `(n, H, W)`. Returns the flattened array and the
/// (H, W) implied by a 4-D/3-D spatial shape, if any.
fn pixel_array(
    ctx: &mut Ctx<'_>,
    key: &str,
    a: NpyArray,
    ch: usize,
) -> Result<(Array3<u8>, Option<(usize, usize)>)> {
    let (shape, mut v) = ctx.u8s(key, a)?;
    let expected = if ch == 3 {
        "(n,H*W,3) or (n,H,W,3)"
    } else {
        "(n,H*W,1), (n,H,W) or (n,H,W,1)"
    };
    let (n, hw, c, spatial) = match shape.as_slice() {
        [n, hw, c] if ch == 3 || *c == 1 => (*n, *hw, *c, None),
        [n, h, w] if ch == 1 => (*n, h * w, 1, Some((*h, *w))),
        [n, h, w, c] => (*n, h * w, *c, Some((*h, *w))),
        _ => return Err(ctx.shape_err(key, expected, &shape)),
    };
    let c = if c == ch {
        c
    } else if ch == 3 && c == 4 {
        if !ctx.opts.drop_alpha {
            return Err(DataError::Dtype {
                file: ctx.file.clone(),
                key: key.into(),
                expected:
                    "3-channel RGB (4-channel RGBA is accepted only with drop_alpha / --drop-alpha)"
                        .into(),
                found: format!("{c} channels, shape {shape:?}"),
            });
        }
        v = v.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect();
        ctx.warn(key, "alpha channel dropped");
        3
    } else {
        return Err(ctx.shape_err(key, expected, &shape));
    };
    Ok((arr3([n, hw, c], v), spatial))
}

/// Read every member of `path` (and of the sibling frames file of a split
/// scene) into a [`Dataset`], without derivations or cross-key checks.
pub(crate) fn read_npz(path: &Path, opts: &ReadOptions) -> Result<Dataset> {
    let mut reader = NpzReader::open(path)?;
    let mut ctx = Ctx {
        file: reader.file().to_string(),
        opts,
        warnings: Vec::new(),
        derived: Vec::new(),
    };
    for other in reader.other_members() {
        ctx.warn("", format!("member {other} is not an .npy array; ignored"));
    }
    let mut members: Vec<(String, NpyArray)> = Vec::new();
    let mut pixel_shape: Option<(usize, usize)> = None;
    for key in reader.keys() {
        if !KNOWN_KEYS.contains(&key.as_str()) {
            ctx.warn(&key, "unknown key; ignored");
            continue;
        }
        members.push((key.clone(), reader.read(&key)?));
    }
    let have_pixels = members
        .iter()
        .any(|(k, _)| PIXEL_KEYS.contains(&k.as_str()));
    if !have_pixels {
        if let Some(frames) = frames_path_for(path) {
            if frames.exists() {
                let mut fr = NpzReader::open(&frames)?;
                for key in fr.keys() {
                    if PIXEL_KEYS.contains(&key.as_str()) {
                        members.push((key.clone(), fr.read(&key)?));
                    } else {
                        ctx.warn(
                            &key,
                            format!(
                                "{}: only pixel keys are read from a frames file; ignored",
                                fr.file()
                            ),
                        );
                    }
                }
            } else {
                ctx.warn(
                    "",
                    format!("split scene without its frames file {}", frames.display()),
                );
            }
        }
    }

    let mut ds = Dataset::from_bones(Array3::zeros((0, N_JOINTS, 3)));
    ds.source = ctx.file.clone();
    let mut have_bones = false;
    for (key, a) in members {
        for n in &a.notes {
            ctx.warn(&key, n.clone());
        }
        let k = key.as_str();
        match k {
            "schema_version" => {
                let (s, v) = ctx.i64s(k, a, false)?;
                if v.len() != 1 || s.len() > 1 {
                    return Err(ctx.shape_err(k, "()", &s));
                }
                if v[0] != super::SCHEMA_VERSION as i64 {
                    return Err(DataError::Value {
                        file: ctx.file.clone(),
                        key: k.into(),
                        problem: "unsupported schema version".into(),
                        expected: super::SCHEMA_VERSION.to_string(),
                        found: v[0].to_string(),
                    });
                }
                ds.schema_version = v[0] as i32;
            }
            "rest_pose" => {
                let (s, v) = ctx.f32s(k, a)?;
                let ok = matches!(s.as_slice(), [24, 3] | [1, 24, 3]);
                if !ok {
                    return Err(ctx.shape_err(k, "(24,3) or (1,24,3)", &s));
                }
                let mut r: Joints = [[0.0; 3]; N_JOINTS];
                for (j, row) in r.iter_mut().enumerate() {
                    row.copy_from_slice(&v[3 * j..3 * j + 3]);
                }
                ds.rest_pose = Some(r);
            }
            "bones" => {
                let (s, v) = ctx.f32s(k, a)?;
                if s.len() == 3 && s[1] == N_JOINTS && s[2] == 6 {
                    let aa = bones_from_6d(&ctx, s[0], &v)?;
                    ctx.warn(k, "6D rotations converted to axis-angle");
                    ds.bones = arr3([s[0], N_JOINTS, 3], aa);
                } else {
                    let sh = pose_array(&ctx, k, &s, 3)?;
                    ds.bones = arr3(sh, v);
                }
                have_bones = true;
            }
            "kp3d" => {
                let (s, v) = ctx.f32s(k, a)?;
                ds.kp3d = Some(arr3(pose_array(&ctx, k, &s, 3)?, v));
            }
            "root_locs" => ds.root_locs = Some(rows(&mut ctx, k, a, 3, "(P,3)")?),
            "skts" => {
                let (s, v) = ctx.f32s(k, a)?;
                if s.len() != 4 || s[1] != N_JOINTS || s[2] != 4 || s[3] != 4 {
                    return Err(ctx.shape_err(k, "(P,24,4,4)", &s));
                }
                ds.skts =
                    Some(Array4::from_shape_vec([s[0], N_JOINTS, 4, 4], v).expect("shape checked"));
            }
            "cyls" => ds.cyls = Some(rows(&mut ctx, k, a, 5, "(P,5)")?),
            "betas" => ds.betas = Some(rows(&mut ctx, k, a, 10, "(P,10) or (1,10)")?),
            "gt_kp3d" => {
                let (s, v) = ctx.f32s(k, a)?;
                if s.len() != 3 || s[2] != 3 {
                    return Err(ctx.shape_err(k, "(P,J',3)", &s));
                }
                ds.gt_kp3d = Some(arr3([s[0], s[1], 3], v));
            }
            "frame_ids" => {
                let (s, v) = ctx.i64s(k, a, false)?;
                if s.len() != 1 {
                    return Err(ctx.shape_err(k, "(P,)", &s));
                }
                ds.frame_ids = Some(Array1::from(v));
            }
            "head_dir" => {
                let (s, v) = ctx.f32s(k, a)?;
                if s != [3] {
                    return Err(ctx.shape_err(k, "(3,)", &s));
                }
                ds.head_dir = [v[0], v[1], v[2]];
            }
            "pose_scale" => ds.pose_scale = ctx.scalar_f64(k, a)? as f32,
            "ext_scale" => ds.ext_scale = Some(ctx.scalar_f64(k, a)?),
            "c2ws" => {
                let (s, v) = ctx.f32s(k, a)?;
                if s.len() != 3 || s[1] != 4 || s[2] != 4 {
                    return Err(ctx.shape_err(k, "(C,4,4)", &s));
                }
                ds.c2ws = Some(arr3([s[0], 4, 4], v));
            }
            "focals" => {
                let (s, v) = ctx.f32s(k, a)?;
                match s.as_slice() {
                    [c, 2] => ds.focals = Some(arr2([*c, 2], v)),
                    [c] => {
                        let v2 = v.iter().flat_map(|&f| [f, f]).collect();
                        ds.focals = Some(arr2([*c, 2], v2));
                        ctx.derived
                            .push("focals (expanded from (C,) to (C,2))".into());
                    }
                    _ => return Err(ctx.shape_err(k, "(C,2) or (C,)", &s)),
                }
            }
            "centers" => {
                let (s, v) = ctx.f32s(k, a)?;
                if s.len() != 2 || s[1] != 2 {
                    return Err(ctx.shape_err(k, "(C,2)", &s));
                }
                ds.centers = Some(arr2([s[0], 2], v));
            }
            "img_shape" => {
                let (s, v) = ctx.i64s(k, a, false)?;
                let chan_ok = v.len() == 4 && (v[3] == 3 || (v[3] == 4 && opts.drop_alpha));
                if s != [4] || !chan_ok || v.iter().any(|&x| x < 0) {
                    return Err(DataError::Value {
                        file: ctx.file.clone(),
                        key: k.into(),
                        problem: "image shape".into(),
                        expected: "4 non-negative entries (N,H,W,3)".into(),
                        found: format!("{v:?} (array shape {s:?})"),
                    });
                }
                ds.img_shape = Some([v[0] as usize, v[1] as usize, v[2] as usize, 3]);
            }
            "kp_idxs" | "img_pose_indices" | "bkgd_idxs" => {
                let (s, v) = ctx.i64s(k, a, k == "bkgd_idxs")?;
                if s.len() != 1 {
                    return Err(ctx.shape_err(k, "(N,)", &s));
                }
                let arr = Some(Array1::from(v));
                match k {
                    "kp_idxs" => ds.kp_idxs = arr,
                    "img_pose_indices" => ds.img_pose_indices = arr,
                    _ => ds.bkgd_idxs = arr,
                }
            }
            "eval_tag" => {
                let (s, v) = ctx.i64s(k, a, false)?;
                if s.len() != 1 {
                    return Err(ctx.shape_err(k, "(N,)", &s));
                }
                if let Some((i, t)) = v.iter().enumerate().find(|(_, t)| !(0..=3).contains(*t)) {
                    return Err(DataError::Index {
                        file: ctx.file.clone(),
                        key: k.into(),
                        position: i,
                        value: t.to_string(),
                        bound: 4,
                    });
                }
                ds.eval_tag = Some(Array1::from_iter(v.into_iter().map(|t| t as i8)));
            }
            "imgs" | "bkgds" => {
                let (arr, spatial) = pixel_array(&mut ctx, k, a, 3)?;
                note_spatial(&ctx, k, spatial, &mut pixel_shape)?;
                if k == "imgs" {
                    ds.imgs = Some(arr);
                } else {
                    ds.bkgds = Some(arr);
                }
            }
            "masks" | "sampling_masks" => {
                let (arr, spatial) = pixel_array(&mut ctx, k, a, 1)?;
                note_spatial(&ctx, k, spatial, &mut pixel_shape)?;
                if k == "masks" {
                    ds.masks = Some(arr);
                } else {
                    ds.sampling_masks = Some(arr);
                }
            }
            _ => unreachable!("KNOWN_KEYS covers every match arm"),
        }
    }
    if !have_bones {
        return Err(DataError::MissingKey {
            file: ctx.file.clone(),
            key: "bones".into(),
            profile: opts.profile.name().into(),
            hint: "; every profile needs the per-pose joint rotations".into(),
        });
    }
    // An unflattened pixel array tells H and W even without `img_shape`.
    if ds.img_shape.is_none() {
        if let (Some((h, w)), Some(imgs)) = (pixel_shape, &ds.imgs) {
            ds.img_shape = Some([imgs.shape()[0], h, w, 3]);
            ctx.derived.push("img_shape (from imgs)".into());
        }
    } else if let (Some((h, w)), Some(s)) = (pixel_shape, ds.img_shape) {
        if (h, w) != (s[1], s[2]) {
            return Err(DataError::Value {
                file: ctx.file.clone(),
                key: "img_shape".into(),
                problem: "image size disagrees with the pixel arrays".into(),
                expected: format!("H,W = {h},{w} (from the pixel arrays)"),
                found: format!("{},{}", s[1], s[2]),
            });
        }
    }
    ds.warnings = ctx.warnings;
    ds.derived = ctx.derived;
    Ok(ds)
}

fn note_spatial(
    ctx: &Ctx<'_>,
    key: &str,
    spatial: Option<(usize, usize)>,
    seen: &mut Option<(usize, usize)>,
) -> Result<()> {
    if let Some(hw) = spatial {
        match seen {
            Some(prev) if *prev != hw => {
                return Err(DataError::Value {
                    file: ctx.file.clone(),
                    key: key.into(),
                    problem: "image size differs between pixel arrays".into(),
                    expected: format!("H,W = {},{}", prev.0, prev.1),
                    found: format!("{},{}", hw.0, hw.1),
                })
            }
            _ => *seen = Some(hw),
        }
    }
    Ok(())
}
