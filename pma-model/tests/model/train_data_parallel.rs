//! Data-parallel training on CPU ranks (threads exchanging host buffers, the test double of
//! NCCL) is the one-device run on the union batch: 2 and 4 ranks, 50 `tiny` steps, through
//! the whole run (`train_group`: run directory, checkpoints, the group's exchanges).
//!
//! The reference is one device whose chunks are the ranks' slices (`chunk_rays` = rays per
//! step / ranks): its gradient is the sum of the same per-slice gradients. Under
//! `deterministic` the group sums in rank order, as the one device sums its chunks, so the
//! parameters match bit for bit. Without it the group sums in ring order (as NCCL's ring
//! all-reduce does), and the parameters match to a tolerance: 50 Adam steps amplify
//! rounding differences of the gradient (see `train_chunked` for Adam's slope near eps).
#![cfg(feature = "train")]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use candle_core::Device;
use pma_model::compute::numerics::Numerics;
use pma_model::train::parallel::{train_group, GroupOptions};
use pma_model::train::{train_run, Silent, TrainOutcome, TrainRequest, MODEL_FILE};

use crate::train_support::{tiny_run, tiny_scene};

const STEPS: u64 = 50;

fn request(data: &Path, out: PathBuf, chunk_rays: usize, deterministic: bool) -> TrainRequest {
    let mut run = tiny_run();
    run.train.chunk_rays = chunk_rays;
    run.train.iters = STEPS;
    TrainRequest {
        data: data.to_path_buf(),
        out,
        run: Some(run),
        resume: false,
        overwrite: false,
        iters: None,
        minutes: None,
        eval_data: None,
        chunk_rays: None,
        device: Device::Cpu,
        numerics: Numerics {
            deterministic,
            ..Numerics::PARITY
        },
    }
}

/// The trained parameters of a run directory, by name.
fn params(out: &Path) -> BTreeMap<String, Vec<f32>> {
    candle_core::safetensors::load(out.join(MODEL_FILE), &Device::Cpu)
        .unwrap()
        .into_iter()
        .filter(|(_, t)| t.dtype() == candle_core::DType::F32)
        .map(|(n, t)| (n, t.flatten_all().unwrap().to_vec1::<f32>().unwrap()))
        .collect()
}

/// The largest absolute difference of two parameter sets (same names, same sizes).
fn max_diff(a: &BTreeMap<String, Vec<f32>>, b: &BTreeMap<String, Vec<f32>>) -> (f32, String) {
    assert_eq!(a.keys().collect::<Vec<_>>(), b.keys().collect::<Vec<_>>());
    let mut worst = (0f32, String::new());
    for (name, x) in a {
        let y = &b[name];
        assert_eq!(x.len(), y.len(), "{name}");
        for (i, (p, q)) in x.iter().zip(y).enumerate() {
            let d = (p - q).abs();
            if d > worst.0 || d.is_nan() {
                worst = (d, format!("{name}[{i}]"));
            }
        }
    }
    worst
}

fn trained(out: &TrainOutcome) {
    assert_eq!(out.iterations, STEPS);
    assert!(!out.interrupted);
}

/// `f(rank, trainer)` on each rank of a group of two CPU ranks (threads), the trainers
/// built from `run` and `data` and joined (`ordered`: summing in rank order); by rank.
fn on_two_ranks<R: Send>(
    run: &pma_model::train::presets::RunConfig,
    data: &std::sync::Arc<pma_data::dataset::Dataset>,
    ordered: bool,
    f: impl Fn(usize, &mut pma_model::train::Trainer) -> R + Sync,
) -> Vec<R> {
    use pma_model::train::parallel::{cpu, Communicator, Group};
    let comms = cpu::group(2, std::time::Duration::from_secs(120));
    std::thread::scope(|s| {
        let ranks: Vec<_> = comms
            .into_iter()
            .map(|comm| {
                let (run, data, f) = (run.clone(), data.clone(), &f);
                s.spawn(move || {
                    let rank = comm.rank();
                    let mut t = pma_model::train::Trainer::new(run, data, &Device::Cpu).unwrap();
                    t.join_group(Group::new(Box::new(comm), ordered)).unwrap();
                    f(rank, &mut t)
                })
            })
            .collect();
        ranks.into_iter().map(|h| h.join().unwrap()).collect()
    })
}

