//! Occupancy grids end to end: `pma train --occupancy` and the run TOML save a grid with the
//! model, `pma occupancy build` gives one to a model trained without it, `--occupancy`
//! renders with it, and a model without a grid or with a bad grid tensor is refused (exit 2).

use std::path::{Path, PathBuf};

use crate::run::{exits_2_with, fails_with, ok, pma, s, tiny_scene, train_tiny_with};
use candle_core::Device;
use pma_model::network::occupancy::OccupancyGrid;
use pma_model::render::avatar::Avatar;

/// `tiny` trained on `scene` for 3 iterations with `extra` flags: the model's path.
fn train(scene: &Path, run: &Path, extra: &[&str]) -> PathBuf {
    train_tiny_with(scene, run, "3", extra, &[]);
    run.join("model.safetensors")
}

/// The occupancy grid saved with the model at `path`.
fn saved_grid(path: &Path) -> OccupancyGrid {
    Avatar::load(path, &Device::Cpu)
        .unwrap()
        .occupancy()
        .cloned()
        .expect("a grid")
}

fn render(model: &Path, scene_dir: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec![
        "render",
        "--model",
        s(model),
        "--data",
        s(scene_dir),
        "--split",
        "novel_view",
        "--frames",
        "0:1",
        "--out",
        s(out),
        "--no-gif",
        "--quiet",
    ];
    args.extend_from_slice(extra);
    pma(&args)
}

/// `pma occupancy build` of `model` over `scene` at 8³ cells into `out`, with `extra` flags.
fn build(model: &Path, scene: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec![
        "occupancy",
        "build",
        "--model",
        s(model),
        "--data",
        s(scene),
        "--resolution",
        "8",
        "--out",
        s(out),
        "--quiet",
    ];
    args.extend_from_slice(extra);
    pma(&args)
}

/// Overwrite the first value of the grid tensor of the checkpoint at `path` with NaN.
fn poison_grid(path: &Path) {
    let mut bytes = std::fs::read(path).unwrap();
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    let start = header["occupancy.density"]["data_offsets"][0]
        .as_u64()
        .unwrap() as usize;
    bytes[8 + n + start..8 + n + start + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    std::fs::write(path, bytes).unwrap();
}

#[test]
fn grids_from_training_and_from_build_render_and_bad_ones_are_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let scene_dir = tmp.path().join("scene");
    let scene = tiny_scene(&scene_dir, 1);

    // Parity training: no grid in the checkpoint.
    let plain = train(&scene, &tmp.path().join("plain"), &[]);
    assert!(Avatar::load(&plain, &Device::Cpu)
        .unwrap()
        .occupancy()
        .is_none());
    fails_with(
        render(&plain, &scene_dir, &tmp.path().join("v0"), &["--occupancy"]),
        "no occupancy grid",
    );
    let out = render(&plain, &scene_dir, &tmp.path().join("v0"), &["--occupancy"]);
    assert_eq!(out.status.code(), Some(2));

    // `pma occupancy build` adds one; the tensors are unchanged.
    let built = tmp.path().join("built.safetensors");
    let stdout = ok(build(&plain, &scene, &built, &["--poses", "2"])).stdout;
    assert!(
        String::from_utf8_lossy(&stdout).contains("occupancy grid: 2 poses"),
        "{}",
        String::from_utf8_lossy(&stdout)
    );
    let (a, b) = (
        Avatar::load(&plain, &Device::Cpu).unwrap(),
        Avatar::load(&built, &Device::Cpu).unwrap(),
    );
    let grid = b.occupancy().expect("a grid");
    assert_eq!((grid.config().resolution, grid.refreshes()), (8, 2));
    for (name, t) in a.tensors() {
        let flat = |t: &candle_core::Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(flat(&t), flat(&b.tensors()[&name]), "{name}");
    }
    assert_eq!(
        grid.config().extent,
        2.0,
        "without --cull-samples: the whole window"
    );
    // `--cull-samples T`: the grid spans only where a window can exceed T; a threshold
    // outside [0, 1) is refused naming the flag.
    let build_for =
        |t: &str, out: &Path| build(&plain, &scene, out, &["--poses", "1", "--cull-samples", t]);
    let narrow = tmp.path().join("narrow.safetensors");
    ok(build_for("0.6", &narrow));
    let n = Avatar::load(&narrow, &Device::Cpu).unwrap();
    let m = n.config();
    let want = pma_model::network::occupancy::window_extent(0.6, m.window_alpha, m.window_beta);
    assert_eq!(n.occupancy().unwrap().config().extent, want);
    ok(render(
        &narrow,
        &scene_dir,
        &tmp.path().join("v3"),
        &["--occupancy", "--cull-samples", "0.6"],
    ));
    let out = build_for("1.5", &tmp.path().join("bad.safetensors"));
    exits_2_with(out, "--cull-samples");
    ok(render(
        &built,
        &scene_dir,
        &tmp.path().join("v1"),
        &["--occupancy"],
    ));
    assert!(tmp.path().join("v1/frame_0000.png").is_file());

    // A NaN in the grid tensor: refused with exit 2, naming the tensor.
    poison_grid(&built);
    let out = render(&built, &scene_dir, &tmp.path().join("v2"), &[]);
    exits_2_with(out, "occupancy.density");

    // `pma train --occupancy`: the grid is saved with the model; a resumed run cannot
    // switch it on.
    let run = tmp.path().join("occ");
    let model = train(&scene, &run, &["--occupancy"]);
    let grid = saved_grid(&model);
    assert_eq!(grid.config().resolution, 32);
    let out = pma(&[
        "train",
        "--data",
        s(&scene),
        "--out",
        s(&run),
        "--resume",
        "--iters",
        "4",
        "--occupancy",
        "--quiet",
    ]);
    assert_eq!(out.status.code(), Some(2));

    // The run TOML's `[train.occupancy]` table: a grid built after one warm-up step.
    let config = tmp.path().join("run.toml");
    std::fs::write(
        &config,
        "preset = \"tiny\"\n[train.occupancy]\nresolution = 8\nwarmup_steps = 1\nrefresh_every = 1\n",
    )
    .unwrap();
    let model = train(&scene, &tmp.path().join("toml"), &["--config", s(&config)]);
    let grid = saved_grid(&model);
    assert_eq!(grid.config().resolution, 8);
    assert_eq!(
        grid.refreshes(),
        3,
        "built after step 1, refreshed after steps 2 and 3"
    );
    // A bad table is refused with exit 2.
    std::fs::write(
        &config,
        "preset = \"tiny\"\n[train.occupancy]\nresolution = 1\n",
    )
    .unwrap();
    let out = pma(&[
        "train",
        "--data",
        s(&scene),
        "--out",
        s(&tmp.path().join("bad")),
        "--config",
        s(&config),
        "--iters",
        "1",
        "--quiet",
    ]);
    exits_2_with(out, "occupancy.resolution");
}
