//! What candle's CUDA backend must implement for pma's CUDA route: every distinct op
//! signature (op, input dtypes and layouts, output dtype, kernel variant, empty grid;
//! `pma_model::compute::account::Issued`) that `tiny` issues accounted as CUDA on the CPU in
//! training steps (one pass and chunked; parity numerics, the generic kernels, the bf16
//! trunk, the ablation variants, the fast recipe), inference passes, occupancy refreshes, culled passes and a
//! checkpoint's save and resume, each found in the table that `scripts/cuda-coverage.py`
//! derives from the vendored candle-core's CUDA backend and candle-kernels' sources
//! (`fixtures/cuda-coverage.tsv`; docs/gpu.md, "What candle's CUDA backend must implement").
//! A new op, dtype or layout in the route fails here until the backend implements it (a hunk
//! of vendor/candle-core/candle-core.patch) or the route stops issuing it. Only the bf16
//! trunk (`--bf16-trunk`) may need a kernel that exists from some compute capability on (its
//! casts: sm_80); everything else runs on any GPU candle supports.
//!
//! `PMA_CUDA_COVERAGE_OUT=FILE` writes the issued signatures, one per line with the passes
//! that issued them, for `scripts/cuda-coverage.py --issued FILE`. The ignored test
//! `the_default_networks_route_issues_what_the_tiny_one_does` (9 min in the dev profile)
//! checks that `tiny` takes the route's every branch: the same passes with the `default`
//! preset's network issue the same signatures.

#![cfg(feature = "train")]

use std::collections::BTreeMap;
use std::sync::Arc;

use candle_core::account::{Lay, Sig};
use candle_core::{DType, Device, Tensor};
use pma_data::dataset::Dataset;
use pma_model::compute::account::{Account, Issued, Report, Route};
use pma_model::compute::numerics::Numerics;
use pma_model::network::config::{Config, Variant};
use pma_model::network::occupancy::{OccupancyConfig, OccupancyGrid};
use pma_model::render::avatar::{Avatar, Mode};
use pma_model::render::occupancy::{refresh, CellChoice, RefreshOptions};
use pma_model::render::{Culling, PassOptions, SampleFill};
use pma_model::train::{BatchSource, DatasetSource, RunConfig, TrainBatch, Trainer};
use rand::SeedableRng;

use crate::common::fixtures;
use crate::train_support::{dataset_source, tiny_run, tiny_scene};

/// One row of the table: a signature the backend implements.
#[derive(Debug)]
struct Row {
    custom: bool,
    op: String,
    variant: String,
    /// Per input: its dtype and the layout letters the backend takes for it; `None` (`*`):
    /// any inputs and output (pma's own kernels, which check their inputs themselves).
    inputs: Option<Vec<(String, String)>>,
    output: String,
    /// Whether an instance with an empty grid is fine (nothing is launched for it).
    empty: bool,
    /// The compute capability the kernel needs (`sm_80`), if any.
    arch: Option<String>,
    line: usize,
}

impl Row {
    fn covers(&self, i: &Issued) -> bool {
        let s = &i.sig;
        let inputs: Vec<_> = s.inputs.iter().flatten().collect();
        let signature = match &self.inputs {
            None => true,
            Some(want) => {
                self.output == s.output.as_str()
                    && want.len() == inputs.len()
                    && want
                        .iter()
                        .zip(&inputs)
                        .all(|((d, ls), (dt, l))| d == dt.as_str() && ls.contains(l.letter()))
            }
        };
        self.custom == s.custom
            && self.op == i.op
            && self.variant == s.variant
            && signature
            && (self.empty || !s.empty)
    }
}

