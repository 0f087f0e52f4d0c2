//! A raw ZJU-MoCap capture (the `Posing` folder of H36M-ZJU, or a ZJU-MoCap
//! sequence) → a pma-npz v1 dataset, the same keys and conventions the `.h5`
//! path produces from the reference preprocessing of the same capture
//! (docs/conventions.md, "ZJU-MoCap capture").
//!
//! The capture folder holds `annots.npy` (cameras and image lists), images,
//! `mask/` and/or `mask_cihp/` PNGs, and `new_params/` or `params/` with one
//! `{frame}.npy` per frame. Both `.npy` kinds are pickles and are read with the
//! restricted machine (`crate::pickle::numpy`): nothing in them executes.
//!
//! Pixels stream image by image through a temporary file next to the output;
//! only the per-camera background plates are held whole.

use std::{
    collections::BTreeMap,
    path::{Path, PathBuf},
};

use ndarray::{Array1, Array2, Array3};
use pma_data::{
    dataset::{Compression, Dataset, Profile, ReadOptions},
    skeleton::{axis_angle_to_matrix, matrix_to_axis_angle, N_JOINTS},
};

use crate::{
    error::{ConvertError, Result},
    pickle::{
        numpy::{dense, item, items, strings, NpObject},
        Heap, Value,
    },
    smpl::SmplModel,
};

pub(crate) mod npy;
mod pixels;

use glam::{DMat3, DMat4, DVec3, DVec4};
use npy::{read_npy, NpyContent};

/// Rotation that puts ZJU's ground plane on x-z (world z-up → y-down).
pub const ZJU_TO_NERF: [[f64; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]];

/// Which images to take (the reference protocol).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Split {
    /// Training views, training frames.
    Train,
    /// The other views, training frames.
    NovelView,
    /// The other views, the frames after the training ones.
    NovelPose,
}

impl Split {
    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::NovelView => "novel_view",
            Split::NovelPose => "novel_pose",
        }
    }
}

/// Frames `START, START+INTERVAL, ...` (`COUNT` of them; all to the end when `None`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Frames {
    pub start: usize,
    pub count: Option<usize>,
    pub interval: usize,
}

impl Default for Frames {
    fn default() -> Self {
        Frames {
            start: 0,
            count: None,
            interval: 5,
        }
    }
}

impl std::str::FromStr for Frames {
    type Err = String;
    /// `START:COUNT:INTERVAL`; COUNT may be empty (to the end), INTERVAL may be omitted (5).
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let parts: Vec<&str> = s.split(':').collect();
        let num = |p: &str, what: &str| {
            p.trim()
                .parse::<usize>()
                .map_err(|_| format!("--frames {s:?}: {what} {p:?} is not a whole number"))
        };
        if parts.len() < 2 || parts.len() > 3 {
            return Err(format!("--frames {s:?}: expected START:COUNT[:INTERVAL]"));
        }
        let start = num(parts[0], "START")?;
        let count = if parts[1].trim().is_empty() {
            None
        } else {
            Some(num(parts[1], "COUNT")?)
        };
        let interval = match parts.get(2) {
            Some(p) => num(p, "INTERVAL")?,
            None => 5,
        };
        if interval == 0 {
            return Err(format!("--frames {s:?}: INTERVAL must be at least 1"));
        }
        Ok(Frames {
            start,
            count,
            interval,
        })
    }
}

/// Options of [`convert_capture`].
#[derive(Clone, Debug)]
pub struct CaptureOptions {
    /// The user's SMPL model (`.pkl` or `.npz`).
    pub smpl: PathBuf,
    pub split: Split,
    pub train_views: Vec<usize>,
    pub frames: Frames,
    /// Novel-pose frames (after the training ones); all remaining when `None`.
    pub eval_frames: Option<usize>,
    /// Resize factor; images area-averaged, masks nearest, intrinsics scaled.
    pub res: Option<f64>,
    /// Parameter folder; `new_params` when it exists, else `params`.
    pub params_dir: Option<String>,
    /// Mark a 5-pixel band around the mask edge with 100 in the sampling
    /// masks (the reference H36M-ZJU setting).
    pub erode_border: bool,
    pub compression: Compression,
}

