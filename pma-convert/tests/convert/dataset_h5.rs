//! `.h5` → pma-npz conversion of the per-layout fixtures written by
//! fixtures/convert/gen_h5_fixtures.py (h5py, reference writer rules).

use crate::support::fixture;
use std::path::Path;

use hdf5_reader::Hdf5File;
use pma_convert::dataset::{convert_dataset, DatasetOptions, Layout};
use pma_data::dataset::{Dataset, Profile, ReadOptions};

fn convert(
    name: &str,
    profile: Profile,
) -> (
    Dataset,
    pma_convert::dataset::DatasetReport,
    tempfile::TempDir,
) {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out.npz");
    let rep = convert_dataset(
        &fixture(name),
        &out,
        &DatasetOptions::new(profile),
        &mut |_, _| {},
    )
    .unwrap();
    let ds = Dataset::read(&out, &ReadOptions::new(profile)).unwrap();
    (ds, rep, dir)
}

/// The h5 array as stored, read with hdf5-reader directly.
fn h5_u8(name: &str, key: &str) -> Vec<u8> {
    let f = Hdf5File::open(fixture(name)).unwrap();
    f.dataset(key)
        .unwrap()
        .read_array::<u8>()
        .unwrap()
        .iter()
        .copied()
        .collect()
}

fn h5_f32(name: &str, key: &str) -> Vec<f32> {
    let f = Hdf5File::open(fixture(name)).unwrap();
    f.dataset(key)
        .unwrap()
        .read_array::<f32>()
        .unwrap()
        .iter()
        .copied()
        .collect()
}

#[test]
fn h36m_zju_keeps_index_maps_pixels_and_poses() {
    let (ds, rep, _d) = convert("h36m_zju.h5", Profile::Train);
    assert_eq!(rep.layout, Some(Layout::H36mZju));
    assert_eq!((ds.n_images(), ds.n_poses(), ds.n_cameras()), (6, 2, 4));
    assert_eq!(ds.kp_idxs.unwrap().to_vec(), [0, 0, 0, 1, 1, 1]);
    assert_eq!(ds.img_pose_indices.unwrap().to_vec(), [0, 1, 2, 0, 1, 2]);
    assert_eq!(ds.bkgd_idxs.unwrap().to_vec(), [0, 1, 2, 0, 1, 2]);
    assert_eq!(ds.head_dir, [0.0, -1.0, 0.0]);
    assert_eq!(
        ds.imgs.unwrap().into_raw_vec_and_offset().0,
        h5_u8("h36m_zju.h5", "imgs")
    );
    assert_eq!(ds.bkgds.unwrap().shape(), [4, 256, 3]);
    // The silhouette-band marker (100) survives.
    let sm = ds.sampling_masks.unwrap();
    assert!(sm.iter().any(|&v| v == 100));
    assert_eq!(
        sm.into_raw_vec_and_offset().0,
        h5_u8("h36m_zju.h5", "sampling_masks")
    );
    assert_eq!(
        ds.kp3d.unwrap().into_raw_vec_and_offset().0,
        h5_f32("h36m_zju.h5", "kp3d")
    );
}

