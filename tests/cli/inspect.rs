//! `pma inspect`: the schema summary of a valid file (exit 0) and the validation error of a
//! broken one (non-zero exit, key named).

use std::path::Path;

use crate::run::pma;
use pma_data::dataset::{Dataset, Profile, ReadOptions, WriteOptions};

fn tiny_scene(dir: &Path) {
    let cfg = pma_data::synth::SynthConfig::small(16, 2, 2);
    pma_data::synth::generate(&cfg, dir, &mut |_, _| {}).expect("synth");
}

#[test]
fn inspect_summarises_a_valid_file() {
    let tmp = tempfile::tempdir().unwrap();
    tiny_scene(tmp.path());
    let out = pma(&["inspect", tmp.path().join("train.npz").to_str().unwrap()]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for want in [
        "profile: train (auto)",
        "imgs",
        "|u1",
        "[4, 256, 3]",
        "N = 4 images",
        "validation: ok",
    ] {
        assert!(stdout.contains(want), "missing {want:?} in\n{stdout}");
    }
    let out = pma(&[
        "inspect",
        tmp.path().join("novel_pose.npz").to_str().unwrap(),
    ]);
    assert!(out.status.success());
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("0 novel view, 4 novel pose"), "{stdout}");
    // Without sampling masks the most demanding profile the file supports is eval.
    let mut ds = Dataset::read(
        tmp.path().join("novel_pose.npz"),
        &ReadOptions::new(Profile::Eval),
    )
    .unwrap();
    ds.sampling_masks = None;
    let p = tmp.path().join("eval_only.npz");
    ds.write(&p, &WriteOptions::default()).unwrap();
    let out = pma(&["inspect", p.to_str().unwrap()]);
    assert!(out.status.success());
    assert!(String::from_utf8_lossy(&out.stdout).contains("profile: eval (auto)"));
    // Forcing the train profile names the missing key.
    let out = pma(&["inspect", p.to_str().unwrap(), "--profile", "train"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("sampling_masks") && err.contains("train"),
        "{err}"
    );
}

#[test]
fn inspect_fails_on_an_invalid_file_and_names_the_key() {
    let tmp = tempfile::tempdir().unwrap();
    tiny_scene(tmp.path());
    let mut ds = Dataset::read(
        tmp.path().join("train.npz"),
        &ReadOptions::new(Profile::Train),
    )
    .unwrap();
    ds.focals.as_mut().unwrap()[[0, 1]] = -3.0;
    let bad = tmp.path().join("bad.npz");
    ds.write(&bad, &WriteOptions::default()).unwrap();
    let out = pma(&["inspect", bad.to_str().unwrap()]);
    assert!(!out.status.success(), "an invalid file passed inspection");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("focals") && err.contains("bad.npz"), "{err}");
    assert!(String::from_utf8_lossy(&out.stdout).contains("validation: FAILED"));
}
