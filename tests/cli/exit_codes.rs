//! One rule for exit codes in every command: refused input exits 2 with a message that names
//! what was wrong. One refused input per command, each refused before any real work.

use std::path::Path;

use crate::convert::rewrite_npz;
use crate::run::{pma, pma_eval, refused, s, tiny_scene};

#[test]
fn refused_input_exits_2_in_every_command() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let train = tiny_scene(&dir.join("scene"), 2);
    let scene = dir.join("scene");
    let garbage = dir.join("garbage.safetensors");
    std::fs::write(&garbage, b"this is not a safetensors file").unwrap();
    let nan_bones = dir.join("nan_bones.npz");
    rewrite_npz(&train, &nan_bones, "bones", |v| v[4] = f32::NAN);
    let out = dir.join("out");
    // Outputs have somewhere to go: what is refused here is the input.
    std::fs::create_dir_all(&out).unwrap();
    let cfg = dir.join("bad.toml");
    std::fs::write(&cfg, "preset = \"tiny\"\n[train]\nrays_per_stp = 4\n").unwrap();

    refused(&pma(&["synth", "--out", s(&out), "--res", "0"]), &["res"]);
    refused(
        &pma(&["inspect", s(&nan_bones)]),
        &["nan_bones.npz", "bones"],
    );
    refused(
        &pma(&[
            "forward",
            "--model",
            s(&garbage),
            "--batch",
            s(&train),
            "--out",
            s(&out.join("o.npz")),
        ]),
        // A dataset is not a ray batch.
        &["train.npz", "rays_o"],
    );
    refused(
        &pma(&[
            "convert",
            "checkpoint",
            s(&garbage),
            "-o",
            s(&out.join("c.safetensors")),
        ]),
        &["garbage.safetensors"],
    );
    refused(
        &pma(&[
            "train",
            "--data",
            s(&train),
            "--out",
            s(&out.join("run")),
            "--config",
            s(&cfg),
        ]),
        &["train.rays_per_stp"],
    );
    refused(
        &pma(&[
            "train",
            "--data",
            s(&nan_bones),
            "--out",
            s(&out.join("run")),
            "--preset",
            "tiny",
        ]),
        &["nan_bones.npz", "bones"],
    );
    let model = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/golden/model.safetensors");
    refused(
        &pma_eval(&model, &scene, &["--split", "novel_vew"]),
        &["novel_vew"],
    );
    refused(
        &pma(&["demo", "--out", s(&out.join("demo")), "--preset", "huge"]),
        &["huge"],
    );
    refused(
        &pma(&[
            "render",
            "--model",
            s(&garbage),
            "--data",
            s(&scene),
            "--res",
            "0x0",
            "--out",
            s(&out.join("r")),
        ]),
        &["0x0"],
    );
    refused(
        &pma(&["mesh", "--model", s(&garbage), "-o", s(&out.join("m.ply"))]),
        &["garbage.safetensors"],
    );
    refused(
        &pma(&[
            "bench",
            "--quick",
            "--thresholds",
            "2",
            "--out",
            s(&out.join("b")),
        ]),
        &["--thresholds"],
    );
    refused(
        &pma(&["check-stability", "--model", s(&garbage)]),
        &["garbage.safetensors"],
    );
}