#[test]
fn perfcap_keeps_scaled_units_and_gets_identity_maps() {
    let (ds, rep, _d) = convert("perfcap.h5", Profile::Train);
    assert_eq!(rep.layout, Some(Layout::PerfCap));
    assert_eq!((ds.n_images(), ds.n_poses(), ds.n_cameras()), (4, 4, 4));
    assert_eq!(ds.img_shape, Some([4, 16, 24, 3]));
    // No scale undo and no ÷1.05 in the file: those are loader behaviours.
    assert_eq!(ds.pose_scale, 1.65);
    assert_eq!(
        ds.kp3d
            .as_ref()
            .unwrap()
            .iter()
            .copied()
            .collect::<Vec<_>>(),
        h5_f32("perfcap.h5", "kp3d")
    );
    assert_eq!(
        ds.c2ws
            .as_ref()
            .unwrap()
            .iter()
            .copied()
            .collect::<Vec<_>>(),
        h5_f32("perfcap.h5", "c2ws")
    );
    // (C,) focals become fx = fy; absent centres are (W/2, H/2).
    let f = h5_f32("perfcap.h5", "focals");
    let focals = ds.focals.as_ref().unwrap();
    for c in 0..4 {
        assert_eq!((focals[[c, 0]], focals[[c, 1]]), (f[c], f[c]));
        let centers = ds.centers.as_ref().unwrap();
        assert_eq!((centers[[c, 0]], centers[[c, 1]]), (12.0, 8.0));
    }
    assert_eq!(ds.kp_idxs.unwrap().to_vec(), [0, 1, 2, 3]);
    assert_eq!(ds.img_pose_indices.unwrap().to_vec(), [0, 1, 2, 3]);
    // float32 zeros on disk → int64.
    assert_eq!(ds.bkgd_idxs.unwrap().to_vec(), [0, 0, 0, 0]);
    // Images span a partial last chunk (384 pixels in chunks of 256).
    assert_eq!(
        ds.imgs.unwrap().into_raw_vec_and_offset().0,
        h5_u8("perfcap.h5", "imgs")
    );
}

#[test]
fn surreal_pose_row_is_image_index_mod_poses() {
    let (ds, rep, _d) = convert("surreal.h5", Profile::Train);
    assert_eq!(rep.layout, Some(Layout::Surreal));
    assert_eq!((ds.n_images(), ds.n_poses(), ds.n_cameras()), (6, 3, 6));
    assert_eq!(ds.kp_idxs.unwrap().to_vec(), [0, 1, 2, 0, 1, 2]);
    assert_eq!(ds.img_pose_indices.unwrap().to_vec(), [0, 1, 2, 3, 4, 5]);
    assert_eq!(ds.betas.unwrap().shape(), [1, 10]);
    assert_eq!(ds.ext_scale, Some(0.7142857));
    assert!(ds.bkgds.unwrap().iter().all(|&v| v == 255));
}

#[test]
fn mixamo_ignores_frame_numbers_and_gets_a_white_plate() {
    let (ds, rep, _d) = convert("mixamo.h5", Profile::Train);
    assert_eq!(rep.layout, Some(Layout::Mixamo));
    // The stored kp_idxs are [10, 11, 40, 41] (frame numbers): pose row = image index.
    assert_eq!(ds.kp_idxs.unwrap().to_vec(), [0, 1, 2, 3]);
    assert_eq!(ds.img_pose_indices.unwrap().to_vec(), [0, 1, 2, 3]);
    let bkgds = ds.bkgds.unwrap();
    assert_eq!(bkgds.shape(), [1, 256, 3]);
    assert!(bkgds.iter().all(|&v| v == 255));
    for dropped in ["cam_idxs", "img_paths", "gt_poses"] {
        assert!(
            rep.warnings.iter().any(|w| w.key == dropped),
            "{dropped} not reported"
        );
    }
}

#[test]
fn aist_is_head_up_with_per_view_backgrounds() {
    let (ds, rep, _d) = convert("aist.h5", Profile::Train);
    assert_eq!(rep.layout, Some(Layout::Aist));
    assert_eq!(ds.head_dir, [0.0, 1.0, 0.0]);
    assert_eq!(ds.img_shape, Some([4, 12, 16, 3]));
    assert_eq!(ds.bkgd_idxs.unwrap().to_vec(), [0, 1, 0, 1]);
    assert_eq!(
        ds.cyls.unwrap().into_raw_vec_and_offset().0,
        h5_f32("aist.h5", "cyls")
    );
    let centers = ds.centers.unwrap();
    assert_eq!((centers[[1, 0]], centers[[1, 1]]), (7.5, 6.5));
}

