//! Step accounting of a `tiny` training step on the CPU, counted as on CUDA
//! (`pma_model::compute::account`): the device → host reads (syncs) of one step exactly
//! (none), and its op count from above, so a new read-back or a per-pose loop inside the
//! step fails here. The bounds are today's step; tighten them when the step sheds work.

#![cfg(feature = "train")]

use pma_model::compute::account::Route;
use pma_model::train::account::{account_one_pass_extrapolated, account_step, StepAccount};
use pma_model::train::{BatchSource, DatasetSource, RunConfig, Trainer};

use crate::train_support::{tiny_run, tiny_scene};

/// A fresh tiny trainer (64 rays of 2 images per step) in chunks of `chunk_rays`, and its
/// batch source.
fn tiny(chunk_rays: usize) -> (tempfile::TempDir, Trainer, DatasetSource) {
    tiny_with_rays(chunk_rays, tiny_run().train.rays_per_step)
}

/// [`tiny`] with `rays` rays per step.
fn tiny_with_rays(chunk_rays: usize, rays: usize) -> (tempfile::TempDir, Trainer, DatasetSource) {
    tiny_with(chunk_rays, rays, |_| {})
}

/// [`tiny_with_rays`] with the run configuration changed by `tweak`.
fn tiny_with(
    chunk_rays: usize,
    rays: usize,
    tweak: impl FnOnce(&mut RunConfig),
) -> (tempfile::TempDir, Trainer, DatasetSource) {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let mut run = tiny_run();
    run.train.chunk_rays = chunk_rays;
    run.train.rays_per_step = rays;
    tweak(&mut run);
    let t = &run.train;
    let dev = candle_core::Device::Cpu;
    let source = DatasetSource::new(
        data.clone(),
        t.rays_per_step,
        t.images_per_step,
        t.perturb_bg,
        t.seed,
        &dev,
    )
    .unwrap();
    let trainer = Trainer::new(run, data, &dev).unwrap();
    (dir, trainer, source)
}

fn account(chunk_rays: usize) -> StepAccount {
    let (_dir, mut trainer, mut source) = tiny(chunk_rays);
    account_step(&mut trainer, &mut source, Route::Cuda).unwrap()
}

fn syncs(a: &StepAccount, stage: &str) -> u64 {
    a.report
        .stages
        .iter()
        .find(|s| s.name == stage)
        .map_or(0, |s| s.counts.syncs)
}

fn table(a: &StepAccount) -> String {
    a.report
        .stages
        .iter()
        .map(|s| {
            format!(
                "\n  {:<30} x{:<3} ops {:>6} syncs {:>3}",
                s.name, s.times, s.counts.ops, s.counts.syncs
            )
        })
        .collect()
}

/// Nothing inside a step reads back: the ray caster, the importance sampler, the loss, the
/// skip rule and the clip factor all stay on the device. The step's numbers come back
/// after it in one read (a run does that once every `read_every` steps).
fn check(a: &StepAccount, chunks: u64, max_ops: u64) {
    let t = table(a);
    assert_eq!(a.chunks, chunks, "{t}");
    for stage in a.report.stages.iter().map(|s| s.name.as_str()) {
        assert_eq!(syncs(a, stage), 0, "{stage} reads back:{t}");
    }
    assert_eq!(a.report.total.syncs, 0, "{t}");
    assert_eq!(a.read_back.syncs, 1, "one read for the step's numbers");
    assert!(
        a.report.total.ops <= max_ops,
        "{} ops in a tiny step (bound {max_ops}):{t}",
        a.report.total.ops
    );
}

#[test]
fn one_pass_step_syncs_and_ops() {
    let (_dir, mut trainer, mut source) = tiny(0);
    let a = account_step(&mut trainer, &mut source, Route::Cuda).unwrap();
    check(&a, 1, 1_450);
    assert!(a.report.total.flops > 0 && a.report.total.param_uploads > 0);
    // The window max-pool counts as its CUDA kernels (per network pass, coarse and fine:
    // one launch forward, one per gradient), not as candle's broadcast add, product and max.
    let launches = |op: &str| a.report.ops.get(op).map_or(0, |c| c.launches);
    assert_eq!(launches("pma-window-pool"), 2, "{:?}", a.report.ops.keys());
    assert_eq!(launches("pma-window-pool-grad"), 4);
    // The first step is every step: the next one launches and moves exactly as much.
    let b = account_step(&mut trainer, &mut source, Route::Cuda).unwrap();
    assert_eq!(a.report.total, b.report.total);
    assert_eq!(a.report.ops, b.report.ops);
}

