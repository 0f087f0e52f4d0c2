//! Refreshing an occupancy grid ([`crate::network::occupancy`]) from the density of the
//! network: per chosen cell of each joint, one random point in the cell (in x̄), mapped to
//! the world by a pose's bone frame, evaluated without density noise.
//!
//! [`refresh_with`] takes the density as a function (tests give it a known body);
//! [`refresh`] evaluates the avatar's network. Training calls it every
//! `refresh_every` steps on the poses of the step's batch; `pma occupancy build` on the
//! training poses of a dataset ([`build`]).

use std::sync::atomic::{AtomicUsize, Ordering};

use candle_core::{DType, Tensor};
use pma_data::skeleton::N_JOINTS;
use rand::Rng;

use crate::compute::host::host_f32;
use crate::error::{ModelError, Result};
use crate::network::occupancy::OccupancyGrid;
use crate::network::{Network, PoseFeatures};
use crate::render::batch::Poses;
use crate::render::bones::BoneFrames;
use crate::render::cull::{JointMask, WindowTest, EXACT_ZERO_EXPONENT};
use crate::render::points::joints::{call_joints, chain_key, joint_calls};

/// Points per network call of a refresh on the CPU's workers: small enough that a training
/// refresh (a few hundred points per pose) gives every worker calls, large enough that a
/// call's fixed cost is small against its points (a full build evaluates hundreds of
/// thousands). A GPU takes the inference pass's calls, as large as its memory allows.
const REFRESH_POINT_CHUNK: usize = 512;

/// Which cells of each joint a refresh evaluates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CellChoice {
    /// Every cell where the joint's window can be non-zero.
    All,
    /// This share of those cells: half drawn uniformly, half among the occupied ones
    /// (nerfacc's rule, so that occupied cells are revisited, and can empty, more often).
    Share(f64),
}

/// How a refresh writes the grid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RefreshOptions {
    pub cells: CellChoice,
    /// Decay every cell's value before taking the maxima (training: Instant-NGP's rule, so
    /// that a cell no sample finds dense again empties); without it a cell keeps the largest
    /// density of every refresh (building a grid for a trained model).
    pub decay: bool,
}

/// What a refresh did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RefreshStats {
    /// Cells evaluated (network points).
    pub cells: usize,
    /// Share of all cells occupied afterwards.
    pub occupied_fraction: f64,
    /// Σ over the network calls of points × joints carried (24 per point without joint
    /// grouping; 0 when the density was not the network's).
    pub joint_rows: usize,
}

/// Cells of a joint's grid where its window can be non-zero in f32 (α·Σ x̄_k^β below the
/// exact-zero cut at the cell's point nearest the box centre): the cells a sample's joint
/// can ever be tested against.
pub fn eligible_cells(grid: &OccupancyGrid, alpha: f64, beta: u32) -> Vec<usize> {
    let w = grid.cell_size();
    let r = grid.config().resolution;
    // The test is a sum of one term per axis, and a term depends on the cell's index along
    // its axis only: r terms, each summed as the per-cell sum did (x, then y, then z).
    let term: Vec<f64> = (0..r)
        .map(|i| {
            let a = grid.cell_corner(i)[0];
            let b = a + w;
            let m = if a <= 0.0 && b >= 0.0 {
                0.0
            } else {
                a.abs().min(b.abs())
            };
            m.powi(beta as i32)
        })
        .collect();
    (0..grid.config().cells_per_joint())
        .filter(|&c| {
            let sum = 0.0 + term[c % r] + term[(c / r) % r] + term[c / (r * r)];
            alpha * sum < EXACT_ZERO_EXPONENT
        })
        .collect()
}

/// One joint's map x̄ → world: (M⁻¹, t, s) of `x = M⁻¹ (s ⊙ x̄ − t)`.
type InverseMap = ([[f64; 3]; 3], [f64; 3], [f64; 3]);

/// The affine maps x̄ → world of every pose and joint, for the box map `x̂ = M x + t`:
/// [P·24].
struct FrameInverse {
    maps: Vec<InverseMap>,
}

impl FrameInverse {
    fn new(frames: &BoneFrames, scales: &[f32]) -> Result<Self> {
        let mut maps = Vec::with_capacity(frames.n_poses() * N_JOINTS);
        for p in 0..frames.n_poses() {
            for j in 0..N_JOINTS {
                let m = frames.world_to_box_f64(p, j);
                let a: [[f64; 3]; 3] = std::array::from_fn(|r| [m[r][0], m[r][1], m[r][2]]);
                let inv = invert3(&a).ok_or_else(|| {
                    ModelError::Input(format!(
                        "occupancy: the box frame of joint {j}, pose {p} is singular"
                    ))
                })?;
                let s = std::array::from_fn(|k| scales[3 * j + k] as f64);
                maps.push((inv, [m[0][3], m[1][3], m[2][3]], s));
            }
        }
        Ok(Self { maps })
    }

