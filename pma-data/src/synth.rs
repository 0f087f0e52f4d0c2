//! The built-in synthetic multi-view scene: a textured, articulated figure
//! on the SMPL skeleton, driven by real motion and ray-traced analytically
//! from a ring of known cameras.
//!
//! * **Subject**: [`figure`]: 24 capsules and ellipsoids attached to the
//!   joints of the A-NeRF rest pose scaled to metres ([`rest_pose`]), with
//!   bone-local textures that mix low and high spatial frequencies.
//! * **Motion**: the CMU 131_01 walk (retargeted, [`crate::motion::retarget`])
//!   for training, its later frames and the AIST++ dance for novel poses.
//!   Both are embedded in the library (`assets/motion`, see SOURCE.md),
//!   turned to the training convention (head −y) and kept
//!   on a treadmill: the root's horizontal drift is removed, its height
//!   kept relative to the first frame.
//! * **Cameras**: [`rig`], a ring; the first cameras in ring order that are
//!   not held out train, evenly spread ones are held out for novel views.
//! * **Splits** (the paper's protocol), one pma-npz v1 file each, images
//!   frame-major and camera-minor:
//!   `train` = training cameras × the first `frames` walk frames;
//!   `novel_view` = held-out cameras × every `novel_view_stride`-th training
//!   frame; `novel_pose` = training cameras × later walk frames, then AIST++
//!   dance frames. Every file stores all cameras (`img_pose_indices` picks
//!   the row), black backgrounds, exact masks and sampling masks (the mask
//!   dilated by `sampling_margin` pixels).
//!
//! Everything is single-threaded f64 arithmetic in a fixed order, so one
//! seed gives byte-identical files.

pub mod figure;
mod preview;
pub mod primitive;
pub mod render;
pub mod rig;
pub mod texture;

use std::path::{Path, PathBuf};

use ndarray::{Array1, Array2, Array3, Array4};
use serde::Serialize;

pub use figure::{rest_pose, Figure, Part, ANERF_REST_POSE, REST_POSE_SCALE};
pub use render::{dilate, render, Light, Rendered};
pub use rig::{ring_cameras, Ring};

use crate::camera::Camera;
use crate::cylinder::{cylinder_from_joints, CylinderParams, HeadDir};
use crate::dataset::{Compression, Dataset, Profile, ReadOptions, WriteOptions};
use crate::error::DataError;
use crate::motion::bvh::Bvh;
use crate::motion::retarget::{retarget_bvh, CMU_TO_SMPL};
use crate::motion::{parse_smpl_npz, Motion, MotionError};
use crate::skeleton::{forward_kinematics, local_to_world, Joints, N_JOINTS};

const WALK_BVH: &str = include_str!("../assets/motion/cmu_131_01_30fps.bvh");
const DANCE_NPZ: &[u8] = include_bytes!("../assets/motion/aist_demo.npz");
/// AIST++ annotations are 60 fps; the demo file stores no rate.
const DANCE_FPS: f64 = 60.0;

