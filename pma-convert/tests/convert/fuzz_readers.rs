//! Property tests of every reader of foreign files (npz, torch zip + pickle,
//! BVH, HDF5): a valid file mutated by truncation, byte flips, extreme
//! integers written over header fields, inserted junk or (BVH) hostile tokens
//! must give an error or a valid result, never a panic.
//!
//! The case counts are bounded so the whole file runs in well under a minute
//! in the test profile; the seed is fixed so CI is deterministic. For a longer
//! local hunt: `PMA_FUZZ_CASES=20000 PMA_FUZZ_SEED=$RANDOM cargo test -p pma-convert --release --test convert fuzz_readers::`.
//! Claims of huge sizes are covered separately (`hostile_sizes.rs`), where
//! peak memory can be measured without other tests running beside them.

use crate::support::{fixture, root};
use std::{
    io::Read,
    path::{Path, PathBuf},
    sync::OnceLock,
};

use pma_convert::{
    checkpoint::{convert_checkpoint, CheckpointOptions},
    dataset::{convert_dataset, DatasetOptions},
    motion::{convert_motion, MotionOptions},
    torch::{read_reference_checkpoint, unpickle},
};
use pma_data::dataset::{npz::NpzReader, Dataset, Profile, ReadOptions};
use proptest::{
    prelude::*,
    sample::{select, Index},
    test_runner::{Config, RngSeed},
};

fn shared(rel: &str) -> PathBuf {
    root().join("../shared/data").join(rel)
}

fn env_or<T: std::str::FromStr>(key: &str, default: T) -> T {
    std::env::var(key)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn config(cases: u32) -> Config {
    Config {
        cases: env_or("PMA_FUZZ_CASES", cases),
        rng_seed: RngSeed::Fixed(env_or("PMA_FUZZ_SEED", 0x5eed_u64)),
        failure_persistence: None,
        // A failing input is reported as found; shrinking it would only add minutes.
        max_shrink_iters: 64,
        ..Config::default()
    }
}

/// One way to damage a file.
#[derive(Clone, Debug)]
enum Mutation {
    Truncate(Index),
    /// XOR the byte at each position with a non-zero mask.
    Flip(Vec<(Index, u8)>),
    /// Overwrite `width` little-endian bytes with an extreme integer: what a
    /// corrupt length, count, offset or dimension field looks like.
    Extreme(Index, u64, usize),
    Insert(Index, Vec<u8>),
    /// Replace everything from a position on with random bytes.
    Garbage(Index, Vec<u8>),
}

fn mutation() -> impl Strategy<Value = Mutation> {
    let extreme = select(vec![
        0u64,
        1,
        0x7f,
        0xff,
        0x7fff_ffff,
        0xffff_ffff,
        1 << 40,
        u64::MAX / 2,
        u64::MAX,
    ]);
    prop_oneof![
        any::<Index>().prop_map(Mutation::Truncate),
        prop::collection::vec((any::<Index>(), 1u8..=255), 1..8).prop_map(Mutation::Flip),
        (any::<Index>(), extreme, select(vec![1usize, 2, 4, 8]))
            .prop_map(|(i, v, w)| Mutation::Extreme(i, v, w)),
        (any::<Index>(), prop::collection::vec(any::<u8>(), 1..64))
            .prop_map(|(i, b)| Mutation::Insert(i, b)),
        (any::<Index>(), prop::collection::vec(any::<u8>(), 0..256))
            .prop_map(|(i, b)| Mutation::Garbage(i, b)),
    ]
}

fn mutate(base: &[u8], m: &Mutation) -> Vec<u8> {
    let mut b = base.to_vec();
    match m {
        Mutation::Truncate(i) => b.truncate(i.index(base.len())),
        Mutation::Flip(flips) => {
            for (i, mask) in flips {
                b[i.index(base.len())] ^= mask;
            }
        }
        Mutation::Extreme(i, v, w) => {
            let at = i.index(base.len().saturating_sub(*w).max(1));
            let bytes = v.to_le_bytes();
            for (k, &x) in bytes[..*w].iter().enumerate() {
                if let Some(slot) = b.get_mut(at + k) {
                    *slot = x;
                }
            }
        }
        Mutation::Insert(i, junk) => {
            let at = i.index(base.len() + 1);
            b.splice(at..at, junk.iter().copied());
        }
        Mutation::Garbage(i, junk) => {
            b.truncate(i.index(base.len()));
            b.extend_from_slice(junk);
        }
    }
    b
}

/// Writes `bytes` as `name` in a fresh directory; the output goes beside it.
fn staged(name: &str, bytes: &[u8]) -> (tempfile::TempDir, PathBuf, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join(name);
    std::fs::write(&input, bytes).unwrap();
    let output = dir.path().join("out.npz");
    (dir, input, output)
}

/// A pma-npz dataset converted from the PerfCap fixture: the input of the npz dataset reader.
fn dataset_npz() -> &'static [u8] {
    static BYTES: OnceLock<Vec<u8>> = OnceLock::new();
    BYTES.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("perfcap.npz");
        convert_dataset(
            &fixture("perfcap.h5"),
            &out,
            &DatasetOptions::new(Profile::Train),
            &mut |_, _| {},
        )
        .unwrap();
        std::fs::read(out).unwrap()
    })
}

