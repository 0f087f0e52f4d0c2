//! What the page can show: the poses its slider runs over, the dataset cameras it can reset
//! to, and the ground-truth images behind a dataset view.
//!
//! Poses come from one of three places:
//! * `--data DS.npz` alone: the dataset's pose rows; a pose seen by a dataset camera has a
//!   ground-truth image, which the page shows beside the render with its scores;
//! * `--poses MOTION.npz`: a motion retargeted onto the avatar as `pma render --poses` does
//!   (FK with the avatar's rest pose, head turned to −y, root path scaled by the leg-length
//!   ratio; `pma_model::tools::retarget`), seen from `--data`'s cameras if given;
//! * neither: the avatar's rest pose.
//!
//! Without dataset cameras the page starts from a framing camera in front of the body.

use std::collections::HashMap;
use std::path::Path;

use pma_data::camera::Camera;
use pma_data::cylinder::{cylinder_from_joints, CylinderParams, HeadDir};
use pma_data::dataset::{Dataset, Profile};
use pma_data::skeleton::Joints;
use pma_model::eval::{dataset_pose, ground_truth, read_dataset, resolve_split};
use pma_model::render::avatar::{Avatar, Poses};
use pma_model::render::camera_path::{facing, framing_camera, FRAMING_FOV_DEG};
use pma_model::tools::retarget::{read_motion, retarget, RetargetedFrame, RootScale};
use serde::Serialize;

use crate::ViewError;

/// Image size of views without a dataset camera.
pub const DEFAULT_SIZE: (usize, usize) = (256, 256);

/// The poses of the slider.
enum PoseSet {
    /// The dataset's pose rows.
    Dataset,
    /// Retargeted motion frames.
    Motion(Vec<RetargetedFrame>),
    /// The avatar's rest pose, once.
    Rest,
}

/// One pose, ready to render.
pub struct PoseItem {
    pub poses: Poses,
    /// Posed joints (world), for the render box and the camera target.
    pub kp3d: Joints,
}

/// Poses, cameras and ground truth of a viewing session (immutable once loaded).
pub struct Scene {
    set: PoseSet,
    data: Option<Dataset>,
    /// Dataset cameras (`--data`), at the dataset's image size.
    cameras: Vec<Camera>,
    /// Image of (pose row, camera row), for ground truth (dataset poses only).
    images: HashMap<(usize, usize), usize>,
    head: HeadDir,
    /// Where the page starts when there is no dataset camera.
    framing: Camera,
    /// Warnings met while reading the inputs, for the caller to print.
    pub warnings: Vec<String>,
}

/// A camera as the page handles it: eye, look-at target and vertical field of view.
#[derive(Debug, Clone, Serialize)]
pub struct ViewCam {
    pub eye: [f32; 3],
    pub target: [f32; 3],
    pub fov_deg: f64,
    pub width: usize,
    pub height: usize,
}

impl Scene {
    /// Read `data` and `motion` for `avatar`. A directory as `data` means its `train.npz`.
    pub fn load(
        avatar: &Avatar,
        data: Option<&Path>,
        motion: Option<&Path>,
        scale: RootScale,
    ) -> Result<Scene, ViewError> {
        let mut warnings = Vec::new();
        let data = match data {
            Some(path) => {
                let (file, _) = resolve_split(path, "train")?;
                let ds = read_dataset(&file, Profile::Render)?;
                warnings.extend(
                    ds.warnings
                        .iter()
                        .map(|w| format!("{}: {w}", file.display())),
                );
                Some(ds)
            }
            None => None,
        };
        let (set, head) = match (motion, &data) {
            (Some(path), _) => {
                let (clip, ds) = read_motion(avatar, path)?;
                warnings.extend(
                    ds.warnings
                        .iter()
                        .map(|w| format!("{}: {w}", path.display())),
                );
                let out = retarget(&clip, avatar.rest_pose(), scale)?;
                (PoseSet::Motion(out.frames), HeadDir::NegY)
            }
            (None, Some(ds)) => (PoseSet::Dataset, ds.head()?),
            (None, None) => (PoseSet::Rest, HeadDir::NegY),
        };
        let cameras = match &data {
            Some(ds) => (0..ds.n_cameras())
                .map(|c| ds.camera(c))
                .collect::<Result<Vec<_>, _>>()?,
            None => Vec::new(),
        };
        let mut images = HashMap::new();
        if let (PoseSet::Dataset, Some(ds)) = (&set, &data) {
            for n in 0..ds.n_images() {
                if ds.image(n).is_some() && ds.mask(n).is_some() {
                    images
                        .entry((ds.pose_row(n)?, ds.camera_row(n)?))
                        .or_insert(n);
                }
            }
        }
        if pose_count(&set, data.as_ref()) == 0 {
            return Err(ViewError::Input("the dataset holds no poses".into()));
        }
        let (_, kp3d) = pose_of(&set, data.as_ref(), 0, avatar)?;
        let (w, h) = DEFAULT_SIZE;
        let bones = match (&set, &data) {
            (PoseSet::Dataset, Some(ds)) => ds.pose_bones(0),
            (PoseSet::Motion(f), _) => f[0].bones,
            _ => REST_BONES,
        };
        let framing = framing_camera(&kp3d, head, facing(&bones), w, h)?;
        Ok(Scene {
            set,
            data,
            cameras,
            images,
            head,
            framing,
            warnings,
        })
    }

    /// Poses on the slider.
    pub fn pose_count(&self) -> usize {
        pose_count(&self.set, self.data.as_ref())
    }