/// Errors from building or writing the synthetic scene.
#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    #[error(transparent)]
    Data(#[from] DataError),
    #[error(transparent)]
    Motion(#[from] MotionError),
    #[error("invalid synth setting `{name}`: expected {expected}, found {found}")]
    Config {
        name: &'static str,
        expected: String,
        found: String,
    },
    /// Writing the scene's files failed.
    #[error("writing {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {msg}")]
    Encode { path: PathBuf, msg: String },
    /// The process-wide interrupt flag was raised (see [`crate::interrupt`]).
    #[error("{0}")]
    Interrupted(#[from] crate::interrupt::Interrupted),
}

impl crate::error::ExitKind for SynthError {
    fn kind(&self) -> crate::error::ErrorKind {
        use crate::error::ErrorKind;
        match self {
            SynthError::Data(d) => d.kind(),
            SynthError::Motion(m) => m.kind(),
            SynthError::Config { .. } => ErrorKind::Refused,
            // The scene is built in; its only files are the ones it writes.
            SynthError::Io { .. } | SynthError::Encode { .. } => ErrorKind::Failure,
            SynthError::Interrupted(_) => ErrorKind::Interrupted,
        }
    }
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> SynthError + '_ {
    move |source| SynthError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Scene settings. The defaults suit a 2-core CPU.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SynthConfig {
    /// Image width and height in pixels.
    pub res: usize,
    pub train_cams: usize,
    /// Held-out cameras for the novel-view split.
    pub test_cams: usize,
    /// Training frames (walk poses).
    pub frames: usize,
    /// Step through the 30 fps walk: 2 gives 15 fps poses.
    pub frame_stride: usize,
    /// Every how many training frames the novel-view split takes.
    pub novel_view_stride: usize,
    /// Walk frames after the training span in the novel-pose split.
    pub novel_pose_walk: usize,
    /// AIST++ dance frames in the novel-pose split.
    pub novel_pose_dance: usize,
    /// Sampling-mask margin around the silhouette, pixels.
    pub sampling_margin: usize,
    /// Jitters colours, glyphs and the camera ring; not the motion.
    pub seed: u64,
    /// Deflate the npz members (otherwise stored, memory-mappable).
    pub compress: bool,
}

impl Default for SynthConfig {
    fn default() -> Self {
        SynthConfig {
            res: 96,
            train_cams: 4,
            test_cams: 2,
            frames: 64,
            frame_stride: 2,
            novel_view_stride: 2,
            novel_pose_walk: 16,
            novel_pose_dance: 16,
            sampling_margin: 3,
            seed: 0,
            compress: true,
        }
    }
}

impl SynthConfig {
    /// A small scene: `train_cams` cameras over `frames` walk frames at `res` pixels, one
    /// held-out camera, and one walk and one dance frame for the novel-pose split; the rest
    /// as [`SynthConfig::default`].
    pub fn small(res: usize, train_cams: usize, frames: usize) -> Self {
        SynthConfig {
            res,
            train_cams,
            test_cams: 1,
            frames,
            novel_pose_walk: 1,
            novel_pose_dance: 1,
            ..Default::default()
        }
    }
}

/// Where a pose row comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum MotionSource {
    /// CMU 131_01, frame index in the 30 fps asset.
    Walk,
    /// AIST++ demo, frame index in the npz.
    Dance,
}

/// One pose of a split.
#[derive(Clone, Debug, PartialEq)]
pub struct PoseRow {
    /// Axis-angle `[24][3]`, root orientation in the training world.
    pub bones: Joints,
    /// Root location (metres).
    pub root: [f32; 3],
    pub source: MotionSource,
    pub frame: usize,
}

/// One split before rendering: images are `poses × cams`, frame-major.
#[derive(Clone, Debug, PartialEq)]
pub struct SplitPlan {
    /// File stem and split name: `train`, `novel_view`, `novel_pose`.
    pub name: &'static str,
    /// `eval_tag` value (0 train, 1 novel view, 2 novel pose).
    pub tag: i8,
    pub poses: Vec<PoseRow>,
    /// Camera rows used, ascending.
    pub cams: Vec<usize>,
}

impl SplitPlan {
    pub fn n_images(&self) -> usize {
        self.poses.len() * self.cams.len()
    }
}

/// Everything needed to render the scene.
#[derive(Clone, Debug)]
pub struct ScenePlan {
    pub config: SynthConfig,
    /// Rest pose in metres (root at the origin).
    pub rest: Joints,
    pub figure: Figure,
    pub ring: Ring,
    pub cameras: Vec<Camera>,
    pub train_cams: Vec<usize>,
    pub test_cams: Vec<usize>,
    pub light: Light,
    /// train, novel_view, novel_pose.
    pub splits: Vec<SplitPlan>,
}

/// The walk, retargeted onto `rest`, in the training convention, on a treadmill.
pub fn walk_motion(rest: &Joints) -> Result<Motion, SynthError> {
    let file = "assets/motion/cmu_131_01_30fps.bvh";
    let bvh = Bvh::parse(WALK_BVH, file)?;
    let m = retarget_bvh(&bvh, file, &CMU_TO_SMPL, rest, &Default::default())?;
    Ok(treadmill(&m.to_up(HeadDir::NegY)))
}

/// The AIST++ dance in the training convention, on a treadmill.
pub fn dance_motion() -> Result<Motion, SynthError> {
    let m = parse_smpl_npz(DANCE_NPZ, "assets/motion/aist_demo.npz", DANCE_FPS)?;
    Ok(treadmill(&m.to_up(HeadDir::NegY)))
}

/// Root x and z to 0; y relative to the first frame.
fn treadmill(m: &Motion) -> Motion {
    let y0 = m.root[0][1];
    let mut out = m.clone();
    for r in &mut out.root {
        *r = [0.0, r[1] - y0, 0.0];
    }
    out
}

fn check(
    cond: bool,
    name: &'static str,
    expected: &str,
    found: impl ToString,
) -> Result<(), SynthError> {
    if cond {
        Ok(())
    } else {
        Err(SynthError::Config {
            name,
            expected: expected.to_string(),
            found: found.to_string(),
        })
    }
}

/// `n` indices spread evenly over `lo..hi`, each the centre of its share.
fn spread(lo: usize, hi: usize, n: usize) -> Vec<usize> {
    let span = (hi - lo) as f64;
    (0..n)
        .map(|k| lo + ((k as f64 + 0.5) * span / n as f64).floor() as usize)
        .collect()
}

/// Held-out cameras: `m` of `n` ring positions, evenly spread and offset
/// by half a share from camera 0 (which always trains).
fn held_out(n: usize, m: usize) -> Vec<usize> {
    (0..m)
        .map(|i| ((2 * i + 1) * n / (2 * m)).min(n - 1))
        .collect()
}

/// Chooses cameras, poses and splits.
pub fn plan(cfg: &SynthConfig) -> Result<ScenePlan, SynthError> {
    check(
        (8..=1024).contains(&cfg.res),
        "res",
        "8..=1024 pixels",
        cfg.res,
    )?;
    check(
        cfg.train_cams >= 1,
        "train_cams",
        "at least 1",
        cfg.train_cams,
    )?;
    check(cfg.test_cams >= 1, "test_cams", "at least 1", cfg.test_cams)?;
    check(
        cfg.train_cams + cfg.test_cams <= 64,
        "train_cams + test_cams",
        "at most 64 cameras",
        cfg.train_cams + cfg.test_cams,
    )?;
    check(cfg.frames >= 1, "frames", "at least 1", cfg.frames)?;
    check(
        cfg.frame_stride >= 1,
        "frame_stride",
        "at least 1",
        cfg.frame_stride,
    )?;
    check(
        cfg.novel_view_stride >= 1,
        "novel_view_stride",
        "at least 1",
        cfg.novel_view_stride,
    )?;
    check(
        cfg.novel_pose_walk + cfg.novel_pose_dance >= 1,
        "novel_pose_walk + novel_pose_dance",
        "at least 1",
        0,
    )?;
    check(
        cfg.sampling_margin <= 64,
        "sampling_margin",
        "at most 64 pixels",
        cfg.sampling_margin,
    )?;

    let rest = rest_pose();
    let walk = walk_motion(&rest)?;
    let dance = dance_motion()?;
    let span = cfg.frames * cfg.frame_stride;
    let walk_left = walk.len().saturating_sub(span);
    check(
        span <= walk.len() && cfg.novel_pose_walk <= walk_left,
        "frames x frame_stride",
        &format!(
            "room in the {}-frame walk for the training span and {} later novel-pose frames",
            walk.len(),
            cfg.novel_pose_walk
        ),
        format!("{} x {} = {span} frames", cfg.frames, cfg.frame_stride),
    )?;
    check(
        cfg.novel_pose_dance <= dance.len(),
        "novel_pose_dance",
        &format!("at most {} (the dance length)", dance.len()),
        cfg.novel_pose_dance,
    )?;

    let row = |m: &Motion, source, f: usize| PoseRow {
        bones: m.bones[f],
        root: m.root[f],
        source,
        frame: f,
    };
    let train_poses: Vec<PoseRow> = (0..cfg.frames)
        .map(|k| row(&walk, MotionSource::Walk, k * cfg.frame_stride))
        .collect();
    let view_poses: Vec<PoseRow> = train_poses
        .iter()
        .step_by(cfg.novel_view_stride)
        .cloned()
        .collect();
    let mut pose_poses: Vec<PoseRow> = spread(span, walk.len(), cfg.novel_pose_walk)
        .into_iter()
        .map(|f| row(&walk, MotionSource::Walk, f))
        .collect();
    pose_poses.extend(
        spread(0, dance.len(), cfg.novel_pose_dance)
            .into_iter()
            .map(|f| row(&dance, MotionSource::Dance, f)),
    );

    let n_cams = cfg.train_cams + cfg.test_cams;
    let ring = Ring::default();
    let cameras = ring_cameras(n_cams, cfg.res, cfg.seed, &ring)?;
    let test_cams = held_out(n_cams, cfg.test_cams);
    let train_cams: Vec<usize> = (0..n_cams).filter(|c| !test_cams.contains(c)).collect();

    let splits = vec![
        SplitPlan {
            name: "train",
            tag: 0,
            poses: train_poses,
            cams: train_cams.clone(),
        },
        SplitPlan {
            name: "novel_view",
            tag: 1,
            poses: view_poses,
            cams: test_cams.clone(),
        },
        SplitPlan {
            name: "novel_pose",
            tag: 2,
            poses: pose_poses,
            cams: train_cams.clone(),
        },
    ];
    Ok(ScenePlan {
        config: cfg.clone(),
        figure: Figure::new(&rest, cfg.seed),
        rest,
        ring,
        cameras,
        train_cams,
        test_cams,
        light: Light::default(),
        splits,
    })
}

/// Renders one split into a validated dataset (Train profile for `train`,
/// Eval with `eval_tag` otherwise). `tick` is called once per image.
pub fn render_split(
    plan: &ScenePlan,
    split: &SplitPlan,
    tick: &mut dyn FnMut(),
) -> Result<Dataset, SynthError> {
    let cfg = &plan.config;
    let (p, c, n) = (split.poses.len(), plan.cameras.len(), split.n_images());
    let hw = cfg.res * cfg.res;

    let mut bones = Array3::<f32>::zeros((p, N_JOINTS, 3));
    let mut roots = Array2::<f32>::zeros((p, 3));
    let mut kp3d = Array3::<f32>::zeros((p, N_JOINTS, 3));
    let mut skts = Array4::<f32>::zeros((p, N_JOINTS, 4, 4));
    let mut cyls = Array2::<f32>::zeros((p, 5));
    let cyl_params = CylinderParams::training(HeadDir::NegY);
    for (i, pose) in split.poses.iter().enumerate() {
        let posed = forward_kinematics(&plan.rest, &pose.bones, pose.root);
        for j in 0..N_JOINTS {
            for k in 0..3 {
                bones[[i, j, k]] = pose.bones[j][k];
                kp3d[[i, j, k]] = posed.kp3d[j][k];
            }
            for r in 0..4 {
                for cc in 0..4 {
                    skts[[i, j, r, cc]] = posed.skts[j][r][cc];
                }
            }
        }
        for k in 0..3 {
            roots[[i, k]] = pose.root[k];
        }
        for (k, v) in cylinder_from_joints(&posed.kp3d, &cyl_params)
            .iter()
            .enumerate()
        {
            cyls[[i, k]] = *v;
        }
    }

    let mut c2ws = Array3::<f32>::zeros((c, 4, 4));
    let mut focals = Array2::<f32>::zeros((c, 2));
    let mut centers = Array2::<f32>::zeros((c, 2));
    for (k, cam) in plan.cameras.iter().enumerate() {
        for r in 0..4 {
            for cc in 0..4 {
                c2ws[[k, r, cc]] = cam.c2w[r][cc];
            }
        }
        focals[[k, 0]] = cam.fx;
        focals[[k, 1]] = cam.fy;
        centers[[k, 0]] = cam.cx;
        centers[[k, 1]] = cam.cy;
    }

    let mut imgs = Array3::<u8>::zeros((n, hw, 3));
    let mut masks = Array3::<u8>::zeros((n, hw, 1));
    let mut sampling = Array3::<u8>::zeros((n, hw, 1));
    let mut kp_idxs = Array1::<i64>::zeros(n);
    let mut cam_idxs = Array1::<i64>::zeros(n);
    let mut image = 0;
    for (i, pose) in split.poses.iter().enumerate() {
        let l2w = local_to_world(
            &plan.rest,
            &pose.bones,
            glam::DVec3::from(pose.root.map(f64::from)),
        );
        for &cam in &split.cams {
            crate::interrupt::check()?;
            let out = render(&plan.figure, &l2w, &plan.cameras[cam], &plan.light);
            let grown = dilate(&out.mask, cfg.res, cfg.res, cfg.sampling_margin);
            for px in 0..hw {
                for k in 0..3 {
                    imgs[[image, px, k]] = out.rgb[3 * px + k];
                }
                masks[[image, px, 0]] = out.mask[px];
                sampling[[image, px, 0]] = grown[px];
            }
            kp_idxs[image] = i as i64;
            cam_idxs[image] = cam as i64;
            image += 1;
            tick();
        }
    }

    let mut ds = Dataset::from_bones(bones);
    ds.source = format!("pma synth ({})", split.name);
    ds.rest_pose = Some(plan.rest);
    ds.root_locs = Some(roots);
    ds.kp3d = Some(kp3d);
    ds.skts = Some(skts);
    ds.cyls = Some(cyls);
    ds.frame_ids = Some(split.poses.iter().map(|p| p.frame as i64).collect());
    ds.head_dir = HeadDir::NegY.vector();
    ds.c2ws = Some(c2ws);
    ds.focals = Some(focals);
    ds.centers = Some(centers);
    ds.img_shape = Some([n, cfg.res, cfg.res, 3]);
    ds.kp_idxs = Some(kp_idxs);
    ds.img_pose_indices = Some(cam_idxs);
    ds.bkgd_idxs = Some(Array1::zeros(n));
    ds.imgs = Some(imgs);
    ds.masks = Some(masks);
    ds.sampling_masks = Some(sampling);
    ds.bkgds = Some(Array3::zeros((1, hw, 3)));
    let profile = if split.tag == 0 {
        Profile::Train
    } else {
        ds.eval_tag = Some(Array1::from_elem(n, split.tag));
        Profile::Eval
    };
    ds.validate(&ReadOptions::new(profile))?;
    Ok(ds)
}

/// What [`generate`] wrote.
#[derive(Clone, Debug, Serialize)]
pub struct SplitSummary {
    pub name: &'static str,
    pub path: PathBuf,
    pub images: usize,
    pub poses: usize,
    pub cameras: Vec<usize>,
    pub bytes: u64,
}

/// Files written by [`generate`].
#[derive(Clone, Debug, Serialize)]
pub struct SynthSummary {
    pub splits: Vec<SplitSummary>,
    pub scene_json: PathBuf,
    pub preview: PathBuf,
}

impl SynthSummary {
    /// Total size of every file written, in bytes.
    pub fn total_bytes(&self) -> u64 {
        self.splits.iter().map(|s| s.bytes).sum::<u64>()
            + [&self.scene_json, &self.preview]
                .iter()
                .filter_map(|p| std::fs::metadata(p).ok())
                .map(|m| m.len())
                .sum::<u64>()
    }
}

/// The human-readable `scene.json`.
#[derive(Serialize)]
struct SceneInfo<'a> {
    format: &'static str,
    config: &'a SynthConfig,
    rest_pose_scale: f32,
    head_dir: [f32; 3],
    ring: &'a Ring,
    train_cams: &'a [usize],
    test_cams: &'a [usize],
    focal_px: f32,
    light: LightInfo,
    splits: Vec<SplitInfo<'a>>,
    motions: [MotionInfo; 2],
}

#[derive(Serialize)]
struct LightInfo {
    dir: [f64; 3],
    ambient: f64,
    diffuse: f64,
}

#[derive(Serialize)]
struct SplitInfo<'a> {
    name: &'static str,
    file: String,
    eval_tag: i8,
    images: usize,
    poses: usize,
    cameras: &'a [usize],
    /// Pose rows per source, as (source, frame) pairs in row order.
    pose_sources: Vec<(MotionSource, usize)>,
}

