//! A run stopped after N iterations, checkpointed and resumed for M more ends bit for bit
//! where an uninterrupted run of N + M iterations ends (CPU): weights, optimizer moments and
//! steps, and the loss of every resumed step.
#![cfg(feature = "train")]

use crate::train_support::*;
use candle_core::Device;
use pma_model::network::run_dir::newest_checkpoint;
use pma_model::train::{TrainError, Trainer, MODEL_FILE};

#[test]
fn resume_equals_uninterrupted_run() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"));
    let (n, m) = (3, 3);

    let mut full = tiny_trainer(&data);
    let full_losses = losses(&mut full, n + m);

    let mut first = tiny_trainer(&data);
    losses(&mut first, n);
    first.set_wall_s(12.5);
    let mut resumed = save_and_resume(first, &tmp.path().join("run"), tiny_run(), &data);
    assert_eq!(resumed.iteration(), n as u64);
    assert_eq!(resumed.progress().wall_s, 12.5);
    let resumed_losses = losses(&mut resumed, m);

    assert_eq!(
        resumed_losses,
        full_losses[n..],
        "losses of the resumed steps differ"
    );
    assert_eq!(resumed.iteration(), full.iteration());
    assert_eq!(resumed.lrs(), full.lrs());
    let (a, b) = (param_bits(&full), param_bits(&resumed));
    assert_eq!(a.len(), b.len());
    for ((na, va), (nb, vb)) in a.iter().zip(&b) {
        assert_eq!(na, nb);
        assert!(va == vb, "parameter {na} differs after resume");
    }
    assert!(
        adam_bits(&full) == adam_bits(&resumed),
        "optimizer state differs after resume"
    );
}

#[test]
fn resume_rejects_a_changed_config_and_a_mismatched_model() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"));
    let ckpt = tmp.path().join("run");
    std::fs::create_dir_all(&ckpt).unwrap();
    let mut t = tiny_trainer(&data);
    t.step().unwrap();
    t.save_checkpoint(&ckpt).unwrap();

    // Only `iters` may change.
    let mut longer = tiny_run();
    longer.train.iters += 100;
    Trainer::resume(&ckpt, longer, data.clone(), &Device::Cpu).unwrap();
    let mut other = tiny_run();
    other.train.lr *= 2.0;
    let err = Trainer::resume(&ckpt, other, data.clone(), &Device::Cpu)
        .err()
        .unwrap();
    assert!(matches!(err, TrainError::Resume { .. }), "{err}");
    assert!(err.to_string().contains("train.lr is"), "{err}");

    // A model file from another iteration than the state in the same checkpoint.
    let mut later = tiny_trainer(&data);
    later.step().unwrap();
    later.step().unwrap();
    let elsewhere = tmp.path().join("later");
    std::fs::create_dir_all(&elsewhere).unwrap();
    later.save_checkpoint(&elsewhere).unwrap();
    let newest = newest_checkpoint(&ckpt).unwrap().unwrap();
    std::fs::copy(elsewhere.join(MODEL_FILE), newest.model()).unwrap();
    let err = Trainer::resume(&ckpt, tiny_run(), data.clone(), &Device::Cpu)
        .err()
        .unwrap();
    assert!(err.to_string().contains("does not belong to"), "{err}");

    // Nothing to resume.
    std::fs::remove_dir_all(&newest.path).unwrap();
    let err = Trainer::resume(&ckpt, tiny_run(), data, &Device::Cpu)
        .err()
        .unwrap();
    assert!(err.to_string().contains("no complete checkpoint"), "{err}");
}

