//! pma-npz v1 datasets: byte-deterministic write → read round trip, import-time derivations
//! equal to the stored keys, and one refused file per bad-input class of docs/conventions.md,
//! "Validation" (each asserts the error kind and that the message names the file and the key).

use std::io::Write;
use std::path::{Path, PathBuf};

use ndarray::{s, Array1, Array3};
use pma_data::dataset::{Dataset, Profile, ReadOptions, WriteOptions};
use pma_data::synth::{plan, render_split, SynthConfig};
use pma_data::DataError;

/// A 2-camera × 2-frame 8×8 training split of the synthetic scene.
fn tiny() -> Dataset {
    let cfg = SynthConfig::small(8, 2, 2);
    let p = plan(&cfg).unwrap();
    render_split(&p, &p.splits[0], &mut || {}).unwrap()
}

fn read(path: &Path, profile: Profile) -> pma_data::error::Result<Dataset> {
    Dataset::read(path, &ReadOptions::new(profile))
}

/// Writes `tiny()` broken by `f` and reads it back for `profile`: the error.
fn refused(f: impl FnOnce(&mut Dataset), profile: Profile) -> (DataError, String) {
    let dir = tempfile::tempdir().unwrap();
    let mut ds = tiny();
    f(&mut ds);
    let path = dir.path().join("broken.npz");
    ds.write(&path, &WriteOptions::default()).unwrap();
    let err = read(&path, profile).expect_err("a broken dataset was accepted");
    let msg = err.to_string();
    assert!(msg.contains("broken.npz"), "file not named: {msg}");
    (err, msg)
}

fn assert_names(msg: &str, words: &[&str]) {
    for w in words {
        assert!(msg.contains(w), "{w:?} not in: {msg}");
    }
}

// --- raw npz surgery -------------------------------------------------------------------