#[test]
fn ranks_train_as_one_device_on_the_union_batch() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let data_path = dir.path().join("train.npz");
    let rays = tiny_run().train.rays_per_step;
    assert!(data.n_images() >= 2);
    for size in [2usize, 4] {
        let devices = vec![Device::Cpu; size];
        let opts = GroupOptions::default();
        for deterministic in [true, false] {
            let tag = format!("{size}-{deterministic}");
            let one = dir.path().join(format!("one-{tag}"));
            trained(
                &train_run(
                    &request(&data_path, one.clone(), rays / size, deterministic),
                    &mut Silent,
                )
                .unwrap(),
            );
            let group = dir.path().join(format!("group-{tag}"));
            let req = request(&data_path, group.clone(), 0, deterministic);
            trained(&train_group(&req, &devices, &opts, &mut Silent).unwrap());
            let (a, b) = (params(&one), params(&group));
            let (d, at) = max_diff(&a, &b);
            println!(
                "{size} ranks, deterministic {deterministic}: parameters after {STEPS} steps \
                 differ from one device by at most {d:.3e} ({at})"
            );
            if deterministic {
                assert_eq!(d, 0.0, "{size} ranks: {at} differs by {d:e}");
            } else {
                assert!(d <= 1e-4, "{size} ranks: {at} differs by {d:e}");
            }
        }
    }
}

/// With the fast recipe's culling and occupancy grid (its warm-up shortened so that 40 of
/// the 50 steps use the grid) and stratified samples, two ranks still train as one device
/// in chunks of their slices, bit for bit under `deterministic`: the model, the averaged
/// weights and the grid. The ranks' graphs differ (each culls its own samples), their grids
/// stay equal because every rank takes in all ranks' observations with each step, and a
/// sample's place in its stratum belongs to its ray's row in the whole batch.
#[test]
fn ranks_with_culling_and_the_grid_train_as_one_device() {
    let dir = tempfile::tempdir().unwrap();
    tiny_scene(dir.path());
    let data_path = dir.path().join("train.npz");
    let rays = tiny_run().train.rays_per_step;
    let fast = |mut req: TrainRequest| {
        let run = req.run.as_mut().unwrap();
        pma_model::train::recipe::fast(run, None);
        let grid = run.train.occupancy.as_mut().unwrap();
        grid.warmup_steps = 10;
        grid.refresh_every = 4;
        run.train.jitter = true;
        req
    };
    let one = dir.path().join("one");
    trained(
        &train_run(
            &fast(request(&data_path, one.clone(), rays / 2, true)),
            &mut Silent,
        )
        .unwrap(),
    );
    let group = dir.path().join("group");
    let req = fast(request(&data_path, group.clone(), 0, true));
    let devices = vec![Device::Cpu; 2];
    trained(&train_group(&req, &devices, &GroupOptions::default(), &mut Silent).unwrap());
    let (a, b) = (params(&one), params(&group));
    let grid = a
        .get("occupancy.density")
        .expect("the model has no occupancy grid");
    assert!(grid.iter().any(|&d| d > 0.0), "the grid saw nothing");
    let (d, at) = max_diff(&a, &b);
    assert_eq!(
        d, 0.0,
        "{at} differs by {d:e} between one device and two ranks"
    );
}

/// A rank's accounted step counts the group's two collectives with the bytes
/// `step_collectives` says (what the scaling estimate prices): all-reduces, or all-gathers
/// when summing in rank order.
#[test]
fn an_accounted_rank_step_counts_its_collectives() {
    use pma_model::compute::account::{Counts, Route};
    use pma_model::train::account::account_step;
    use pma_model::train::parallel::step_collectives;

    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let mut run = tiny_run();
    run.model.n_framecodes = data.n_images();
    for ordered in [false, true] {
        let counted = on_two_ranks(&run, &data, ordered, |rank, t| {
            let mut source = crate::train_support::dataset_source(&data, &run);
            let trainable = t.avatar().trainable();
            let model = (
                trainable.len(),
                trainable.iter().map(|(_, v)| v.elem_count()).sum::<usize>(),
            );
            let a = account_step(t, &mut source, Route::Cpu).unwrap();
            (rank, a.report.total, model)
        });
        for (rank, total, (params, elems)) in counted {
            let mut want = Counts::default();
            for c in step_collectives(2, elems, params, ordered) {
                want.add_collective(c);
            }
            println!(
                "rank {rank}, ordered {ordered}: {} all-reduces of {} bytes, {} all-gathers \
                 of {} bytes per step ({elems} parameters in {params} tensors)",
                total.all_reduces,
                total.all_reduce_bytes,
                total.all_gathers,
                total.all_gather_bytes
            );
            assert_eq!(
                (
                    total.all_reduces,
                    total.all_reduce_bytes,
                    total.all_gathers,
                    total.all_gather_bytes
                ),
                (
                    want.all_reduces,
                    want.all_reduce_bytes,
                    want.all_gathers,
                    want.all_gather_bytes
                ),
                "rank {rank}"
            );
            assert_eq!(want.all_reduces + want.all_gathers, 2);
            assert_eq!(
                want.all_reduce_bytes + want.all_gather_bytes,
                4 * elems as u64 + 8 * (5 + 4 + 1 + params) as u64
            );
        }
    }
}