    fn world(&self, p: usize, j: usize, x_bar: [f64; 3]) -> [f32; 3] {
        let (inv, t, s) = &self.maps[p * N_JOINTS + j];
        let v: [f64; 3] = std::array::from_fn(|k| s[k] * x_bar[k] - t[k]);
        std::array::from_fn(|r| (inv[r][0] * v[0] + inv[r][1] * v[1] + inv[r][2] * v[2]) as f32)
    }
}

fn invert3(a: &[[f64; 3]; 3]) -> Option<[[f64; 3]; 3]> {
    let c = |r: usize, k: usize| {
        let (r1, r2) = ((r + 1) % 3, (r + 2) % 3);
        let (k1, k2) = ((k + 1) % 3, (k + 2) % 3);
        a[r1][k1] * a[r2][k2] - a[r1][k2] * a[r2][k1]
    };
    let det = a[0][0] * c(0, 0) + a[0][1] * c(0, 1) + a[0][2] * c(0, 2);
    if !(det.is_finite() && det.abs() > 1e-12) {
        return None;
    }
    // inverse[k][r] = cofactor(r, k) / det
    Some(std::array::from_fn(|k| {
        std::array::from_fn(|r| c(r, k) / det)
    }))
}

/// One refresh of `grid` for the poses of `frames` (host bone frames, [P]) with box
/// half-extents `scales` [24·3]: the cells `opts` chooses, each for one pose drawn at random,
/// at a random point inside the cell; `density(points)` takes the world points of every pose
/// (`points[p]` for pose p) and returns relu(σ) at each, in the same layout.
#[allow(clippy::too_many_arguments)]
pub fn refresh_with<R: Rng>(
    grid: &mut OccupancyGrid,
    frames: &BoneFrames,
    scales: &[f32],
    alpha: f64,
    beta: u32,
    opts: RefreshOptions,
    rng: &mut R,
    mut density: impl FnMut(&[Vec<[f32; 3]>]) -> Result<Vec<Vec<f32>>>,
) -> Result<RefreshStats> {
    let n_poses = frames.n_poses();
    let inv = FrameInverse::new(frames, scales)?;
    let eligible = eligible_cells(grid, alpha, beta);
    let w = grid.cell_size();
    // Per pose: (joint, cell) and its world point.
    let mut jobs: Vec<Vec<(usize, usize)>> = vec![Vec::new(); n_poses];
    let mut points: Vec<Vec<[f32; 3]>> = vec![Vec::new(); n_poses];
    for j in 0..N_JOINTS {
        let cells: Vec<usize> = match opts.cells {
            CellChoice::All => eligible.clone(),
            CellChoice::Share(share) => {
                let n = ((eligible.len() as f64 * share).ceil() as usize).max(1);
                let occ = grid.joint_occupied(j);
                let occupied: Vec<usize> = eligible.iter().copied().filter(|&c| occ[c]).collect();
                let mut v: Vec<usize> = (0..n.div_ceil(2))
                    .map(|_| eligible[rng.gen_range(0..eligible.len())])
                    .collect();
                if !occupied.is_empty() {
                    v.extend((0..n / 2).map(|_| occupied[rng.gen_range(0..occupied.len())]));
                }
                v
            }
        };
        for c in cells {
            let p = if n_poses > 1 {
                rng.gen_range(0..n_poses)
            } else {
                0
            };
            let lo = grid.cell_corner(c);
            let x_bar: [f64; 3] = std::array::from_fn(|k| lo[k] + w * rng.gen::<f64>());
            jobs[p].push((j, c));
            points[p].push(inv.world(p, j, x_bar));
        }
    }
    if opts.decay {
        grid.decay_all();
    }
    let sigmas = density(&points)?;
    if sigmas.len() != n_poses {
        return Err(ModelError::shape(
            "occupancy densities (poses)",
            [n_poses],
            [sigmas.len()],
        ));
    }
    let mut cells = 0;
    for ((job, pts), sigma) in jobs.iter().zip(&points).zip(&sigmas) {
        if sigma.len() != pts.len() {
            return Err(ModelError::shape(
                "occupancy densities",
                [pts.len()],
                [sigma.len()],
            ));
        }
        for (&(j, c), &s) in job.iter().zip(sigma) {
            grid.update_max(j, c, s)?;
        }
        cells += job.len();
    }
    grid.finish_refresh();
    Ok(RefreshStats {
        cells,
        occupied_fraction: grid.occupied_fraction(),
        joint_rows: 0,
    })
}