/// A run directory as checkpoints accumulate: each is its own directory, the two newest are
/// kept, a second checkpoint of one iteration gets a sequence number, the published model
/// is the newest one's, and what an interrupted checkpoint leaves is cleaned up and never
/// taken for a checkpoint.
#[test]
fn checkpoints_are_directories_and_the_newest_complete_one_wins() {
    use pma_model::network::run_dir::{checkpoints, newest_model, CheckpointDir};
    use pma_model::train::checkpoint::{clean_stale, resume_point, KEEP};

    let (_tmp, data, run, t) = checkpointed_run(3);
    t.save_checkpoint(&run).unwrap();
    let names: Vec<(u64, u32)> = checkpoints(&run)
        .unwrap()
        .iter()
        .map(|c| (c.iteration, c.seq))
        .collect();
    assert_eq!(names, [(3, 0), (3, 1)]);
    assert_eq!(KEEP, 2);
    let newest = checkpoints(&run).unwrap().pop().unwrap();
    assert_eq!(newest_model(&run).unwrap(), newest.model());
    assert_eq!(
        std::fs::read(run.join(MODEL_FILE)).unwrap(),
        std::fs::read(newest.model()).unwrap()
    );

    // A crash in the middle of the next checkpoint: a newer, incomplete directory.
    let partial = run.join(format!("{}.tmp", CheckpointDir::name(4, 0)));
    std::fs::create_dir_all(&partial).unwrap();
    std::fs::copy(newest.model(), partial.join(MODEL_FILE)).unwrap();
    std::fs::copy(newest.state(), partial.join("train_state.safetensors")).unwrap();
    std::fs::write(run.join(".pma-abc.tmp"), b"half").unwrap();
    assert_eq!(newest_model(&run).unwrap(), newest.model());
    assert_eq!(resume_point(&run).unwrap().model, newest.model());
    let removed = clean_stale(&run).unwrap();
    assert_eq!(removed.len(), 2, "{removed:?}");
    assert!(!partial.exists());
    let resumed = Trainer::resume(&run, tiny_run(), data, &Device::Cpu).unwrap();
    assert_eq!(resumed.iteration(), 3);
}

/// A newest checkpoint whose model was truncated after its commit is passed over: the run
/// resumes from the one before, which is listed with why the newest was skipped; with no
/// checkpoint that reads back, resuming is refused.
#[test]
fn resume_passes_over_a_checkpoint_that_does_not_read_back() {
    use pma_model::network::run_dir::checkpoints;
    use pma_model::train::checkpoint::verified_resume_point;

    let (_tmp, data, run, _t) = checkpointed_run(2);
    let all = checkpoints(&run).unwrap();
    let (older, newest) = (&all[0], &all[1]);
    let bytes = std::fs::read(newest.model()).unwrap();
    std::fs::write(newest.model(), &bytes[..bytes.len() / 2]).unwrap();
    let point = verified_resume_point(&run).unwrap();
    assert_eq!(point.model, older.model());
    assert_eq!(point.skipped.len(), 1);
    assert_eq!(point.skipped[0].0, newest.path);
    assert!(
        point.skipped[0].1.contains("does not belong to"),
        "{:?}",
        point.skipped
    );
    let resumed = Trainer::resume(&run, tiny_run(), data.clone(), &Device::Cpu).unwrap();
    assert_eq!(resumed.iteration(), older.iteration);

    let state = std::fs::read(older.state()).unwrap();
    std::fs::write(older.state(), &state[..state.len() / 2]).unwrap();
    let err = verified_resume_point(&run).err().unwrap();
    assert!(matches!(err, TrainError::Resume { .. }), "{err}");
    let text = err.to_string();
    assert!(text.contains("no complete checkpoint reads back"), "{text}");
}

