//! The occupancy grid only leaves work out: without the option every output is bit for bit
//! what it is without a grid; a grid with every cell occupied changes nothing; a checkpoint
//! with a grid round-trips and, stripped of it, is byte for byte the parity checkpoint; bad
//! grid tensors are refused; a model trained with the grid renders without it exactly as
//! its tensors do.

use std::collections::HashMap;

use crate::common::*;
use crate::culling::{assert_close, assert_identical, FAR_CALL_TOLERANCE};
use candle_core::{Device, Tensor};
use pma_model::error::ModelError;
use pma_model::network::checkpoint::{self, OCCUPANCY_KEY, OCCUPANCY_TENSOR};
use pma_model::network::occupancy::{OccupancyConfig, OccupancyGrid};
use pma_model::render::avatar::{Avatar, Outputs};
use pma_model::render::{Culling, PassOptions, SampleFill};

/// A grid of resolution 16 where about `share` of each joint's cells hold density 1
/// (a fixed pseudo-random pattern), the rest 0; no dilation.
fn patterned_grid(share: f32) -> OccupancyGrid {
    let cfg = OccupancyConfig {
        resolution: 16,
        dilation: 0,
        ..Default::default()
    };
    let mut grid = OccupancyGrid::new(cfg).unwrap();
    let mut state = 7u64;
    for j in 0..24 {
        for c in 0..16 * 16 * 16 {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let u = (state >> 40) as f32 / (1u64 << 24) as f32;
            grid.update_max(j, c, if u < share { 1.0 } else { 0.0 })
                .unwrap();
        }
    }
    grid.finish_refresh();
    grid
}

fn with_grid(case: GoldenCase, grid: Option<OccupancyGrid>) -> GoldenCase {
    GoldenCase {
        avatar: case.avatar.with_occupancy(grid),
        ..case
    }
}

fn occupancy_only() -> PassOptions {
    PassOptions {
        occupancy: true,
        ..PassOptions::parity()
    }
}

#[test]
fn without_the_option_a_grid_changes_no_output() {
    let plain = GoldenCase::load("golden/dense", true);
    let gridded = with_grid(
        GoldenCase::load("golden/dense", true),
        Some(patterned_grid(0.3)),
    );
    assert_identical(&plain.forward(None), &gridded.forward(None), "parity");
    let cull = PassOptions::culled(Culling {
        rays: true,
        sample_threshold: Some(0.0),
        sample_fill: SampleFill::Network,
    });
    let (a, b) = (
        plain.forward_with(&cull, None),
        gridded.forward_with(&cull, None),
    );
    assert_identical(&a, &b, "culling without --occupancy");
    assert_eq!(a.stats, b.stats);
    assert_eq!(b.stats.skipped_empty, 0);

    // With the option the same grid does leave samples out (the test above is not vacuous).
    let on = gridded.forward_with(&occupancy_only(), None);
    println!("with the grid: {:?}", on.stats);
    assert!(on.stats.skipped_empty > 0, "{:?}", on.stats);
    assert!(
        on.stats.points_evaluated < a.stats.points_evaluated,
        "{:?} vs {:?}",
        on.stats,
        a.stats
    );
}

#[test]
fn a_grid_with_every_cell_occupied_is_parity() {
    let plain = GoldenCase::load("golden/dense", true);
    let parity = plain.forward(None);
    // The grid's test runs at threshold 0: with no cell empty the pass is culling at 0.
    let at_zero = plain.forward_with(
        &PassOptions::culled(Culling {
            rays: false,
            sample_threshold: Some(0.0),
            sample_fill: SampleFill::Network,
        }),
        None,
    );
    // Never refreshed (every cell counts as occupied), then refreshed with density
    // everywhere.
    let fresh = OccupancyGrid::new(OccupancyConfig::default()).unwrap();
    let full = patterned_grid(1.1);
    assert_eq!(full.occupied_fraction(), 1.0);
    let mut case = GoldenCase::load("golden/dense", true);
    for (what, grid) in [("unbuilt grid", fresh), ("full grid", full)] {
        case = with_grid(case, Some(grid));
        let out = case.forward_with(&occupancy_only(), None);
        assert_eq!(out.stats.skipped_empty, 0, "{what}");
        assert_identical(&at_zero, &out, what);
        let against = format!("{what} against parity");
        assert_close(&parity, &out, FAR_CALL_TOLERANCE, &against);
    }
}