impl CaptureOptions {
    pub fn new(smpl: impl Into<PathBuf>) -> Self {
        CaptureOptions {
            smpl: smpl.into(),
            split: Split::Train,
            train_views: vec![0, 1, 2],
            frames: Frames::default(),
            eval_frames: None,
            res: None,
            params_dir: None,
            erode_border: true,
            compression: Compression::Stored,
        }
    }
}

/// What a conversion did.
#[derive(Clone, Debug, Default)]
pub struct CaptureReport {
    pub n_poses: usize,
    pub n_cameras: usize,
    pub n_images: usize,
    pub height: usize,
    pub width: usize,
    pub views: Vec<usize>,
    pub params_dir: String,
}

/// One camera of `annots.npy`.
#[derive(Clone, Debug)]
pub struct CaptureCamera {
    pub k: [[f64; 3]; 3],
    pub r: [[f64; 3]; 3],
    /// Millimetres.
    pub t: [f64; 3],
    /// k1, k2, p1, p2, k3.
    pub d: [f64; 5],
}

/// `annots.npy`: cameras and, per frame, one image path per camera.
#[derive(Clone, Debug)]
pub struct Annots {
    pub cams: Vec<CaptureCamera>,
    pub ims: Vec<Vec<String>>,
}

/// One SMPL parameter file.
#[derive(Clone, Debug)]
pub struct FrameParams {
    pub poses: [[f64; 3]; N_JOINTS],
    pub rh: [f64; 3],
    pub th: [f64; 3],
    pub shapes: Vec<f64>,
}

/// One selected image.
#[derive(Clone, Debug)]
pub(crate) struct ImageRef {
    pub rel: String,
    pub cam: usize,
    pub frame: i64,
}

fn pickled_root(path: &Path) -> Result<(Heap<NpObject>, Value<NpObject>)> {
    match read_npy(path)? {
        NpyContent::Pickled(t) => {
            let root = item(&t.root);
            Ok((t.heap, root))
        }
        NpyContent::Array(_) => Err(ConvertError::format(
            path,
            "a numeric array; expected a pickled dict (np.save of a dict)",
        )),
    }
}

fn get<'h>(
    heap: &'h Heap<NpObject>,
    d: &Value<NpObject>,
    path: &Path,
    key: &str,
) -> Result<&'h Value<NpObject>> {
    if heap.items(d).is_none() {
        return Err(ConvertError::format(
            path,
            format!("holds a {}, expected a dict with `{key}`", d.kind()),
        ));
    }
    heap.get(d, key)
        .ok_or_else(|| ConvertError::missing(path, key, ""))
}

fn dense_of(
    heap: &Heap<NpObject>,
    v: &Value<NpObject>,
    path: &Path,
    key: &str,
) -> Result<(Vec<usize>, Vec<f64>)> {
    let d = dense(heap, v).map_err(|m| ConvertError::invalid(path, key, m))?;
    if let Some(i) = d.1.iter().position(|x| !x.is_finite()) {
        return Err(ConvertError::invalid(
            path,
            key,
            format!("element {i} is {} (not finite)", d.1[i]),
        ));
    }
    Ok(d)
}