/// The table's rows (tab-separated: kind, op, variant, inputs, output, empty, arch, then
/// the kernel and its source, which only a reader needs).
fn table() -> Vec<Row> {
    let path = fixtures().join("cuda-coverage.tsv");
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| {
        panic!(
            "{}: {e} (scripts/cuda-coverage.py writes it)",
            path.display()
        )
    });
    let dash = |s: &str| {
        if s == "-" {
            String::new()
        } else {
            s.to_string()
        }
    };
    text.lines()
        .enumerate()
        .filter(|(_, l)| !l.starts_with('#') && !l.trim().is_empty())
        .skip(1) // the header
        .map(|(n, l)| {
            let f: Vec<&str> = l.split('\t').collect();
            assert!(
                f.len() >= 7,
                "{}:{}: too few columns",
                path.display(),
                n + 1
            );
            let inputs = match f[3] {
                "*" => None,
                "-" => Some(Vec::new()),
                s => Some(
                    s.split(',')
                        .map(|x| {
                            let (d, ls) = x.split_once(':').unwrap_or_else(|| {
                                panic!("{}:{}: `{x}` is not dtype:layouts", path.display(), n + 1)
                            });
                            (d.to_string(), ls.to_string())
                        })
                        .collect(),
                ),
            };
            Row {
                custom: f[0] == "custom",
                op: f[1].to_string(),
                variant: dash(f[2]),
                inputs,
                output: f[4].to_string(),
                empty: f[5] == "yes",
                arch: Some(dash(f[6])).filter(|a| !a.is_empty()),
                line: n + 1,
            }
        })
        .collect()
}

/// A trainer of the `tiny` run (64 rays of 2 images per step) with `model`'s network and
/// `tweak` applied, and the account of making it.
fn trainer(
    data: &Arc<Dataset>,
    model: &Config,
    tweak: impl FnOnce(&mut RunConfig),
) -> (Trainer, DatasetSource, Report) {
    let mut run = tiny_run();
    run.model = model.clone();
    tweak(&mut run);
    let ((trainer, source), made) = accounted(None, || {
        let source = dataset_source(data, &run);
        (
            Trainer::new(run, data.clone(), &Device::Cpu).unwrap(),
            source,
        )
    });
    (trainer, source, made)
}

/// `f` accounted as CUDA on the CPU (sized, when `gpu_memory` is given, as a GPU with that
/// much free memory would size its calls).
fn accounted<T>(gpu_memory: Option<usize>, f: impl FnOnce() -> T) -> (T, Report) {
    let account = Account::start(&Device::Cpu, Route::Cuda).unwrap();
    if let Some(bytes) = gpu_memory {
        account.model_free_memory(bytes);
    }
    let out = f();
    (out, account.finish())
}

/// A training step on the next batch (and the read-back of its numbers) accounted as CUDA.
fn step(trainer: &mut Trainer, source: &mut DatasetSource) -> Report {
    let batch = source.next_batch().unwrap();
    accounted(None, || {
        trainer.advance(&batch).unwrap();
        trainer.read_back().unwrap();
    })
    .1
}

/// `render_rays` of `batch` with `opts`, in the CPU's calls and in the calls of a GPU with
/// 1 GB free.
fn inference(avatar: &Avatar, batch: &TrainBatch, opts: &PassOptions) -> Vec<Report> {
    [None, Some(1 << 30)]
        .into_iter()
        .map(|memory| {
            accounted(memory, || {
                avatar.render_rays(&batch.rays, &batch.poses, opts).unwrap()
            })
            .1
        })
        .collect()
}

/// The generic path: candle's ops where pma has kernels of its own (what runs when a
/// kernel steps aside).
const GENERIC: Numerics = Numerics {
    fused: false,
    row_ops: false,
    ..Numerics::PARITY
};