#[test]
fn one_pass_step_extrapolates_exactly() {
    // 64, 128 and 192 rays extrapolated to 256, against the 256-ray step itself: sizes whose
    // every count is affine (the fused kernels' partial sums come in blocks of 256 and 1,024
    // rows, so their bytes are affine only where the rows fill whole blocks).
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let mut run = tiny_run();
    run.train.rays_per_step = 256;
    let e = account_one_pass_extrapolated(&run, data, &candle_core::Device::Cpu, Route::Cuda, 64)
        .unwrap();
    assert_eq!(e.from, [64, 128, 192]);
    assert!(e.counts_constant);
    let (_dir, mut trainer, mut source) = tiny_with_rays(0, 256);
    let direct = account_step(&mut trainer, &mut source, Route::Cuda).unwrap();
    assert_eq!(e.report.total, direct.report.total);
    assert_eq!(e.report.ops, direct.report.ops);
    assert_eq!(e.report.stages, direct.report.stages);
}

#[test]
fn chunked_step_syncs_and_ops() {
    // 4 chunks of 16 rays (8 per image).
    let a = account(16);
    check(&a, 4, 4_700);
}

#[test]
fn an_inference_pass_sized_for_a_gpu_takes_fewer_calls_and_renders_the_same() {
    use pma_model::compute::account::Account;
    // 2,048 rays of 2 poses, 8 coarse samples: 8,192 points per pose, two calls of the
    // CPU's 4,096 points each per pose and pass.
    let (_dir, trainer, mut source) = tiny_with_rays(0, 2048);
    let batch = source.next_batch().unwrap();
    let avatar = trainer.avatar();
    let render = |memory: Option<usize>| {
        let account = Account::start(&candle_core::Device::Cpu, Route::Cuda).unwrap();
        if let Some(bytes) = memory {
            account.model_free_memory(bytes);
        }
        let out = avatar
            .render_rays(&batch.rays, &batch.poses, &Default::default())
            .unwrap();
        let rgb: Vec<f32> = out.fine.rgb.flatten_all().unwrap().to_vec1().unwrap();
        (rgb, account.finish())
    };
    let (cpu_sized, per_chunk) = render(None);
    // 1 GB holds the whole pass in one call per network pass: 2 calls instead of 6 (4
    // coarse, 2 fine of 4,096 points), each with the same matmuls.
    let (gpu_sized, grouped) = render(Some(1 << 30));
    let matmuls = |r: &pma_model::compute::account::Report| r.ops["matmul"].launches;
    assert!(
        2 * matmuls(&grouped) < matmuls(&per_chunk),
        "{} matmuls grouped, {} per pose and chunk",
        matmuls(&grouped),
        matmuls(&per_chunk)
    );
    assert!(grouped.total.launches < per_chunk.total.launches);
    // The same samples through the same network, in larger products: equal up to the
    // products' summation order.
    let worst = cpu_sized
        .iter()
        .zip(&gpu_sized)
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    assert!(worst <= 1e-5, "rgb differs by {worst}");
}