/// Per-camera matrices stored as a list of arrays or one stacked array.
fn per_camera(
    heap: &Heap<NpObject>,
    v: &Value<NpObject>,
    path: &Path,
    key: &str,
    per: usize,
) -> Result<Vec<Vec<f64>>> {
    let list = items(heap, v).unwrap_or_else(|| vec![v.clone()]);
    let stacked = list.len() == 1 && !matches!(v, Value::List(_) | Value::Tuple(_));
    let (shape, all) = if stacked {
        dense_of(heap, v, path, key)?
    } else {
        let mut all = Vec::new();
        for (c, x) in list.iter().enumerate() {
            let (_, d) = dense_of(heap, x, path, &format!("{key}[{c}]"))?;
            if d.len() != per && !(key == "cams.D" && d.len() == 4) {
                return Err(ConvertError::mismatch(
                    path,
                    format!("{key}[{c}]"),
                    format!("{per} values"),
                    format!("{} values", d.len()),
                ));
            }
            all.push(d);
        }
        return Ok(all);
    };
    let c = shape.first().copied().unwrap_or(0);
    if c == 0 || all.len() != c * per {
        return Err(ConvertError::mismatch(
            path,
            key,
            format!("C arrays of {per} values"),
            format!("shape {shape:?}"),
        ));
    }
    Ok(all.chunks(per).map(<[f64]>::to_vec).collect())
}

fn mat3(v: &[f64]) -> [[f64; 3]; 3] {
    [[v[0], v[1], v[2]], [v[3], v[4], v[5]], [v[6], v[7], v[8]]]
}

impl Annots {
    /// Reads `annots.npy`.
    pub fn read(path: &Path) -> Result<Annots> {
        let (heap, root) = pickled_root(path)?;
        let cams = get(&heap, &root, path, "cams")?;
        let k = per_camera(&heap, get(&heap, cams, path, "K")?, path, "cams.K", 9)?;
        let r = per_camera(&heap, get(&heap, cams, path, "R")?, path, "cams.R", 9)?;
        let t = per_camera(&heap, get(&heap, cams, path, "T")?, path, "cams.T", 3)?;
        let d = per_camera(&heap, get(&heap, cams, path, "D")?, path, "cams.D", 5)?;
        let n = k.len();
        for (key, len) in [
            ("cams.R", r.len()),
            ("cams.T", t.len()),
            ("cams.D", d.len()),
        ] {
            if len != n {
                return Err(ConvertError::mismatch(
                    path,
                    key,
                    format!("{n} cameras (as cams.K)"),
                    format!("{len}"),
                ));
            }
        }
        let cams = (0..n)
            .map(|c| {
                let mut dd = [0.0; 5];
                dd[..d[c].len()].copy_from_slice(&d[c]);
                CaptureCamera {
                    k: mat3(&k[c]),
                    r: mat3(&r[c]),
                    t: [t[c][0], t[c][1], t[c][2]],
                    d: dd,
                }
            })
            .collect();
        let ims_v = get(&heap, &root, path, "ims")?;
        let frames = items(&heap, ims_v).ok_or_else(|| {
            ConvertError::mismatch(path, "ims", "a list of per-frame dicts", ims_v.kind())
        })?;
        let mut ims = Vec::with_capacity(frames.len());
        for (f, fr) in frames.iter().enumerate() {
            let key = format!("ims[{f}].ims");
            let list = get(&heap, fr, path, "ims")?;
            let paths = strings(&heap, list).map_err(|m| ConvertError::invalid(path, &key, m))?;
            if paths.len() != n {
                return Err(ConvertError::mismatch(
                    path,
                    key,
                    format!("one image per camera ({n} cameras in cams.K)"),
                    format!("{} images", paths.len()),
                ));
            }
            ims.push(paths);
        }
        Ok(Annots { cams, ims })
    }
}