/// The passes of a network of `model`, by name: what each issued.
fn passes(model: &Config) -> BTreeMap<&'static str, Vec<Issued>> {
    let mut out: BTreeMap<&'static str, Vec<Issued>> = BTreeMap::new();
    let mut add = |pass: &'static str, r: Report| out.entry(pass).or_default().extend(r.issued);
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());

    // The default training step (making the trainer, a one-pass step, a step in 4 chunks),
    // then inference (`render_rays`) with the trained model, each with the parity numerics,
    // the generic kernels, and the bf16 trunk.
    let variants: [(&'static str, &'static str, Numerics); 3] = [
        ("train", "inference", Numerics::PARITY),
        (
            "train (generic kernels)",
            "inference (generic kernels)",
            GENERIC,
        ),
        (
            "train (bf16 trunk)",
            "inference (bf16 trunk)",
            Numerics {
                bf16_trunk: true,
                ..Numerics::PARITY
            },
        ),
    ];
    for (train, infer, numerics) in variants {
        let (mut one, mut source, made) = trainer(&data, model, |r| r.numerics = numerics);
        add(train, made);
        add(train, step(&mut one, &mut source));
        let (mut chunked, mut s, _) = trainer(&data, model, |r| {
            r.numerics = numerics;
            r.train.chunk_rays = 16;
        });
        add(train, step(&mut chunked, &mut s));
        let batch = source.next_batch().unwrap();
        for r in inference(one.avatar(), &batch, &PassOptions::parity()) {
            add(infer, r);
        }
    }

    // The ablation variants (`pma ablate`): making each, a step, an inference pass.
    for variant in Variant::ALL.into_iter().filter(|v| !v.is_full()) {
        let model = Config {
            variant,
            ..model.clone()
        };
        let (mut t, mut source, made) = trainer(&data, &model, |_| {});
        add("variants", made);
        add("variants", step(&mut t, &mut source));
        let batch = source.next_batch().unwrap();
        for r in inference(t.avatar(), &batch, &PassOptions::parity()) {
            add("variants", r);
        }
    }

    // A checkpoint written and the run resumed from it.
    let (mut one, mut source, _) = trainer(&data, model, |_| {});
    one.advance(&source.next_batch().unwrap()).unwrap();
    one.read_back().unwrap();
    let ckpt = tempfile::tempdir().unwrap();
    let (_, r) = accounted(None, || one.save_checkpoint(ckpt.path()).unwrap());
    add("checkpoint", r);
    let run = one.run_config().clone();
    let (_, r) = accounted(None, || {
        Trainer::resume(ckpt.path(), run, data.clone(), &Device::Cpu).unwrap()
    });
    add("checkpoint", r);

    // Occupancy refreshes: every cell (the one that ends the warm-up), then a share.
    let batch = source.next_batch().unwrap();
    let avatar = one.avatar();
    let net = avatar.network();
    let pose = avatar.pose_features(&batch.poses, None).unwrap();
    let mut grid = OccupancyGrid::new(OccupancyConfig {
        resolution: 8,
        ..Default::default()
    })
    .unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    for cells in [CellChoice::All, CellChoice::Share(0.25)] {
        let opts = RefreshOptions { cells, decay: true };
        let (_, r) = accounted(Some(1 << 30), || {
            refresh(net, &mut grid, &batch.poses, &pose, opts, &mut rng).unwrap()
        });
        add("occupancy refresh", r);
    }

    // Culled passes: a training-mode pass that culls rays and samples (each fill); training
    // steps that cull and train the occupancy grid (the step that ends the warm-up refreshes
    // it, the next one consults and feeds it); inference passes that cull, consult the grid,
    // place the fine samples from it, stop early or group joints.
    let culling = |fill| Culling {
        rays: true,
        sample_threshold: Some(0.6),
        sample_fill: fill,
    };
    for fill in [SampleFill::Network, SampleFill::Zero] {
        let opts = PassOptions::culled(culling(fill));
        let (_, r) = accounted(None, || {
            avatar
                .forward(
                    &batch.rays,
                    &batch.poses,
                    &mut Mode::Train(None),
                    &opts,
                    None,
                )
                .unwrap()
        });
        add("culled", r);
    }
    let (mut fed, mut s, _) = trainer(&data, model, |r| {
        r.train.culling = culling(SampleFill::Network);
        r.train.occupancy = Some(OccupancyConfig {
            warmup_steps: 1,
            refresh_every: 1,
            ..OccupancyConfig::default()
        });
    });
    for _ in 0..2 {
        add("culled", step(&mut fed, &mut s));
    }
    let avatar = fed.avatar();
    assert!(avatar.occupancy().is_some(), "no grid after the warm-up");
    let options = [
        PassOptions::culled(culling(SampleFill::Network)),
        PassOptions::culled(culling(SampleFill::Zero)),
        PassOptions {
            occupancy: true,
            ..PassOptions::culled(culling(SampleFill::Network))
        },
        PassOptions {
            occupancy: true,
            occupancy_fine: true,
            ..PassOptions::default()
        },
        PassOptions {
            early_stop: Some(1e-3),
            cull_joints: true,
            ..PassOptions::culled(culling(SampleFill::Network))
        },
    ];
    for opts in &options {
        for r in inference(avatar, &batch, opts) {
            add("culled", r);
        }
    }

    // Culled passes whose rays all miss the body: every culled stage is empty.
    let away = missing_rays(&batch);
    for opts in &options {
        for r in inference(avatar, &away, opts) {
            add("culled (every ray misses)", r);
        }
    }
    let opts = PassOptions::culled(culling(SampleFill::Network));
    let (_, r) = accounted(None, || {
        avatar
            .forward(&away.rays, &away.poses, &mut Mode::Train(None), &opts, None)
            .unwrap()
    });
    add("culled (every ray misses)", r);

    // The fast recipe (`--fast`: culling, the grid, averaged weights) with the other
    // time-to-quality options: coarse samples placed from the grid, the error map's per-ray
    // errors and the annealed rates; the warm-up's step, then two that consult and feed the
    // grid.
    let (mut quick, s, _) = trainer(&data, model, |r| {
        pma_model::train::recipe::fast(r, None);
        r.train.coarse_from_grid = true;
        r.train.error_map = Some(pma_data::error_map::ErrorMapConfig::default());
        r.train.anneal = Some(pma_model::train::presets::Anneal::default());
        r.train.occupancy = Some(OccupancyConfig {
            warmup_steps: 1,
            refresh_every: 1,
            ..OccupancyConfig::default()
        });
    });
    let mut s = s
        .with_error_map(pma_data::error_map::ErrorMapConfig::default())
        .unwrap();
    for _ in 0..3 {
        add("fast recipe", step(&mut quick, &mut s));
    }
    out
}