/// [`refresh_with`] on the network's density relu(σ) (no noise) for `poses`, whose pose
/// features are `pose` (they are detached here; a training step's may be passed as is).
pub fn refresh<R: Rng>(
    net: &Network,
    grid: &mut OccupancyGrid,
    poses: &Poses,
    pose: &PoseFeatures,
    opts: RefreshOptions,
    rng: &mut R,
) -> Result<RefreshStats> {
    let cfg = net.config();
    let pose = PoseFeatures {
        g: pose.g.detach(),
        skts: pose.skts.detach(),
        scales: pose.scales.detach(),
    };
    let skts = host_f32(&poses.skts)?;
    let frames = BoneFrames::new(net.bone_align(), &skts)?;
    let scales = host_f32(&pose.scales)?;
    let dev = net.device().clone();
    let cpu_plan = dev.is_cpu() && !crate::compute::account::emulates_cuda();
    let part = match cpu_plan {
        true => REFRESH_POINT_CHUNK,
        false => crate::render::points::inference_point_chunk(&dev, cfg),
    };
    // On the CPU a part's points are sorted by the joints whose window is not exactly 0 at
    // them and evaluated in calls that carry only those (the render's joint grouping): a
    // cell's point lies in its joint's box, where a few of the 24 windows are non-zero.
    let joint_test = match cpu_plan {
        true => Some(WindowTest::new(
            net.bone_align(),
            &skts,
            &scales,
            cfg.window_alpha,
            cfg.window_beta,
            0.0,
        )?),
        false => None,
    };
    let joint_rows = AtomicUsize::new(0);
    let density = |points: &[Vec<[f32; 3]>]| -> Result<Vec<Vec<f32>>> {
        // Every pose's points in parts of a size fixed per device, all parts on the workers
        // at once: a training refresh holds a few hundred points per pose, which would
        // otherwise leave the other workers idle. The parts do not depend on the worker count.
        let parts: Vec<(usize, std::ops::Range<usize>)> = points
            .iter()
            .enumerate()
            .flat_map(|(p, pts)| {
                (0..pts.len())
                    .step_by(part)
                    .map(move |a| (p, a..(a + part).min(pts.len())))
            })
            .collect();
        let workers = crate::compute::parallel::workers_on(&dev);
        let sigma_at = |p: usize, pts: &[[f32; 3]], joints: Option<&[u32]>| -> Result<Vec<f32>> {
            let t = Tensor::from_vec(
                pts.iter().flatten().copied().collect::<Vec<f32>>(),
                (pts.len(), 3),
                &dev,
            )?
            .to_dtype(net.dtype())?;
            let sigma = net.eval_density_joints(&pose, p, &t, joints)?;
            Ok(sigma
                .relu()?
                .to_dtype(DType::F32)?
                .flatten_all()?
                .to_vec1::<f32>()?)
        };
        // No interruption check: training refreshes after its step is applied, and a step
        // is undone only before that (callers that loop over refreshes check between them).
        let outs = crate::compute::parallel::map_ordered(workers, parts.len(), |i| {
            let (p, range) = &parts[i];
            let part = &points[*p][range.clone()];
            let Some(test) = &joint_test else {
                joint_rows.fetch_add(part.len() * N_JOINTS, Ordering::Relaxed);
                return sigma_at(*p, part, None);
            };
            let masks: Vec<JointMask> = part.iter().map(|&x| test.point_joints(*p, x)).collect();
            let mut order: Vec<usize> = (0..part.len()).collect();
            order.sort_by_key(|&i| chain_key(masks[i]));
            let sorted: Vec<JointMask> = order.iter().map(|&i| masks[i]).collect();
            let mut out = vec![0f32; part.len()];
            for (start, len, union) in joint_calls(&sorted, part.len().max(1)) {
                let idx = &order[start..start + len];
                let joints = call_joints(union);
                let carried = joints.as_ref().map_or(N_JOINTS, Vec::len);
                joint_rows.fetch_add(len * carried, Ordering::Relaxed);
                let pts: Vec<[f32; 3]> = idx.iter().map(|&i| part[i]).collect();
                for (&i, s) in idx.iter().zip(sigma_at(*p, &pts, joints.as_deref())?) {
                    out[i] = s;
                }
            }
            Ok::<_, ModelError>(out)
        })?;
        let mut sigmas: Vec<Vec<f32>> =
            points.iter().map(|p| Vec::with_capacity(p.len())).collect();
        for ((p, _), out) in parts.iter().zip(outs) {
            sigmas[*p].extend(out);
        }
        Ok(sigmas)
    };
    let stats = refresh_with(
        grid,
        &frames,
        &scales,
        cfg.window_alpha,
        cfg.window_beta,
        opts,
        rng,
        density,
    )?;
    Ok(RefreshStats {
        joint_rows: joint_rows.into_inner(),
        ..stats
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::network::occupancy::OccupancyConfig;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn frames_at(offsets: &[f32]) -> BoneFrames {
        let mut eye = vec![0f32; N_JOINTS * 16];
        for j in 0..N_JOINTS {
            for d in 0..4 {
                eye[j * 16 + 5 * d] = 1.0;
            }
        }
        let mut skts = Vec::new();
        for &o in offsets {
            let mut m = eye.clone();
            for j in 0..N_JOINTS {
                m[j * 16 + 3] = -o; // world → joint: x − o
            }
            skts.extend(m);
        }
        BoneFrames::new(&eye, &skts).unwrap()
    }

    #[test]
    fn cells_map_back_to_their_world_points() {
        let frames = frames_at(&[0.5]);
        let scales = vec![0.25f32; N_JOINTS * 3];
        let inv = FrameInverse::new(&frames, &scales).unwrap();
        // x̄ = ((x − 0.5)/0.25, y/0.25, z/0.25).
        let x = inv.world(0, 3, [1.0, -2.0, 0.4]);
        assert!((x[0] - 0.75).abs() < 1e-6, "{x:?}");
        assert!(
            (x[1] + 0.5).abs() < 1e-6 && (x[2] - 0.1).abs() < 1e-6,
            "{x:?}"
        );
    }

    #[test]
    fn eligible_cells_are_where_the_window_can_be_non_zero() {
        let g = OccupancyGrid::new(OccupancyConfig::default()).unwrap();
        let e = eligible_cells(&g, 2.0, 6);
        let n = g.config().cells_per_joint();
        // The corners of [-2,2]³ are out of reach (2·3·(1.875)⁶ > 105), the centre is not.
        assert!(!e.contains(&0) && e.contains(&g.cell_of([0.0, 0.0, 0.0]).unwrap()));
        let share = e.len() as f64 / n as f64;
        assert!((0.7..0.99).contains(&share), "{share}");
    }

    /// A body that grows into cells a refresh found empty is found again by the next one.
    #[test]
    fn a_growing_body_is_found_after_the_next_refresh() {
        let frames = frames_at(&[0.0]);
        let scales = vec![0.2f32; N_JOINTS * 3];
        let cfg = OccupancyConfig {
            resolution: 16,
            ..Default::default()
        };
        let mut grid = OccupancyGrid::new(cfg).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        // A ball of density 10 of radius r around the world origin.
        let ball = |r: f32| {
            move |pts: &[Vec<[f32; 3]>]| -> Result<Vec<Vec<f32>>> {
                Ok(pts
                    .iter()
                    .map(|pose| {
                        pose.iter()
                            .map(|x| {
                                let d = (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt();
                                if d < r {
                                    10.0
                                } else {
                                    0.0
                                }
                            })
                            .collect()
                    })
                    .collect())
            }
        };
        // A refresh of `cells` of `grid` over a ball of radius r (window α 2, β 6).
        let mut refresh = |grid: &mut OccupancyGrid, cells: CellChoice, r: f32| {
            let opts = RefreshOptions { cells, decay: true };
            refresh_with(grid, &frames, &scales, 2.0, 6, opts, &mut rng, ball(r)).unwrap()
        };
        let s = refresh(&mut grid, CellChoice::All, 0.05);
        assert!(s.cells > 0 && s.occupied_fraction < 0.2, "{s:?}");
        // A point at 0.25 from the origin: empty for every joint now.
        let probe = [0.25f64, 0.0, 0.0];
        let x_bar = |j: usize| -> [f64; 3] {
            let m = frames.world_to_box_f64(0, j);
            std::array::from_fn(|r| {
                (m[r][0] * probe[0] + m[r][1] * probe[1] + m[r][2] * probe[2] + m[r][3]) / 0.2
            })
        };
        assert!((0..N_JOINTS).all(|j| !grid.occupied(j, x_bar(j))));
        // The body grows to radius 0.4: refreshes that evaluate a share of the cells find
        // the probe's cells again (they revisit every cell at random), a full one at once.
        let mut found = false;
        for _ in 0..40 {
            refresh(&mut grid, CellChoice::Share(0.25), 0.4);
            if (0..N_JOINTS).all(|j| grid.occupied(j, x_bar(j))) {
                found = true;
                break;
            }
        }
        assert!(found, "the grown body was not found");
        let mut fresh = OccupancyGrid::new(grid.config().clone()).unwrap();
        refresh(&mut fresh, CellChoice::All, 0.05);
        assert!((0..N_JOINTS).all(|j| !fresh.occupied(j, x_bar(j))));
        refresh(&mut fresh, CellChoice::All, 0.4);
        assert!((0..N_JOINTS).all(|j| fresh.occupied(j, x_bar(j))));
    }
}