/// A pass that feeds the grid (training's `grid_feed`) reports, for every sample it
/// evaluated, the cells it lies in with the density it found there; without probes it
/// leaves out what the plain grid pass leaves out and renders the same; probes run a share
/// of the samples the grid would leave out, and with every one probed the pass evaluates
/// what culling at the same threshold evaluates.
#[test]
fn a_feeding_pass_reports_what_it_saw_and_probes_empty_cells() {
    use pma_model::render::options::GridFeed;
    let case = with_grid(
        GoldenCase::load("golden/dense", true),
        Some(patterned_grid(0.3)),
    );
    let feeding = |share: f64| PassOptions {
        grid_feed: Some(GridFeed {
            probe_share: share,
            seed: 11,
        }),
        ..occupancy_only()
    };
    let plain = infer(&case, &occupancy_only()).unwrap();
    assert!(plain.observed.is_empty());
    assert!(plain.stats.skipped_empty > 0, "{:?}", plain.stats);

    let fed = infer(&case, &feeding(0.0)).unwrap();
    assert_identical(&plain, &fed, "feeding without probes");
    assert_eq!(plain.stats, fed.stats);
    let evaluated = (fed.stats.coarse_evaluated + fed.stats.fine_evaluated) as usize;
    // An evaluated sample has a joint above the threshold whose cell is occupied: at least
    // one observation each.
    assert!(
        fed.observed.len() >= evaluated,
        "{} < {evaluated}",
        fed.observed.len()
    );
    let cells = 16 * 16 * 16;
    let seen_sigma: std::collections::HashSet<u32> = flat(&fed.raw)
        .chunks(4)
        .chain(flat(&fed.raw_coarse).chunks(4))
        .map(|r| r[3].to_bits())
        .collect();
    for o in &fed.observed {
        assert!(
            (o.joint as usize) < 24 && (o.cell as usize) < cells,
            "{o:?}"
        );
        assert!(o.sigma.is_finite() && o.sigma >= 0.0, "{o:?}");
        assert!(
            seen_sigma.contains(&o.sigma.to_bits()),
            "observed density {} is no sample's relu(σ)",
            o.sigma
        );
    }
    assert!(fed.observed.iter().any(|o| o.sigma > 0.0));

    // Fed to the grid, every observed cell holds at least what was seen in it, and cells
    // whose value was below what a sample found rise.
    let before = case.avatar.occupancy().unwrap().clone();
    let mut avatar = Avatar::from_tensors(
        case.avatar.config().clone(),
        case.avatar.tensors(),
        &Device::Cpu,
    )
    .unwrap()
    .with_occupancy(Some(before.clone()));
    avatar.observe_occupancy(&fed.observed).unwrap();
    let after = avatar.occupancy().unwrap();
    let at = |g: &OccupancyGrid, o: &pma_model::render::avatar::GridObservation| {
        g.density()[o.joint as usize * cells + o.cell as usize]
    };
    assert!(fed.observed.iter().all(|o| at(after, o) >= o.sigma));
    assert!(fed
        .observed
        .iter()
        .any(|o| at(&before, o) < o.sigma && at(after, o) == o.sigma));
    let pairs = before.density().iter().zip(after.density());
    assert!(pairs.clone().all(|(a, b)| b >= a), "a fed cell went down");

    let half = infer(&case, &feeding(0.5)).unwrap();
    let left = half.stats.skipped_empty as f64 / plain.stats.skipped_empty as f64;
    assert!(
        (0.35..0.65).contains(&left),
        "probes at 0.5 left {left} of the skips"
    );
    assert!(half.observed.len() > fed.observed.len());

    let all = infer(&case, &feeding(1.0)).unwrap();
    assert_eq!(all.stats.skipped_empty, 0);
    let culled = infer(
        &case,
        &PassOptions::culled(Culling {
            rays: false,
            sample_threshold: Some(0.0),
            sample_fill: SampleFill::Network,
        }),
    )
    .unwrap();
    assert_eq!(all.stats.coarse_evaluated, culled.stats.coarse_evaluated);
    assert_eq!(all.stats.fine_evaluated, culled.stats.fine_evaluated);
    let d = max_abs_diff(&flat(&all.raw), &flat(&culled.raw));
    assert!(
        d <= 1e-5,
        "every empty sample probed differs from culling by {d}"
    );
}

