//! `pma doctor` on the CPU (its kernel checks on the emulated grid, the golden case on both
//! routes, a burst), and a run's first contact with failures: a kernel that fails (injected
//! with `PMA_KERNEL_FAULT`) steps aside and the run goes on; a device out of memory
//! (`PMA_FAULT_OOM_RAYS`) halves the chunk and retries the same step.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use crate::run::{ok, pma, pma_env, read_json, tiny_scene, train_tiny_with};
use candle_core::{Device, Tensor};

/// [`train_tiny_with`] into `out`: the model's path and the run's stderr.
fn trained(
    data: &Path,
    out: &Path,
    iters: &str,
    extra: &[&str],
    env: &[(&str, &str)],
) -> (PathBuf, String) {
    let o = train_tiny_with(data, out, iters, extra, env);
    let stderr = String::from_utf8_lossy(&o.stderr).to_string();
    (out.join("model.safetensors"), stderr)
}

fn rows<'a>(r: &'a serde_json::Value, section: &str) -> Vec<&'a serde_json::Value> {
    r["checks"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| c["section"] == section)
        .collect()
}

#[test]
fn doctor_passes_on_the_cpu_and_writes_its_report() {
    let tmp = tempfile::tempdir().unwrap();
    let json = tmp.path().join("doctor.json");
    let out = ok(pma(&[
        "doctor",
        "--steps",
        "3",
        "--preset",
        "tiny",
        "--quiet",
        "--json",
        json.to_str().unwrap(),
    ]));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("checks passed"), "{stdout}");
    let r = read_json(&json);
    assert_eq!(r["passed"], true);
    assert_eq!(r["device"]["spec"], "cpu");
    // Two rows per kernel module (compiled, checked), each checked case by case.
    let kernels = rows(&r, "kernels");
    assert_eq!(kernels.len(), 12, "{kernels:?}");
    for c in &kernels {
        assert_eq!(c["passed"], true, "{c}");
    }
    let checked: Vec<_> = kernels
        .iter()
        .filter(|c| c["max_err"].is_number())
        .collect();
    assert_eq!(checked.len(), 6);
    // The golden case on the CPU's route and on the CUDA route, emulated: the forward, the
    // gradients and the Adam step, all within their tolerances.
    for section in ["golden, cpu route", "golden, cuda route (emulated)"] {
        let g = rows(&r, section);
        assert!(g.len() >= 30, "{section}: {} rows", g.len());
        for what in [
            "forward fine rgb",
            "gradient norms",
            "Adam step: update norms",
        ] {
            assert!(
                g.iter()
                    .any(|c| c["what"].as_str().unwrap().starts_with(what)),
                "{section}: {what}"
            );
        }
        for c in g {
            assert!(
                c["max_err"].as_f64().unwrap() <= c["tol"].as_f64().unwrap(),
                "{c}"
            );
        }
    }
    assert_eq!(r["burst"]["steps"], 3);
    assert!(r["burst"]["it_per_s"].as_f64().unwrap() > 0.0);
    assert!(r["burst"]["peak_memory_bytes"].as_u64().unwrap() > 0);
    for (_, state) in r["kernel_states"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| (&p[0], &p[1]))
    {
        assert_eq!(state, "on");
    }
}

/// A kernel whose results are wrong (caught by its first-use check), one that does not
/// compile and one whose launch errors: each is named once on stderr, the doctor exits 1
/// and its report says which failed; the others pass.
#[test]
fn doctor_names_each_broken_kernel_and_exits_1() {
    let tmp = tempfile::tempdir().unwrap();
    let json = tmp.path().join("doctor.json");
    let out = pma_env(
        &[
            "doctor",
            "--no-golden",
            "--steps",
            "0",
            "--quiet",
            "--json",
            json.to_str().unwrap(),
        ],
        &[(
            "PMA_KERNEL_FAULT",
            "film_sine=wrong,rows=compile,adam=launch",
        )],
    );
    assert_eq!(out.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&out.stderr);
    for m in ["film_sine", "rows", "adam"] {
        let needle = format!("warning: kernel {m} switched off");
        assert_eq!(stderr.matches(&needle).count(), 1, "{m}: {stderr}");
    }
    assert!(stderr.contains("its first-use check found"), "{stderr}");
    assert!(
        stderr
            .lines()
            .last()
            .unwrap()
            .starts_with("error: doctor: 4 of 12 checks failed"),
        "{stderr}"
    );
    let r = read_json(&json);
    assert_eq!(r["passed"], false);
    let failed: Vec<String> = rows(&r, "kernels")
        .iter()
        .filter(|c| c["passed"] == false)
        .map(|c| c["what"].as_str().unwrap().to_string())
        .collect();
    assert_eq!(failed.len(), 4, "{failed:?}");
    for m in [
        "film_sine against",
        "rows compiles",
        "rows against",
        "adam against",
    ] {
        assert!(failed.iter().any(|w| w.starts_with(m)), "{m}: {failed:?}");
    }
}

