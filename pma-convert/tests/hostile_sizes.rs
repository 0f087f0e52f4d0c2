//! Files whose headers claim enormous sizes (a 40 GB npy member, a billion BVH
//! frames, a 10¹²-element torch storage, an HDF5 dataset of 10⁹ poses, a
//! 100,000² image) must be refused before anything of that size is allocated,
//! and hostile nesting must not overflow the stack.
//!
//! This binary holds a single test so that its peak RSS (`VmHWM`) is not
//! shared with other tests running in parallel.

use std::{
    io::Write,
    path::{Path, PathBuf},
};

use hdf5_writer::{DatasetBuilder, Hdf5Builder, Hdf5Writer, WriteOptions};
use pma_convert::{
    dataset::{convert_dataset, DatasetOptions},
    motion::{convert_motion, MotionOptions},
    torch::read_reference_checkpoint,
};
use pma_data::dataset::Profile;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

fn vm_hwm_kb() -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").expect("/proc/self/status");
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .expect("VmHWM in /proc/self/status")
}

/// An NPY v1 member: header text padded to a 64-byte boundary, then `payload`.
fn npy(descr: &str, shape: &str, payload: &[u8]) -> Vec<u8> {
    let mut h = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
    while (10 + h.len() + 1) % 64 != 0 {
        h.push(' ');
    }
    h.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(h.len() as u16).to_le_bytes());
    out.extend_from_slice(h.as_bytes());
    out.extend_from_slice(payload);
    out
}

fn write_zip(path: &Path, members: &[(&str, Vec<u8>)]) {
    let mut z = zip::ZipWriter::new(std::fs::File::create(path).unwrap());
    let opts =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    for (name, bytes) in members {
        z.start_file(*name, opts).unwrap();
        z.write_all(bytes).unwrap();
    }
    z.finish().unwrap();
}

fn expect_err<T: std::fmt::Debug, E: std::fmt::Display>(
    what: &str,
    r: Result<T, E>,
    needles: &[&str],
) {
    match r {
        Ok(v) => panic!("{what}: accepted ({v:?})"),
        Err(e) => {
            let msg = e.to_string();
            for n in needles {
                assert!(msg.contains(n), "{what}: message lacks {n:?}: {msg}");
            }
            println!("{what}: {msg}");
        }
    }
}

fn npz_claims(dir: &Path) {
    let trans = npy("<f4", "(4, 3)", &[0u8; 48]);
    for (name, shape) in [
        ("huge.npz", "(100000, 100000)"),
        ("overflow.npz", "(1099511627776, 1099511627776)"),
    ] {
        let p = dir.join(name);
        write_zip(
            &p,
            &[
                ("poses.npy", npy("<f4", shape, &[0u8; 64])),
                ("trans.npy", trans.clone()),
            ],
        );
        expect_err(
            name,
            convert_motion(&p, &dir.join("o.npz"), &MotionOptions::default()),
            &[name, "poses"],
        );
    }
}

fn bvh_claims(dir: &Path) {
    let full = std::fs::read_to_string(root().join("../shared/data/cmu_mocap_131_bvh/131_01.bvh"))
        .unwrap();
    let (head, motion) = full.split_once("MOTION").unwrap();
    let first_frame = motion.trim_start().lines().nth(2).unwrap();
    for (name, frames) in [("billion.bvh", "1000000000"), ("e300.bvh", "1e300")] {
        let p = dir.join(name);
        std::fs::write(
            &p,
            format!("{head}MOTION\nFrames: {frames}\nFrame Time: .0083333\n{first_frame}\n"),
        )
        .unwrap();
        expect_err(
            name,
            convert_motion(&p, &dir.join("o.npz"), &MotionOptions::default()),
            &[name],
        );
    }
    // 200,000 nested joints: a recursive parser would overflow the stack.
    let depth = 200_000;
    let mut text = String::from("HIERARCHY\nROOT Hips\n{\nOFFSET 0 0 0\nCHANNELS 0\n");
    for j in 0..depth {
        text.push_str(&format!("JOINT j{j}\n{{\nOFFSET 0 0 0\nCHANNELS 0\n"));
    }
    text.push_str(&"}\n".repeat(depth + 1));
    text.push_str("MOTION\nFrames: 1\nFrame Time: 0.01\n\n");
    let p = dir.join("deep.bvh");
    std::fs::write(&p, text).unwrap();
    expect_err(
        "deep.bvh",
        convert_motion(&p, &dir.join("o.npz"), &MotionOptions::default()),
        &["deep.bvh"],
    );
}

/// `{'model': {'w': _rebuild_tensor_v2(storage('0', FloatStorage, numel), 0, shape, stride, False, OrderedDict())}}`
fn tensor_pickle(numel: u64, shape: (u64, u64)) -> Vec<u8> {
    let int = |v: u64| {
        let mut b = vec![0x8a, 8];
        b.extend_from_slice(&v.to_le_bytes());
        b
    };
    let s = |t: &str| {
        let mut b = vec![b'X'];
        b.extend_from_slice(&(t.len() as u32).to_le_bytes());
        b.extend_from_slice(t.as_bytes());
        b
    };
    let mut p = vec![0x80, 0x02, b'}'];
    p.extend(s("model"));
    p.push(b'}');
    p.extend(s("w"));
    p.extend(b"ctorch._utils\n_rebuild_tensor_v2\n(");
    p.push(b'(');
    p.extend(s("storage"));
    p.extend(b"ctorch\nFloatStorage\n");
    p.extend(s("0"));
    p.extend(s("cpu"));
    p.extend(int(numel));
    p.extend(b"tQ");
    p.extend(int(0));
    p.push(b'(');
    p.extend(int(shape.0));
    p.extend(int(shape.1));
    p.push(b't');
    p.push(b'(');
    p.extend(int(shape.1));
    p.extend(int(1));
    p.push(b't');
    p.push(0x89);
    p.extend(b"ccollections\nOrderedDict\n)R");
    p.extend(b"tR");
    p.extend(b"ss.");
    p
}