/// On a GPU a culled pass is one network call for all poses per stage (each pose's kept
/// samples padded to the longest block), as the dense pass is, and renders what the CPU's
/// per-pose calls render.
#[test]
fn a_culled_pass_on_the_cuda_route_is_one_network_call_per_stage() {
    use pma_model::compute::account::Account;
    use pma_model::render::avatar::Mode;
    use pma_model::render::{Culling, PassOptions, SampleFill};
    let (_dir, trainer, mut source) = tiny_with_rays(0, 256);
    let batch = source.next_batch().unwrap();
    assert!(batch.poses.bones.len() > 1, "several poses per step");
    let avatar = trainer.avatar();
    let culled = PassOptions::culled(Culling {
        rays: true,
        sample_threshold: Some(1e-2),
        sample_fill: SampleFill::Network,
    });
    let pass = |opts: &PassOptions, cuda: bool| {
        let account = cuda.then(|| Account::start(&candle_core::Device::Cpu, Route::Cuda).unwrap());
        let out = avatar
            .forward(
                &batch.rays,
                &batch.poses,
                &mut Mode::Train(None),
                opts,
                None,
            )
            .unwrap();
        let rgb: Vec<f32> = [&out.fine.rgb, &out.coarse.rgb]
            .iter()
            .flat_map(|t| t.flatten_all().unwrap().to_vec1::<f32>().unwrap())
            .collect();
        (rgb, out.stats, account.map(|a| a.finish()))
    };
    let (cpu_rgb, cpu_stats, _) = pass(&culled, false);
    let (gpu_rgb, gpu_stats, gpu) = pass(&culled, true);
    let (_, _, dense) = pass(&PassOptions::parity(), true);
    let matmuls = |r: &pma_model::compute::account::Report| r.ops["matmul"].launches;
    let (gpu, dense) = (gpu.unwrap(), dense.unwrap());
    assert!(
        gpu_stats.coarse_evaluated + gpu_stats.fine_evaluated < gpu_stats.samples,
        "culling leaves samples out: {gpu_stats:?}"
    );
    assert_eq!(cpu_stats.coarse_evaluated, gpu_stats.coarse_evaluated);
    assert_eq!(cpu_stats.fine_evaluated, gpu_stats.fine_evaluated);
    assert!(
        matmuls(&gpu) <= matmuls(&dense),
        "{} matmuls culled, {} dense",
        matmuls(&gpu),
        matmuls(&dense)
    );
    // The same samples through the same network in one larger product per stage.
    let worst = cpu_rgb
        .iter()
        .zip(&gpu_rgb)
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    assert!(worst <= 1e-5, "rgb differs by {worst}");
}

/// A step that leaves work out reads back on the host what its culling decides there (ray
/// casting, each stage's fates, the importance sampler's inputs); a step that also trains the
/// occupancy grid reads each network stage's σ once more, for the cells its samples saw.
/// docs/gpu.md and docs/performance.md quote these counts.
#[test]
fn a_culled_step_reads_back_per_stage_and_the_grid_feed_once_more_per_network_stage() {
    use pma_model::network::occupancy::OccupancyConfig;
    use pma_model::render::{Culling, SampleFill};
    let culled = |grid: bool| {
        let (_dir, mut trainer, mut source) = tiny_with(0, 64, |run| {
            run.train.culling = Culling {
                rays: true,
                sample_threshold: Some(0.6),
                sample_fill: SampleFill::Network,
            };
            run.train.occupancy = grid.then(|| OccupancyConfig {
                warmup_steps: 1,
                ..OccupancyConfig::default()
            });
        });
        if grid {
            // The refresh that ends the warm-up step builds the grid.
            trainer.advance(&source.next_batch().unwrap()).unwrap();
            trainer.read_back().unwrap();
            assert!(
                trainer.avatar().occupancy().is_some(),
                "no grid after the warm-up"
            );
        }
        account_step(&mut trainer, &mut source, Route::Cuda).unwrap()
    };
    let (plain, fed) = (culled(false), culled(true));
    let by_stage = |a: &StepAccount| -> Vec<(String, u64)> {
        a.report
            .stages
            .iter()
            .filter(|s| s.counts.syncs > 0)
            .map(|s| (s.name.clone(), s.counts.syncs))
            .collect()
    };
    let expect = |coarse: u64, fine: u64| -> Vec<(String, u64)> {
        [
            ("cast", 5),
            ("coarse network", coarse),
            ("resample", 4),
            ("fine network", fine),
        ]
        .into_iter()
        .map(|(n, k)| (n.to_string(), k))
        .collect()
    };
    assert_eq!(by_stage(&plain), expect(3, 1), "{}", table(&plain));
    assert_eq!(plain.report.total.syncs, 13);
    assert_eq!(by_stage(&fed), expect(4, 2), "{}", table(&fed));
    assert_eq!(fed.report.total.syncs, 15);
    // The feed adds reads, not launches: the network calls are the same ones.
    assert_eq!(
        plain.report.total.ops,
        fed.report.total.ops,
        "{}",
        table(&fed)
    );
}