impl FrameParams {
    /// Reads one `params/{frame}.npy` (`poses (1,72)`, `Rh (1,3)`, `Th (1,3)`, `shapes (1,B)`).
    pub fn read(path: &Path) -> Result<FrameParams> {
        let (heap, root) = pickled_root(path)?;
        let vals = |key: &str, n: Option<usize>| -> Result<Vec<f64>> {
            let (shape, v) = dense_of(&heap, get(&heap, &root, path, key)?, path, key)?;
            if n.is_some_and(|n| v.len() != n) || v.is_empty() {
                return Err(ConvertError::mismatch(
                    path,
                    key,
                    match n {
                        Some(n) => format!("{n} values (shape (1,{n}))"),
                        None => "at least one value".into(),
                    },
                    format!("shape {shape:?}"),
                ));
            }
            Ok(v)
        };
        let p = vals("poses", Some(72))?;
        let rh = vals("Rh", Some(3))?;
        let th = vals("Th", Some(3))?;
        let shapes = vals("shapes", None)?;
        let mut poses = [[0.0; 3]; N_JOINTS];
        for (j, row) in poses.iter_mut().enumerate() {
            row.copy_from_slice(&p[3 * j..3 * j + 3]);
        }
        Ok(FrameParams {
            poses,
            rh: [rh[0], rh[1], rh[2]],
            th: [th[0], th[1], th[2]],
            shapes,
        })
    }
}

fn rn() -> DMat3 {
    DMat3::from_cols_array_2d(&ZJU_TO_NERF).transpose()
}

fn dv(a: [f64; 3]) -> DVec3 {
    DVec3::from_array(a)
}

/// The views and frame rows of a split (the reference protocol).
pub(crate) fn select_images(
    annots: &Annots,
    opts: &CaptureOptions,
    path: &Path,
) -> Result<(Vec<usize>, Vec<ImageRef>)> {
    let n_cams = annots.cams.len();
    if let Some(&v) = opts.train_views.iter().find(|&&v| v >= n_cams) {
        return Err(ConvertError::Usage(format!(
            "--train-views: view {v} does not exist ({} has {n_cams} cameras)",
            path.display()
        )));
    }
    let views: Vec<usize> = match opts.split {
        Split::Train => opts.train_views.clone(),
        _ => {
            let v: Vec<usize> = (0..n_cams)
                .filter(|c| !opts.train_views.contains(c))
                .collect();
            if v.is_empty() {
                vec![0]
            } else {
                v
            }
        }
    };
    let f = opts.frames;
    let n_frames = annots.ims.len();
    let (start, count) = match opts.split {
        Split::NovelPose => {
            let Some(c) = f.count else {
                return Err(ConvertError::Usage(
                    "--split novel_pose needs the training frame COUNT (--frames START:COUNT:INTERVAL): novel poses are the frames after them".into(),
                ));
            };
            (f.start + c * f.interval, opts.eval_frames)
        }
        _ => (f.start, f.count),
    };
    let end = match count {
        Some(c) => (start + c * f.interval).min(n_frames),
        None => n_frames,
    };
    let mut refs = Vec::new();
    let mut row = start;
    while row < end {
        for &c in &views {
            let rel = annots.ims[row][c].clone();
            let frame = frame_number(&rel).ok_or_else(|| {
                ConvertError::invalid(
                    path,
                    format!("ims[{row}].ims[{c}]"),
                    format!("image name {rel:?} does not end in a frame number (e.g. 000123.jpg)"),
                )
            })?;
            refs.push(ImageRef { rel, cam: c, frame });
        }
        row += f.interval;
    }
    if refs.is_empty() {
        return Err(ConvertError::Usage(format!(
            "{}: the {} split selects no image ({n_frames} frames, first frame {start}, interval {})",
            path.display(),
            opts.split.name(),
            f.interval
        )));
    }
    Ok((views, refs))
}

/// `Camera_B1/000123.jpg` → 123.
fn frame_number(rel: &str) -> Option<i64> {
    let name = rel.rsplit(['/', '\\']).next()?;
    let stem = name.rsplit_once('.').map_or(name, |(s, _)| s);
    stem.parse().ok()
}

/// The pose side: bones with the root rotation `Rn·R(Rh)`, root locations,
/// rest pose from the mean shape (docs/conventions.md, "ZJU-MoCap capture").
pub struct Poses {
    pub bones: Array3<f32>,
    pub root_locs: Array2<f32>,
    pub rest_pose: [[f32; 3]; N_JOINTS],
    pub betas: Array2<f32>,
}

