//! `pma convert` exit status and messages: 0 on success; 2 with one line on
//! stderr naming the file and the key or offset when an input is refused, and
//! no output file; 1 when the output cannot be written.

use std::{
    path::{Path, PathBuf},
    process::{Command, Output},
};

use pma_data::dataset::npz::{MemberData, NpzWriter};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn fixture(name: &str) -> PathBuf {
    root().join("fixtures/convert").join(name)
}

fn pma(args: &[&str], paths: &[&Path]) -> Output {
    let mut c = Command::new(env!("CARGO_BIN_EXE_pma"));
    c.arg("convert").args(args);
    for p in paths {
        c.arg(p);
    }
    c.output().unwrap()
}

/// Asserts a refusal: exit 2, exactly one non-empty stderr line holding every needle.
fn refused(out: &Output, needles: &[&str]) -> String {
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert_eq!(out.status.code(), Some(2), "stderr: {err}");
    let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(lines.len(), 1, "expected one line, got:\n{err}");
    for n in needles {
        assert!(lines[0].contains(n), "{n:?} missing from: {}", lines[0]);
    }
    lines[0].to_string()
}

#[test]
fn a_checkpoint_converts_with_exit_0() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("m.safetensors");
    let o = pma(
        &["checkpoint"],
        &[
            &root().join("fixtures/golden/ckpt.th"),
            Path::new("-o"),
            &out,
        ],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.is_file());
}

#[test]
fn hostile_corrupt_and_mismatched_checkpoints_exit_2_without_output() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("m.safetensors");
    let o = pma(
        &["checkpoint"],
        &[&fixture("evil_global.th"), Path::new("-o"), &out],
    );
    refused(&o, &["evil_global.th", "byte", "posix", "system"]);
    let o = pma(
        &["checkpoint"],
        &[&fixture("evil_opcode.th"), Path::new("-o"), &out],
    );
    refused(&o, &["evil_opcode.th", "byte", "NEWOBJ"]);
    // Several problems, joined into the one line.
    let o = pma(
        &["checkpoint"],
        &[&fixture("bad_config.th"), Path::new("-o"), &out],
    );
    refused(
        &o,
        &["bad_config.th", "pts_linears.5.weight", "[256, 1000]"],
    );

    let bytes = std::fs::read(fixture("ckpt_adam.th")).unwrap();
    let cut = dir.path().join("cut.th");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let o = pma(
        &["checkpoint", "--with-optimizer"],
        &[&cut, Path::new("-o"), &out],
    );
    refused(&o, &["cut.th"]);
    let o = pma(
        &["checkpoint"],
        &[&dir.path().join("absent.th"), Path::new("-o"), &out],
    );
    refused(&o, &["absent.th"]);
    assert!(!out.exists());
    assert!(!dir.path().join("m.optim.safetensors").exists());
}

#[test]
fn an_unwritable_output_exits_1() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("no/such/dir/m.safetensors");
    let o = pma(
        &["checkpoint"],
        &[
            &root().join("fixtures/golden/ckpt.th"),
            Path::new("-o"),
            &out,
        ],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("no/such/dir"), "{err}");
}

#[test]
fn bad_datasets_exit_2_naming_file_and_key() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("d.npz");
    let o = pma(
        &["dataset"],
        &[&fixture("masks255.h5"), Path::new("-o"), &out],
    );
    refused(&o, &["masks255.h5", "masks", "255"]);

    let bytes = std::fs::read(fixture("aist.h5")).unwrap();
    let cut = dir.path().join("cut.h5");
    std::fs::write(&cut, &bytes[..bytes.len() / 3]).unwrap();
    let o = pma(&["dataset"], &[&cut, Path::new("-o"), &out]);
    refused(&o, &["cut.h5"]);
    assert!(!out.exists());

    // A good conversion, then the same npz with a non-finite camera.
    let o = pma(
        &["dataset"],
        &[&fixture("perfcap.h5"), Path::new("-o"), &out],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let bad = dir.path().join("nan_cam.npz");
    rewrite_npz(&out, &bad, "c2ws", |v| v[5] = f32::NAN);
    let out2 = dir.path().join("d2.npz");
    let o = pma(&["dataset"], &[&bad, Path::new("-o"), &out2]);
    refused(&o, &["nan_cam.npz", "c2ws"]);
    assert!(!out2.exists());
}