/// The launched path (one process per rank, here threads standing for them, with the CPU
/// engine): rank 0 locks and prepares the run and posts the group in the rendezvous file,
/// the other ranks wait for it, and the group trains the model the in-process group does.
#[test]
fn launched_ranks_meet_at_the_rendezvous_and_train_as_the_group() {
    use pma_model::train::parallel::launch::Launch;
    use pma_model::train::parallel::{cpu_engine, train_launched};

    let dir = tempfile::tempdir().unwrap();
    tiny_scene(dir.path());
    let data_path = dir.path().join("train.npz");
    let rays = tiny_run().train.rays_per_step;
    let opts = GroupOptions::default();
    let group = dir.path().join("group");
    let req = request(&data_path, group.clone(), rays / 2, true);
    trained(&train_group(&req, &[Device::Cpu, Device::Cpu], &opts, &mut Silent).unwrap());

    let launched = dir.path().join("launched");
    let rendezvous = dir.path().join("rendezvous");
    let req = request(&data_path, launched.clone(), rays / 2, true);
    let engine = cpu_engine(2, &opts);
    let results: Vec<_> = std::thread::scope(|s| {
        let ranks: Vec<_> = (0..2)
            .rev()
            .map(|rank| {
                let (req, engine, rendezvous, opts) = (&req, &engine, &rendezvous, &opts);
                s.spawn(move || {
                    let launch = Launch {
                        rank,
                        size: 2,
                        local_rank: rank,
                        launcher: "test",
                        job: None,
                    };
                    train_launched(req, &launch, rendezvous, engine, opts, &mut Silent)
                })
            })
            .collect();
        ranks.into_iter().map(|h| h.join().unwrap()).collect()
    });
    for r in results {
        trained(&r.unwrap());
    }
    let (d, at) = max_diff(&params(&group), &params(&launched));
    assert_eq!(d, 0.0, "{at} differs by {d:e}");
    assert!(
        !rendezvous.exists(),
        "rank 0 leaves no rendezvous file behind"
    );
}

/// Rates over the wall clock (annealing, the pose side's boost) follow rank 0's clock in a
/// group: ranks whose own clocks run apart (rank 1's three times as fast) set the same
/// rates at every step and keep the same weights. With each rank on its own clock the
/// rates differ from the second step on.
#[test]
fn clocked_schedules_follow_rank_0_s_clock() {
    use pma_model::train::presets::{Anneal, PoseBoost};

    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let mut run = tiny_run();
    run.model.n_framecodes = data.n_images();
    run.train.anneal = Some(Anneal {
        seconds: 10.0,
        ..Anneal::default()
    });
    run.train.pose_boost = Some(PoseBoost {
        seconds: 10.0,
        ..PoseBoost::default()
    });
    let ranks = on_two_ranks(&run, &data, true, |rank, t| {
        let pace = 1.0 + 2.0 * rank as f64;
        let lrs: Vec<Vec<f64>> = (1..=6)
            .map(|i| {
                t.set_wall_s(i as f64 * pace);
                t.step_read().unwrap().lrs
            })
            .collect();
        let bits: Vec<u32> = t
            .avatar()
            .trainable()
            .iter()
            .flat_map(|(_, v)| {
                v.as_tensor()
                    .flatten_all()
                    .unwrap()
                    .to_vec1::<f32>()
                    .unwrap()
            })
            .map(f32::to_bits)
            .collect();
        (lrs, bits)
    });
    let (lrs0, bits0) = &ranks[0];
    let (lrs1, bits1) = &ranks[1];
    for (i, (a, b)) in lrs0.iter().zip(lrs1).enumerate() {
        println!("step {}: rank 0 rates {a:?}, rank 1 {b:?}", i + 1);
    }
    assert_eq!(lrs0, lrs1, "the ranks set different rates");
    // The clock moved the schedule: the last step's rates are below the first's.
    let (first, last) = (&lrs0[0], &lrs0[lrs0.len() - 1]);
    assert!(
        first.iter().zip(last).all(|(f, l)| l < f),
        "rates did not follow the clock: {first:?} then {last:?}"
    );
    assert!(bits0 == bits1, "the ranks' weights differ");
}