/// The numbers of a step reach the host every `read_every` steps; when they do changes
/// nothing in the run: the same weights, moments and numbers, bit for bit. A checkpoint
/// waits for the numbers (its skip counters come from them).
#[test]
fn read_back_interval_does_not_change_the_run() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"));
    let mut every = tiny_trainer(&data);
    assert_eq!(every.read_every(), 1, "the CPU reads every step by default");
    let mut run = tiny_run();
    run.train.read_every = 3;
    let mut third = Trainer::new(run, data.clone(), &Device::Cpu).unwrap();
    assert_eq!(third.read_every(), 3);
    let (mut a, mut b) = (Vec::new(), Vec::new());
    for i in 1..=5 {
        a.extend(every.step().unwrap());
        let arrived = third.step().unwrap();
        assert_eq!(arrived.len(), if i % 3 == 0 { 3 } else { 0 }, "step {i}");
        b.extend(arrived);
    }
    assert_eq!(third.pending(), 2);
    let dir = tmp.path().join("run");
    std::fs::create_dir_all(&dir).unwrap();
    let err = third.save_checkpoint(&dir).unwrap_err().to_string();
    assert!(err.contains("read_back"), "{err}");
    b.extend(third.read_back().unwrap());
    assert_eq!(third.pending(), 0);
    assert_eq!(a, b, "numbers of the steps");
    assert!(param_bits(&every) == param_bits(&third), "weights");
    assert!(adam_bits(&every) == adam_bits(&third), "optimizer state");
    third.save_checkpoint(&dir).unwrap();
}

/// With an occupancy grid: the grid is saved with the model and refreshed on resume exactly
/// as in the uninterrupted run (its cells are drawn from the run seed and the iteration).
#[test]
fn resume_with_an_occupancy_grid_equals_uninterrupted_run() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"));
    let mut run = tiny_run();
    run.train.occupancy = Some(pma_model::network::occupancy::OccupancyConfig {
        resolution: 8,
        warmup_steps: 1,
        refresh_every: 1,
        ..Default::default()
    });
    let (n, m) = (2, 2);
    let trainer = || Trainer::new(run.clone(), data.clone(), &Device::Cpu).unwrap();
    let mut full = trainer();
    losses(&mut full, n + m);
    let mut first = trainer();
    losses(&mut first, n);
    let mut resumed = save_and_resume(first, &tmp.path().join("run"), run.clone(), &data);
    assert!(resumed.avatar().occupancy().is_some_and(|g| g.is_built()));
    losses(&mut resumed, m);
    let (a, b) = (full.avatar().occupancy(), resumed.avatar().occupancy());
    assert_eq!(a.unwrap().refreshes(), (n + m) as u64);
    assert!(a == b, "the grid differs after resume");
    assert!(
        param_bits(&full) == param_bits(&resumed),
        "parameters differ after resume"
    );
}