/// Copies an npz, passing the f32 member `key` through `edit`.
pub(crate) fn rewrite_npz(from: &Path, to: &Path, key: &str, edit: impl Fn(&mut Vec<f32>)) {
    use pma_data::dataset::npz::{NpyData, NpzReader};
    let mut r = NpzReader::open(from).unwrap();
    let mut w = NpzWriter::new(std::fs::File::create(to).unwrap(), false, "x");
    for k in r.keys() {
        let a = r.read(&k).unwrap();
        match a.data {
            NpyData::F32(mut v) => {
                if k == key {
                    edit(&mut v);
                }
                w.add(&k, &a.shape, MemberData::F32(&v)).unwrap()
            }
            NpyData::F64(v) => w.add(&k, &a.shape, MemberData::F64(&v)).unwrap(),
            NpyData::I64(v) => w.add(&k, &a.shape, MemberData::I64(&v)).unwrap(),
            NpyData::I32(v) => w.add(&k, &a.shape, MemberData::I32(&v)).unwrap(),
            NpyData::U8(v) => w.add(&k, &a.shape, MemberData::U8(&v)).unwrap(),
            NpyData::I8(v) => w.add(&k, &a.shape, MemberData::I8(&v)).unwrap(),
            NpyData::Bool(v) => {
                let b: Vec<u8> = v.iter().map(|&x| x as u8).collect();
                w.add(&k, &a.shape, MemberData::U8(&b)).unwrap()
            }
        }
    }
    w.finish().unwrap();
}

#[test]
fn bad_motion_exits_2_naming_the_frame() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("nan.npz");
    let mut poses = vec![0.1f32; 4 * 72];
    poses[2 * 72 + 7] = f32::NAN;
    let mut w = NpzWriter::new(std::fs::File::create(&p).unwrap(), false, "nan.npz");
    w.add("poses", &[4, 72], MemberData::F32(&poses)).unwrap();
    w.add("trans", &[4, 3], MemberData::F32(&[0.0; 12]))
        .unwrap();
    w.finish().unwrap();
    let out = dir.path().join("m.npz");
    let o = pma(&["motion"], &[&p, Path::new("-o"), &out]);
    refused(&o, &["nan.npz", "poses", "frame 2"]);

    let bvh = dir.path().join("broken.bvh");
    std::fs::write(&bvh, "HIERARCHY\nROOT Hips\n{\nOFFSET 0 0 zero\n").unwrap();
    let o = pma(&["motion"], &[&bvh, Path::new("-o"), &out]);
    refused(&o, &["broken.bvh:4", "zero"]);
    assert!(!out.exists());
}

/// A raw ZJU-MoCap capture (fixtures/capture) converted, trained on for a few
/// iterations of `tiny`, and evaluated on its converted novel poses.
#[test]
fn capture_converts_trains_and_evaluates() {
    let dir = tempfile::tempdir().unwrap();
    let cap = root().join("fixtures/capture/data/S1/Posing");
    let smpl = root().join("fixtures/capture/data/smplx/smpl/SMPL_NEUTRAL.pkl");
    let train = dir.path().join("train.npz");
    let novel = dir.path().join("novel_pose.npz");
    let common = ["--frames", "0:4:2", "--smpl"];
    let o = pma(
        &["capture"],
        &[
            &cap,
            Path::new(common[0]),
            Path::new(common[1]),
            Path::new(common[2]),
            &smpl,
            Path::new("-o"),
            &train,
        ],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("12 images of 64x64"), "{stdout}");
    let o = pma(
        &["capture", "--split", "novel_pose", "--eval-frames", "1"],
        &[
            &cap,
            Path::new(common[0]),
            Path::new(common[1]),
            Path::new(common[2]),
            &smpl,
            Path::new("-o"),
            &novel,
        ],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));

    let run = dir.path().join("run");
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let (train_s, run_s, novel_s) = (s(&train), s(&run), s(&novel));
    crate::run::ok(crate::run::pma(&[
        "train", "--data", &train_s, "--out", &run_s, "--preset", "tiny", "--iters", "2", "--quiet",
    ]));
    let model = s(&run.join("model.safetensors"));
    let out_dir = s(&dir.path().join("eval"));
    let o = crate::run::ok(crate::run::pma(&[
        "eval",
        "--model",
        &model,
        "--data",
        &novel_s,
        "--split",
        "novel_pose",
        "--out",
        &out_dir,
        "--train-data",
        &train_s,
    ]));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("PSNR"), "{stdout}");
}

#[test]
fn bad_capture_exits_2_without_output() {
    let dir = tempfile::tempdir().unwrap();
    let cap = root().join("fixtures/capture/data/S1/Posing");
    let out = dir.path().join("c.npz");
    let bad_smpl = dir.path().join("smpl.pkl");
    std::fs::write(&bad_smpl, b"\x80\x02cbuiltins\neval\nq\x00.").unwrap();
    let o = pma(
        &["capture", "--smpl"],
        &[&bad_smpl, &cap, Path::new("-o"), &out],
    );
    refused(&o, &["smpl.pkl", "forbidden global `builtins.eval`"]);
    let o = pma(
        &["capture", "--train-views", "0,7", "--smpl"],
        &[
            &root().join("fixtures/capture/data/smpl_neutral.npz"),
            &cap,
            Path::new("-o"),
            &out,
        ],
    );
    refused(&o, &["view 7 does not exist", "4 cameras"]);
    assert!(!out.exists());
}
