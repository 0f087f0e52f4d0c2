//! `pma synth` end to end: a tiny scene is written as three valid pma-npz files, the same
//! seed gives byte-identical files, another seed changes the pixels, and bad settings fail
//! with the setting named.

use crate::run::{ok, pma};
use std::path::Path;
use std::process::Output;

fn synth(dir: &Path, seed: &str) -> Output {
    pma(&[
        "synth",
        "--out",
        dir.to_str().unwrap(),
        "--res",
        "16",
        "--train-cams",
        "2",
        "--test-cams",
        "1",
        "--frames",
        "2",
        "--novel-pose-walk",
        "1",
        "--novel-pose-dance",
        "1",
        "--seed",
        seed,
        "--quiet",
    ])
}

#[test]
fn synth_writes_valid_deterministic_splits() {
    let tmp = tempfile::tempdir().unwrap();
    let (a, b, c) = (
        tmp.path().join("a"),
        tmp.path().join("b"),
        tmp.path().join("c"),
    );
    let out = ok(synth(&a, "3"));
    let stdout = String::from_utf8_lossy(&out.stdout);
    for split in ["train", "novel_view", "novel_pose"] {
        assert!(stdout.contains(split), "{stdout}");
    }
    ok(synth(&b, "3"));
    ok(synth(&c, "4"));
    for name in [
        "train.npz",
        "novel_view.npz",
        "novel_pose.npz",
        "scene.json",
    ] {
        let (x, y) = (
            std::fs::read(a.join(name)).unwrap(),
            std::fs::read(b.join(name)).unwrap(),
        );
        assert!(x == y, "{name} differs between two runs with the same seed");
    }
    assert!(a.join("preview.png").is_file());
    assert_ne!(
        std::fs::read(a.join("train.npz")).unwrap(),
        std::fs::read(c.join("train.npz")).unwrap(),
        "another seed gave the same training file"
    );

    use pma_data::dataset::{Dataset, Profile, ReadOptions};
    let train = Dataset::read(a.join("train.npz"), &ReadOptions::new(Profile::Train)).unwrap();
    // 2 training cameras x 2 frames, 16x16.
    assert_eq!(train.img_shape, Some([4, 16, 16, 3]));
    let view = Dataset::read(a.join("novel_view.npz"), &ReadOptions::new(Profile::Eval)).unwrap();
    assert!(view.eval_tag.unwrap().iter().all(|&t| t == 1));
}

#[test]
fn synth_rejects_bad_settings_by_name() {
    let tmp = tempfile::tempdir().unwrap();
    let out = pma(&[
        "synth",
        "--out",
        tmp.path().join("x").to_str().unwrap(),
        "--res",
        "4",
        "--quiet",
    ]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("res") && err.contains('4'), "{err}");
}
