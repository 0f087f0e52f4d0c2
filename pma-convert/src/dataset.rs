//! Processed A-NeRF/DANBO/PM datasets (`.h5`, docs/conventions.md "A-NeRF/DANBO
//! .h5") and pma-npz files ("pma-npz v1") → a validated pma-npz v1 file.
//!
//! What the converter does with an `.h5`:
//! * every array keeps its name, dtype class and shape; pixel arrays keep the
//!   flattened `(n, H·W, C)` layout; `focals (C,)` becomes `(C,2)`;
//! * the per-image index maps are written explicitly (image → pose row,
//!   camera row, background plate), because the reference loaders interpret
//!   the stored ones per layout:
//!   SURREAL's pose row is `n mod F`, Mixamo's stored `kp_idxs` are frame
//!   numbers that the loader ignores (pose and camera row = image index),
//!   PerfCap and SURREAL always use background plate 0, Mixamo a white one;
//! * `cam_idxs`, `img_paths`, `gt_poses` and `selected_idx` are not part of
//!   the schema and are dropped (reported as warnings);
//! * **no dataset-specific corrections are applied.** In particular the
//!   PerfCap scale undo and the ÷1.05 camera fudge are loader
//!   behaviours: the file stays in scaled SPIN units with its `pose_scale`,
//!   so a loader can still reproduce the reference exactly (`--perfcap-undo-scale`);
//! * `head_dir` is +y for AIST and −y for every other layout;
//! * absent derivable keys (`skts`, `cyls`, centres, root locations) are filled
//!   by `pma_data` and the result is validated (docs/conventions.md, "Validation").
//!
//! Pixels are never held whole: each image is read as one hyperslab, checked
//! (mask values, empty sampling masks) and appended to the output member, so
//! memory stays at one image plus the reader's small chunk cache whatever N is.

use std::{
    fs::File,
    io::{BufWriter, Seek, Write},
    path::Path,
    str::FromStr,
};

use ndarray::{Array1, Array2, Array3};
use npyz::{DType, TypeStr, WriterBuilder};
use pma_data::{
    dataset::{Compression, Dataset, Profile, ReadOptions, Warning, WriteOptions},
    fsio::{parent_dir, AtomicFile},
    skeleton::Joints,
    DataError,
};

use crate::{
    error::{ConvertError, Result},
    h5::H5File,
};

/// The `.h5` layouts (docs/conventions.md, "A-NeRF/DANBO .h5").
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    H36mZju,
    PerfCap,
    Surreal,
    Mixamo,
    Aist,
}

impl Layout {
    pub const ALL: [Layout; 5] = [
        Layout::H36mZju,
        Layout::PerfCap,
        Layout::Surreal,
        Layout::Mixamo,
        Layout::Aist,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Layout::H36mZju => "h36m_zju",
            Layout::PerfCap => "perfcap",
            Layout::Surreal => "surreal",
            Layout::Mixamo => "mixamo",
            Layout::Aist => "aist",
        }
    }

    /// Head direction of the file's world (docs/conventions.md, "Units and up axis").
    pub fn head_dir(self) -> [f32; 3] {
        match self {
            Layout::Aist => [0.0, 1.0, 0.0],
            _ => [0.0, -1.0, 0.0],
        }
    }
}

impl std::fmt::Display for Layout {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Layout {
    type Err = ConvertError;
    fn from_str(s: &str) -> Result<Self> {
        Layout::ALL
            .into_iter()
            .find(|l| l.name() == s)
            .ok_or_else(|| {
                ConvertError::Usage(format!(
                    "unknown layout {s:?}; expected h36m_zju|perfcap|surreal|mixamo|aist"
                ))
            })
    }
}

/// Options of [`convert_dataset`].
#[derive(Clone, Debug)]
pub struct DatasetOptions {
    /// Which uses the output must support; it also selects what is written:
    /// motion = poses only, render = + cameras, index maps and background
    /// plates, eval/train = + images and masks.
    pub profile: Profile,
    /// `.h5` layout; `None` detects it from the keys (see [`detect_layout`]).
    pub layout: Option<Layout>,
    pub compression: Compression,
    pub allow_offset_root: bool,
    /// Accept 0/255 masks and store them as {0,1} (threshold ≥ 2, as the reference).
    pub binarize_masks: bool,
    /// Accept 4-channel images and drop alpha.
    pub drop_alpha: bool,
}

impl DatasetOptions {
    pub fn new(profile: Profile) -> Self {
        Self {
            profile,
            layout: None,
            compression: Compression::Stored,
            allow_offset_root: false,
            binarize_masks: false,
            drop_alpha: false,
        }
    }