#[test]
fn motion_and_render_profiles_keep_only_what_they_use() {
    let (ds, _, d) = convert("h36m_zju.h5", Profile::Motion);
    assert!(ds.c2ws.is_none() && ds.imgs.is_none() && ds.img_shape.is_none());
    assert_eq!(ds.n_poses(), 2);
    let motion_size = std::fs::metadata(d.path().join("out.npz")).unwrap().len();
    let (ds, _, d) = convert("h36m_zju.h5", Profile::Render);
    assert!(ds.c2ws.is_some() && ds.bkgds.is_some());
    assert!(ds.imgs.is_none() && ds.masks.is_none() && ds.sampling_masks.is_none());
    let render_size = std::fs::metadata(d.path().join("out.npz")).unwrap().len();
    assert!(motion_size < render_size);
}

#[test]
fn the_output_is_deterministic() {
    let (_, _, a) = convert("aist.h5", Profile::Train);
    let (_, _, b) = convert("aist.h5", Profile::Train);
    let read = |d: &tempfile::TempDir| std::fs::read(d.path().join("out.npz")).unwrap();
    assert!(read(&a) == read(&b));
}

#[test]
fn a_pma_npz_round_trips_through_the_converter() {
    let (first, _, d) = convert("h36m_zju.h5", Profile::Train);
    let again = d.path().join("again.npz");
    convert_dataset(
        &d.path().join("out.npz"),
        &again,
        &DatasetOptions::new(Profile::Train),
        &mut |_, _| {},
    )
    .unwrap();
    let second = Dataset::read(&again, &ReadOptions::new(Profile::Train)).unwrap();
    assert_eq!(first.bones, second.bones);
    assert_eq!(first.skts, second.skts);
    assert_eq!(first.imgs, second.imgs);
    assert_eq!(first.kp_idxs, second.kp_idxs);
}

#[test]
fn unbinarised_masks_are_rejected_unless_asked_for() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out.npz");
    let opts = DatasetOptions::new(Profile::Train);
    let msg = convert_dataset(&fixture("masks255.h5"), &out, &opts, &mut |_, _| {})
        .unwrap_err()
        .to_string();
    assert!(
        msg.contains("masks255.h5") && msg.contains("masks") && msg.contains("255"),
        "{msg}"
    );
    assert!(msg.contains("--binarize-masks"), "{msg}");
    assert!(!out.exists());

    let mut opts = DatasetOptions::new(Profile::Train);
    opts.binarize_masks = true;
    convert_dataset(&fixture("masks255.h5"), &out, &opts, &mut |_, _| {}).unwrap();
    let ds = Dataset::read(&out, &ReadOptions::new(Profile::Train)).unwrap();
    let expect: Vec<u8> = h5_u8("masks255.h5", "masks")
        .iter()
        .map(|&v| (v >= 2) as u8)
        .collect();
    assert!(expect.contains(&1));
    assert_eq!(ds.masks.unwrap().into_raw_vec_and_offset().0, expect);
}

#[test]
fn a_truncated_h5_is_a_clear_error() {
    let bytes = std::fs::read(fixture("h36m_zju.h5")).unwrap();
    let dir = tempfile::tempdir().unwrap();
    for keep in [bytes.len() / 3, bytes.len() * 9 / 10] {
        let cut = dir.path().join("cut.h5");
        std::fs::write(&cut, &bytes[..keep]).unwrap();
        let out = dir.path().join("out.npz");
        let err = convert_dataset(
            &cut,
            &out,
            &DatasetOptions::new(Profile::Train),
            &mut |_, _| {},
        )
        .unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("cut.h5") && msg.contains("truncated"), "{msg}");
        assert!(!out.exists());
    }
}

#[test]
fn progress_reports_every_image_of_every_pixel_key() {
    let dir = tempfile::tempdir().unwrap();
    let mut calls = Vec::new();
    convert_dataset(
        &fixture("h36m_zju.h5"),
        &dir.path().join("o.npz"),
        &DatasetOptions::new(Profile::Train),
        &mut |done, total| calls.push((done, total)),
    )
    .unwrap();
    // imgs, masks, sampling_masks (6 rows each) and bkgds (4 rows).
    assert_eq!(calls.last(), Some(&(22, 22)));
    assert_eq!(calls.len(), 23);
}

