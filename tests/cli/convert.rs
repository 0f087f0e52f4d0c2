//! `pma convert` exit status and messages: 0 on success; 2 with one line on
//! stderr naming the file and the key or offset when an input is refused, and
//! no output file; 1 when the output cannot be written.

use std::path::{Path, PathBuf};
use std::process::Output;

use crate::run::{ok, pma, refused, s, train_tiny};
use pma_data::dataset::npz::{MemberData, NpzWriter};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn fixture(name: &str) -> PathBuf {
    root().join("fixtures/convert").join(name)
}

/// `pma convert ARGS... -o OUT`.
fn convert(args: &[&str], out: &Path) -> Output {
    pma(&[&["convert"], args, &["-o", s(out)]].concat())
}

#[test]
fn a_checkpoint_converts_with_exit_0() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("m.safetensors");
    let golden = root().join("fixtures/golden/ckpt.th");
    ok(convert(&["checkpoint", s(&golden)], &out));
    assert!(out.is_file());
}

#[test]
fn hostile_corrupt_and_mismatched_checkpoints_exit_2_without_output() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("m.safetensors");
    let checkpoint = |input: &Path| convert(&["checkpoint", s(input)], &out);
    let o = checkpoint(&fixture("evil_global.th"));
    refused(&o, &["evil_global.th", "byte", "posix", "system"]);
    let o = checkpoint(&fixture("evil_opcode.th"));
    refused(&o, &["evil_opcode.th", "byte", "NEWOBJ"]);
    // Several problems, joined into the one line.
    let o = checkpoint(&fixture("bad_config.th"));
    refused(
        &o,
        &["bad_config.th", "pts_linears.5.weight", "[256, 1000]"],
    );

    let bytes = std::fs::read(fixture("ckpt_adam.th")).unwrap();
    let cut = dir.path().join("cut.th");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let o = convert(&["checkpoint", "--with-optimizer", s(&cut)], &out);
    refused(&o, &["cut.th"]);
    let o = checkpoint(&dir.path().join("absent.th"));
    refused(&o, &["absent.th"]);
    assert!(!out.exists());
    assert!(!dir.path().join("m.optim.safetensors").exists());
}

#[test]
fn an_unwritable_output_exits_1() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("no/such/dir/m.safetensors");
    let golden = root().join("fixtures/golden/ckpt.th");
    let o = convert(&["checkpoint", s(&golden)], &out);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("no/such/dir"), "{err}");
}

#[test]
fn bad_datasets_exit_2_naming_file_and_key() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("d.npz");
    let o = convert(&["dataset", s(&fixture("masks255.h5"))], &out);
    refused(&o, &["masks255.h5", "masks", "255"]);

    let bytes = std::fs::read(fixture("aist.h5")).unwrap();
    let cut = dir.path().join("cut.h5");
    std::fs::write(&cut, &bytes[..bytes.len() / 3]).unwrap();
    let o = convert(&["dataset", s(&cut)], &out);
    refused(&o, &["cut.h5"]);
    assert!(!out.exists());

    // A good conversion, then the same npz with a non-finite camera.
    ok(convert(&["dataset", s(&fixture("perfcap.h5"))], &out));
    let bad = dir.path().join("nan_cam.npz");
    rewrite_npz(&out, &bad, "c2ws", |v| v[5] = f32::NAN);
    let out2 = dir.path().join("d2.npz");
    let o = convert(&["dataset", s(&bad)], &out2);
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
    let o = convert(&["motion", s(&p)], &out);
    refused(&o, &["nan.npz", "poses", "frame 2"]);

    let bvh = dir.path().join("broken.bvh");
    std::fs::write(&bvh, "HIERARCHY\nROOT Hips\n{\nOFFSET 0 0 zero\n").unwrap();
    let o = convert(&["motion", s(&bvh)], &out);
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
    let capture = [s(&cap), "--frames", "0:4:2", "--smpl", s(&smpl)];
    let o = ok(convert(&[&["capture"], &capture[..]].concat(), &train));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("12 images of 64x64"), "{stdout}");
    let novel_split = ["capture", "--split", "novel_pose", "--eval-frames", "1"];
    ok(convert(&[&novel_split[..], &capture[..]].concat(), &novel));

    let model = train_tiny(&train, &dir.path().join("run"), "2");
    let out_dir = dir.path().join("eval");
    let o = ok(pma(&[
        "eval",
        "--model",
        s(&model),
        "--data",
        s(&novel),
        "--split",
        "novel_pose",
        "--out",
        s(&out_dir),
        "--train-data",
        s(&train),
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
    let o = convert(&["capture", "--smpl", s(&bad_smpl), s(&cap)], &out);
    refused(&o, &["smpl.pkl", "forbidden global `builtins.eval`"]);
    let smpl = root().join("fixtures/capture/data/smpl_neutral.npz");
    let o = convert(
        &[
            "capture",
            "--train-views",
            "0,7",
            "--smpl",
            s(&smpl),
            s(&cap),
        ],
        &out,
    );
    refused(&o, &["view 7 does not exist", "4 cameras"]);
    assert!(!out.exists());
}