    fn read_options(&self, profile: Profile) -> ReadOptions {
        let mut o = ReadOptions::new(profile);
        o.allow_offset_root = self.allow_offset_root;
        o.binarize_masks = self.binarize_masks;
        o.drop_alpha = self.drop_alpha;
        o
    }
}

/// What a conversion did.
#[derive(Clone, Debug, Default)]
pub struct DatasetReport {
    /// `None` for npz input.
    pub layout: Option<Layout>,
    pub n_poses: usize,
    pub n_cameras: usize,
    pub n_images: usize,
    /// Keys computed rather than read.
    pub derived: Vec<String>,
    /// Non-fatal findings, dropped keys included.
    pub warnings: Vec<Warning>,
}

/// Progress of the pixel streaming: `(images done, images total)` over all pixel keys.
pub type Progress<'a> = &'a mut dyn FnMut(u64, u64);

/// Converts `input` (`.h5`/`.hdf5` or `.npz`) into a validated pma-npz v1 file
/// at `output` (written atomically).
pub fn convert_dataset(
    input: &Path,
    output: &Path,
    opts: &DatasetOptions,
    progress: Progress,
) -> Result<DatasetReport> {
    let ext = crate::extension(input);
    match ext.as_str() {
        "h5" | "hdf5" => convert_h5(input, output, opts, progress),
        "npz" => convert_npz(input, output, opts),
        _ => Err(ConvertError::Usage(format!(
            "{}: unknown dataset type; expected a .h5/.hdf5 or .npz file",
            input.display()
        ))),
    }
}

fn convert_npz(input: &Path, output: &Path, opts: &DatasetOptions) -> Result<DatasetReport> {
    let mut ds = Dataset::read(input, &opts.read_options(opts.profile))?;
    keep_profile_groups(&mut ds, opts.profile);
    ds.write(
        output,
        &WriteOptions {
            compression: opts.compression,
        },
    )?;
    Ok(report(&ds, None))
}

fn report(ds: &Dataset, layout: Option<Layout>) -> DatasetReport {
    DatasetReport {
        layout,
        n_poses: ds.n_poses(),
        n_cameras: ds.n_cameras(),
        n_images: ds.n_images(),
        derived: ds.derived.clone(),
        warnings: ds.warnings.clone(),
    }
}

/// Drops the groups a profile does not use (see [`DatasetOptions::profile`]).
fn keep_profile_groups(ds: &mut Dataset, profile: Profile) {
    if profile == Profile::Motion {
        ds.c2ws = None;
        ds.focals = None;
        ds.centers = None;
        ds.img_shape = None;
        ds.kp_idxs = None;
        ds.img_pose_indices = None;
        ds.bkgd_idxs = None;
        ds.eval_tag = None;
        ds.bkgds = None;
    }
    if profile <= Profile::Render {
        ds.imgs = None;
        ds.masks = None;
        ds.sampling_masks = None;
    }
}

/// Guesses the layout from which keys a file has:
/// `img_paths`/`gt_poses` → Mixamo; `img_pose_indices` → H36M-ZJU or AIST,
/// told apart by whether the head is below (−y) or above (+y) the pelvis in
/// `kp3d`; `pose_scale` → PerfCap; otherwise SURREAL (per-image cameras, no
/// index maps).
pub fn detect_layout(h5: &H5File) -> Result<Layout> {
    let keys = h5.keys()?;
    let has = |k: &str| keys.iter().any(|x| x == k);
    if has("img_paths") || has("gt_poses") {
        return Ok(Layout::Mixamo);
    }
    if has("img_pose_indices") {
        let (shape, kp) = h5.read_f32("kp3d")?;
        if shape.len() != 3 || shape[1] != 24 || shape[2] != 3 || shape[0] == 0 {
            return Err(ConvertError::mismatch(
                h5.path(),
                "kp3d",
                "shape (P,24,3) with P > 0",
                format!("{shape:?}"),
            ));
        }
        // Head (joint 15) above or below the pelvis, summed over poses.
        let dy: f32 = kp.chunks_exact(72).map(|p| p[15 * 3 + 1] - p[1]).sum();
        return Ok(if dy > 0.0 {
            Layout::Aist
        } else {
            Layout::H36mZju
        });
    }
    if has("pose_scale") {
        return Ok(Layout::PerfCap);
    }
    if has("ext_scale") || has("gt_kp3d") {
        return Ok(Layout::Surreal);
    }
    Err(ConvertError::format(
        h5.path(),
        "cannot tell the dataset layout from its keys; pass --layout h36m_zju|perfcap|surreal|mixamo|aist",
    ))
}

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

/// Largest image side accepted (JPEG's limit): a larger `img_shape` is
/// corruption, and it would size buffers and the generated background plate.
pub const MAX_SIDE: usize = 65_535;

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
fn read_h5_scene(h5: &H5File, layout: Layout) -> Result<(Dataset, PixelPlan)> {
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

/// One pixel member to stream: its source key and the channel count written.
#[derive(Clone, Debug)]
struct PixelMember {
    key: &'static str,
    rows: usize,
    channels_in: usize,
    channels_out: usize,
}

/// The pixel members of an `.h5` and their checked shapes.
#[derive(Clone, Debug, Default)]
struct PixelPlan {
    members: Vec<PixelMember>,
    /// Mixamo's white plate, written in place of a stored `bkgds`.
    white_plate: bool,
    hw: usize,
}

impl PixelPlan {
    fn new(h5: &H5File, keys: &[String], ds: &Dataset, layout: Layout) -> Result<Self> {
        let path = h5.path();
        let n = ds.n_images();
        let hw = ds.height() * ds.width();
        let mut members = Vec::new();
        for (key, channels) in [
            ("imgs", 3usize),
            ("masks", 1),
            ("sampling_masks", 1),
            ("bkgds", 3),
        ] {
            if !keys.iter().any(|k| k == key) || (key == "bkgds" && layout == Layout::Mixamo) {
                continue;
            }
            if ds.img_shape.is_none() {
                return Err(ConvertError::missing(
                    path,
                    "img_shape",
                    format!(" (needed to read `{key}`)"),
                ));
            }
            let info = h5.info(key)?;
            let s = &info.shape;
            let expect = format!("(n, H·W = {hw}, {channels}) uint8");
            if info.kind
                != (crate::h5::H5Kind::Int {
                    size: 1,
                    signed: false,
                })
            {
                return Err(ConvertError::mismatch(
                    path,
                    key,
                    expect,
                    format!("{} of shape {s:?}", info.kind),
                ));
            }
            let c_in = match s.as_slice() {
                [_, p, c] if *p == hw => *c,
                _ => {
                    return Err(ConvertError::mismatch(
                        path,
                        key,
                        expect,
                        format!("shape {s:?}"),
                    ))
                }
            };
            if key != "bkgds" && s[0] != n {
                return Err(ConvertError::mismatch(
                    path,
                    key,
                    format!("{n} rows (img_shape[0])"),
                    format!("{} rows", s[0]),
                ));
            }
            let c_out = if channels == 3 && c_in == 4 { 3 } else { c_in };
            if c_in != channels && !(channels == 3 && c_in == 4) {
                return Err(ConvertError::mismatch(
                    path,
                    key,
                    expect,
                    format!("shape {s:?}"),
                ));
            }
            members.push(PixelMember {
                key,
                rows: s[0],
                channels_in: c_in,
                channels_out: c_out,
            });
        }
        Ok(Self {
            members,
            white_plate: layout == Layout::Mixamo,
            hw,
        })
    }

    fn get(&self, key: &str) -> Option<&PixelMember> {
        self.members.iter().find(|m| m.key == key)
    }

    fn n_backgrounds(&self) -> Option<usize> {
        if self.white_plate {
            Some(1)
        } else {
            self.get("bkgds").map(|m| m.rows)
        }
    }
}

fn convert_h5(
    input: &Path,
    output: &Path,
    opts: &DatasetOptions,
    progress: Progress,
) -> Result<DatasetReport> {
    let h5 = H5File::open(input)?;
    let layout = match opts.layout {
        Some(l) => l,
        None => detect_layout(&h5)?,
    };
    let (mut ds, plan) = read_h5_scene(&h5, layout)?;
    ds.derive(None)?;

    // Pixels are not in `ds`; the data layer validates everything else at the
    // render level, and the pixel requirements of eval/train are checked here
    // and while streaming. Background indices are checked against the plates
    // in the file (`check_background_rows`), which `ds` does not hold.
    let scene_profile = opts.profile.min(Profile::Render);
    let bkgd_idxs = ds.bkgd_idxs.take();
    ds.validate(&opts.read_options(scene_profile))?;
    ds.bkgd_idxs = bkgd_idxs;
    let source = ds.source.clone();
    let missing = |key: &str| DataError::MissingKey {
        file: source.clone(),
        key: key.into(),
        profile: opts.profile.name().into(),
        hint: String::new(),
    };
    if opts.profile >= Profile::Eval {
        if ds.rest_pose.is_none() {
            return Err(missing("rest_pose").into());
        }
        for key in ["imgs", "masks"] {
            if plan.get(key).is_none() {
                return Err(missing(key).into());
            }
        }
        if opts.profile == Profile::Train && plan.get("sampling_masks").is_none() {
            return Err(missing("sampling_masks").into());
        }
    }
    if opts.profile >= Profile::Render {
        check_background_rows(&ds, &plan, input)?;
    }
    for m in &plan.members {
        if m.channels_in == 4 && !opts.drop_alpha {
            return Err(ConvertError::mismatch(
                input,
                m.key,
                "3 channels (pass --drop-alpha to drop a 4th)",
                "4 channels",
            ));
        }
    }

    keep_profile_groups(&mut ds, opts.profile);
    let mut rep = report(&ds, Some(layout));
    if layout == Layout::Mixamo && opts.profile >= Profile::Render {
        rep.derived
            .push("bkgds (one white plate: Mixamo images are composited on white)".into());
    }

    let streamed: Vec<&PixelMember> = plan
        .members
        .iter()
        .filter(|m| match m.key {
            "bkgds" => opts.profile >= Profile::Render,
            _ => opts.profile >= Profile::Eval,
        })
        .collect();
    write_h5_output(&h5, &ds, &plan, &streamed, output, opts, &mut rep, progress)?;
    Ok(rep)
}

fn check_background_rows(ds: &Dataset, plan: &PixelPlan, input: &Path) -> Result<()> {
    let Some(idx) = &ds.bkgd_idxs else {
        return Ok(());
    };
    let bound = plan.n_backgrounds().unwrap_or(1);
    if let Some((i, &b)) = idx
        .iter()
        .enumerate()
        .find(|(_, &b)| b < 0 || b as usize >= bound)
    {
        return Err(DataError::Index {
            file: input.display().to_string(),
            key: "bkgd_idxs".into(),
            position: i,
            value: b.to_string(),
            bound,
        }
        .into());
    }
    Ok(())
}

#[allow(clippy::too_many_arguments)]
fn write_h5_output(
    h5: &H5File,
    ds: &Dataset,
    plan: &PixelPlan,
    streamed: &[&PixelMember],
    output: &Path,
    opts: &DatasetOptions,
    rep: &mut DatasetReport,
    progress: Progress,
) -> Result<()> {
    let dir = parent_dir(output);
    // The data layer writes the scene members; they are copied verbatim into
    // the final archive, followed by the streamed pixel members.
    let scene = tempfile::NamedTempFile::new_in(dir).map_err(|e| ConvertError::io(dir, e))?;
    ds.write(
        scene.path(),
        &WriteOptions {
            compression: opts.compression,
        },
    )?;
    let scene_zip = zip::ZipArchive::new(
        File::open(scene.path()).map_err(|e| ConvertError::io(scene.path(), e))?,
    )
    .map_err(|source| ConvertError::Zip {
        path: scene.path().to_path_buf(),
        cause: source,
    })?;

    let out = AtomicFile::create(output).map_err(|e| ConvertError::io(dir, e))?;
    let zerr = |source| ConvertError::Zip {
        path: output.to_path_buf(),
        cause: source,
    };
    let mut zip = zip::ZipWriter::new(BufWriter::new(out.file()));
    zip.merge_archive(scene_zip).map_err(zerr)?;

    let total: u64 = streamed.iter().map(|m| m.rows as u64).sum::<u64>() + plan.white_plate as u64;
    let mut done = 0u64;
    progress(done, total);
    for m in streamed {
        let shape = [m.rows, plan.hw, m.channels_out];
        start_member(&mut zip, output, m.key, &shape, opts.compression)?;
        for row in 0..m.rows {
            let raw = h5.read_u8_rows(m.key, row, row + 1)?;
            let px = prepare_row(raw, m, row, opts, h5.path(), rep)?;
            zip.write_all(&px)
                .map_err(|e| ConvertError::io(output, e))?;
            done += 1;
            progress(done, total);
        }
    }
    if plan.white_plate && opts.profile >= Profile::Render {
        start_member(
            &mut zip,
            output,
            "bkgds",
            &[1, plan.hw, 3],
            opts.compression,
        )?;
        // In pieces: a plate is as large as one image, whatever that is.
        let piece = vec![255u8; (plan.hw * 3).min(1 << 20)];
        let mut left = plan.hw * 3;
        while left > 0 {
            let k = left.min(piece.len());
            zip.write_all(&piece[..k])
                .map_err(|e| ConvertError::io(output, e))?;
            left -= k;
        }
        done += 1;
        progress(done, total);
    }
    let mut buf = zip.finish().map_err(zerr)?;
    buf.flush().map_err(|e| ConvertError::io(output, e))?;
    drop(buf);
    out.commit().map_err(|e| ConvertError::io(output, e))
}

/// Checks one row of pixels (mask values, empty sampling masks) and converts
/// it to the stored form.
fn prepare_row(
    raw: Vec<u8>,
    m: &PixelMember,
    row: usize,
    opts: &DatasetOptions,
    input: &Path,
    rep: &mut DatasetReport,
) -> Result<Vec<u8>> {
    let mut px = if m.channels_in != m.channels_out {
        raw.chunks_exact(m.channels_in)
            .flat_map(|c| c[..m.channels_out].iter().copied())
            .collect()
    } else {
        raw
    };
    match m.key {
        "masks" => {
            if let Some(pos) = px.iter().position(|&v| v > 1) {
                if !opts.binarize_masks {
                    return Err(ConvertError::invalid(
                        input,
                        "masks",
                        format!(
                            "image {row}, pixel {pos}: value {} is not 0 or 1 (pass --binarize-masks for 0/255 masks)",
                            px[pos]
                        ),
                    ));
                }
                for v in &mut px {
                    *v = (*v >= 2) as u8;
                }
            }
        }
        "sampling_masks" if px.iter().all(|&v| v == 0) => {
            rep.warnings.push(Warning {
                key: "sampling_masks".into(),
                message: format!(
                    "image {row} allows no pixel; the reference falls back to sampling every pixel"
                ),
            });
        }
        _ => {}
    }
    Ok(px)
}

/// Starts `<key>.npy` in the archive and writes its NPY header; the payload
/// is appended by the caller. Options match the data layer's writer (fixed
/// timestamp and permissions) so outputs are byte-deterministic.
fn start_member<W: Write + Seek>(
    zip: &mut zip::ZipWriter<W>,
    output: &Path,
    key: &str,
    shape: &[usize],
    compression: Compression,
) -> Result<()> {
    let payload: u64 = shape.iter().map(|&d| d as u64).product();
    let method = match compression {
        Compression::Stored => zip::CompressionMethod::Stored,
        Compression::Deflated => zip::CompressionMethod::Deflated,
    };
    let options = zip::write::SimpleFileOptions::default()
        .compression_method(method)
        .last_modified_time(zip::DateTime::default())
        .unix_permissions(0o644)
        .large_file(payload + 4096 >= u32::MAX as u64);
    zip.start_file(format!("{key}.npy"), options)
        .map_err(|source| ConvertError::Zip {
            path: output.to_path_buf(),
            cause: source,
        })?;
    let ts: TypeStr = "|u1".parse().expect("static dtype descriptor");
    let shape64: Vec<u64> = shape.iter().map(|&d| d as u64).collect();
    npyz::WriteOptions::new_header_only()
        .dtype(DType::Plain(ts))
        .shape(&shape64)
        .writer(&mut *zip)
        .write_header_only()
        .map_err(|e| ConvertError::io(output, e))?;
    Ok(())
}
