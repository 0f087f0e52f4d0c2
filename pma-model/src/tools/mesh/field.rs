//! A trained avatar as a density/radiance field for mesh extraction.

use std::sync::atomic::{AtomicUsize, Ordering};

use candle_core::{DType, Device, Tensor};
use pma_data::skeleton::N_JOINTS;

use crate::compute::host::host_f32;
use crate::error::{ModelError, Result};
use crate::render::avatar::{Avatar, PoseFeatures, Poses};
use crate::render::cull::{SampleFate, WindowTest};
use crate::render::points::INFERENCE_POINT_CHUNK;

/// One part's box in world space: `x_aligned = rot·x + trans`, inside iff every
/// `|x_aligned[k]| <= half[k]`.
#[derive(Debug, Clone, Copy)]
struct PartBox {
    rot: [[f32; 3]; 3],
    trans: [f32; 3],
    half: [f32; 3],
}

impl PartBox {
    fn contains(&self, p: &[f32; 3]) -> bool {
        (0..3).all(|r| {
            let x = self.rot[r][0] * p[0]
                + self.rot[r][1] * p[1]
                + self.rot[r][2] * p[2]
                + self.trans[r];
            x.abs() <= self.half[r]
        })
    }
}

/// Density and radiance of a trained avatar in one pose, queried at arbitrary world points
/// (eval mode: no density noise, the mean frame code).
///
/// Points outside every part box (the enlarged bone-aligned boxes the ray caster samples in,
/// docs/conventions.md, "Ray sampler") get density 0 unless [`AvatarField::mask_outside_boxes`] is off: the
/// network was never asked about those regions while training, and its output there is
/// whatever the untrained constant branch says (floaters).
///
/// With [`AvatarField::skip_empty_cells`], points that the avatar's occupancy grid marks
/// empty for every joint whose window reaches them get density 0 without the network, as a
/// render with `--occupancy` leaves them out.
pub struct AvatarField<'a> {
    avatar: &'a Avatar,
    pose: PoseFeatures,
    /// World → root rotation (rotation part of `skts[0]`), row-major.
    root_rot: [[f32; 3]; 3],
    boxes: Vec<PartBox>,
    pub mask_outside_boxes: bool,
    /// Points per network call.
    pub chunk: usize,
    /// The window test of the pose, when empty cells are skipped.
    empty_cells: Option<WindowTest>,
    /// Density points so far that ran the network, and that the grid left out.
    evaluated: AtomicUsize,
    skipped_empty: AtomicUsize,
}

impl<'a> AvatarField<'a> {
    /// The field of `avatar` in the single pose of `poses`.
    pub fn new(avatar: &'a Avatar, poses: &Poses) -> Result<Self> {
        if poses.bones.len() != 1 {
            return Err(ModelError::Input(format!(
                "AvatarField takes one pose, found {}",
                poses.bones.len()
            )));
        }
        let pose = avatar.pose_features(poses, None)?;
        let cfg = avatar.config();
        let frames = avatar.bone_frames(&poses.skts)?;
        let scales = host_f32(&pose.scales)?;
        let boxes = (0..N_JOINTS)
            .map(|j| {
                let m = frames.world_to_box_f64(0, j);
                let rot = std::array::from_fn(|r| std::array::from_fn(|c| m[r][c] as f32));
                let trans = std::array::from_fn(|r| m[r][3] as f32);
                let half = std::array::from_fn(|k| scales[3 * j + k] * cfg.box_bound as f32);
                PartBox { rot, trans, half }
            })
            .collect();
        let root = frames.skt(0, 0);
        let root_rot = std::array::from_fn(|r| std::array::from_fn(|c| root[r * 4 + c]));
        Ok(Self {
            avatar,
            pose,
            root_rot,
            boxes,
            mask_outside_boxes: true,
            chunk: INFERENCE_POINT_CHUNK,
            empty_cells: None,
            evaluated: AtomicUsize::new(0),
            skipped_empty: AtomicUsize::new(0),
        })
    }

    /// The same field with density 0 in the cells the avatar's occupancy grid marks empty
    /// (see the type's docs); an avatar without a grid is refused.
    pub fn skip_empty_cells(mut self, poses: &Poses) -> Result<Self> {
        if self.avatar.occupancy().is_none() {
            return Err(ModelError::Input(
                "occupancy: the model has no occupancy grid (train with `--occupancy` or build \
                 one with `pma occupancy build`)"
                    .into(),
            ));
        }
        let cfg = self.avatar.config();
        self.empty_cells = Some(WindowTest::new(
            self.avatar.bone_align(),
            &host_f32(&poses.skts)?,
            &host_f32(&self.pose.scales)?,
            cfg.window_alpha,
            cfg.window_beta,
            0.0,
        )?);
        Ok(self)
    }

