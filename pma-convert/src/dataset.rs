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
//!   so a loader can still reproduce the reference exactly (pma's loader does not undo
//!   the scale; the file keeps what the reference's loader would start from);
//! * `head_dir` is +y for AIST and −y for every other layout;
//! * absent derivable keys (`skts`, `cyls`, centres, root locations) are filled
//!   by `pma_data` and the result is validated (docs/conventions.md, "Validation").
//!
//! Pixels are never held whole: each image is read as one hyperslab, checked
//! (mask values, empty sampling masks) and appended to the output member, so
//! memory stays at one image plus the reader's small chunk cache whatever N is.

use std::{path::Path, str::FromStr};

use pma_data::{
    dataset::{Compression, Dataset, Profile, ReadOptions, Warning, WriteOptions},
    DataError,
};

use crate::{
    error::{ConvertError, Result},
    h5::H5File,
};

mod h5_scene;
pub(crate) mod pixels;

pub(crate) use h5_scene::joints;
use h5_scene::read_h5_scene;
use pixels::{write_h5_output, PixelMember, PixelPlan};

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

/// Largest image side accepted (JPEG's limit): a larger `img_shape` is
/// corruption, and it would size buffers and the generated background plate.
pub const MAX_SIDE: usize = 65_535;

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
