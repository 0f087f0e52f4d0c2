//! Real motion → a `motion`-profile pma-npz for retargeting (docs/conventions.md,
//! "Motion files").
//!
//! Inputs: SMPL-parameter npz (AIST++ style `poses (T,72)` + `trans (T,3)`)
//! and CMU BVH (31 joints), read and retargeted onto SMPL 24 by
//! `pma_data::motion` (the joint map and rest-pose alignment are documented
//! there, `CMU_TO_SMPL`). Then, in this order:
//! 1. `--frames a:b` keeps source frames `a..b` (end exclusive);
//! 2. `--fps F` resamples (slerp of joint rotations, linear root);
//! 3. the motion is turned so the head points the target dataset's way
//!    (H36M-ZJU and the other SPIN/ZJU layouts: −y; AIST: +y), by a 180°
//!    turn about x of the root rotation and translation (docs/conventions.md,
//!    "Units and up axis");
//! 4. `kp3d`, `skts` and `cyls` come from forward kinematics with the rest
//!    pose (the trained model's, ideally: `--rest-pose` takes a pma
//!    checkpoint or a dataset npz; the default is the synthetic scene's SMPL
//!    rest pose), in f64, stored f32; the file is validated and written.
//!
//! The output holds `bones`, `root_locs`, `kp3d`, `skts`, `cyls`,
//! `rest_pose` (the one used for `kp3d`), `head_dir`, and `frame_ids`
//! (source frame numbers) when no resampling happened.

use std::{ops::Range, path::Path};

use ndarray::{Array1, Array2, Array3};
use pma_data::{
    dataset::{
        npz::NpyData, npz::NpzReader, Compression, Dataset, Profile, ReadOptions, WriteOptions,
    },
    motion::{
        bvh::Bvh,
        read_smpl_npz,
        retarget::{retarget_bvh, RetargetOptions, CMU_TO_SMPL},
        HeadDir, Motion,
    },
    skeleton::Joints,
};
use safetensors::{Dtype, SafeTensors};

use crate::{
    dataset::Layout,
    error::{ConvertError, Result},
};

/// AIST++ annotations are 60 fps; SMPL npz files that store no rate are assumed to be.
pub const DEFAULT_NPZ_FPS: f64 = 60.0;

/// Options of [`convert_motion`].
#[derive(Clone, Debug)]
pub struct MotionOptions {
    /// Source frames to keep (end exclusive; `usize::MAX` = to the last frame), before resampling.
    pub frames: Option<Range<usize>>,
    /// Output frame rate; `None` keeps the source rate.
    pub fps: Option<f64>,
    /// Dataset whose up-axis convention the output follows.
    pub target: Layout,
    /// Rest pose for forward kinematics (and BVH retargeting); `None` = the
    /// synthetic scene's SMPL rest pose.
    pub rest_pose: Option<Joints>,
    /// Frame rate of an SMPL npz that stores none.
    pub npz_fps: f64,
    pub compression: Compression,
}

impl Default for MotionOptions {
    fn default() -> Self {
        Self {
            frames: None,
            fps: None,
            target: Layout::H36mZju,
            rest_pose: None,
            npz_fps: DEFAULT_NPZ_FPS,
            compression: Compression::Stored,
        }
    }
}

/// What a conversion produced.
#[derive(Clone, Debug)]
pub struct MotionReport {
    pub source_frames: usize,
    pub source_fps: f64,
    pub frames: usize,
    pub fps: f64,
    pub source_up: HeadDir,
    pub up: HeadDir,
}

/// Reads a motion file (`.npz` or `.bvh`). BVH retargeting needs the rest pose.
pub fn read_motion(input: &Path, rest: &Joints, npz_fps: f64) -> Result<Motion> {
    let ext = crate::extension(input);
    match ext.as_str() {
        "npz" => Ok(read_smpl_npz(input, npz_fps)?),
        "bvh" => {
            let bvh = Bvh::read(input)?;
            Ok(retarget_bvh(
                &bvh,
                &input.display().to_string(),
                &CMU_TO_SMPL,
                rest,
                &RetargetOptions::default(),
            )?)
        }
        _ => Err(ConvertError::Usage(format!(
            "{}: unknown motion type; expected an SMPL .npz (poses + trans) or a CMU .bvh",
            input.display()
        ))),
    }
}