#[test]
fn occupancy_without_a_grid_is_refused() {
    let case = GoldenCase::load("golden/dense", true);
    let mut mode = pma_model::render::avatar::Mode::Infer;
    let Err(err) = case
        .avatar
        .forward(&case.rays, &case.poses, &mut mode, &occupancy_only(), None)
    else {
        panic!("a pass with --occupancy on a model without a grid ran");
    };
    assert!(err.to_string().contains("no occupancy grid"), "{err}");
}

fn golden_avatar() -> Avatar {
    Avatar::load(fixtures().join("golden/model.safetensors"), &Device::Cpu).unwrap()
}

#[test]
fn a_checkpoint_with_a_grid_round_trips_and_without_it_is_the_parity_file() {
    let dir = tempfile::tempdir().unwrap();
    let (plain_path, grid_path) = (dir.path().join("plain.st"), dir.path().join("grid.st"));
    let grid = patterned_grid(0.4);
    golden_avatar().save(&plain_path).unwrap();
    let gridded = golden_avatar().with_occupancy(Some(grid.clone()));
    gridded.save(&grid_path).unwrap();

    let back = Avatar::load(&grid_path, &Device::Cpu).unwrap();
    assert_eq!(back.occupancy(), Some(&grid), "grid round trip");
    let (a, b) = (gridded.tensors(), back.tensors());
    assert_eq!(a.len(), b.len());
    for (name, t) in &a {
        assert_eq!(flat(t), flat(&b[name]), "{name}");
    }
    assert!(Avatar::load(&plain_path, &Device::Cpu)
        .unwrap()
        .occupancy()
        .is_none());

    // Stripped of its grid, the model saves to exactly the parity file.
    let stripped = dir.path().join("stripped.st");
    back.with_occupancy(None).save(&stripped).unwrap();
    let plain = std::fs::read(&plain_path).unwrap();
    assert_eq!(plain, std::fs::read(&stripped).unwrap());
    // The parity file holds neither part of the optional group.
    let (_, header) = safetensors::SafeTensors::read_metadata(&plain).unwrap();
    assert!(!header
        .metadata()
        .clone()
        .unwrap_or_default()
        .contains_key(OCCUPANCY_KEY));
    let st = safetensors::SafeTensors::deserialize(&plain).unwrap();
    assert!(st.names().iter().all(|n| *n != OCCUPANCY_TENSOR));
}

/// A copy of the checkpoint at `src` with its grid tensor replaced by `f32` values of
/// `shape` (`None`: without the tensor) and its grid metadata kept.
fn tampered(src: &std::path::Path, dst: &std::path::Path, grid: Option<(Vec<usize>, Vec<f32>)>) {
    let bytes = std::fs::read(src).unwrap();
    let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).unwrap();
    let meta: HashMap<String, String> = header.metadata().clone().unwrap();
    let st = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let mut views: Vec<(String, safetensors::tensor::TensorView<'_>)> = st
        .tensors()
        .into_iter()
        .filter(|(n, _)| n != OCCUPANCY_TENSOR)
        .collect();
    let data: Vec<u8>;
    if let Some((shape, values)) = grid {
        data = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        views.push((
            OCCUPANCY_TENSOR.to_string(),
            safetensors::tensor::TensorView::new(safetensors::Dtype::F32, shape, &data).unwrap(),
        ));
    }
    let out = safetensors::serialize(views, Some(meta)).unwrap();
    std::fs::write(dst, out).unwrap();
}