    /// World-space bounds of the union of the part boxes.
    pub fn bounds(&self) -> ([f32; 3], [f32; 3]) {
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        for b in &self.boxes {
            for corner in 0..8 {
                let xa: [f32; 3] = std::array::from_fn(|k| {
                    if corner >> k & 1 == 1 {
                        b.half[k]
                    } else {
                        -b.half[k]
                    }
                });
                // x = rotᵀ·(x_aligned − trans); rot is orthonormal.
                let d: [f32; 3] = std::array::from_fn(|k| xa[k] - b.trans[k]);
                for c in 0..3 {
                    let x = (0..3).map(|r| b.rot[r][c] * d[r]).sum::<f32>();
                    lo[c] = lo[c].min(x);
                    hi[c] = hi[c].max(x);
                }
            }
        }
        (lo, hi)
    }

    fn device(&self) -> &Device {
        self.avatar.device()
    }

    /// View features for world directions (the mean frame code).
    fn view(&self, dirs: &[[f32; 3]]) -> Result<Tensor> {
        let d: Vec<f32> = dirs
            .iter()
            .flat_map(|d| {
                let r: [f32; 3] = std::array::from_fn(|i| {
                    (0..3).map(|k| self.root_rot[i][k] * d[k]).sum::<f32>()
                });
                r
            })
            .collect();
        let d = Tensor::from_vec(d, (dirs.len(), 3), self.device())?;
        self.avatar
            .network()
            .view_features(&d, &vec![-1; dirs.len()], false)
    }

    /// (rgb, density) of the network at `pts` seen along `dirs`, in chunks on the CPU
    /// workers (each chunk's values are its own, so the result does not depend on them).
    fn query(&self, pts: &[[f32; 3]], dirs: &[[f32; 3]]) -> Result<(Vec<[f32; 3]>, Vec<f32>)> {
        let chunk = self.chunk.max(1);
        let n = pts.len().div_ceil(chunk);
        let workers = crate::compute::parallel::workers_on(self.device());
        let outs = crate::compute::parallel::map_ordered(workers, n, |i| {
            crate::interrupt::check()?;
            let p = &pts[i * chunk..((i + 1) * chunk).min(pts.len())];
            let d = &dirs[i * chunk..((i + 1) * chunk).min(dirs.len())];
            let t = Tensor::from_vec(
                p.iter().flatten().copied().collect::<Vec<f32>>(),
                (p.len(), 3),
                self.device(),
            )?;
            let (c, s) =
                self.avatar
                    .network()
                    .eval_points(&self.pose, 0, &t, &self.view(d)?, None)?;
            let c = c.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
            let s = s
                .relu()?
                .to_dtype(DType::F32)?
                .flatten_all()?
                .to_vec1::<f32>()?;
            Ok::<_, ModelError>((c, s))
        })?;
        let mut rgb = Vec::with_capacity(pts.len());
        let mut sigma = Vec::with_capacity(pts.len());
        for (c, s) in outs {
            rgb.extend(c.chunks_exact(3).map(|x| [x[0], x[1], x[2]]));
            sigma.extend(s);
        }
        Ok((rgb, sigma))
    }

    fn in_any_box(&self, p: &[f32; 3]) -> bool {
        self.boxes.iter().any(|b| b.contains(p))
    }

    /// Whether the occupancy grid leaves `p` out (only with [`Self::skip_empty_cells`]).
    fn in_empty_cell(&self, p: &[f32; 3]) -> bool {
        match (&self.empty_cells, self.avatar.occupancy()) {
            (Some(test), Some(grid)) => test.fate(0, *p, Some(grid)) == SampleFate::Empty,
            _ => false,
        }
    }

    /// Density points [`Self::density`] has sent through the network so far, and those the
    /// occupancy grid left out (points outside the boxes, when masked, count in neither).
    pub fn density_counts(&self) -> (usize, usize) {
        (
            self.evaluated.load(Ordering::Relaxed),
            self.skipped_empty.load(Ordering::Relaxed),
        )
    }

    /// Density `relu(σ)` at `pts` (no noise).
    pub fn density(&self, pts: &[[f32; 3]]) -> Result<Vec<f32>> {
        let in_boxes: Vec<usize> = (0..pts.len())
            .filter(|&i| !self.mask_outside_boxes || self.in_any_box(&pts[i]))
            .collect();
        let keep: Vec<usize> = in_boxes
            .iter()
            .copied()
            .filter(|&i| !self.in_empty_cell(&pts[i]))
            .collect();
        self.evaluated.fetch_add(keep.len(), Ordering::Relaxed);
        self.skipped_empty
            .fetch_add(in_boxes.len() - keep.len(), Ordering::Relaxed);
        let mut out = vec![0f32; pts.len()];
        if keep.is_empty() {
            return Ok(out);
        }
        let sel: Vec<[f32; 3]> = keep.iter().map(|&i| pts[i]).collect();
        // The density does not depend on the view; any direction will do.
        let dirs = vec![[0.0, 0.0, 1.0]; sel.len()];
        let (_, s) = self.query(&sel, &dirs)?;
        for (&i, v) in keep.iter().zip(s) {
            out[i] = v;
        }
        Ok(out)
    }

    /// Radiance at `pts` seen along the world directions `dirs`.
    pub fn radiance(&self, pts: &[[f32; 3]], dirs: &[[f32; 3]]) -> Result<Vec<[f32; 3]>> {
        Ok(self.query(pts, dirs)?.0)
    }
}
