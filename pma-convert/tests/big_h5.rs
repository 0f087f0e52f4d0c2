//! Memory bound of the `.h5` conversion: 200 images of 256×256 in the
//! reference writer's layout (flattened, chunked (1, 4096, C), gzip 4).
//!
//! The conversion runs in a child process (this test binary re-run on the
//! ignored `big_h5_child` test) so that its peak RSS (`VmHWM`) is not mixed
//! with the parent's, which builds the input file in memory.

use std::{
    path::{Path, PathBuf},
    process::Command,
};

use hdf5_writer::{DatasetBuilder, FilterDescription, Hdf5Builder, Hdf5Writer, WriteOptions};
use pma_convert::dataset::{convert_dataset, DatasetOptions};
use pma_data::dataset::{npz::NpzReader, Profile};

const N: usize = 200;
const SIDE: usize = 256;
const HW: usize = SIDE * SIDE;

fn vm_kb(field: &str) -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").expect("/proc/self/status");
    let line = status
        .lines()
        .find(|l| l.starts_with(field))
        .expect("field in /proc/self/status");
    line.split_whitespace().nth(1).unwrap().parse().unwrap()
}

fn gzip() -> FilterDescription {
    FilterDescription {
        id: 1,
        name: None,
        client_data: vec![4],
    }
}

fn pixel(n: usize, p: usize, c: usize) -> u8 {
    ((n * 7 + p * 3 + c * 101) % 251) as u8
}

/// The non-pixel keys, taken from the h36m_zju fixture (6 images of 2 poses
/// and 4 cameras) and extended to N images.
fn write_big_h5(path: &Path) {
    let small = hdf5_reader::Hdf5File::open(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures/convert/h36m_zju.h5"),
    )
    .unwrap();
    let f32s = |k: &str| -> (Vec<u64>, Vec<f32>) {
        let d = small.dataset(k).unwrap();
        (
            d.shape().to_vec(),
            d.read_array::<f32>().unwrap().iter().copied().collect(),
        )
    };
    let mut b = Hdf5Builder::new().dataset(
        DatasetBuilder::typed_data(
            "img_shape",
            vec![4],
            &[N as i32, SIDE as i32, SIDE as i32, 3],
        )
        .unwrap(),
    );
    for k in [
        "bones",
        "kp3d",
        "skts",
        "cyls",
        "rest_pose",
        "betas",
        "c2ws",
        "centers",
    ] {
        let (shape, v) = f32s(k);
        b = b.dataset(DatasetBuilder::typed_data(k, shape, &v).unwrap());
    }
    // The fixture's 16×16 intrinsics, scaled to 256×256.
    let (fshape, focals) = f32s("focals");
    let focals: Vec<f32> = focals.iter().map(|f| f * 16.0).collect();
    b = b.dataset(DatasetBuilder::typed_data("focals", fshape, &focals).unwrap());
    let cams: Vec<i64> = (0..N as i64).map(|n| n % 3).collect();
    let poses: Vec<i64> = (0..N as i64).map(|n| (n / 3) % 2).collect();
    b = b
        .dataset(DatasetBuilder::typed_data("img_pose_indices", vec![N as u64], &cams).unwrap())
        .dataset(DatasetBuilder::typed_data("kp_idxs", vec![N as u64], &poses).unwrap());
    let imgs: Vec<u8> = (0..N * HW * 3)
        .map(|i| pixel(i / (HW * 3), (i / 3) % HW, i % 3))
        .collect();
    let masks: Vec<u8> = (0..N * HW)
        .map(|i| ((i % HW) / SIDE > SIDE / 2) as u8)
        .collect();
    let chunked = |name: &str, c: u64, data: &[u8], chunk: u64| {
        DatasetBuilder::typed_data(name, vec![N as u64, HW as u64, c], data)
            .unwrap()
            .chunked(vec![1, chunk, c])
            .filter(gzip())
    };
    b = b
        .dataset(chunked("imgs", 3, &imgs, 4096))
        .dataset(chunked("masks", 1, &masks, 4096))
        .dataset(chunked("sampling_masks", 1, &masks, HW as u64));
    let plan = b.into_plan().unwrap();
    let file = std::fs::File::create(path).unwrap();
    Hdf5Writer::new(std::io::BufWriter::new(file), WriteOptions::default())
        .finish(plan)
        .unwrap();
}

#[test]
#[ignore = "child process of big_h5_converts_with_bounded_memory"]
fn big_h5_child() {
    let input = PathBuf::from(std::env::var("PMA_BIG_H5_IN").unwrap());
    let output = PathBuf::from(std::env::var("PMA_BIG_H5_OUT").unwrap());
    let before = vm_kb("VmHWM:");
    convert_dataset(
        &input,
        &output,
        &DatasetOptions::new(Profile::Train),
        &mut |_, _| {},
    )
    .unwrap();
    println!("PMA_HWM_KB {before} {}", vm_kb("VmHWM:"));
}

#[test]
fn big_h5_converts_with_bounded_memory() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("big.h5");
    let output = dir.path().join("big.npz");
    write_big_h5(&input);

    let out = Command::new(std::env::current_exe().unwrap())
        .args([
            "big_h5_child",
            "--exact",
            "--ignored",
            "--nocapture",
            "--test-threads=1",
        ])
        .env("PMA_BIG_H5_IN", &input)
        .env("PMA_BIG_H5_OUT", &output)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "child failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // The harness prints "test big_h5_child ... " on the same line.
    let report = stdout
        .lines()
        .find_map(|l| l.split_once("PMA_HWM_KB ").map(|(_, r)| r))
        .unwrap_or_else(|| panic!("child did not report VmHWM:\n{stdout}"));
    let v: Vec<u64> = report
        .split_whitespace()
        .take(2)
        .map(|x| x.parse().unwrap())
        .collect();
    let growth_kb = v[1].saturating_sub(v[0]);
    println!(
        "peak RSS before {} KiB, after {} KiB, growth {growth_kb} KiB",
        v[0], v[1]
    );
    // imgs alone are N·H·W·3 = 37.5 MiB (u8); materialising any full pixel
    // array (or one image set as f32) would exceed this. Streaming needs one
    // image, the reader's 4 MiB chunk cache and buffers.
    let imgs_kib = (N * HW * 3 / 1024) as u64;
    assert!(
        growth_kb < imgs_kib / 2,
        "peak RSS grew by {growth_kb} KiB while converting {imgs_kib} KiB of images"
    );

    let mut r = NpzReader::open(&output).unwrap();
    let info = r.info("imgs").unwrap();
    assert_eq!(info.shape, [N, HW, 3]);
    assert!(!info.compressed);
    assert_eq!(r.info("masks").unwrap().shape, [N, HW, 1]);
    // Spot-check pixels of the last image.
    let imgs = r.read("imgs").unwrap();
    let pma_data::dataset::npz::NpyData::U8(px) = imgs.data else {
        panic!("imgs not u8")
    };
    for p in [0, 12345, HW - 1] {
        for c in 0..3 {
            assert_eq!(px[((N - 1) * HW + p) * 3 + c], pixel(N - 1, p, c));
        }
    }
}