    /// What the slider runs over: `dataset`, `motion` or `rest`.
    pub fn pose_kind(&self) -> &'static str {
        match self.set {
            PoseSet::Dataset => "dataset",
            PoseSet::Motion(_) => "motion",
            PoseSet::Rest => "rest",
        }
    }

    /// Pose `i` (< [`Self::pose_count`]) as model input on the avatar's device.
    pub fn pose(&self, i: usize, avatar: &Avatar) -> Result<PoseItem, ViewError> {
        if i >= self.pose_count() {
            return Err(ViewError::Input(format!(
                "pose {i} is past the {} pose(s)",
                self.pose_count()
            )));
        }
        let (poses, kp3d) = pose_of(&self.set, self.data.as_ref(), i, avatar)?;
        Ok(PoseItem { poses, kp3d })
    }

    pub fn head(&self) -> HeadDir {
        self.head
    }

    /// Dataset camera `c` at the dataset's image size.
    pub fn camera(&self, c: usize) -> Option<&Camera> {
        self.cameras.get(c)
    }

    /// The size a view starts at: the dataset's images', or [`DEFAULT_SIZE`].
    pub fn default_size(&self) -> (usize, usize) {
        self.cameras
            .first()
            .map_or(DEFAULT_SIZE, |c| (c.width, c.height))
    }

    /// (pose row, camera row, image) of every image with ground truth.
    pub fn images(&self) -> Vec<[usize; 3]> {
        let mut v: Vec<[usize; 3]> = self.images.iter().map(|(&(p, c), &n)| [p, c, n]).collect();
        v.sort_unstable();
        v
    }

    pub fn camera_count(&self) -> usize {
        self.cameras.len()
    }

    /// The dataset image of pose `p` seen by camera `c`, if the file holds it (with a mask).
    pub fn image_of(&self, p: usize, c: usize) -> Option<usize> {
        self.images.get(&(p, c)).copied()
    }

    /// Ground truth of image `n` on black, its mask and its size (h, w).
    pub fn ground_truth(&self, n: usize) -> Result<(Vec<f32>, Vec<u8>, usize, usize), ViewError> {
        let ds = self
            .data
            .as_ref()
            .ok_or_else(|| ViewError::Input("no dataset".into()))?;
        let (gt, mask) = ground_truth(ds, n)?;
        Ok((gt, mask, ds.height(), ds.width()))
    }

    /// Images of the dataset (0 without one).
    pub fn image_count(&self) -> usize {
        self.data.as_ref().map_or(0, |ds| ds.n_images())
    }

    /// Whether `n` is an image with ground truth.
    pub fn has_image(&self, n: usize) -> bool {
        self.images.values().any(|&m| m == n)
    }

    /// Centre of the body's render cylinder: the point the camera turns about.
    pub fn centre(&self, kp3d: &Joints) -> [f32; 3] {
        let c = cylinder_from_joints(kp3d, &CylinderParams::render(self.head));
        [c[0], 0.5 * (c[3] + c[4]), c[1]]
    }

    /// Each dataset camera as eye, target (on its optical axis, as far as the first pose's
    /// centre) and field of view; without dataset cameras, the framing camera.
    pub fn view_cams(&self, avatar: &Avatar) -> Result<(Vec<ViewCam>, ViewCam), ViewError> {
        let centre = self.centre(&self.pose(0, avatar)?.kp3d);
        let cams = self
            .cameras
            .iter()
            .map(|c| view_cam(c, centre))
            .collect::<Vec<_>>();
        let start = cams
            .first()
            .cloned()
            .unwrap_or_else(|| view_cam(&self.framing, centre));
        Ok((cams, start))
    }
}

/// The rest pose's joint rotations (all zero).
const REST_BONES: Joints = [[0.0; 3]; 24];

fn pose_count(set: &PoseSet, data: Option<&Dataset>) -> usize {
    match (set, data) {
        (PoseSet::Dataset, Some(ds)) => ds.n_poses(),
        (PoseSet::Motion(f), _) => f.len(),
        _ => 1,
    }
}

fn pose_of(
    set: &PoseSet,
    data: Option<&Dataset>,
    i: usize,
    avatar: &Avatar,
) -> Result<(Poses, Joints), ViewError> {
    Ok(match (set, data) {
        (PoseSet::Dataset, Some(ds)) => dataset_pose(ds, i, avatar.device())?,
        (PoseSet::Motion(f), _) => avatar.pose_from_bones(&f[i].bones, f[i].root)?,
        _ => avatar.pose_from_bones(&REST_BONES, [0.0; 3])?,
    })
}

/// `cam` as eye, target and field of view; the target is where the optical axis passes
/// closest to `centre`.
fn view_cam(cam: &Camera, centre: [f32; 3]) -> ViewCam {
    let eye = cam.origin();
    // OpenGL axes: the camera looks along its −z, the third column of c2w.
    let fwd = [-cam.c2w[0][2], -cam.c2w[1][2], -cam.c2w[2][2]];
    let along: f32 = (0..3).map(|k| (centre[k] - eye[k]) * fwd[k]).sum();
    let d = along.max(0.1);
    ViewCam {
        eye,
        target: [0, 1, 2].map(|k| eye[k] + d * fwd[k]),
        fov_deg: if cam.fy > 0.0 {
            2.0 * (0.5 * cam.height as f64 / cam.fy as f64)
                .atan()
                .to_degrees()
        } else {
            FRAMING_FOV_DEG
        },
        width: cam.width,
        height: cam.height,
    }
}