fn torch_claims(dir: &Path) {
    // Sanity: the same pickle with honest sizes reads.
    let ok = dir.join("ok.th");
    write_zip(
        &ok,
        &[
            ("ok/data.pkl", tensor_pickle(4, (2, 2))),
            ("ok/data/0", vec![0u8; 16]),
        ],
    );
    let ck = read_reference_checkpoint(&ok).unwrap();
    assert_eq!(ck.model[0].1.shape, [2, 2]);

    let p = dir.join("huge.th");
    write_zip(
        &p,
        &[
            ("huge/data.pkl", tensor_pickle(1 << 40, (1 << 20, 1 << 20))),
            ("huge/data/0", vec![0u8; 16]),
        ],
    );
    expect_err(
        "huge.th",
        read_reference_checkpoint(&p),
        &["huge.th", "model.w"],
    );
    // A shape whose element count overflows.
    let p = dir.join("overflow.th");
    write_zip(
        &p,
        &[
            ("overflow/data.pkl", tensor_pickle(4, (1 << 40, 1 << 40))),
            ("overflow/data/0", vec![0u8; 16]),
        ],
    );
    expect_err(
        "overflow.th",
        read_reference_checkpoint(&p),
        &["overflow.th"],
    );
    // A pickle deflated from 300 MB of zeros: refused by its declared size, not read.
    let p = dir.join("bomb.th");
    {
        let mut z = zip::ZipWriter::new(std::fs::File::create(&p).unwrap());
        let opts = zip::write::SimpleFileOptions::default()
            .compression_method(zip::CompressionMethod::Deflated)
            .large_file(false);
        z.start_file("bomb/data.pkl", opts).unwrap();
        let zeros = vec![0u8; 1 << 20];
        for _ in 0..300 {
            z.write_all(&zeros).unwrap();
        }
        z.finish().unwrap();
    }
    expect_err(
        "bomb.th",
        read_reference_checkpoint(&p),
        &["bomb.th", "data.pkl"],
    );
}

/// The non-pixel keys of the Mixamo fixture under an `img_shape` of `side`².
fn mixamo_with_side(path: &Path, side: i32) {
    let small = hdf5_reader::Hdf5File::open(root().join("fixtures/convert/mixamo.h5")).unwrap();
    let mut b = Hdf5Builder::new()
        .dataset(DatasetBuilder::typed_data("img_shape", vec![4], &[4, side, side, 3]).unwrap());
    for k in [
        "bones",
        "kp3d",
        "skts",
        "cyls",
        "rest_pose",
        "c2ws",
        "focals",
    ] {
        let d = small.dataset(k).unwrap();
        let v: Vec<f32> = d.read_array::<f32>().unwrap().iter().copied().collect();
        b = b.dataset(DatasetBuilder::typed_data(k, d.shape().to_vec(), &v).unwrap());
    }
    // Only its presence matters: it marks the Mixamo layout.
    b = b.dataset(DatasetBuilder::typed_data("img_paths", vec![1], &[0u8]).unwrap());
    let plan = b.into_plan().unwrap();
    let file = std::fs::File::create(path).unwrap();
    Hdf5Writer::new(std::io::BufWriter::new(file), WriteOptions::default())
        .finish(plan)
        .unwrap();
}

fn h5_claims(dir: &Path) {
    // `bones` claims 10⁹ never-written poses (fixtures/convert/gen_hostile_h5.py).
    expect_err(
        "huge_claim.h5",
        convert_dataset(
            &root().join("fixtures/convert/huge_claim.h5"),
            &dir.join("o.npz"),
            &DatasetOptions::new(Profile::Motion),
            &mut |_, _| {},
        ),
        &["huge_claim.h5", "bones", "limit"],
    );
    // A render-profile Mixamo file gets a white plate of img_shape's size.
    let p = dir.join("plate.h5");
    mixamo_with_side(&p, 100_000);
    expect_err(
        "plate.h5",
        convert_dataset(
            &p,
            &dir.join("o.npz"),
            &DatasetOptions::new(Profile::Render),
            &mut |_, _| {},
        ),
        &["plate.h5", "img_shape"],
    );
    assert!(!dir.join("o.npz").exists());
}

#[test]
fn size_claims_are_refused_before_allocation() {
    let dir = tempfile::tempdir().unwrap();
    let before = vm_hwm_kb();
    npz_claims(dir.path());
    bvh_claims(dir.path());
    torch_claims(dir.path());
    h5_claims(dir.path());
    let growth_mb = vm_hwm_kb().saturating_sub(before) / 1024;
    println!("peak RSS growth {growth_mb} MiB");
    // The inputs themselves are small; the claims are tens of GB and more.
    assert!(
        growth_mb < 256,
        "peak RSS grew by {growth_mb} MiB while refusing size claims"
    );
}
