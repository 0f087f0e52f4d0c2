//! `pma_convert::capture`: parity with the reference preprocessing on the
//! synthetic capture in fixtures/capture (its outputs come from the official
//! code, fixtures/capture/official_parity.py), and clear errors on bad input.

use std::path::{Path, PathBuf};

use pma_convert::{
    capture::{convert_capture, CaptureOptions, Frames, Split},
    smpl::SmplModel,
    ConvertError,
};
use pma_data::{
    dataset::{Dataset, Profile, ReadOptions},
    skeleton::axis_angle_to_matrix,
};

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures/capture")
}

fn capture_dir() -> PathBuf {
    fixture().join("data/S1/Posing")
}

fn smpl_pkl() -> PathBuf {
    fixture().join("data/smplx/smpl/SMPL_NEUTRAL.pkl")
}

/// The reference run's setting: 4 training frames, interval 2, 1 evaluation frame.
fn opts(split: Split) -> CaptureOptions {
    let mut o = CaptureOptions::new(smpl_pkl());
    o.split = split;
    o.frames = Frames {
        start: 0,
        count: Some(4),
        interval: 2,
    };
    o.eval_frames = Some(1);
    o
}

fn convert(dir: &Path, out: &Path, o: &CaptureOptions) -> Result<Dataset, ConvertError> {
    convert_capture(dir, out, o, &mut |_, _| {})?;
    Ok(Dataset::read(out, &ReadOptions::new(Profile::Train)).expect("output reads back"))
}

struct Npz(npyz::npz::NpzArchive<std::io::BufReader<std::fs::File>>);

impl Npz {
    fn open(p: &Path) -> Npz {
        Npz(npyz::npz::NpzArchive::open(p).unwrap())
    }
    fn f64s(&mut self, k: &str) -> (Vec<u64>, Vec<f64>) {
        let a = self.0.by_name(k).unwrap().unwrap();
        let shape = a.shape().to_vec();
        let v = match a.dtype().descr().trim_matches('\'') {
            "<f4" => a
                .into_vec::<f32>()
                .unwrap()
                .into_iter()
                .map(f64::from)
                .collect(),
            "<f8" => a.into_vec::<f64>().unwrap(),
            "<i8" => a
                .into_vec::<i64>()
                .unwrap()
                .into_iter()
                .map(|x| x as f64)
                .collect(),
            "|u1" => a
                .into_vec::<u8>()
                .unwrap()
                .into_iter()
                .map(f64::from)
                .collect(),
            d => panic!("{k}: dtype {d}"),
        };
        (shape, v)
    }
}