#[derive(Serialize)]
struct MotionInfo {
    source: MotionSource,
    asset: &'static str,
    fps: f64,
    frames: usize,
    credit: &'static str,
}

/// Writes `bytes` to `path` atomically.
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), SynthError> {
    crate::fsio::write_atomic(path, bytes).map_err(io_err(path))
}

/// Renders every split and writes `out/{train,novel_view,novel_pose}.npz`,
/// `out/scene.json` and `out/preview.png` (a contact sheet). `progress`
/// receives (images done, images total).
pub fn generate(
    cfg: &SynthConfig,
    out: &Path,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<SynthSummary, SynthError> {
    let plan = plan(cfg)?;
    crate::fsio::create_dir_all(out).map_err(io_err(out))?;
    let total: usize = plan.splits.iter().map(SplitPlan::n_images).sum();
    let mut done = 0;
    progress(0, total);
    let opts = WriteOptions {
        compression: if cfg.compress {
            Compression::Deflated
        } else {
            Compression::Stored
        },
    };
    let mut datasets = Vec::with_capacity(plan.splits.len());
    let mut splits = Vec::with_capacity(plan.splits.len());
    for split in &plan.splits {
        let ds = render_split(&plan, split, &mut || {
            done += 1;
            progress(done, total);
        })?;
        let path = out.join(format!("{}.npz", split.name));
        ds.write(&path, &opts)?;
        let bytes = std::fs::metadata(&path).map_err(io_err(&path))?.len();
        splits.push(SplitSummary {
            name: split.name,
            path,
            images: split.n_images(),
            poses: split.poses.len(),
            cameras: split.cams.clone(),
            bytes,
        });
        datasets.push(ds);
    }

    let info = SceneInfo {
        format: "pma synth v1",
        config: cfg,
        rest_pose_scale: REST_POSE_SCALE,
        head_dir: HeadDir::NegY.vector(),
        ring: &plan.ring,
        train_cams: &plan.train_cams,
        test_cams: &plan.test_cams,
        focal_px: plan.cameras[0].fx,
        light: LightInfo {
            dir: plan.light.dir.to_array(),
            ambient: plan.light.ambient,
            diffuse: plan.light.diffuse,
        },
        splits: plan
            .splits
            .iter()
            .map(|s| SplitInfo {
                name: s.name,
                file: format!("{}.npz", s.name),
                eval_tag: s.tag,
                images: s.n_images(),
                poses: s.poses.len(),
                cameras: &s.cams,
                pose_sources: s.poses.iter().map(|p| (p.source, p.frame)).collect(),
            })
            .collect(),
        motions: [
            MotionInfo {
                source: MotionSource::Walk,
                asset: "pma-data/assets/motion/cmu_131_01_30fps.bvh",
                fps: 30.0,
                frames: Bvh::parse(WALK_BVH, "walk")?.n_frames(),
                credit: "CMU Graphics Lab Motion Capture Database (mocap.cs.cmu.edu), subject 131 trial 01",
            },
            MotionInfo {
                source: MotionSource::Dance,
                asset: "pma-data/assets/motion/aist_demo.npz",
                fps: DANCE_FPS,
                frames: dance_motion()?.len(),
                credit: "AIST++ (Li et al. 2021), CC BY 4.0",
            },
        ],
    };
    let scene_json = out.join("scene.json");
    let mut text = serde_json::to_string_pretty(&info).map_err(|e| SynthError::Encode {
        path: scene_json.clone(),
        msg: e.to_string(),
    })?;
    text.push('\n');
    write_atomic(&scene_json, text.as_bytes())?;

    let preview = out.join("preview.png");
    let png = preview::contact_sheet(&plan, &datasets).encode_png(&preview)?;
    write_atomic(&preview, &png)?;
    Ok(SynthSummary {
        splits,
        scene_json,
        preview,
    })
}