/// Reads a rest pose from a pma checkpoint (`.safetensors`, tensor
/// `rest_pose`) or a dataset npz (key `rest_pose`), shape `(24,3)` or `(1,24,3)`.
pub fn read_rest_pose(path: &Path) -> Result<Joints> {
    let ext = crate::extension(path);
    let (shape, values): (Vec<usize>, Vec<f32>) = match ext.as_str() {
        "safetensors" => {
            let bytes = pma_data::fsio::read_input(
                path,
                pma_model::network::checkpoint::MAX_CHECKPOINT_BYTES,
            )
            .map_err(|e| ConvertError::io(path, e))?;
            let st =
                SafeTensors::deserialize(&bytes).map_err(|source| ConvertError::Safetensors {
                    path: path.to_path_buf(),
                    cause: source,
                })?;
            let t = st
                .tensor("rest_pose")
                .map_err(|_| ConvertError::missing(path, "rest_pose", " (tensor)"))?;
            if t.dtype() != Dtype::F32 {
                return Err(ConvertError::mismatch(
                    path,
                    "rest_pose",
                    "F32",
                    format!("{:?}", t.dtype()),
                ));
            }
            let v = t
                .data()
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect();
            (t.shape().to_vec(), v)
        }
        "npz" => {
            let mut r = NpzReader::open(path)?;
            let a = r.read("rest_pose")?;
            match a.data {
                NpyData::F32(v) => (a.shape, v),
                NpyData::F64(v) => (a.shape, v.into_iter().map(|x| x as f32).collect()),
                other => {
                    return Err(ConvertError::mismatch(
                        path,
                        "rest_pose",
                        "float32",
                        format!("{:?}", other.elem()),
                    ))
                }
            }
        }
        _ => {
            return Err(ConvertError::Usage(format!(
                "{}: a rest pose is read from a pma checkpoint (.safetensors) or a dataset (.npz)",
                path.display()
            )))
        }
    };
    let j = crate::dataset::joints(path, "rest_pose", &shape, &values)?;
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        return Err(ConvertError::invalid(
            path,
            "rest_pose",
            format!("non-finite value at flat index {i}"),
        ));
    }
    Ok(j)
}

/// Applies the frame range, resampling and up-axis turn of the module docs
/// and builds the derived, validated dataset.
pub fn motion_dataset(
    motion: &Motion,
    source: &str,
    opts: &MotionOptions,
) -> Result<(Dataset, MotionReport)> {
    let rest = opts.rest_pose.unwrap_or_else(pma_data::synth::rest_pose);
    let mut m = motion.clone();
    let mut frame_ids: Option<Vec<i64>> = Some((0..m.len() as i64).collect());
    if let Some(r) = &opts.frames {
        let r = r.start..if r.end == usize::MAX { m.len() } else { r.end };
        m = m.frames(r.clone())?;
        frame_ids = Some((r.start as i64..r.end as i64).collect());
    }
    if let Some(fps) = opts.fps {
        if fps != m.fps {
            m = m.resample(fps)?;
            frame_ids = None;
        }
    }
    let up = match opts.target.head_dir()[1] > 0.0 {
        true => HeadDir::PosY,
        false => HeadDir::NegY,
    };
    let m = m.to_up(up);
    m.validate()?;

    let p = m.len();
    let bones = Array3::from_shape_vec(
        (p, 24, 3),
        m.bones.iter().flatten().flatten().copied().collect(),
    )
    .expect("24x3 per frame");
    let mut ds = Dataset::from_bones(bones);
    ds.source = source.to_string();
    ds.rest_pose = Some(rest);
    ds.root_locs = Some(
        Array2::from_shape_vec((p, 3), m.root.iter().flatten().copied().collect())
            .expect("3 per frame"),
    );
    ds.head_dir = up.vector();
    ds.frame_ids = frame_ids.map(Array1::from_vec);
    ds.derive(None)?;
    ds.validate(&ReadOptions::new(Profile::Motion))?;
    let report = MotionReport {
        source_frames: motion.len(),
        source_fps: motion.fps,
        frames: p,
        fps: m.fps,
        source_up: motion.up,
        up,
    };
    Ok((ds, report))
}

/// `pma convert motion`: reads `input`, writes the motion-profile npz `output` atomically.
pub fn convert_motion(input: &Path, output: &Path, opts: &MotionOptions) -> Result<MotionReport> {
    let rest = opts.rest_pose.unwrap_or_else(pma_data::synth::rest_pose);
    let motion = read_motion(input, &rest, opts.npz_fps)?;
    let (ds, report) = motion_dataset(&motion, &input.display().to_string(), opts)?;
    ds.write(
        output,
        &WriteOptions {
            compression: opts.compression,
        },
    )?;
    Ok(report)
}