fn max_diff(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

fn flat<T: Copy + Into<f64>, D: ndarray::Dimension>(a: &ndarray::Array<T, D>) -> Vec<f64> {
    a.iter().map(|&x| x.into()).collect()
}

fn check_parity(split: Split, name: &str) {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("c.npz");
    let ds = convert(&capture_dir(), &out, &opts(split)).unwrap();
    let mut r = Npz::open(&fixture().join(name));

    for (key, ours) in [
        ("kp3d", flat(ds.kp3d.as_ref().unwrap())),
        ("skts", flat(ds.skts.as_ref().unwrap())),
        ("cyls", flat(ds.cyls.as_ref().unwrap())),
        ("c2ws", flat(ds.c2ws.as_ref().unwrap())),
        ("focals", flat(ds.focals.as_ref().unwrap())),
        ("centers", flat(ds.centers.as_ref().unwrap())),
        ("betas", flat(ds.betas.as_ref().unwrap())),
        (
            "rest_pose",
            ds.rest_pose
                .unwrap()
                .iter()
                .flatten()
                .map(|&x| x as f64)
                .collect(),
        ),
    ] {
        let (_, theirs) = r.f64s(key);
        let d = max_diff(&ours, &theirs);
        assert!(d < 1e-4, "{name} {key}: max difference {d}");
    }
    // Bones: the same rotations (a root angle of exactly pi has two axis-angle forms).
    let (_, bones) = r.f64s("bones");
    for (i, (a, b)) in flat(&ds.bones).chunks(3).zip(bones.chunks(3)).enumerate() {
        let ma = axis_angle_to_matrix(glam::DVec3::from_slice(a));
        let mb = axis_angle_to_matrix(glam::DVec3::from_slice(b));
        let d = (ma - mb)
            .to_cols_array()
            .iter()
            .fold(0.0f64, |m, x| m.max(x.abs()));
        assert!(d < 1e-5, "{name} bone {i}: rotations differ by {d}");
    }
    for (key, ours) in [
        ("kp_idxs", ds.kp_idxs.as_ref().unwrap()),
        ("img_pose_indices", ds.img_pose_indices.as_ref().unwrap()),
        ("bkgd_idxs", ds.bkgd_idxs.as_ref().unwrap()),
    ] {
        let (_, theirs) = r.f64s(key);
        let ours: Vec<f64> = ours.iter().map(|&x| x as f64).collect();
        assert_eq!(ours, theirs, "{name} {key}");
    }
    // Pixels: the fixed-point remap reproduces OpenCV's exactly, so every
    // member is compared for equality (images are allowed one level).
    for (key, ours, tol) in [
        ("imgs", ds.imgs.as_ref().unwrap(), 1.0),
        ("masks", ds.masks.as_ref().unwrap(), 0.0),
        ("sampling_masks", ds.sampling_masks.as_ref().unwrap(), 0.0),
        ("bkgds", ds.bkgds.as_ref().unwrap(), 1.0),
    ] {
        let (shape, theirs) = r.f64s(key);
        let ours = flat(ours);
        assert_eq!(
            ours.len() as u64,
            shape.iter().product::<u64>(),
            "{name} {key}"
        );
        let d = max_diff(&ours, &theirs);
        assert!(d <= tol, "{name} {key}: max difference {d}");
    }
    // The fixture has both undistortion border values and boundary marks.
    assert!(ds
        .sampling_masks
        .as_ref()
        .unwrap()
        .iter()
        .any(|&v| v > 1 && v < 100));
}

#[test]
fn train_split_matches_the_reference_preprocessing() {
    check_parity(Split::Train, "official_train.npz");
}

#[test]
fn novel_pose_split_matches_the_reference_preprocessing() {
    check_parity(Split::NovelPose, "official_test.npz");
}

#[test]
fn smpl_pkl_and_npz_give_the_same_joints() {
    let a = SmplModel::read(&smpl_pkl()).unwrap();
    let b = SmplModel::read(&fixture().join("data/smpl_neutral.npz")).unwrap();
    let betas = [0.3, -0.2, 0.1, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0, 1.0];
    let (ja, jb) = (a.rest_joints(&betas), b.rest_joints(&betas));
    let d = max_diff(
        &ja.iter().flatten().copied().collect::<Vec<_>>(),
        &jb.iter().flatten().copied().collect::<Vec<_>>(),
    );
    assert!(d < 1e-12, "{d}");
    // The shape space is used: other betas move the joints.
    let j0 = a.rest_joints(&[0.0; 10]);
    assert!((j0[20][0] - ja[20][0]).abs() + (j0[20][1] - ja[20][1]).abs() > 1e-4);
}

/// A copy of the fixture capture to break.
fn scratch() -> (tempfile::TempDir, PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let dst = tmp.path().join("cap");
    copy_dir(&capture_dir(), &dst);
    (tmp, dst)
}

fn copy_dir(src: &Path, dst: &Path) {
    std::fs::create_dir_all(dst).unwrap();
    for e in std::fs::read_dir(src).unwrap() {
        let e = e.unwrap();
        let to = dst.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &to);
        } else {
            std::fs::copy(e.path(), &to).unwrap();
        }
    }
}

fn refused(dir: &Path, o: &CaptureOptions, needle: &str) {
    let out = dir.parent().unwrap().join("out.npz");
    let Err(e) = convert(dir, &out, o) else {
        panic!("conversion must fail");
    };
    let msg = e.to_string();
    assert!(msg.contains(needle), "{needle:?} not in: {msg}");
    assert!(!out.exists(), "no output on error");
}

#[test]
fn missing_mask_is_refused() {
    let (_t, dir) = scratch();
    // Camera 3 has only mask/; camera 1 only mask_cihp/.
    std::fs::remove_file(dir.join("mask/Camera_B3/000002.png")).unwrap();
    refused(
        &dir,
        &opts(Split::Train),
        "no mask for image Camera_B3/000002.png",
    );
}