/// The fast recipe (culling, the grid) with every other time-to-quality option (coarse
/// samples from the grid, stratified samples, the error map with its unbiased weights, rates
/// annealed over the run's iterations, the pose side's boost, averaged weights): a run stopped, checkpointed and resumed ends bit for
/// bit where the uninterrupted run ends, its error map and its average included, and the
/// map, the schedule and the average did move.
#[test]
fn resume_with_the_fast_recipe_equals_uninterrupted_run() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"));
    let mut run = tiny_run();
    pma_model::train::recipe::fast(&mut run, None);
    run.train.coarse_from_grid = true;
    run.train.jitter = true;
    run.train.error_map = Some(pma_data::error_map::ErrorMapConfig::default());
    run.train.anneal = Some(pma_model::train::presets::Anneal::default());
    run.train.pose_boost = Some(pma_model::train::presets::PoseBoost::default());
    run.train.average = Some(pma_model::train::average::AverageConfig { decay: 0.5 });
    // The grid refreshes after steps 1, 3, 5, ...: the checkpoint after step 4 holds values
    // that step 4's samples raised and cells marked at step 3's refresh.
    let (n, m) = (4, 3);
    run.train.iters = (n + m) as u64;
    run.train.occupancy = Some(pma_model::network::occupancy::OccupancyConfig {
        resolution: 8,
        warmup_steps: 1,
        refresh_every: 2,
        ..Default::default()
    });
    let map = run.train.error_map.as_mut().unwrap();
    (map.unbiased, map.cell) = (true, 4);
    let trainer = || Trainer::new(run.clone(), data.clone(), &Device::Cpu).unwrap();
    let mut full = trainer();
    let lr0 = full.lrs();
    let full_losses = losses(&mut full, n + m);
    let mut first = trainer();
    losses(&mut first, n);
    let mut resumed = save_and_resume(first, &tmp.path().join("run"), run.clone(), &data);
    let resumed_losses = losses(&mut resumed, m);
    assert_eq!(
        resumed_losses,
        full_losses[n..],
        "losses of the resumed steps"
    );
    let (a, b) = (full.error_map().unwrap(), resumed.error_map().unwrap());
    assert!(a == b, "the error map differs after resume");
    let visited = a.values().iter().filter(|&&v| v >= 0.0).count();
    assert!(visited > 0, "no cell of the error map was visited");
    assert_eq!(resumed.lrs(), full.lrs());
    // The pose side starts at 4x its rate, the trunk at its own.
    let (lr_freq, lr) = (run.train.lr_freq, run.train.lr);
    assert!((lr0[0] / lr_freq - 4.0).abs() < 1e-9, "{lr0:?}");
    assert!((lr0[1] / lr - 1.0).abs() < 1e-9, "{lr0:?}");
    // Annealed over the 7 iterations, the boost down to 1x: a tenth of the rates at the end.
    for (end, start) in full.lrs().iter().zip([lr_freq, lr]) {
        assert!((end / start - 0.1).abs() < 1e-9, "{end} vs {start}");
    }
    assert!(param_bits(&full) == param_bits(&resumed), "parameters");
    assert!(adam_bits(&full) == adam_bits(&resumed), "optimizer state");
    assert!(
        model_bits(&full) == model_bits(&resumed),
        "averaged weights"
    );
    assert!(
        full.avatar().occupancy() == resumed.avatar().occupancy(),
        "the occupancy grid differs after resume"
    );
    assert!(
        model_bits(&full) != param_bits(&full),
        "the average is the last weights"
    );
    // Using the model leaves the trained weights as they were.
    let before = param_bits(&full);
    full.with_model(|_| Ok::<_, TrainError>(())).unwrap();
    assert!(param_bits(&full) == before);
}

/// An averaged run's checkpoint holds the average as its model and the trained weights in
/// its train state; a train state without them is refused, naming them.
#[test]
fn an_averaged_run_saves_the_average_as_its_model() {
    use pma_model::train::average::AverageConfig;
    use pma_model::train::TrainState;
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"));
    let mut run = tiny_run();
    run.train.average = Some(AverageConfig { decay: 0.5 });
    let mut t = Trainer::new(run.clone(), data.clone(), &Device::Cpu).unwrap();
    for _ in 0..3 {
        t.step().unwrap();
    }
    let dir = tmp.path().join("run");
    std::fs::create_dir_all(&dir).unwrap();
    t.save_checkpoint(&dir).unwrap();
    let saved = pma_model::render::Avatar::load(dir.join(MODEL_FILE), &Device::Cpu).unwrap();
    let saved: Vec<(String, Vec<u32>)> = saved
        .trainable()
        .into_iter()
        .map(|(n, v)| (n, bits(v.as_tensor())))
        .collect();
    assert!(saved == model_bits(&t), "the model file is not the average");
    assert!(saved != param_bits(&t));

    let newest = newest_checkpoint(&dir).unwrap().unwrap();
    let mut state = TrainState::load(&newest.state(), &Device::Cpu).unwrap();
    assert_eq!(state.weights.len(), param_bits(&t).len());
    let gone = state.weights.keys().min().unwrap().clone();
    state.weights.remove(&gone);
    state.save(&newest.state()).unwrap();
    let err = Trainer::resume_at(
        &dir,
        &pma_model::train::checkpoint::ResumePoint {
            model: newest.model(),
            state: newest.state(),
            config: newest.config(),
            log: None,
            skipped: Vec::new(),
        },
        run,
        data,
        &Device::Cpu,
    )
    .err()
    .unwrap();
    assert!(
        err.to_string().contains(&format!("weights.{gone}")),
        "{err}"
    );
}

