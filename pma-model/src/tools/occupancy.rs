//! Building an occupancy grid ([`crate::network::occupancy`]) for a model trained without
//! one (`pma occupancy build`): every cell where a joint's window can be non-zero is
//! evaluated once per chosen training pose, and keeps the largest density relu(σ) (no noise)
//! seen over those poses — no decay, since the weights do not change between poses.

use pma_data::dataset::Dataset;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::eval::{dataset_pose, spread, EvalError, Result};
use crate::network::occupancy::{OccupancyConfig, OccupancyGrid};
use crate::render::avatar::Avatar;
use crate::render::occupancy::{CellChoice, RefreshOptions};

/// What [`build`] does.
#[derive(Debug, Clone, PartialEq)]
pub struct BuildOptions {
    /// Layout and threshold of the grid (the schedule fields are saved, unused here).
    pub config: OccupancyConfig,
    /// Pose rows of the dataset to evaluate, spread evenly over them (0: every pose).
    pub poses: usize,
    /// Seed of the random point inside each cell.
    pub seed: u64,
}

impl Default for BuildOptions {
    fn default() -> Self {
        Self {
            config: OccupancyConfig::default(),
            poses: 16,
            seed: 0,
        }
    }
}

/// What [`build`] did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BuildStats {
    /// Pose rows evaluated.
    pub poses: usize,
    /// Network points (cells × poses).
    pub points: usize,
    /// Share of all cells marked occupied.
    pub occupied_fraction: f64,
}

/// `avatar` with a grid built from the poses of `data` (any grid it had is replaced);
/// `progress(done, total)` after each pose. The network is not changed.
pub fn build(
    avatar: Avatar,
    data: &Dataset,
    opts: &BuildOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<(Avatar, BuildStats)> {
    let rows: Vec<usize> = (0..data.n_poses()).collect();
    let rows = match opts.poses {
        0 => rows,
        n => spread(&rows, n),
    };
    if rows.is_empty() {
        return Err(EvalError::Incomplete {
            source_name: data.source.clone(),
            what: "no pose rows to build an occupancy grid from".into(),
        });
    }
    let grid = OccupancyGrid::new(opts.config.clone())?;
    let mut avatar = avatar.with_occupancy(Some(grid));
    let mut rng = ChaCha8Rng::seed_from_u64(opts.seed);
    let refresh = RefreshOptions {
        cells: CellChoice::All,
        decay: false,
    };
    let device = avatar.device().clone();
    let mut points = 0;
    let mut occupied_fraction = 1.0;
    for (k, &p) in rows.iter().enumerate() {
        crate::interrupt::check()?;
        let (poses, _) = dataset_pose(data, p, &device)?;
        let pose = avatar.pose_features(&poses, None)?;
        let s = avatar.refresh_occupancy(&poses, &pose, refresh, &mut rng)?;
        points += s.cells;
        occupied_fraction = s.occupied_fraction;
        progress(k + 1, rows.len());
    }
    Ok((
        avatar,
        BuildStats {
            poses: rows.len(),
            points,
            occupied_fraction,
        },
    ))
}