fn problems_of(path: &std::path::Path) -> Vec<String> {
    match checkpoint::load(path, &Device::Cpu) {
        Err(ModelError::Checkpoint { problems, .. }) => problems,
        Err(other) => panic!("expected a checkpoint error, got {other}"),
        Ok(_) => panic!("{} loaded", path.display()),
    }
}

#[test]
fn bad_grid_tensors_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("good.st");
    golden_avatar()
        .with_occupancy(Some(patterned_grid(0.4)))
        .save(&good)
        .unwrap();
    let n = 24 * 16 * 16 * 16;
    let bad = dir.path().join("bad.st");

    // Each tampered file is refused with a problem naming what is wrong.
    let refused = |grid: Option<(Vec<usize>, Vec<f32>)>, says: &[&str]| {
        tampered(&good, &bad, grid);
        let p = problems_of(&bad);
        assert!(
            p.iter().any(|l| says.iter().all(|s| l.contains(s))),
            "{says:?}: {p:#?}"
        );
    };
    let shape = vec![24, 16, 16, 16];
    refused(
        Some((vec![24, 16, 16, 8], vec![0.0; n / 2])),
        &[OCCUPANCY_TENSOR, "[24, 16, 16, 8]"],
    );
    let mut nan = vec![0.0; n];
    nan[1234] = f32::NAN;
    refused(
        Some((shape.clone(), nan)),
        &[OCCUPANCY_TENSOR, "flat index 1234"],
    );
    let mut negative = vec![0.0; n];
    negative[7] = -1.0;
    refused(Some((shape.clone(), negative)), &["flat index 7"]);
    refused(None, &["without the tensor"]);

    // The values themselves load (the tampering keeps a valid file valid).
    tampered(&good, &bad, Some((shape, vec![0.25; n])));
    let ck = checkpoint::load(&bad, &Device::Cpu).unwrap();
    assert_eq!(ck.occupancy.unwrap().density()[0], 0.25);
}

#[cfg(feature = "train")]
mod trained {
    use super::*;
    use crate::train_support::{first_batch, tiny_run, tiny_scene};
    use pma_model::render::avatar::Mode;
    use pma_model::train::Trainer;

    /// The tiny run on a tiny scene in `dir`, trained with a grid of `occupancy`.
    fn grid_run(
        dir: &std::path::Path,
        occupancy: OccupancyConfig,
    ) -> (
        pma_model::train::RunConfig,
        std::sync::Arc<pma_data::dataset::Dataset>,
    ) {
        let data = tiny_scene(dir);
        let mut run = tiny_run();
        run.model.n_framecodes = data.n_images();
        run.train.occupancy = Some(occupancy);
        (run, data)
    }