/// `batch` with every ray starting far from the body and pointing away from it.
fn missing_rays(batch: &TrainBatch) -> TrainBatch {
    let n = batch.rays.origins.dim(0).unwrap();
    let dirs = Tensor::from_vec([0.6f32, 0.0, 0.8].repeat(n), (n, 3), &Device::Cpu).unwrap();
    let mut away = batch.clone();
    away.rays.origins = (&dirs * 50.0).unwrap();
    away.rays.dirs = dirs;
    away
}

/// The backend calls a custom op's CUDA forward makes itself, past the dispatch point (so
/// the hook does not see them): pma's fused product ops (`custom matmul`: the linear layer,
/// the linear-activation layer, the window pool of a product) run cuBLAS's x·Wᵀ on their
/// inputs (x as it is laid out, W transposed) and the linear layer the backend's bias add,
/// broadcast over the product's rows.
fn implied(i: &Issued) -> Vec<Issued> {
    let s = &i.sig;
    if !(s.custom && i.op == "matmul") {
        return Vec::new();
    }
    let [Some((d, x)), Some((_, w)), _] = s.inputs else {
        return Vec::new();
    };
    let gemm = |l| match l {
        Lay::Contiguous => Lay::Normal,
        other => other,
    };
    let wt = match w {
        Lay::Contiguous => Lay::Transposed,
        other => other,
    };
    let sig = |inputs: [Option<(DType, Lay)>; 3]| Sig {
        custom: false,
        inputs,
        ..*s
    };
    vec![
        Issued {
            op: "matmul",
            sig: sig([Some((d, gemm(x))), Some((d, wt)), None]),
        },
        Issued {
            op: "add",
            sig: sig([Some((d, Lay::Contiguous)), Some((d, Lay::Strided)), None]),
        },
    ]
}