/// The first frames of a CMU BVH: a valid file small enough to parse many times.
fn small_bvh() -> &'static str {
    static TEXT: OnceLock<String> = OnceLock::new();
    TEXT.get_or_init(|| {
        let full = std::fs::read_to_string(shared("cmu_mocap_131_bvh/131_01.bvh")).unwrap();
        let (head, motion) = full.split_once("MOTION").unwrap();
        let mut lines = motion.trim_start().lines();
        let _frames = lines.next().unwrap();
        let frame_time = lines.next().unwrap();
        let frames: Vec<&str> = lines.take(12).collect();
        format!(
            "{head}MOTION\nFrames: {}\n{frame_time}\n{}\n",
            frames.len(),
            frames.join("\n")
        )
    })
}

/// The `data.pkl` of a torch checkpoint with a full Adam state.
fn adam_pickle() -> &'static [u8] {
    static BYTES: OnceLock<Vec<u8>> = OnceLock::new();
    BYTES.get_or_init(|| {
        let f = std::fs::File::open(fixture("ckpt_adam.th")).unwrap();
        let mut z = zip::ZipArchive::new(f).unwrap();
        let mut e = z.by_name("ckpt_adam/data.pkl").unwrap();
        let mut v = Vec::new();
        e.read_to_end(&mut v).unwrap();
        v
    })
}

#[test]
fn the_unmutated_bases_are_valid() {
    // Otherwise every property below would only exercise the first error path.
    let (_d, i, o) = staged("d.npz", dataset_npz());
    convert_dataset(&i, &o, &DatasetOptions::new(Profile::Train), &mut |_, _| {}).unwrap();
    let (_d, i, o) = staged("m.bvh", small_bvh().as_bytes());
    assert_eq!(
        convert_motion(&i, &o, &MotionOptions::default())
            .unwrap()
            .frames,
        12
    );
    unpickle(adam_pickle(), Path::new("ckpt_adam.th"), "data.pkl").unwrap();
    read_reference_checkpoint(&fixture("tiny_views.th")).unwrap();
}