    /// A model trained with the grid (refreshed during training, used by the steps after the
    /// warm-up) renders without it exactly as its tensors do without a grid, and its saved
    /// checkpoint carries the grid the trainer built.
    #[test]
    fn a_model_trained_with_the_grid_renders_without_it() {
        let dir = tempfile::tempdir().unwrap();
        let (run, data) = grid_run(
            dir.path(),
            OccupancyConfig {
                resolution: 16,
                warmup_steps: 2,
                refresh_every: 1,
                refresh_share: 0.25,
                threshold: 0.05,
                ..Default::default()
            },
        );
        let probe = first_batch(&data, &run);
        let mut trainer = Trainer::new(run, data.clone(), &Device::Cpu).unwrap();
        for _ in 0..6 {
            trainer.step().unwrap();
        }
        let totals = trainer.pass_totals();
        let grid = trainer.avatar().occupancy().expect("a grid").clone();
        println!(
            "trained: {totals:?}; grid refreshed {} times, {:.1} % occupied; {} refresh points",
            grid.refreshes(),
            100.0 * grid.occupied_fraction(),
            trainer.refresh_points()
        );
        // Built at the end of the warm-up and refreshed after every later step.
        assert_eq!(grid.refreshes(), 5);
        assert!(trainer.refresh_points() > 0);
        assert!(
            totals.skipped_empty > 0,
            "no training sample was skipped: the test would not exercise the grid ({totals:?})"
        );

        let trained = trainer.avatar();
        let bare = Avatar::from_tensors(trained.config().clone(), trained.tensors(), &Device::Cpu)
            .unwrap();
        let render = |a: &Avatar, opts: &PassOptions| {
            a.forward(&probe.rays, &probe.poses, &mut Mode::Infer, opts, None)
                .unwrap()
        };
        let parity = PassOptions::parity();
        let (with, without) = (render(trained, &parity), render(&bare, &parity));
        assert_identical(&with, &without, "trained model, parity");

        let path = dir.path().join("model.safetensors");
        trained.save(&path).unwrap();
        let loaded = Avatar::load(&path, &Device::Cpu).unwrap();
        assert_eq!(loaded.occupancy(), Some(&grid));
        assert_identical(&render(&loaded, &parity), &without, "saved model, parity");
        let skipped = render(&loaded, &occupancy_only());
        println!("probe with the grid: {:?}", skipped.stats);
        assert!(skipped.stats.points_evaluated <= without.stats.points_evaluated);
    }

    /// A training step after the warm-up feeds its pass: with every empty sample probed it
    /// leaves none out, without probes it does (the same run otherwise).
    #[test]
    fn training_steps_probe_the_cells_their_grid_leaves_out() {
        let skipped_with = |probe_share: f64| {
            let dir = tempfile::tempdir().unwrap();
            let (run, data) = grid_run(
                dir.path(),
                OccupancyConfig {
                    resolution: 16,
                    warmup_steps: 2,
                    threshold: 0.05,
                    probe_share,
                    ..Default::default()
                },
            );
            let mut trainer = Trainer::new(run, data, &Device::Cpu).unwrap();
            for _ in 0..4 {
                trainer.step().unwrap();
            }
            trainer.pass_totals()
        };
        let (none, all) = (skipped_with(0.0), skipped_with(1.0));
        println!("no probes: {none:?}\nall probed: {all:?}");
        assert!(none.skipped_empty > 0, "{none:?}");
        assert_eq!(all.skipped_empty, 0, "{all:?}");
        assert!(all.coarse_evaluated > none.coarse_evaluated);
    }
}

#[allow(clippy::result_large_err)]
fn infer(case: &GoldenCase, opts: &PassOptions) -> pma_model::error::Result<Outputs> {
    let mut mode = pma_model::render::avatar::Mode::Infer;
    case.avatar
        .forward(&case.rays, &case.poses, &mut mode, opts, None)
}