/// Each pass's distinct signatures (with what its custom ops call past the hook), by text.
fn issued_by_pass(model: &Config) -> BTreeMap<&'static str, BTreeMap<String, Issued>> {
    passes(model)
        .into_iter()
        .map(|(pass, issued)| {
            let all = issued
                .iter()
                .flat_map(|i| std::iter::once(*i).chain(implied(i)))
                .map(|i| (i.to_string(), i))
                .collect();
            (pass, all)
        })
        .collect()
}

#[test]
fn the_cuda_route_issues_only_what_candles_cuda_backend_implements() {
    let rows = table();
    let by_pass = issued_by_pass(&Config::tiny());
    let mut all: BTreeMap<&str, (Issued, Vec<&str>)> = BTreeMap::new();
    for (pass, issued) in &by_pass {
        for (text, i) in issued {
            all.entry(text)
                .or_insert_with(|| (*i, Vec::new()))
                .1
                .push(pass);
        }
    }
    let mut summary: String = by_pass
        .iter()
        .map(|(pass, issued)| format!("\n  {pass:<28} {:>4}", issued.len()))
        .collect();
    summary += &format!("\n  {:<28} {:>4}", "all", all.len());
    eprintln!("distinct signatures the CUDA route issues:{summary}");
    if let Ok(path) = std::env::var("PMA_CUDA_COVERAGE_OUT") {
        let text: String = all
            .iter()
            .map(|(text, (_, p))| format!("{text}\t{}\n", p.join(",")))
            .collect();
        std::fs::write(&path, text).unwrap();
    }
    let missing: Vec<String> = all
        .iter()
        .filter(|(_, (i, _))| !rows.iter().any(|r| r.covers(i)))
        .map(|(text, (i, p))| {
            let near: Vec<usize> = rows
                .iter()
                .filter(|r| r.op == i.op && r.custom == i.sig.custom)
                .map(|r| r.line)
                .collect();
            format!("{text}  (issued by {p:?}; the table's lines of this op: {near:?})")
        })
        .collect();
    assert!(
        missing.is_empty(),
        "{} of {} signatures the CUDA route issues are not in fixtures/cuda-coverage.tsv \
         (what candle's CUDA backend implements):\n  {}{summary}",
        missing.len(),
        all.len(),
        missing.join("\n  ")
    );

    // The compute capability each signature needs: none when a row without one covers it.
    let needs: Vec<(String, &Vec<&str>)> = all
        .iter()
        .filter_map(|(text, (i, p))| {
            let covering = rows.iter().filter(|r| r.covers(i));
            let arch = covering.map(|r| r.arch.as_deref()).min()??;
            Some((format!("{text} needs {arch}"), p))
        })
        .collect();
    eprintln!("signatures that need a compute capability: {needs:#?}");
    let beyond: Vec<_> = needs
        .iter()
        .filter(|(_, p)| p.iter().any(|pass| !pass.ends_with("(bf16 trunk)")))
        .collect();
    assert!(
        beyond.is_empty(),
        "signatures outside the bf16 trunk that some GPUs lack: {beyond:#?}"
    );
}

/// `tiny`'s network takes every branch of the route that the `default` preset's does: the
/// same passes issue the same signatures. Ignored (9 minutes in the dev profile); run with
/// `cargo test -p pma-model --features train --test model cuda_coverage -- --ignored`.
#[test]
#[ignore]
fn the_default_networks_route_issues_what_the_tiny_one_does() {
    let all = |model: &Config| -> std::collections::BTreeSet<String> {
        issued_by_pass(model)
            .into_values()
            .flat_map(|m| m.into_keys())
            .collect()
    };
    let (tiny, default) = (all(&Config::tiny()), all(&Config::paper()));
    let only_default: Vec<_> = default.difference(&tiny).collect();
    let only_tiny: Vec<_> = tiny.difference(&default).collect();
    eprintln!(
        "{} signatures with tiny's network, {} with default's",
        tiny.len(),
        default.len()
    );
    assert!(
        only_default.is_empty() && only_tiny.is_empty(),
        "only with default's network: {only_default:#?}\nonly with tiny's: {only_tiny:#?}"
    );
}