/// The run's model (the averaged weights where it averages them) as raw f32 bits, by name.
fn model_bits(t: &Trainer) -> Vec<(String, Vec<u32>)> {
    t.with_model(|a| {
        Ok::<_, TrainError>(
            a.trainable()
                .into_iter()
                .map(|(n, v)| (n, bits(v.as_tensor())))
                .collect(),
        )
    })
    .unwrap()
}

/// A run with sample culling builds its grid only where the window can pass its threshold
/// (finer cells, none spent on culled space); without culling the grid spans the whole
/// window. Saved and resumed, the narrowed grid keeps its span.
#[test]
fn a_culling_run_builds_its_grid_over_the_windows_span() {
    use pma_model::network::occupancy::{window_extent, OccupancyConfig};
    use pma_model::render::Culling;
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"));
    let mut run = tiny_run();
    run.train.occupancy = Some(OccupancyConfig {
        resolution: 8,
        warmup_steps: 1,
        refresh_every: 1,
        ..Default::default()
    });
    let plain = Trainer::new(run.clone(), data.clone(), &Device::Cpu).unwrap();
    assert_eq!(plain.avatar().occupancy().unwrap().config().extent, 2.0);
    run.train.culling = Culling {
        rays: true,
        sample_threshold: Some(0.6),
        ..Default::default()
    };
    let mut culled = Trainer::new(run.clone(), data.clone(), &Device::Cpu).unwrap();
    let m = &run.model;
    let want = window_extent(0.6, m.window_alpha, m.window_beta);
    let cfg = culled.avatar().occupancy().unwrap().config().clone();
    assert_eq!((cfg.extent, cfg.resolution), (want, 8));
    for _ in 0..2 {
        culled.step().unwrap();
    }
    let ckpt = tmp.path().join("run");
    std::fs::create_dir_all(&ckpt).unwrap();
    culled.save_checkpoint(&ckpt).unwrap();
    let resumed = Trainer::resume(&ckpt, run, data, &Device::Cpu).unwrap();
    assert!(resumed.avatar().occupancy() == culled.avatar().occupancy());
}

/// `steps` steps of `t`: the bits of each one's total loss.
fn losses(t: &mut Trainer, steps: usize) -> Vec<u64> {
    (0..steps)
        .map(|_| t.step_read().unwrap().loss.total.to_bits())
        .collect()
}

/// `t` checkpointed into a new directory `dir`, dropped, and resumed from there with `run`.
fn save_and_resume(
    t: Trainer,
    dir: &std::path::Path,
    run: pma_model::train::RunConfig,
    data: &std::sync::Arc<pma_data::dataset::Dataset>,
) -> Trainer {
    std::fs::create_dir_all(dir).unwrap();
    t.save_checkpoint(dir).unwrap();
    drop(t);
    Trainer::resume(dir, run, data.clone(), &Device::Cpu).unwrap()
}

/// A tiny run directory with a checkpoint after each of `steps` steps: the temporary
/// directory (the scene and the run live in it), the scene, the run directory, the trainer.
fn checkpointed_run(
    steps: usize,
) -> (
    tempfile::TempDir,
    std::sync::Arc<pma_data::dataset::Dataset>,
    std::path::PathBuf,
    Trainer,
) {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"));
    let run = tmp.path().join("run");
    std::fs::create_dir_all(&run).unwrap();
    let mut t = tiny_trainer(&data);
    for _ in 0..steps {
        t.step().unwrap();
        t.save_checkpoint(&run).unwrap();
    }
    (tmp, data, run, t)
}