/// Fine samples placed from the grid: the coarse samples, their fates and (within a few ulps:
/// their rows now share calls with the fine samples) their outputs are those of the two-round
/// pass; the fine samples are where the grid's weights put them, which is not where the
/// coarse render puts them; the option is refused without the grid option and in training.
#[test]
fn fine_samples_placed_from_the_grid() {
    let case = with_grid(
        GoldenCase::load("golden/dense", true),
        Some(patterned_grid(0.3)),
    );
    let grid_fine = PassOptions {
        occupancy_fine: true,
        ..occupancy_only()
    };
    let two = infer(&case, &occupancy_only()).unwrap();
    let one = infer(&case, &grid_fine).unwrap();
    assert_eq!(flat(&two.z_coarse), flat(&one.z_coarse));
    let d = max_abs_diff(&flat(&two.raw_coarse), &flat(&one.raw_coarse));
    assert!(d <= 1e-5, "coarse outputs differ by {d}");
    assert_eq!(two.stats.coarse_evaluated, one.stats.coarse_evaluated);
    assert_eq!(two.stats.samples, one.stats.samples);
    assert!(one.stats.fine_evaluated > 0, "{:?}", one.stats);
    assert!(
        max_abs_diff(&flat(&two.z_vals), &flat(&one.z_vals)) > 1e-3,
        "the fine samples did not move"
    );

    // A grid that was refreshed and found no density anywhere: zero weights, so the fine
    // samples are the importance sampler's for zero coarse weights, and every sample with
    // an active joint is left out.
    let mut empty = OccupancyGrid::new(OccupancyConfig::default()).unwrap();
    empty.finish_refresh();
    let case = with_grid(case, Some(empty));
    let out = infer(&case, &grid_fine).unwrap();
    let caster = case.avatar.ray_caster();
    let zc = flat(&out.z_coarse);
    let expected = caster
        .importance_z(&zc, &vec![0.0; zc.len()], None)
        .unwrap();
    let mut placed: Vec<f32> = Vec::new();
    let (sc, all) = (caster.n_samples(), out.z_vals.dim(1).unwrap());
    let (zc_rows, z_rows) = (zc.chunks(sc), flat(&out.z_vals));
    for (ray, zc_row) in z_rows.chunks(all).zip(zc_rows) {
        // The merged z less the coarse ones, in order: the fine samples of this ray.
        let mut rest: Vec<f32> = ray.to_vec();
        for z in zc_row {
            let i = rest.iter().position(|v| v == z).unwrap();
            rest.remove(i);
        }
        placed.extend(rest);
    }
    assert_eq!(placed, expected);
    assert_eq!(out.stats.coarse_evaluated + out.stats.fine_evaluated, 0);

    let no_grid_option = PassOptions {
        occupancy: false,
        ..grid_fine.clone()
    };
    let err = infer(&case, &no_grid_option).unwrap_err();
    assert!(err.to_string().contains("occupancy_fine"), "{err}");
    let mut mode = pma_model::render::avatar::Mode::Train(None);
    let Err(err) = case
        .avatar
        .forward(&case.rays, &case.poses, &mut mode, &grid_fine, None)
    else {
        panic!("a training pass placed its fine samples from the grid");
    };
    assert!(err.to_string().contains("rendering option"), "{err}");
}

/// Coarse samples placed from the grid: before the grid is built the cast is the even one bit
/// for bit; with a patterned grid every ray's samples stay ascending inside its [near, far],
/// rays that cross no box keep the even placement, some rays move, more coarse samples run
/// the network than with the even placement, and the option is refused without the grid
/// option.
#[test]
fn coarse_samples_placed_from_the_grid() {
    let placed = PassOptions {
        coarse_from_grid: true,
        ..occupancy_only()
    };
    let unbuilt = with_grid(
        GoldenCase::load("golden/dense", true),
        Some(OccupancyGrid::new(OccupancyConfig::default()).unwrap()),
    );
    let even = infer(&unbuilt, &occupancy_only()).unwrap();
    let same = infer(&unbuilt, &placed).unwrap();
    assert_eq!(flat(&even.z_coarse), flat(&same.z_coarse));

    let case = with_grid(unbuilt, Some(patterned_grid(0.3)));
    let even = infer(&case, &occupancy_only()).unwrap();
    let moved = infer(&case, &placed).unwrap();
    let bounds = moved.bounds.as_ref().expect("cast on the host");
    let sc = case.avatar.ray_caster().n_samples();
    let (ze, zm) = (flat(&even.z_coarse), flat(&moved.z_coarse));
    let mut rows_moved = 0;
    for (r, (e, m)) in ze.chunks(sc).zip(zm.chunks(sc)).enumerate() {
        assert!(m.windows(2).all(|w| w[0] <= w[1]), "ray {r}: {m:?}");
        let (near, far) = (bounds.near[r], bounds.far[r]);
        let tol = 1e-4 * far.abs().max(1.0);
        assert!(
            m[0] >= near - tol && m[sc - 1] <= far + tol,
            "ray {r}: {m:?} outside [{near}, {far}]"
        );
        if !bounds.ray_hits_body[r] {
            assert_eq!(e, m, "ray {r} crosses no box");
        }
        rows_moved += usize::from(e != m);
    }
    assert!(rows_moved > 0, "no ray moved its samples");
    assert!(
        moved.stats.coarse_evaluated > even.stats.coarse_evaluated,
        "{:?} vs {:?}",
        moved.stats,
        even.stats
    );
    let no_grid_option = PassOptions {
        occupancy: false,
        ..placed
    };
    let err = infer(&case, &no_grid_option).unwrap_err();
    assert!(err.to_string().contains("coarse_from_grid"), "{err}");
}

