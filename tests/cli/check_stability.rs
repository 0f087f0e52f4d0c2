//! `pma check-stability`: the probe table on a fresh avatar and on a checkpoint, a non-zero
//! exit when a checkpoint produces non-finite values, and the probes of a model with an
//! occupancy grid run with the grid on.

use std::path::Path;

use candle_core::{Device, Tensor};
use pma_model::render::avatar::Avatar;
use pma_model::Config;

use crate::run::{number_before, ok, patterned_grid, pma, refused, s};

#[test]
fn fresh_tiny_avatar_passes_and_prints_every_case() {
    let out = ok(pma(&[
        "check-stability",
        "--preset",
        "tiny",
        "--quiet",
        "--fixes",
        "--strict",
    ]));
    let stdout = String::from_utf8_lossy(&out.stdout);
    for case in [
        "pose: every joint pi about x",
        "AIST++ frame",
        "gamma 1e4",
        "axis scale",
        "composite all-zero density",
        "ray bounds",
    ] {
        assert!(stdout.contains(case), "missing `{case}` in\n{stdout}");
    }
    assert!(
        stdout.contains("non-finite values: 0; broken invariants: 0"),
        "{stdout}"
    );
}

#[test]
fn a_poisoned_checkpoint_fails() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = Config {
        n_framecodes: 2,
        ..Config::tiny()
    };
    let a = Avatar::new(cfg.clone(), &pma_data::synth::rest_pose(), 0, &Device::Cpu).unwrap();
    let good = tmp.path().join("good.safetensors");
    a.save(&good).unwrap();
    ok(pma(&["check-stability", "--quiet", "--model", s(&good)]));

    // A NaN in the density head reaches every output.
    let mut t = a.tensors();
    let b = t["sigma_linear.bias"].clone();
    t.insert(
        "sigma_linear.bias".into(),
        Tensor::full(f32::NAN, b.shape(), &Device::Cpu).unwrap(),
    );
    let bad = tmp.path().join("bad.safetensors");
    Avatar::from_tensors(cfg, t, &Device::Cpu)
        .unwrap()
        .save(&bad)
        .unwrap();
    let out = pma(&["check-stability", "--quiet", "--model", s(&bad)]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(!out.status.success(), "{stdout}");
    assert!(String::from_utf8_lossy(&out.stderr).contains("non-finite"));
}

#[test]
fn a_model_with_a_grid_is_probed_with_the_grid_on() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = Config {
        n_framecodes: 2,
        ..Config::tiny()
    };
    let plain = Avatar::new(cfg, &pma_data::synth::rest_pose(), 0, &Device::Cpu).unwrap();
    let plain_path = tmp.path().join("plain.safetensors");
    plain.save(&plain_path).unwrap();
    let gridded_path = tmp.path().join("grid.safetensors");
    plain
        .with_occupancy(Some(patterned_grid(11)))
        .save(&gridded_path)
        .unwrap();
    let probe = |model: &Path, extra: &[&str]| {
        // `--fixes` rebuilds the avatar from its tensors: the grid has to survive that too.
        let args = [
            "check-stability",
            "--quiet",
            "--fixes",
            "--strict",
            "--model",
        ];
        pma(&[&args[..], &[s(model)], extra].concat())
    };

    // The grid is on without asking: every forward probe consults it and it skips samples.
    let out = ok(probe(&gridded_path, &[]));
    let stdout = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(stdout.contains("skipped (empty)"), "{stdout}");
    let summary = stdout
        .lines()
        .find(|l| l.starts_with("occupancy grid: on in "))
        .unwrap_or_else(|| panic!("no grid summary in\n{stdout}"));
    let on = number_before(summary, "of");
    let forward = number_before(summary, "forward probes");
    assert_eq!(on, forward, "{summary}");
    // Extreme poses, the γ and the axis-scale probes: every one renders through the grid.
    assert!(forward >= 20, "{summary}");
    let rest = &summary[summary.find(';').unwrap()..];
    let skipped_samples = number_before(rest, "of");
    let total_samples = number_before(rest, "samples skipped");
    assert!(
        skipped_samples > 0 && skipped_samples < total_samples,
        "{summary}"
    );
    assert!(
        stdout.contains("non-finite values: 0; broken invariants: 0"),
        "{stdout}"
    );

    // The same with `--occupancy` said out loud, and the parity route with `--no-occupancy`.
    let same = probe(&gridded_path, &["--occupancy"]);
    assert!(same.status.success());
    assert_eq!(String::from_utf8_lossy(&same.stdout), stdout);
    let off = probe(&gridded_path, &["--no-occupancy"]);
    let off_stdout = String::from_utf8_lossy(&off.stdout);
    assert!(off.status.success(), "{off_stdout}");
    assert!(
        off_stdout.contains("occupancy grid: off (") && !off_stdout.contains("skipped (empty)"),
        "{off_stdout}"
    );

    // `--occupancy` on a model without a grid: exit 2, one line naming the flag.
    refused(
        &probe(&plain_path, &["--occupancy"]),
        &["--occupancy", "no occupancy grid"],
    );
}
