//! `pma-npz v1` datasets (docs/conventions.md, "pma-npz v1"): the arrays of
//! one scene, read from / written to numpy `.npz` archives, with the
//! import-time derivations and the validation ("Validation").
//!
//! Counts: `P` pose rows, `C` camera rows, `N` images, `B` background plates,
//! images `H × W`. Pixels stay `u8` and are held once (a 2,000-frame
//! 1000×1000 scene is 6 GB); use the per-image accessors, never convert
//! whole pixel arrays to float.

use std::fmt;
use std::path::{Path, PathBuf};

use ndarray::{s, Array1, Array2, Array3, Array4, ArrayView2};

use crate::camera::Camera;
use crate::cylinder::HeadDir;
use crate::error::{DataError, Result};
use crate::skeleton::Joints;

mod derive;
pub mod npz;
mod read;
mod validate;
mod write;

pub use write::{Compression, WriteOptions};

/// Current schema version written to `schema_version`.
pub const SCHEMA_VERSION: i32 = 1;

/// Which uses a file must support; each profile requires
/// everything the previous one does.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Profile {
    /// Poses only (retargeting, mesh extraction).
    Motion,
    /// Motion + cameras and image size.
    Render,
    /// Render + rest pose, ground-truth images and masks.
    Eval,
    /// Eval + sampling masks.
    Train,
}

impl Profile {
    pub fn name(self) -> &'static str {
        match self {
            Profile::Motion => "motion",
            Profile::Render => "render",
            Profile::Eval => "eval",
            Profile::Train => "train",
        }
    }
}

impl fmt::Display for Profile {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Profile {
    type Err = DataError;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "motion" => Ok(Profile::Motion),
            "render" => Ok(Profile::Render),
            "eval" => Ok(Profile::Eval),
            "train" => Ok(Profile::Train),
            other => Err(DataError::arg("profile", "motion|render|eval|train", other)),
        }
    }
}

/// A non-fatal finding: the data is usable but suspicious, or a default or
/// conversion was applied.
#[derive(Debug, Clone, PartialEq)]
pub struct Warning {
    /// The key concerned (or "" for the file as a whole).
    pub key: String,
    pub message: String,
}

impl fmt::Display for Warning {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.key.is_empty() {
            f.write_str(&self.message)
        } else {
            write!(f, "`{}`: {}", self.key, self.message)
        }
    }
}

/// Options for [`Dataset::read`].
#[derive(Debug, Clone)]
pub struct ReadOptions {
    /// Requirements to enforce.
    pub profile: Profile,
    /// The trained model's rest pose, used when the file has none (motion and
    /// render files may omit it; kinematics then use the model's).
    pub rest_pose: Option<Joints>,
    /// Accept `rest_pose[0]` away from the origin.
    pub allow_offset_root: bool,
    /// Turn 0/255 masks into {0,1} with the reference's threshold (≥ 2 → 1).
    pub binarize_masks: bool,
    /// Accept 4-channel images by dropping alpha.
    pub drop_alpha: bool,
}

impl ReadOptions {
    pub fn new(profile: Profile) -> Self {
        ReadOptions {
            profile,
            rest_pose: None,
            allow_offset_root: false,
            binarize_masks: false,
            drop_alpha: false,
        }
    }
}

/// One scene in the pma-npz v1 schema. Field shapes are given in brackets;
/// `None` means absent from the file and not derivable.
#[derive(Debug, Clone)]
pub struct Dataset {
    /// Where the data came from, for messages (`"<memory>"` when built in code).
    pub source: String,
    pub schema_version: i32,

    // --- pose group (P rows) ---
    /// Canonical joints `[24,3]`, root-centred, head +y.
    pub rest_pose: Option<Joints>,
    /// Axis-angle per joint `[P,24,3]`; joint 0 is the global orientation.
    pub bones: Array3<f32>,
    /// Root translation `[P,3]` (`kp3d[:,0] − rest_pose[0]`).
    pub root_locs: Option<Array2<f32>>,
    /// World joint positions `[P,24,3]`.
    pub kp3d: Option<Array3<f32>>,
    /// World→joint transforms `[P,24,4,4]`.
    pub skts: Option<Array4<f32>>,
    /// Bounding cylinders `[P,5]` = (x_c, z_c, r, y_top, y_bot).
    pub cyls: Option<Array2<f32>>,
    /// SMPL shape `[P,10]` or `[1,10]` (informational).
    pub betas: Option<Array2<f32>>,
    /// Ground-truth joints `[P,J',3]` (informational).
    pub gt_kp3d: Option<Array3<f32>>,
    /// Original frame numbers `[P]` (provenance).
    pub frame_ids: Option<Array1<i64>>,
    /// Head direction, (0,−1,0) or (0,1,0).
    pub head_dir: [f32; 3],
    /// Scale of SPIN-derived files; 1 means metres.
    pub pose_scale: f32,
    /// Informational global scale.
    pub ext_scale: Option<f64>,