pub fn capture_poses(smpl: &SmplModel, params: &[FrameParams]) -> Poses {
    let p = params.len();
    let b = params.iter().map(|x| x.shapes.len()).max().unwrap_or(0);
    let mut mean = vec![0.0; b];
    for x in params {
        for (m, s) in mean.iter_mut().zip(&x.shapes) {
            *m += s / p as f64;
        }
    }
    let j_mean = smpl.rest_joints(&mean);
    let t = dv(j_mean[0]);
    let mut rest_pose = [[0f32; 3]; N_JOINTS];
    for (r, j) in rest_pose.iter_mut().zip(&j_mean) {
        for k in 0..3 {
            r[k] = (j[k] - j_mean[0][k]) as f32;
        }
    }
    let rn = rn();
    let mut bones = Array3::<f32>::zeros((p, N_JOINTS, 3));
    let mut roots = Array2::<f32>::zeros((p, 3));
    let mut betas = Array2::<f32>::zeros((p, b));
    for (i, x) in params.iter().enumerate() {
        let root_rot = rn * axis_angle_to_matrix(dv(x.rh));
        let root_aa = matrix_to_axis_angle(root_rot);
        for j in 0..N_JOINTS {
            let v = if j == 0 {
                root_aa.to_array()
            } else {
                x.poses[j]
            };
            for k in 0..3 {
                bones[[i, j, k]] = v[k] as f32;
            }
        }
        // The frame's own shape places its pelvis; the rest pose uses the mean.
        let j0 = dv(smpl.rest_joints(&x.shapes)[0]);
        let root = j0 - t + root_rot * t + rn * dv(x.th);
        for k in 0..3 {
            roots[[i, k]] = root[k] as f32;
        }
        for (k, s) in x.shapes.iter().enumerate() {
            betas[[i, k]] = *s as f32;
        }
    }
    Poses {
        bones,
        root_locs: roots,
        rest_pose,
        betas,
    }
}

/// NeRF camera-to-world from ZJU's extrinsics (R, T in mm): inverse of
/// `[R | T/1000]`, rotated by [`ZJU_TO_NERF`], then y and z axes negated.
pub fn capture_c2w(cam: &CaptureCamera) -> [[f32; 4]; 4] {
    let r = DMat3::from_cols_array_2d(&cam.r).transpose();
    let ext = DMat4::from_cols(
        r.x_axis.extend(0.0),
        r.y_axis.extend(0.0),
        r.z_axis.extend(0.0),
        DVec4::new(cam.t[0] / 1000.0, cam.t[1] / 1000.0, cam.t[2] / 1000.0, 1.0),
    );
    let c2w = ext.inverse();
    let rn = rn();
    let rot = rn * DMat3::from_mat4(c2w);
    let tr = rn * c2w.w_axis.truncate();
    let mut out = [[0f32; 4]; 4];
    for (i, row) in out.iter_mut().take(3).enumerate() {
        for (j, x) in row.iter_mut().take(3).enumerate() {
            let s = if j == 0 { 1.0 } else { -1.0 };
            *x = (s * rot.col(j)[i]) as f32;
        }
        row[3] = tr[i] as f32;
    }
    out[3] = [0.0, 0.0, 0.0, 1.0];
    out
}

/// The parameter folder: the option, else `new_params` when present, else `params`.
fn params_dir(dir: &Path, opts: &CaptureOptions) -> String {
    opts.params_dir.clone().unwrap_or_else(|| {
        if dir.join("new_params").is_dir() {
            "new_params".into()
        } else {
            "params".into()
        }
    })
}

/// Progress of the pixel pass: `(images done, images total)`.
pub type Progress<'a> = &'a mut dyn FnMut(u64, u64);