#[test]
fn a_missing_h5_key_is_named() {
    let h5 = pma_convert::h5::H5File::open(&fixture("h36m_zju.h5")).unwrap();
    let err = h5.read_f32("no_such_key").unwrap_err();
    let msg = err.to_string();
    assert!(
        matches!(err, pma_convert::ConvertError::MissingKey { .. }),
        "{msg}"
    );
    assert!(
        msg.contains("h36m_zju.h5") && msg.contains("no_such_key"),
        "{msg}"
    );
    // Pixels are uint8; asking for floats names the key and both types.
    let msg = h5.read_f32("imgs").unwrap_err().to_string();
    assert!(
        msg.contains("imgs") && msg.contains("float32") && msg.contains("uint8"),
        "{msg}"
    );
}

/// Rewrites the h36m_zju fixture with 4-channel (RGBA) images.
fn write_rgba_copy(path: &Path) -> Vec<u8> {
    use hdf5_reader::Datatype;
    use hdf5_writer::{DatasetBuilder, Hdf5Builder, Hdf5Writer, WriteOptions};
    let src = Hdf5File::open(fixture("h36m_zju.h5")).unwrap();
    let (_, names) = src.root_group().unwrap().member_names().unwrap();
    let mut b = Hdf5Builder::new();
    let mut rgba = Vec::new();
    for name in names {
        let d = src.dataset(&name).unwrap();
        let shape = d.shape().to_vec();
        let ds = match d.dtype() {
            Datatype::FloatingPoint { .. } => {
                let v: Vec<f32> = d.read_array::<f32>().unwrap().iter().copied().collect();
                DatasetBuilder::typed_data(&name, shape, &v).unwrap()
            }
            Datatype::FixedPoint { size: 8, .. } => {
                let v: Vec<i64> = d.read_array::<i64>().unwrap().iter().copied().collect();
                DatasetBuilder::typed_data(&name, shape, &v).unwrap()
            }
            Datatype::FixedPoint { size: 4, .. } => {
                let v: Vec<i32> = d.read_array::<i32>().unwrap().iter().copied().collect();
                DatasetBuilder::typed_data(&name, shape, &v).unwrap()
            }
            _ if name == "imgs" => {
                let v: Vec<u8> = d.read_array::<u8>().unwrap().iter().copied().collect();
                rgba = v
                    .chunks_exact(3)
                    .flat_map(|p| [p[0], p[1], p[2], 200])
                    .collect();
                DatasetBuilder::typed_data(&name, vec![shape[0], shape[1], 4], &rgba).unwrap()
            }
            _ => {
                let v: Vec<u8> = d.read_array::<u8>().unwrap().iter().copied().collect();
                DatasetBuilder::typed_data(&name, shape, &v).unwrap()
            }
        };
        b = b.dataset(ds);
    }
    let file = std::fs::File::create(path).unwrap();
    Hdf5Writer::new(file, WriteOptions::default())
        .finish(b.into_plan().unwrap())
        .unwrap();
    rgba
}

#[test]
fn rgba_images_need_drop_alpha() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("rgba.h5");
    let rgba = write_rgba_copy(&input);
    let out = dir.path().join("out.npz");
    let msg = convert_dataset(
        &input,
        &out,
        &DatasetOptions::new(Profile::Train),
        &mut |_, _| {},
    )
    .unwrap_err()
    .to_string();
    assert!(
        msg.contains("imgs") && msg.contains("4 channels") && msg.contains("--drop-alpha"),
        "{msg}"
    );

    let mut opts = DatasetOptions::new(Profile::Train);
    opts.drop_alpha = true;
    opts.layout = Some(Layout::H36mZju);
    convert_dataset(&input, &out, &opts, &mut |_, _| {}).unwrap();
    let ds = Dataset::read(&out, &ReadOptions::new(Profile::Train)).unwrap();
    let rgb: Vec<u8> = rgba
        .chunks_exact(4)
        .flat_map(|p| [p[0], p[1], p[2]])
        .collect();
    assert_eq!(ds.imgs.unwrap().into_raw_vec_and_offset().0, rgb);
}