    // --- camera group (C rows) ---
    /// Camera-to-world, OpenGL axes `[C,4,4]`.
    pub c2ws: Option<Array3<f32>>,
    /// `[C,2]` = (fx, fy) in pixels (a `(C,)` file array is expanded).
    pub focals: Option<Array2<f32>>,
    /// `[C,2]` = (cx, cy); derived as (W/2, H/2) when absent.
    pub centers: Option<Array2<f32>>,

    // --- image group (N rows) ---
    /// `(N, H, W, 3)`.
    pub img_shape: Option<[usize; 4]>,
    /// Image → pose row `[N]`.
    pub kp_idxs: Option<Array1<i64>>,
    /// Image → camera row `[N]`.
    pub img_pose_indices: Option<Array1<i64>>,
    /// Image → background row `[N]`.
    pub bkgd_idxs: Option<Array1<i64>>,
    /// 0 train, 1 novel view, 2 novel pose, 3 held-out val `[N]`.
    pub eval_tag: Option<Array1<i8>>,
    /// RGB `[N, H·W, 3]`.
    pub imgs: Option<Array3<u8>>,
    /// Foreground {0,1} `[N, H·W, 1]`.
    pub masks: Option<Array3<u8>>,
    /// Pixels allowed for ray sampling (> 0) `[N, H·W, 1]`.
    pub sampling_masks: Option<Array3<u8>>,
    /// Background plates `[B, H·W, 3]`; absent = one black plate.
    pub bkgds: Option<Array3<u8>>,

    // --- provenance ---
    /// Keys computed at import rather than read.
    pub derived: Vec<String>,
    /// Non-fatal findings of reading and validation.
    pub warnings: Vec<Warning>,
}

impl Dataset {
    /// A dataset holding only poses (`bones` `[P,24,3]`), everything else
    /// absent; fill the other fields, then call [`Dataset::derive`] and
    /// [`Dataset::validate`].
    pub fn from_bones(bones: Array3<f32>) -> Self {
        Dataset {
            source: "<memory>".into(),
            schema_version: SCHEMA_VERSION,
            rest_pose: None,
            bones,
            root_locs: None,
            kp3d: None,
            skts: None,
            cyls: None,
            betas: None,
            gt_kp3d: None,
            frame_ids: None,
            head_dir: [0.0, -1.0, 0.0],
            pose_scale: 1.0,
            ext_scale: None,
            c2ws: None,
            focals: None,
            centers: None,
            img_shape: None,
            kp_idxs: None,
            img_pose_indices: None,
            bkgd_idxs: None,
            eval_tag: None,
            imgs: None,
            masks: None,
            sampling_masks: None,
            bkgds: None,
            derived: Vec::new(),
            warnings: Vec::new(),
        }
    }

    /// Read a `.npz` (or a `.scene.npz` with its sibling `.frames.npz`),
    /// derive the absent keys and validate against `opts.profile`.
    /// Warnings end up in [`Dataset::warnings`].
    pub fn read(path: impl AsRef<Path>, opts: &ReadOptions) -> Result<Dataset> {
        let mut ds = read::read_npz(path.as_ref(), opts)?;
        ds.derive(opts.rest_pose.as_ref())?;
        ds.validate(opts)?;
        Ok(ds)
    }

    /// Fill absent derivable keys: `(C,)` focals, centres, root
    /// locations, `kp3d`, `skts`, `cyls`, identity index maps. `rest` is used
    /// when the dataset has no rest pose of its own. Keys already present are
    /// kept as they are (stored values win, for bit-parity).
    pub fn derive(&mut self, rest: Option<&Joints>) -> Result<()> {
        derive::derive(self, rest)
    }

