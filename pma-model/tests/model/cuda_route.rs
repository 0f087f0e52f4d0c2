//! The CUDA route composed on the CPU: a CPU run accounted as CUDA takes every branch a CUDA
//! device takes (device ray casting and importance sampling, one network call per pass for
//! all poses, the flat masked Adam update) and runs pma's kernels as their host builds on
//! the emulated grid, so all of the route but candle's CUDA backend and the driver runs here.
//! Checked against the official code's golden outputs, and over 50 training steps against
//! the CPU's route.

use std::sync::Arc;

use candle_core::Device;
use pma_model::compute::account::{Account, Report, Route};
use pma_model::doctor::golden::{self, Golden};

use crate::common::fixtures;
use crate::train_support::{tiny_run, tiny_scene};

fn on_the_cuda_route<T>(f: impl FnOnce() -> T) -> (T, Report) {
    let account = Account::start(&Device::Cpu, Route::Cuda).unwrap();
    let out = f();
    (out, account.finish())
}

/// The golden forward stage by stage, the gradients and one Adam step on the emulated
/// CUDA route, each within the doctor's tolerances (forward 1e-4, gradients 2e-3 of the
/// largest entry for the cancellation-bound sums, Adam's losses 1e-5 and its parameters
/// 2e-4; `pma_model::doctor::golden`), with the kernels that route launches really run.
#[test]
fn the_golden_case_on_the_emulated_cuda_route() {
    let dev = Device::Cpu;
    let g = Golden::load(&fixtures().join("golden"), &dev).unwrap();
    let (rows, report) = on_the_cuda_route(|| {
        let mut rows = golden::forward(&g, &dev, "cuda route").unwrap();
        rows.extend(golden::gradients(&g, &dev, "cuda route").unwrap());
        rows.extend(golden::adam_step(&g, &dev, "cuda route").unwrap());
        rows
    });
    let mut failed = Vec::new();
    for r in &rows {
        eprintln!(
            "{:<60} {:>10.2e} (tolerance {:.0e})",
            r.what,
            r.max_err.unwrap(),
            r.tol.unwrap()
        );
        if !r.passed {
            failed.push(r.what.clone());
        }
    }
    assert!(rows.len() >= 30);
    assert!(failed.is_empty(), "{failed:?}");
    let launches = |op: &str| report.ops.get(op).map_or(0, |c| c.launches);
    for op in [
        "pma-window-pool",
        "pma-window-pool-grad",
        "pma-film-sine",
        "pma-film-sine-grad",
        "pma-sine-linear",
        "pma-sine-linear-grad",
        "pma-bias-relu",
        "pma-relu-grad",
        "pma-bias-sine",
        "pma-gather-rows",
        "pma-scatter-add-rows",
        "pma-adam",
    ] {
        assert!(
            launches(op) > 0,
            "{op} did not run: {:?}",
            report.ops.keys()
        );
    }
    // Ray casting and importance sampling as device tensor ops, and nothing read back
    // inside the training step (the step's numbers are read once, after it).
    let cast = report
        .stages
        .iter()
        .find(|s| s.name == "cast")
        .expect("a cast stage");
    assert!(cast.counts.ops > 50, "{} ops", cast.counts.ops);
}

/// 50 `tiny` steps on the emulated CUDA route against 50 on the CPU's route, from the same
/// initialisation and batches: the kernels sum some gradients per block of rows where the
/// CPU sums row by row, and the device route casts rays in its own float order, so the
/// runs differ by rounding, which Adam carries; they stay within 1e-4 of each parameter's
/// largest value, and both learn (the loss falls).
#[test]
fn fifty_tiny_steps_on_the_emulated_cuda_route_match_the_cpu_route() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"));
    let train = |data: &Arc<pma_data::dataset::Dataset>| {
        let mut t = pma_model::train::Trainer::new(tiny_run(), data.clone(), &Device::Cpu).unwrap();
        let first = t.step_read().unwrap().loss.total;
        for _ in 1..49 {
            t.step().unwrap();
        }
        let last = t.step_read().unwrap().loss.total;
        let params: Vec<(String, Vec<f32>)> = t
            .avatar()
            .trainable()
            .into_iter()
            .map(|(n, v)| {
                (
                    n,
                    v.as_tensor()
                        .flatten_all()
                        .unwrap()
                        .to_vec1::<f32>()
                        .unwrap(),
                )
            })
            .collect();
        (first, last, params)
    };
    let cpu = train(&data);
    let (cuda, report) = on_the_cuda_route(|| train(&data));
    assert!(report.ops.get("pma-adam").is_some_and(|c| c.launches == 50));
    let mut worst = (0f32, String::new());
    for ((name, a), (_, b)) in cpu.2.iter().zip(&cuda.2) {
        let scale = a.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-12);
        let d = a.iter().zip(b).fold(0f32, |m, (x, y)| m.max((x - y).abs())) / scale;
        if d > worst.0 || d.is_nan() {
            worst = (d, name.clone());
        }
    }
    eprintln!(
        "loss {:.4} -> {:.4} (cpu) and {:.4} -> {:.4} (cuda route); largest parameter difference {:e} ({})",
        cpu.0, cpu.1, cuda.0, cuda.1, worst.0, worst.1
    );
    assert!(worst.0 <= 1e-4, "{worst:?}");
    assert!(cpu.1 < cpu.0 && cuda.1 < cuda.0);
}