fn tensors(path: &Path) -> HashMap<String, Vec<f32>> {
    candle_core::safetensors::load(path, &Device::Cpu)
        .unwrap()
        .into_iter()
        .map(|(k, t): (String, Tensor)| (k, t.flatten_all().unwrap().to_vec1::<f32>().unwrap()))
        .collect()
}

/// The largest difference of any parameter between two models, relative to the largest
/// magnitude of that parameter.
fn max_relative_diff(a: &Path, b: &Path) -> f32 {
    let (ta, tb) = (tensors(a), tensors(b));
    assert_eq!(ta.len(), tb.len());
    ta.iter()
        .map(|(k, x)| {
            let y = &tb[k];
            let scale = x.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-12);
            x.iter().zip(y).fold(0f32, |m, (p, q)| m.max((p - q).abs())) / scale
        })
        .fold(0f32, f32::max)
}

/// The one line of `text` that `pick` picks; the test fails on none or several.
fn only_line(text: &str, pick: impl Fn(&str) -> bool) -> &str {
    let picked: Vec<&str> = text.lines().filter(|l| pick(l)).collect();
    assert_eq!(picked.len(), 1, "{text}");
    picked[0]
}

/// 50 `tiny` steps with the window pool's kernel failing from its 7th launch on (a
/// backward mid-step) and with every kernel off (`--generic-kernels`): both runs go on to
/// the end, the first with one warning line naming the kernel, and end within 1e-5
/// (relative to each parameter's largest value) of the run on pma's kernels: the generic
/// ops compute the same numbers, up to the sign of a zero where the window pool's joints
/// tie and float rounding that Adam carries over 50 steps.
#[test]
fn a_failing_kernel_steps_aside_and_the_run_goes_on() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"), 2);
    let run = |name: &str, extra: &[&str], env: &[(&str, &str)]| {
        trained(&data, &tmp.path().join(name), "50", extra, env)
    };
    let (fused, _) = run("fused", &[], &[]);
    let (stepped_aside, stderr) = run(
        "fault",
        &[],
        &[("PMA_KERNEL_FAULT", "window_pool=launch@7")],
    );
    let warning = only_line(&stderr, |l| l.starts_with("warning: kernel"));
    assert!(
        warning.contains("window_pool") && warning.contains("launch 7"),
        "{stderr}"
    );
    let (generic, _) = run("generic", &["--generic-kernels"], &[]);
    let d_fault = max_relative_diff(&fused, &stepped_aside);
    let d_generic = max_relative_diff(&fused, &generic);
    eprintln!("max relative parameter difference after 50 steps: fault {d_fault:e}, --generic-kernels {d_generic:e}");
    assert!(d_fault <= 1e-5, "{d_fault}");
    assert!(d_generic <= 1e-5, "{d_generic}");
}

/// A step whose chunk runs out of device memory (injected: chunks of more than 20 rays)
/// is retried with the chunk halved until it fits (64 → 32 → 16 rays), said once; the run
/// keeps that chunk, and is then the run that asked for it, bit for bit.
#[test]
fn out_of_memory_halves_the_chunk_and_retries_the_same_step() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tiny_scene(&tmp.path().join("scene"), 2);
    let run = |name: &str, chunk: &str, env: &[(&str, &str)]| {
        let extra = ["--chunk-rays", chunk, "--workers", "2"];
        trained(&data, &tmp.path().join(name), "8", &extra, env)
    };
    let (asked, _) = run("asked", "16", &[]);
    let (halved, stderr) = run("halved", "64", &[("PMA_FAULT_OOM_RAYS", "20")]);
    let note = only_line(&stderr, |l| l.contains("out of device memory"));
    assert!(
        note.contains("at 64 rays per chunk") && note.contains("retried at 16"),
        "{stderr}"
    );
    assert_eq!(max_relative_diff(&asked, &halved), 0.0);
    let (ta, tb) = (tensors(&asked), tensors(&halved));
    for (k, x) in &ta {
        let same = x
            .iter()
            .zip(&tb[k])
            .all(|(p, q)| p.to_bits() == q.to_bits());
        assert!(same, "{k} differs");
    }
}