    /// Recompute `kp3d`, `skts` and `cyls` from `bones` and `root_locs` with
    /// another rest pose (retargeting onto a trained model).
    pub fn repose(&mut self, rest: &Joints) -> Result<()> {
        derive::repose(self, rest)
    }

    /// Check everything in docs/conventions.md, "Validation", that applies to `opts.profile`.
    /// Errors name the file and key; warnings are appended to `self.warnings`.
    /// May rewrite masks (`binarize_masks`) and images (`drop_alpha`).
    pub fn validate(&mut self, opts: &ReadOptions) -> Result<()> {
        validate::validate(self, opts)
    }

    /// Write one `.npz` atomically (temp file + rename) with fixed zip
    /// metadata, so equal datasets give byte-identical files.
    pub fn write(&self, path: impl AsRef<Path>, opts: &WriteOptions) -> Result<()> {
        write::write_npz(self, path.as_ref(), opts, write::Members::All)
    }

    /// Write `<name>.scene.npz` (everything but pixels) and
    /// `<name>.frames.npz` (`imgs`, `masks`, `sampling_masks`, `bkgds`).
    /// `scene_path` must end in `.scene.npz`.
    pub fn write_split(&self, scene_path: impl AsRef<Path>, opts: &WriteOptions) -> Result<()> {
        let scene = scene_path.as_ref();
        let frames = frames_path_for(scene).ok_or_else(|| {
            DataError::arg("scene_path", "a path ending in .scene.npz", scene.display())
        })?;
        write::write_npz(self, scene, opts, write::Members::Scene)?;
        write::write_npz(self, &frames, opts, write::Members::Frames)
    }

    // --- counts -----------------------------------------------------------

    /// P: pose rows.
    pub fn n_poses(&self) -> usize {
        self.bones.shape()[0]
    }

    /// C: camera rows (0 without cameras).
    pub fn n_cameras(&self) -> usize {
        self.c2ws.as_ref().map_or(0, |c| c.shape()[0])
    }

    /// N: images (0 without `img_shape`).
    pub fn n_images(&self) -> usize {
        self.img_shape.map_or(0, |s| s[0])
    }

    /// H (rows).
    pub fn height(&self) -> usize {
        self.img_shape.map_or(0, |s| s[1])
    }

    /// W (columns).
    pub fn width(&self) -> usize {
        self.img_shape.map_or(0, |s| s[2])
    }

    /// The head direction as an enum (validated to be ±y).
    pub fn head(&self) -> Result<HeadDir> {
        HeadDir::from_vector(self.head_dir).ok_or_else(|| DataError::Value {
            file: self.source.clone(),
            key: "head_dir".into(),
            problem: "unsupported head direction".into(),
            expected: "(0,-1,0) or (0,1,0)".into(),
            found: format!("{:?}", self.head_dir),
        })
    }

    // --- per-image index maps --------------------------------------------

    fn lookup(
        &self,
        key: &str,
        arr: &Option<Array1<i64>>,
        n: usize,
        bound: usize,
    ) -> Result<usize> {
        let v = match arr {
            Some(a) => *a.get(n).ok_or_else(|| DataError::Index {
                file: self.source.clone(),
                key: "image index".into(),
                position: n,
                value: n.to_string(),
                bound: a.len(),
            })?,
            // An absent index map is the identity.
            None => n as i64,
        };
        if v < 0 || v as usize >= bound {
            return Err(DataError::Index {
                file: self.source.clone(),
                key: key.into(),
                position: n,
                value: v.to_string(),
                bound,
            });
        }
        Ok(v as usize)
    }

    /// Pose row of image n.
    pub fn pose_row(&self, n: usize) -> Result<usize> {
        self.lookup("kp_idxs", &self.kp_idxs, n, self.n_poses())
    }

    /// Camera row of image n.
    pub fn camera_row(&self, n: usize) -> Result<usize> {
        self.lookup(
            "img_pose_indices",
            &self.img_pose_indices,
            n,
            self.n_cameras(),
        )
    }

    /// Background row of image n, or `None` for the default black plate.
    pub fn background_row(&self, n: usize) -> Result<Option<usize>> {
        match &self.bkgds {
            None => Ok(None),
            Some(b) => {
                let i = match &self.bkgd_idxs {
                    Some(_) => self.lookup("bkgd_idxs", &self.bkgd_idxs, n, b.shape()[0])?,
                    None => 0,
                };
                Ok(Some(i))
            }
        }
    }