/// An NPY v1.0 member with a hand-written header (any descr, even invalid ones).
fn npy(descr: &str, shape: &[usize], fortran: bool, payload: &[u8]) -> Vec<u8> {
    let shape_txt = match shape.len() {
        0 => "()".to_string(),
        1 => format!("({},)", shape[0]),
        _ => format!(
            "({})",
            shape
                .iter()
                .map(|d| d.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    let fo = if fortran { "True" } else { "False" };
    let mut dict = format!("{{'descr': '{descr}', 'fortran_order': {fo}, 'shape': {shape_txt}, }}");
    while (10 + dict.len() + 1) % 64 != 0 {
        dict.push(' ');
    }
    dict.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    out.extend_from_slice(dict.as_bytes());
    out.extend_from_slice(payload);
    out
}

/// Copy of the npz at `src` with member `key` replaced (or added) by raw bytes.
fn replace_member(src: &Path, dst: &Path, key: &str, bytes: &[u8]) {
    let mut zin = zip::ZipArchive::new(std::fs::File::open(src).unwrap()).unwrap();
    let mut zout = zip::ZipWriter::new(std::fs::File::create(dst).unwrap());
    let name = format!("{key}.npy");
    for i in 0..zin.len() {
        let f = zin.by_index(i).unwrap();
        if f.name().unwrap() != name {
            zout.raw_copy_file(f).unwrap();
        }
    }
    let opts =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    zout.start_file(name, opts).unwrap();
    zout.write_all(bytes).unwrap();
    zout.finish().unwrap();
}

fn tiny_file(dir: &Path) -> PathBuf {
    let p = dir.join("good.npz");
    tiny().write(&p, &WriteOptions::default()).unwrap();
    p
}

fn f32_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// Replaces `key` with raw NPY bytes and returns the read error for `profile`.
fn refused_raw(key: &str, bytes: Vec<u8>, profile: Profile) -> (DataError, String) {
    let dir = tempfile::tempdir().unwrap();
    let good = tiny_file(dir.path());
    let bad = dir.path().join("broken.npz");
    replace_member(&good, &bad, key, &bytes);
    let err = read(&bad, profile).expect_err("a broken dataset was accepted");
    let msg = err.to_string();
    assert!(msg.contains("broken.npz"), "file not named: {msg}");
    (err, msg)
}

// --- round trip and derivations ------------------------------------------------------

#[test]
fn write_read_round_trip_is_exact_and_byte_deterministic() {
    let dir = tempfile::tempdir().unwrap();
    let ds = tiny();
    let (a, b) = (dir.path().join("a.npz"), dir.path().join("b.npz"));
    ds.write(&a, &WriteOptions::default()).unwrap();
    ds.write(&b, &WriteOptions::default()).unwrap();
    let bytes = std::fs::read(&a).unwrap();
    assert_eq!(bytes, std::fs::read(&b).unwrap(), "two writes differ");

    let back = read(&a, Profile::Train).unwrap();
    assert!(back.derived.is_empty(), "{:?}", back.derived);
    assert_eq!(back.bones, ds.bones);
    assert_eq!(back.kp3d, ds.kp3d);
    assert_eq!(back.skts, ds.skts);
    assert_eq!(back.cyls, ds.cyls);
    assert_eq!(back.rest_pose, ds.rest_pose);
    assert_eq!(back.c2ws, ds.c2ws);
    assert_eq!(back.focals, ds.focals);
    assert_eq!(back.centers, ds.centers);
    assert_eq!(back.img_shape, ds.img_shape);
    assert_eq!(back.kp_idxs, ds.kp_idxs);
    assert_eq!(back.img_pose_indices, ds.img_pose_indices);
    assert_eq!(back.imgs, ds.imgs);
    assert_eq!(back.masks, ds.masks);
    assert_eq!(back.sampling_masks, ds.sampling_masks);
    assert_eq!(back.head_dir, ds.head_dir);
    // Read → write reproduces the same bytes.
    let c = dir.path().join("c.npz");
    back.write(&c, &WriteOptions::default()).unwrap();
    assert_eq!(bytes, std::fs::read(&c).unwrap(), "re-written file differs");

    // A split scene reads back the same.
    let scene = dir.path().join("s.scene.npz");
    ds.write_split(&scene, &WriteOptions::default()).unwrap();
    let split = read(&scene, Profile::Train).unwrap();
    assert_eq!(split.imgs, ds.imgs);
    assert_eq!(split.kp3d, ds.kp3d);
}

#[test]
fn derived_kinematics_and_cylinders_equal_the_stored_ones() {
    let dir = tempfile::tempdir().unwrap();
    let full = tiny();
    let mut bare = full.clone();
    bare.kp3d = None;
    bare.skts = None;
    bare.cyls = None;
    bare.centers = None;
    let p = dir.path().join("bare.npz");
    bare.write(&p, &WriteOptions::default()).unwrap();
    let back = read(&p, Profile::Train).unwrap();
    for key in ["kp3d", "skts", "cyls", "centers"] {
        assert!(
            back.derived.iter().any(|d| d.starts_with(key)),
            "{key} not derived: {:?}",
            back.derived
        );
    }
    let diff = |a: &[f32], b: &[f32]| {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max)
    };
    let flat =
        |a: &Option<ndarray::ArrayD<f32>>| a.as_ref().unwrap().iter().copied().collect::<Vec<_>>();
    let kp = |d: &Dataset| flat(&d.kp3d.clone().map(|a| a.into_dyn()));
    let sk = |d: &Dataset| flat(&d.skts.clone().map(|a| a.into_dyn()));
    let cy = |d: &Dataset| flat(&d.cyls.clone().map(|a| a.into_dyn()));
    assert!(diff(&kp(&back), &kp(&full)) <= 1e-6);
    assert!(diff(&sk(&back), &sk(&full)) <= 1e-6);
    assert!(diff(&cy(&back), &cy(&full)) <= 1e-6);
    // The synthetic cameras have their principal point at the image centre.
    assert_eq!(back.centers, full.centers);

    // root_locs alone (kp3d absent) is enough.
    let mut roots_only = full.clone();
    roots_only.kp3d = None;
    let p = dir.path().join("roots.npz");
    roots_only.write(&p, &WriteOptions::default()).unwrap();
    assert!(diff(&kp(&read(&p, Profile::Train).unwrap()), &kp(&full)) <= 1e-6);
}

// --- structure ------------------------------------------------------------------------

#[test]
fn s10_1_missing_key_names_the_profile() {
    let (e, msg) = refused(|d| d.sampling_masks = None, Profile::Train);
    assert!(matches!(e, DataError::MissingKey { .. }), "{e:?}");
    assert_names(&msg, &["sampling_masks", "train"]);
    // The same file is fine for evaluation.
    let (e, msg) = refused(
        |d| {
            d.sampling_masks = None;
            d.masks = None;
        },
        Profile::Eval,
    );
    assert!(matches!(e, DataError::MissingKey { .. }), "{e:?}");
    assert_names(&msg, &["masks", "eval"]);
    let (e, msg) = refused(
        |d| {
            d.kp3d = None;
            d.root_locs = None;
        },
        Profile::Motion,
    );
    assert!(matches!(e, DataError::MissingKey { .. }), "{e:?}");
    assert_names(&msg, &["kp3d", "root_locs", "motion"]);
}

#[test]
fn s10_2_wrong_shapes_are_refused() {
    let (e, msg) = refused(
        |d| d.kp3d = Some(d.kp3d.take().unwrap().slice(s![.., ..23, ..]).to_owned()),
        Profile::Motion,
    );
    assert!(matches!(e, DataError::Shape { .. }), "{e:?}");
    assert_names(&msg, &["kp3d", "24", "23"]);
    let (e, msg) = refused(
        |d| d.cyls = Some(d.cyls.take().unwrap().slice(s![.., ..4]).to_owned()),
        Profile::Motion,
    );
    assert!(matches!(e, DataError::Shape { .. }), "{e:?}");
    assert_names(&msg, &["cyls", "(P,5)"]);
    let (e, msg) = refused_raw(
        "c2ws",
        npy("<f4", &[3, 3, 4], false, &f32_bytes(&[0.0; 36])),
        Profile::Render,
    );
    assert!(matches!(e, DataError::Shape { .. }), "{e:?}");
    assert_names(&msg, &["c2ws", "(C,4,4)"]);
    let (e, msg) = refused_raw(
        "img_shape",
        npy(
            "<i8",
            &[4],
            false,
            &[4i64, 8, 8, 5].map(|v| v.to_le_bytes()).concat(),
        ),
        Profile::Render,
    );
    assert!(matches!(e, DataError::Value { .. }), "{e:?}");
    assert_names(&msg, &["img_shape", "(N,H,W,3)"]);
}

#[test]
fn s10_3_inconsistent_counts_are_refused() {
    let (e, msg) = refused(
        |d| d.skts = Some(d.skts.take().unwrap().slice(s![..1, .., .., ..]).to_owned()),
        Profile::Motion,
    );
    assert!(matches!(e, DataError::Count { .. }), "{e:?}");
    assert_names(&msg, &["skts", "bones", "P"]);
    let (e, msg) = refused(
        |d| d.focals = Some(d.focals.take().unwrap().slice(s![..1, ..]).to_owned()),
        Profile::Render,
    );
    assert!(matches!(e, DataError::Count { .. }), "{e:?}");
    assert_names(&msg, &["focals", "c2ws"]);
    let (e, msg) = refused(
        |d| d.kp_idxs = Some(d.kp_idxs.take().unwrap().slice(s![..3]).to_owned()),
        Profile::Render,
    );
    assert!(matches!(e, DataError::Count { .. }), "{e:?}");
    assert_names(&msg, &["kp_idxs", "img_shape"]);
    let (e, msg) = refused(
        |d| d.masks = Some(d.masks.take().unwrap().slice(s![.., ..60, ..]).to_owned()),
        Profile::Eval,
    );
    assert!(matches!(e, DataError::Count { .. }), "{e:?}");
    assert_names(&msg, &["masks", "H*W"]);
}

#[test]
fn s10_4_out_of_range_and_non_integral_indices_are_refused() {
    let (e, msg) = refused(|d| d.kp_idxs.as_mut().unwrap()[2] = 7, Profile::Render);
    assert!(matches!(e, DataError::Index { .. }), "{e:?}");
    assert_names(&msg, &["kp_idxs", "7"]);
    let (e, msg) = refused(
        |d| d.img_pose_indices.as_mut().unwrap()[0] = -1,
        Profile::Render,
    );
    assert!(matches!(e, DataError::Index { .. }), "{e:?}");
    assert_names(&msg, &["img_pose_indices", "-1"]);
    let (e, msg) = refused(|d| d.bkgd_idxs.as_mut().unwrap()[1] = 1, Profile::Render);
    assert!(matches!(e, DataError::Index { .. }), "{e:?}");
    assert_names(&msg, &["bkgd_idxs"]);
    let (e, msg) = refused_raw(
        "bkgd_idxs",
        npy("<f4", &[4], false, &f32_bytes(&[0.0, 0.5, 0.0, 0.0])),
        Profile::Render,
    );
    assert!(matches!(e, DataError::Value { .. }), "{e:?}");
    assert_names(&msg, &["bkgd_idxs", "0.5"]);
}

#[test]
fn s10_5_wrong_dtypes_and_layouts() {
    let (e, msg) = refused_raw(
        "imgs",
        npy("<f4", &[4, 64, 3], false, &f32_bytes(&[0.5; 4 * 64 * 3])),
        Profile::Eval,
    );
    assert!(matches!(e, DataError::Dtype { .. }), "{e:?}");
    assert_names(&msg, &["imgs", "u1", "<f4"]);
    // An object (pickled) member: refused whether or not its header parses.
    let (e, msg) = refused_raw("betas", npy("|O", &[1], false, &[0u8; 8]), Profile::Motion);
    assert!(
        matches!(e, DataError::Dtype { .. } | DataError::Format { .. }),
        "{e:?}"
    );
    assert_names(&msg, &["betas"]);
    let (e, msg) = refused_raw(
        "imgs",
        npy("|u1", &[4, 64, 4], false, &[7u8; 4 * 64 * 4]),
        Profile::Eval,
    );
    assert!(matches!(e, DataError::Dtype { .. }), "{e:?}");
    assert_names(&msg, &["imgs", "4 channels", "drop"]);

    // Big-endian and Fortran-ordered members are converted, with a warning.
    let dir = tempfile::tempdir().unwrap();
    let good = tiny_file(dir.path());
    let ds = tiny();
    let (p, j) = (ds.n_poses(), 24);
    let mut fortran = Vec::new();
    for k in 0..3 {
        for jj in 0..j {
            for pp in 0..p {
                fortran.extend_from_slice(&ds.bones[[pp, jj, k]].to_be_bytes());
            }
        }
    }
    let odd = dir.path().join("odd.npz");
    replace_member(
        &good,
        &odd,
        "bones",
        &npy(">f4", &[p, j, 3], true, &fortran),
    );
    let back = read(&odd, Profile::Train).unwrap();
    assert_eq!(back.bones, ds.bones);
    let notes: Vec<String> = back.warnings.iter().map(|w| w.to_string()).collect();
    assert!(
        notes
            .iter()
            .any(|w| w.contains("bones") && w.contains("big-endian"))
            && notes.iter().any(|w| w.contains("Fortran")),
        "{notes:?}"
    );
}

#[test]
fn s10_5_truncated_files_are_format_errors_naming_the_member() {
    let dir = tempfile::tempdir().unwrap();
    let good = tiny_file(dir.path());
    // A member whose header promises more than it holds.
    let bad = dir.path().join("short.npz");
    replace_member(
        &good,
        &bad,
        "kp3d",
        &npy("<f4", &[2, 24, 3], false, &[0u8; 100]),
    );
    let err = read(&bad, Profile::Motion).unwrap_err();
    assert!(matches!(err, DataError::Format { .. }), "{err:?}");
    assert_names(&err.to_string(), &["short.npz", "kp3d", "truncated"]);
    // A file cut in half (its zip directory is gone).
    let bytes = std::fs::read(&good).unwrap();
    let cut = dir.path().join("cut.npz");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let err = read(&cut, Profile::Motion).unwrap_err();
    assert!(matches!(err, DataError::Format { .. }), "{err:?}");
    assert_names(&err.to_string(), &["cut.npz", "archive"]);
}

#[test]
fn s10_6_empty_splits_are_refused() {
    let (e, msg) = refused(
        |d| {
            *d = Dataset::from_bones(Array3::zeros((0, 24, 3)));
            d.kp3d = Some(Array3::zeros((0, 24, 3)));
        },
        Profile::Motion,
    );
    assert!(matches!(e, DataError::Empty { .. }), "{e:?}");
    assert_names(&msg, &["bones", "P = 0"]);
}

// --- numerics -------------------------------------------------------------------------

#[test]
fn s10_7_non_finite_values_are_refused() {
    let (e, msg) = refused(|d| d.bones[[1, 5, 2]] = f32::NAN, Profile::Motion);
    assert!(matches!(e, DataError::NonFinite { .. }), "{e:?}");
    assert_names(&msg, &["bones", "NaN"]);
    let (e, msg) = refused(|d| d.pose_scale = f32::INFINITY, Profile::Motion);
    assert!(matches!(e, DataError::NonFinite { .. }), "{e:?}");
    assert_names(&msg, &["pose_scale", "inf"]);
    let (e, msg) = refused(
        |d| d.centers.as_mut().unwrap()[[0, 1]] = f32::NEG_INFINITY,
        Profile::Render,
    );
    assert!(matches!(e, DataError::NonFinite { .. }), "{e:?}");
    assert_names(&msg, &["centers"]);
}

#[test]
fn s10_8_non_positive_focals_are_refused_and_far_centres_warned() {
    let (e, msg) = refused(
        |d| d.focals.as_mut().unwrap()[[1, 0]] = 0.0,
        Profile::Render,
    );
    assert!(matches!(e, DataError::Value { .. }), "{e:?}");
    assert_names(&msg, &["focals", "camera row 1", "> 0"]);
    let dir = tempfile::tempdir().unwrap();
    let mut ds = tiny();
    ds.centers.as_mut().unwrap()[[0, 0]] = 100.0;
    let p = dir.path().join("far.npz");
    ds.write(&p, &WriteOptions::default()).unwrap();
    let back = read(&p, Profile::Render).unwrap();
    assert!(
        back.warnings.iter().any(|w| w.key == "centers"),
        "{:?}",
        back.warnings
    );
}

#[test]
fn s10_9_non_rigid_rotations_are_refused() {
    let (e, msg) = refused(
        |d| {
            let c = d.c2ws.as_mut().unwrap();
            for r in 0..3 {
                for k in 0..3 {
                    c[[1, r, k]] *= 1.1;
                }
            }
        },
        Profile::Render,
    );
    assert!(matches!(e, DataError::Value { .. }), "{e:?}");
    assert_names(&msg, &["c2ws", "camera row 1", "orthonormal"]);
    let (e, msg) = refused(
        |d| {
            let c = d.c2ws.as_mut().unwrap();
            for r in 0..3 {
                c[[0, r, 0]] = -c[[0, r, 0]];
            }
        },
        Profile::Render,
    );
    assert!(matches!(e, DataError::Value { .. }), "{e:?}");
    assert_names(&msg, &["c2ws", "reflection"]);
    let (e, msg) = refused(
        |d| d.c2ws.as_mut().unwrap()[[0, 3, 1]] = 0.1,
        Profile::Render,
    );
    assert!(matches!(e, DataError::Value { .. }), "{e:?}");
    assert_names(&msg, &["c2ws", "last row"]);
    let (e, msg) = refused(
        |d| d.skts.as_mut().unwrap()[[1, 4, 0, 1]] += 0.01,
        Profile::Motion,
    );
    assert!(matches!(e, DataError::Value { .. }), "{e:?}");
    assert_names(&msg, &["skts", "pose 1 joint 4", "orthonormal"]);
}

#[test]
fn s10_10_degenerate_6d_bones_are_refused() {
    let ds = tiny();
    let mut v = vec![0f32; ds.n_poses() * 24 * 6];
    for (i, c) in v.chunks_exact_mut(6).enumerate() {
        // Identity (a1 = x, a2 = y), except pose 1 joint 3 (a1 = 0).
        if i != 24 + 3 {
            c.copy_from_slice(&[1.0, 0.0, 0.0, 1.0, 0.0, 0.0]);
        }
    }
    let (e, msg) = refused_raw(
        "bones",
        npy("<f4", &[ds.n_poses(), 24, 6], false, &f32_bytes(&v)),
        Profile::Motion,
    );
    assert!(matches!(e, DataError::Value { .. }), "{e:?}");
    assert_names(&msg, &["bones", "pose 1 joint 3"]);
}

#[test]
fn s10_11_garbage_axis_angles_are_refused_and_large_ones_warned() {
    let (e, msg) = refused(|d| d.bones[[0, 3, 0]] = 5e3, Profile::Motion);
    assert!(matches!(e, DataError::Value { .. }), "{e:?}");
    assert_names(&msg, &["bones", "pose 0 joint 3", "1000"]);
    // |w| slightly above π: legal (kp3d etc. derived from it), with a warning.
    let dir = tempfile::tempdir().unwrap();
    let mut ds = tiny();
    ds.bones[[0, 20, 0]] = 3.3;
    ds.kp3d = None;
    ds.skts = None;
    ds.cyls = None;
    let p = dir.path().join("pi.npz");
    ds.write(&p, &WriteOptions::default()).unwrap();
    let back = read(&p, Profile::Motion).unwrap();
    assert!(
        back.warnings
            .iter()
            .any(|w| w.key == "bones" && w.message.contains("pi")),
        "{:?}",
        back.warnings
    );
}

#[test]
fn s10_12_non_positive_pose_scale_is_refused() {
    let (e, msg) = refused(|d| d.pose_scale = 0.0, Profile::Motion);
    assert!(matches!(e, DataError::Value { .. }), "{e:?}");
    assert_names(&msg, &["pose_scale", "> 0"]);
}

// --- geometry ---------------------------------------------------------------------------

#[test]
fn s10_13_offset_root_is_refused_unless_allowed() {
    let shift = |d: &mut Dataset| {
        let r = d.rest_pose.as_mut().unwrap();
        for j in r.iter_mut() {
            j[0] += 0.05;
        }
        // Keep the stored kinematics consistent: only the root offset is wrong.
        for mut row in d.root_locs.as_mut().unwrap().rows_mut() {
            row[0] -= 0.05;
        }
    };
    let (e, msg) = refused(shift, Profile::Motion);
    assert!(matches!(e, DataError::Value { .. }), "{e:?}");
    assert_names(&msg, &["rest_pose", "origin", "allow-offset-root"]);
    let dir = tempfile::tempdir().unwrap();
    let mut ds = tiny();
    shift(&mut ds);
    let p = dir.path().join("offset.npz");
    ds.write(&p, &WriteOptions::default()).unwrap();
    let mut opts = ReadOptions::new(Profile::Train);
    opts.allow_offset_root = true;
    Dataset::read(&p, &opts).expect("allowed offset root");
}

#[test]
fn s10_14_degenerate_rest_pose_is_refused() {
    let (e, msg) = refused(
        |d| {
            let r = d.rest_pose.as_mut().unwrap();
            r[7] = r[4];
        },
        Profile::Motion,
    );
    assert!(matches!(e, DataError::Value { .. }), "{e:?}");
    assert_names(&msg, &["rest_pose", "joint 7", "left_ankle"]);
}

#[test]
fn s10_15_kp3d_that_disagrees_with_fk_is_refused() {
    let (e, msg) = refused(
        |d| d.kp3d.as_mut().unwrap()[[1, 7, 1]] += 0.05,
        Profile::Motion,
    );
    assert!(matches!(e, DataError::Value { .. }), "{e:?}");
    assert_names(&msg, &["kp3d", "pose 1", "forward kinematics"]);
    let (e, msg) = refused(
        |d| d.root_locs.as_mut().unwrap()[[0, 2]] += 0.05,
        Profile::Motion,
    );
    assert!(matches!(e, DataError::Value { .. }), "{e:?}");
    assert_names(&msg, &["root_locs", "pose 0"]);
}

#[test]
fn s10_16_skts_that_are_not_the_inverse_of_fk_are_refused() {
    // A rigid but wrong transform: a translation offset.
    let (e, msg) = refused(
        |d| d.skts.as_mut().unwrap()[[0, 9, 1, 3]] += 0.05,
        Profile::Motion,
    );
    assert!(matches!(e, DataError::Value { .. }), "{e:?}");
    assert_names(&msg, &["skts", "pose 0 joint 9", "inverse"]);
}

#[test]
fn s10_17_cylinders_that_do_not_enclose_the_joints_are_refused() {
    let (e, msg) = refused(|d| d.cyls.as_mut().unwrap()[[1, 2]] = 0.01, Profile::Motion);
    assert!(matches!(e, DataError::Value { .. }), "{e:?}");
    assert_names(&msg, &["cyls", "pose 1", "radius"]);
    // Head −y: swapping the caps puts them on the wrong side.
    let (e, msg) = refused(
        |d| {
            let c = d.cyls.as_mut().unwrap();
            let (t, b) = (c[[0, 3]], c[[0, 4]]);
            c[[0, 3]] = b;
            c[[0, 4]] = t;
        },
        Profile::Motion,
    );
    assert!(matches!(e, DataError::Value { .. }), "{e:?}");
    assert_names(&msg, &["cyls", "wrong side"]);
}

#[test]
fn s10_18_implausible_units_are_refused() {
    // A millimetre rest pose in a metre file.
    let (e, msg) = refused(
        |d| {
            for j in d.rest_pose.as_mut().unwrap().iter_mut() {
                for v in j.iter_mut() {
                    *v *= 1000.0;
                }
            }
        },
        Profile::Motion,
    );
    assert!(matches!(e, DataError::Value { .. }), "{e:?}");
    assert_names(&msg, &["rest_pose", "units", "mean bone length"]);
    // A camera 1000x farther away than the others (translation in mm).
    let (e, msg) = refused(
        |d| {
            let c = d.c2ws.as_mut().unwrap();
            for r in 0..3 {
                c[[0, r, 3]] *= 1000.0;
            }
        },
        Profile::Render,
    );
    assert!(matches!(e, DataError::Value { .. }), "{e:?}");
    assert_names(&msg, &["c2ws", "camera distance"]);
}

#[test]
fn s10_19_person_behind_the_camera_is_refused() {
    let (e, msg) = refused(
        |d| {
            // Turn training camera 0 around (180° about its y axis): columns x and z flip.
            let c = d.c2ws.as_mut().unwrap();
            for r in 0..3 {
                c[[0, r, 0]] = -c[[0, r, 0]];
                c[[0, r, 2]] = -c[[0, r, 2]];
            }
        },
        Profile::Eval,
    );
    assert!(matches!(e, DataError::Value { .. }), "{e:?}");
    assert_names(&msg, &["c2ws", "behind camera row 0"]);
}

#[test]
fn s10_20_head_direction_must_be_plus_or_minus_y() {
    let (e, msg) = refused(|d| d.head_dir = [0.0, 0.0, 1.0], Profile::Motion);
    assert!(matches!(e, DataError::Value { .. }), "{e:?}");
    assert_names(&msg, &["head_dir", "(0,-1,0) or (0,1,0)"]);
}

// --- pixels -------------------------------------------------------------------------------

#[test]
fn s10_21_non_binary_masks_are_refused_unless_binarised() {
    let to255 = |d: &mut Dataset| d.masks.as_mut().unwrap().mapv_inplace(|v| v * 255);
    let (e, msg) = refused(to255, Profile::Eval);
    assert!(matches!(e, DataError::Value { .. }), "{e:?}");
    assert_names(&msg, &["masks", "255", "binarize"]);
    let dir = tempfile::tempdir().unwrap();
    let mut ds = tiny();
    let want = ds.masks.clone();
    to255(&mut ds);
    let p = dir.path().join("m255.npz");
    ds.write(&p, &WriteOptions::default()).unwrap();
    let mut opts = ReadOptions::new(Profile::Train);
    opts.binarize_masks = true;
    assert_eq!(Dataset::read(&p, &opts).unwrap().masks, want);
}

#[test]
fn s10_22_23_empty_sampling_and_foreground_masks_are_warned() {
    let dir = tempfile::tempdir().unwrap();
    let mut ds = tiny();
    ds.sampling_masks
        .as_mut()
        .unwrap()
        .slice_mut(s![2, .., ..])
        .fill(0);
    ds.masks.as_mut().unwrap().slice_mut(s![1, .., ..]).fill(0);
    let p = dir.path().join("empty.npz");
    ds.write(&p, &WriteOptions::default()).unwrap();
    let back = read(&p, Profile::Train).unwrap();
    let w: Vec<String> = back.warnings.iter().map(|w| w.to_string()).collect();
    assert!(
        w.iter()
            .any(|w| w.contains("sampling_masks") && w.contains("first: 2")),
        "{w:?}"
    );
    assert!(
        w.iter()
            .any(|w| w.contains("`masks`") && w.contains("first: 1")),
        "{w:?}"
    );
}

#[test]
fn in_memory_validation_uses_the_same_checks() {
    let mut ds = tiny();
    ds.eval_tag = Some(Array1::zeros(3));
    let err = ds.validate(&ReadOptions::new(Profile::Eval)).unwrap_err();
    assert!(matches!(err, DataError::Count { .. }), "{err:?}");
    assert_names(&err.to_string(), &["eval_tag", "img_shape"]);
}