/// Converts the capture in `dir` into a pma-npz v1 file at `output`
/// (written atomically; nothing is written on error).
pub fn convert_capture(
    dir: &Path,
    output: &Path,
    opts: &CaptureOptions,
    progress: Progress,
) -> Result<CaptureReport> {
    if let Some(r) = opts.res {
        if !(r > 0.0 && r <= 1.0) {
            return Err(ConvertError::Usage(format!(
                "--res {r}: expected a factor in (0, 1]"
            )));
        }
    }
    let annots_path = dir.join("annots.npy");
    let annots = Annots::read(&annots_path)?;
    let (views, refs) = select_images(&annots, opts, &annots_path)?;
    let smpl = SmplModel::read(&opts.smpl)?;

    // Pose rows: the distinct frame numbers, sorted (as np.unique).
    let frames: Vec<i64> = {
        let mut f: Vec<i64> = refs.iter().map(|r| r.frame).collect();
        f.sort_unstable();
        f.dedup();
        f
    };
    let row_of: BTreeMap<i64, usize> = frames.iter().enumerate().map(|(i, &f)| (f, i)).collect();
    let pdir = params_dir(dir, opts);
    let params = frames
        .iter()
        .map(|f| FrameParams::read(&dir.join(&pdir).join(format!("{f}.npy"))))
        .collect::<Result<Vec<_>>>()?;
    let poses = capture_poses(&smpl, &params);

    let mut ds = Dataset::from_bones(poses.bones);
    ds.source = dir.display().to_string();
    ds.head_dir = [0.0, -1.0, 0.0];
    ds.rest_pose = Some(poses.rest_pose);
    ds.root_locs = Some(poses.root_locs);
    ds.betas = Some(poses.betas);
    ds.frame_ids = Some(Array1::from_vec(frames.clone()));

    let n_cams = annots.cams.len();
    let scale = opts.res.unwrap_or(1.0);
    let mut c2ws = Array3::<f32>::zeros((n_cams, 4, 4));
    let mut focals = Array2::<f32>::zeros((n_cams, 2));
    let mut centers = Array2::<f32>::zeros((n_cams, 2));
    for (c, cam) in annots.cams.iter().enumerate() {
        let m = capture_c2w(cam);
        for i in 0..4 {
            for j in 0..4 {
                c2ws[[c, i, j]] = m[i][j];
            }
        }
        focals[[c, 0]] = (cam.k[0][0] * scale) as f32;
        focals[[c, 1]] = (cam.k[1][1] * scale) as f32;
        centers[[c, 0]] = (cam.k[0][2] * scale) as f32;
        centers[[c, 1]] = (cam.k[1][2] * scale) as f32;
    }
    ds.c2ws = Some(c2ws);
    ds.focals = Some(focals);
    ds.centers = Some(centers);
    let cam_idx = Array1::from_iter(refs.iter().map(|r| r.cam as i64));
    ds.kp_idxs = Some(Array1::from_iter(
        refs.iter().map(|r| row_of[&r.frame] as i64),
    ));
    ds.img_pose_indices = Some(cam_idx.clone());
    ds.bkgd_idxs = Some(cam_idx);

    // Every input must be there before the long pass starts.
    for r in &refs {
        pixels::check_inputs(dir, &r.rel)?;
    }
    let (h, w) = pixels::output_size(dir, &refs[0].rel, opts.res)?;
    ds.img_shape = Some([refs.len(), h, w, 3]);
    ds.derive(None)?;
    let bkgd_idxs = ds.bkgd_idxs.take();
    ds.validate(&ReadOptions::new(Profile::Render))?;
    ds.bkgd_idxs = bkgd_idxs;

    pixels::write_capture(dir, &annots, &refs, &ds, output, opts, (h, w), progress)?;
    Ok(CaptureReport {
        n_poses: ds.n_poses(),
        n_cameras: n_cams,
        n_images: refs.len(),
        height: h,
        width: w,
        views,
        params_dir: pdir,
    })
}