#[test]
fn missing_params_file_is_refused() {
    let (_t, dir) = scratch();
    std::fs::remove_file(dir.join("params/4.npy")).unwrap();
    refused(&dir, &opts(Split::Train), "params/4.npy");
}

/// Writes `annots.npy`-style pickles by hand: protocol 3, the npy header of a 0-d object array.
fn npy_with_pickle(pickle: &[u8]) -> Vec<u8> {
    let mut h = b"{'descr': '|O', 'fortran_order': False, 'shape': (), }".to_vec();
    while (10 + h.len() + 1) % 64 != 0 {
        h.push(b' ');
    }
    h.push(b'\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend((h.len() as u16).to_le_bytes());
    out.extend(h);
    out.extend(pickle);
    out
}

#[test]
fn hostile_pickle_is_refused_naming_the_global() {
    let (_t, dir) = scratch();
    // os.system('true') as the pickled object.
    let p = b"\x80\x03cos\nsystem\nq\x00X\x04\x00\x00\x00trueq\x01\x85q\x02Rq\x03.";
    std::fs::write(dir.join("annots.npy"), npy_with_pickle(p)).unwrap();
    refused(&dir, &opts(Split::Train), "forbidden global `os.system`");
}

#[test]
fn camera_count_mismatch_is_refused() {
    let (_t, dir) = scratch();
    // Frame 0 lists 3 images for 4 cameras.
    let bad = fixture().join("data/annots_cam_mismatch.npy");
    std::fs::copy(bad, dir.join("annots.npy")).unwrap();
    refused(
        &dir,
        &opts(Split::Train),
        "key `ims[0].ims`: expected one image per camera (4 cameras",
    );
    // A dict without cameras.
    std::fs::copy(dir.join("params/0.npy"), dir.join("annots.npy")).unwrap();
    refused(&dir, &opts(Split::Train), "key `cams` is missing");
}

#[test]
fn wrong_smpl_shape_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let p = tmp.path().join("bad.npz");
    {
        use npyz::WriterBuilder;
        let mut npz = npyz::npz::NpzWriter::create(&p).unwrap();
        let mut put = |name: &str, shape: &[u64], v: &[f64]| {
            let mut w = npz
                .array(name, Default::default())
                .unwrap()
                .default_dtype()
                .shape(shape)
                .begin_nd()
                .unwrap();
            w.extend(v.iter().copied()).unwrap();
            w.finish().unwrap();
        };
        put("v_template", &[5, 3], &[0.0; 15]);
        put("shapedirs", &[4, 3, 2], &[0.0; 24]);
        put("J_regressor", &[24, 5], &[0.0; 120]);
        put("kintree_table", &[2, 24], &[0.0; 48]);
    }
    let e = SmplModel::read(&p).unwrap_err().to_string();
    assert!(
        e.contains("shapedirs") && e.contains("(5,3,B)") && e.contains("[4, 3, 2]"),
        "{e}"
    );
    let mut o = opts(Split::Train);
    o.smpl = p;
    let (_t, dir) = scratch();
    refused(&dir, &o, "shapedirs");
}

#[test]
fn nan_params_are_refused() {
    let (_t, dir) = scratch();
    // Patch one f8 of Th in frame 2's pickle to NaN: find the Th array's bytes.
    let path = dir.join("params/2.npy");
    let mut b = std::fs::read(&path).unwrap();
    let key = b"Th";
    let at = b.windows(2).position(|w| w == key).unwrap();
    // The array's raw data is the first 24-byte BINBYTES ('C', 24) after the key.
    let rel = b[at..].windows(2).position(|w| w == [b'C', 24]).unwrap();
    let data = at + rel + 2;
    b[data..data + 8].copy_from_slice(&f64::NAN.to_le_bytes());
    std::fs::write(&path, b).unwrap();
    refused(&dir, &opts(Split::Train), "not finite");
}

#[test]
fn frames_option_parses() {
    let f: Frames = "3:10:2".parse().unwrap();
    assert_eq!((f.start, f.count, f.interval), (3, Some(10), 2));
    let f: Frames = "0:".parse().unwrap();
    assert_eq!((f.start, f.count, f.interval), (0, None, 5));
    assert!("1:2:0".parse::<Frames>().is_err());
    assert!("x".parse::<Frames>().is_err());
}