    // --- cameras ------------------------------------------------------------

    /// Camera row c at the dataset's image size.
    pub fn camera(&self, c: usize) -> Result<Camera> {
        let missing = |key: &str| DataError::MissingKey {
            file: self.source.clone(),
            key: key.into(),
            profile: Profile::Render.name().into(),
            hint: String::new(),
        };
        let c2ws = self.c2ws.as_ref().ok_or_else(|| missing("c2ws"))?;
        let focals = self.focals.as_ref().ok_or_else(|| missing("focals"))?;
        let shape = self.img_shape.ok_or_else(|| missing("img_shape"))?;
        if c >= c2ws.shape()[0] {
            return Err(DataError::Index {
                file: self.source.clone(),
                key: "camera row".into(),
                position: 0,
                value: c.to_string(),
                bound: c2ws.shape()[0],
            });
        }
        let (cx, cy) = match &self.centers {
            Some(ce) => (ce[[c, 0]], ce[[c, 1]]),
            None => (shape[2] as f32 / 2.0, shape[1] as f32 / 2.0),
        };
        let mut m = [[0.0f32; 4]; 4];
        for (r, row) in m.iter_mut().enumerate() {
            for (k, v) in row.iter_mut().enumerate() {
                *v = c2ws[[c, r, k]];
            }
        }
        let cam = Camera {
            width: shape[2],
            height: shape[1],
            fx: focals[[c, 0]],
            fy: focals[[c, 1]],
            cx,
            cy,
            c2w: m,
        };
        cam.validate().map_err(|e| DataError::Value {
            file: self.source.clone(),
            key: "c2ws/focals/centers".into(),
            problem: format!("camera row {c}"),
            expected: "a valid pinhole camera".into(),
            found: e.to_string(),
        })?;
        Ok(cam)
    }

    /// The camera of image n.
    pub fn image_camera(&self, n: usize) -> Result<Camera> {
        self.camera(self.camera_row(n)?)
    }

    // --- poses ----------------------------------------------------------------

    /// Rotation vectors of pose row p, `[24][3]`.
    pub fn pose_bones(&self, p: usize) -> Joints {
        crate::skeleton::joints_from_view(self.bones.slice(s![p, .., ..]))
    }

    /// Joint positions of pose row p, `[24][3]` (`None` before derivation
    /// when the dataset has no rest pose and no stored `kp3d`).
    pub fn pose_kp3d(&self, p: usize) -> Option<Joints> {
        self.kp3d
            .as_ref()
            .map(|k| crate::skeleton::joints_from_view(k.slice(s![p, .., ..])))
    }

    // --- pixels ---------------------------------------------------------------

    /// RGB of image n, `[H·W, 3]`.
    pub fn image(&self, n: usize) -> Option<ArrayView2<'_, u8>> {
        self.imgs.as_ref().map(|a| a.slice(s![n, .., ..]))
    }

    /// Foreground mask of image n, `[H·W, 1]`.
    pub fn mask(&self, n: usize) -> Option<ArrayView2<'_, u8>> {
        self.masks.as_ref().map(|a| a.slice(s![n, .., ..]))
    }

    /// Sampling mask of image n, `[H·W, 1]`.
    pub fn sampling_mask(&self, n: usize) -> Option<ArrayView2<'_, u8>> {
        self.sampling_masks.as_ref().map(|a| a.slice(s![n, .., ..]))
    }

    /// Background plate of image n, `[H·W, 3]`; `None` = black.
    pub fn background(&self, n: usize) -> Result<Option<ArrayView2<'_, u8>>> {
        Ok(match (self.background_row(n)?, &self.bkgds) {
            (Some(b), Some(a)) => Some(a.slice(s![b, .., ..])),
            _ => None,
        })
    }
}

/// `<name>.frames.npz` for `<name>.scene.npz`.
pub fn frames_path_for(scene: &Path) -> Option<PathBuf> {
    let name = scene.file_name()?.to_str()?;
    let stem = name.strip_suffix(".scene.npz")?;
    Some(scene.with_file_name(format!("{stem}.frames.npz")))
}