/// The time-to-quality options add no read-back inside a step: the error map's per-ray errors
/// come back with the step's numbers in its one read, the annealed and boosted rates are host numbers,
/// the averaged weights are element-wise ops on the device, the stratified samples' places
/// are drawn on the host and copied up, and the coarse samples placed from the grid are
/// placed from the host copies a culled step's cast reads already (the same syncs per stage
/// as without them).
#[test]
fn the_time_to_quality_options_add_no_read_back_inside_a_step() {
    use pma_model::network::occupancy::OccupancyConfig;
    use pma_model::render::{Culling, SampleFill};
    let (_dir, mut trainer, mut source) = tiny_with(0, 64, |run| {
        run.train.error_map = Some(Default::default());
        run.train.anneal = Some(Default::default());
        run.train.pose_boost = Some(Default::default());
        run.train.average = Some(Default::default());
        run.train.jitter = true;
    });
    let a = account_step(&mut trainer, &mut source, Route::Cuda).unwrap();
    check(&a, 1, 1_470);
    assert_eq!(
        a.stats.ray_errors.len(),
        64,
        "the errors came back with the numbers"
    );
    assert!(trainer
        .error_map()
        .unwrap()
        .values()
        .iter()
        .any(|&v| v >= 0.0));

    let culled = |coarse_from_grid: bool| {
        let (_dir, mut trainer, mut source) = tiny_with(0, 64, |run| {
            run.train.culling = Culling {
                rays: true,
                sample_threshold: Some(0.6),
                sample_fill: SampleFill::Network,
            };
            run.train.occupancy = Some(OccupancyConfig {
                warmup_steps: 1,
                ..OccupancyConfig::default()
            });
            run.train.coarse_from_grid = coarse_from_grid;
            run.train.jitter = coarse_from_grid;
            run.train.error_map = coarse_from_grid.then(Default::default);
        });
        trainer.advance(&source.next_batch().unwrap()).unwrap();
        trainer.read_back().unwrap();
        account_step(&mut trainer, &mut source, Route::Cuda).unwrap()
    };
    let (grid, placed) = (culled(false), culled(true));
    let syncs = |a: &StepAccount| -> Vec<(String, u64)> {
        a.report
            .stages
            .iter()
            .map(|s| (s.name.clone(), s.counts.syncs))
            .collect()
    };
    assert_eq!(syncs(&placed), syncs(&grid), "{}", table(&placed));
    assert_eq!(placed.report.total.syncs, 15);
    assert_eq!(placed.read_back.syncs, 1);
}

/// The automatic chunk rule (`compute::device::BYTES_PER_ELEMENT`) against the counted peak of
/// live memory of the paper config's step: what a chunk's point × joint × feature element adds
/// to the peak, from chunks of 16 and 64 rays. The rule must leave room above the count for
/// what the count does not see (the allocator's slack, cuBLAS's workspace, a custom op's
/// transient product), and not so much that a GPU runs several chunks where one fits.
#[test]
fn the_chunk_rule_leaves_room_above_the_counted_peak() {
    let paper = RunConfig::from_preset(pma_model::train::Preset::Paper).model;
    let m = paper.clone();
    let per_ray = (m.n_samples + m.n_importance) * m.n_joints * m.win_hidden.max(m.point_enc_dim);
    let peak = |chunk: usize| {
        let model = paper.clone();
        let (_dir, mut trainer, mut source) = tiny_with(chunk, 64, |run| run.model = model);
        let a = account_step(&mut trainer, &mut source, Route::Cuda).unwrap();
        assert_eq!(a.chunks, (64 / chunk) as u64);
        a.report.peak_live_bytes
    };
    let (small, large) = (peak(16), peak(64));
    let per_element = (large as f64 - small as f64) / ((64 - 16) * per_ray) as f64;
    let rule = pma_model::compute::device::BYTES_PER_ELEMENT as f64;
    eprintln!("counted {per_element:.2} bytes per element (peaks {small} and {large} bytes); the rule {rule}");
    assert!(per_element > 4.0, "{per_element}");
    assert!(
        rule >= 1.5 * per_element,
        "the rule {rule} is under 1.5x the counted {per_element}"
    );
    assert!(
        rule <= 2.0 * per_element,
        "the rule {rule} is over 2x the counted {per_element}"
    );
}