proptest! {
    #![proptest_config(config(160))]

    #[test]
    fn npz_motion_reader_never_panics(m in mutation()) {
        let base = std::fs::read(shared("aistpp_smpl_demo/aist_demo.npz")).unwrap();
        let (_d, input, output) = staged("motion.npz", &mutate(&base, &m));
        let res = convert_motion(&input, &output, &MotionOptions::default());
        prop_assert_eq!(res.is_ok(), output.exists());
    }

    #[test]
    fn npz_dataset_reader_never_panics(m in mutation()) {
        let (_d, input, output) = staged("data.npz", &mutate(dataset_npz(), &m));
        // The raw member reader on every key, then the full read + validation.
        if let Ok(mut r) = NpzReader::open(&input) {
            for k in r.keys() {
                let _ = r.read(&k);
            }
        }
        let _ = Dataset::read(&input, &ReadOptions::new(Profile::Train));
        let res = convert_dataset(&input, &output, &DatasetOptions::new(Profile::Train), &mut |_, _| {});
        prop_assert_eq!(res.is_ok(), output.exists());
    }

    #[test]
    fn torch_zip_reader_never_panics(m in mutation(), evil in any::<bool>()) {
        let base = std::fs::read(fixture(if evil { "evil_global.th" } else { "tiny_views.th" })).unwrap();
        let (_d, input, _) = staged("ckpt.th", &mutate(&base, &m));
        let _ = read_reference_checkpoint(&input);
    }

    #[test]
    fn pickle_machine_never_panics(m in mutation()) {
        let _ = unpickle(&mutate(adam_pickle(), &m), Path::new("ckpt_adam.th"), "data.pkl");
    }

    /// Random programs over the opcodes the machine accepts, with random operands:
    /// these reach stack, memo and container states that byte flips rarely do.
    #[test]
    fn random_pickle_programs_never_panic(
        ops in prop::collection::vec(
            (select(b"()]}tsuaeqrhjbQR.NKJMX\x85\x86\x87\x88\x89\x8a\x8c\x93\x94\x95G".to_vec()),
             prop::collection::vec(any::<u8>(), 0..9)),
            1..80)
    ) {
        let mut p = vec![0x80, 0x02];
        for (op, arg) in &ops {
            p.push(*op);
            p.extend_from_slice(arg);
        }
        let _ = unpickle(&p, Path::new("random.th"), "data.pkl");
    }

    #[test]
    fn bvh_reader_never_panics_on_bytes(m in mutation()) {
        let (_d, input, output) = staged("m.bvh", &mutate(small_bvh().as_bytes(), &m));
        let res = convert_motion(&input, &output, &MotionOptions::default());
        prop_assert_eq!(res.is_ok(), output.exists());
    }

    /// Whole tokens replaced, dropped or repeated: structural damage that
    /// keeps the file tokenisable, so the parser (not the UTF-8 check) sees it.
    #[test]
    fn bvh_reader_never_panics_on_tokens(
        edits in prop::collection::vec(
            (any::<Index>(), select(vec![
                "", "0", "-1", "6", "7", "1e308", "-1e308", "nan", "inf", "1e9", "99999999999999999999",
                "4294967296", "0.0000001", "-0", "{", "}", "JOINT", "End", "Site", "ROOT", "OFFSET",
                "CHANNELS", "Xrotation", "Zposition", "MOTION", "Frames:", "Frame", "Time:", "Hips",
            ]), 0usize..3),
            1..6)
    ) {
        let mut toks: Vec<String> = small_bvh().split_whitespace().map(str::to_string).collect();
        for (i, t, how) in &edits {
            let at = i.index(toks.len());
            match how {
                0 => toks[at] = t.to_string(),
                1 => { toks.remove(at); }
                _ => { let dup = toks[at..(at + 8).min(toks.len())].to_vec(); toks.splice(at..at, dup); }
            }
            if toks.is_empty() { break; }
        }
        let (_d, input, output) = staged("m.bvh", toks.join(" ").as_bytes());
        let res = convert_motion(&input, &output, &MotionOptions::default());
        prop_assert_eq!(res.is_ok(), output.exists());
    }

    #[test]
    fn h5_reader_never_panics(
        m in mutation(),
        base in select(vec!["h36m_zju.h5", "perfcap.h5", "surreal.h5", "mixamo.h5", "aist.h5"]),
    ) {
        let bytes = std::fs::read(fixture(base)).unwrap();
        let (_d, input, output) = staged("data.h5", &mutate(&bytes, &m));
        let res = convert_dataset(&input, &output, &DatasetOptions::new(Profile::Train), &mut |_, _| {});
        prop_assert_eq!(res.is_ok(), output.exists());
    }

    #[test]
    fn checkpoint_converter_never_panics(m in mutation()) {
        let base = std::fs::read(fixture("tiny_views.th")).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("ckpt.th");
        std::fs::write(&input, mutate(&base, &m)).unwrap();
        let out = dir.path().join("out.safetensors");
        let res = convert_checkpoint(&input, &out, &CheckpointOptions { with_optimizer: true });
        // tiny_views is not a PM-Avatar: it must never convert.
        prop_assert!(res.is_err());
        prop_assert!(!out.exists());
    }
}