/// A refresh on the CPU runs each point in a call that carries only the joints whose window
/// is not exactly 0 there (the render's joint grouping): the grid is what calls with all 24
/// joints give, up to float summation order, for far fewer joint rows. Leaving out a live
/// joint would move a density by order 1.
#[test]
#[allow(clippy::result_large_err)] // the density callback returns the crate's Result
fn a_refresh_carries_only_the_joints_its_points_need() {
    use pma_model::compute::host::host_f32;
    use pma_model::render::bones::BoneFrames;
    use pma_model::render::occupancy::{refresh, refresh_with, CellChoice, RefreshOptions};
    use rand::SeedableRng;

    let case = GoldenCase::load("golden", false);
    let net = case.avatar.network();
    let pose = case.avatar.pose_features(&case.poses, None).unwrap();
    let cfg = OccupancyConfig {
        resolution: 4,
        dilation: 0,
        ..Default::default()
    };
    let opts = RefreshOptions {
        cells: CellChoice::All,
        decay: false,
    };
    let mut grouped = OccupancyGrid::new(cfg.clone()).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    let stats = refresh(net, &mut grouped, &case.poses, &pose, opts, &mut rng).unwrap();

    let mut full = OccupancyGrid::new(cfg).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    let skts = host_f32(&case.poses.skts).unwrap();
    let frames = BoneFrames::new(net.bone_align(), &skts).unwrap();
    let scales = host_f32(&pose.scales).unwrap();
    let dev = pose.g.device().clone();
    let c = net.config();
    refresh_with(
        &mut full,
        &frames,
        &scales,
        c.window_alpha,
        c.window_beta,
        opts,
        &mut rng,
        |points| {
            points
                .iter()
                .enumerate()
                .map(|(p, pts)| {
                    if pts.is_empty() {
                        return Ok(Vec::new());
                    }
                    let flat_pts: Vec<f32> = pts.iter().flatten().copied().collect();
                    let t = Tensor::from_vec(flat_pts, (pts.len(), 3), &dev)?;
                    Ok(flat(&net.eval_density(&pose, p, &t)?.relu()?))
                })
                .collect()
        },
    )
    .unwrap();

    let (a, b) = (grouped.density(), full.density());
    assert!(
        b.iter().filter(|&&v| v > 0.0).count() > b.len() / 10,
        "too little density to compare"
    );
    // Float summation order only: the per-joint sums skip exact zeros.
    let worst = a
        .iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs() / y.abs().max(1.0))
        .fold(0f32, f32::max);
    assert!(
        worst <= 1e-5,
        "grouped refresh differs from all-joint calls by {worst}"
    );
    let all_rows = stats.cells * 24;
    assert!(
        stats.joint_rows > 0 && stats.joint_rows * 4 < all_rows * 3,
        "joint rows {} of {all_rows}",
        stats.joint_rows
    );
    eprintln!(
        "{} points, {:.1} joints per point, worst relative difference {worst:e}",
        stats.cells,
        stats.joint_rows as f64 / stats.cells as f64
    );
}
