//! Retargeting (docs/conventions.md, "Motion files"): bone lengths from the avatar's rest pose,
//! the root trajectory rescaled by the leg-length ratio, y-up motion turned head-down; on
//! synthetic clips and on the embedded AIST++ dance.

use ndarray::{Array2, Array3};
use pma_data::cylinder::HeadDir;
use pma_data::dataset::Dataset;
use pma_data::skeleton::{Joints, PARENTS};
use pma_data::synth;
use pma_model::tools::retarget::{leg_length, retarget, root_scale, MotionClip, RootScale};

fn bone_lengths(k: &Joints) -> Vec<f64> {
    (1..24)
        .map(|j| {
            (0..3)
                .map(|c| (k[j][c] as f64 - k[PARENTS[j]][c] as f64).powi(2))
                .sum::<f64>()
                .sqrt()
        })
        .collect()
}

fn scaled(rest: &Joints, s: f32) -> Joints {
    rest.map(|r| r.map(|x| x * s))
}

fn clip(n: usize, head: HeadDir, rest: Option<Joints>) -> MotionClip {
    // Deterministic, non-trivial rotations.
    let bones = (0..n)
        .map(|f| {
            std::array::from_fn(|j| {
                std::array::from_fn(|c| 0.3 * ((f * 7 + j * 3 + c) as f32 * 0.37).sin())
            })
        })
        .collect();
    let roots = (0..n)
        .map(|f| [0.1 * f as f32, 0.9 + 0.01 * f as f32, -0.05 * f as f32])
        .collect();
    MotionClip {
        bones,
        roots,
        head,
        rest,
    }
}

#[test]
fn bone_lengths_come_from_the_avatar_and_roots_scale_with_legs() {
    let avatar_rest = synth::rest_pose();
    let dancer_rest = scaled(&avatar_rest, 1.25);
    let c = clip(5, HeadDir::NegY, Some(dancer_rest));
    let out = retarget(&c, &avatar_rest, RootScale::LegRatio).unwrap();
    assert!((out.root_scale - 0.8).abs() < 1e-6, "{}", out.root_scale);
    assert!(!out.flipped);
    let want = bone_lengths(&avatar_rest);
    for (f, fr) in out.frames.iter().enumerate() {
        for (got, want) in bone_lengths(&fr.kp3d).iter().zip(&want) {
            assert!((got - want).abs() < 1e-5, "frame {f}: {got} vs {want}");
        }
        for k in 0..3 {
            assert!((fr.root[k] - 0.8 * c.roots[f][k]).abs() < 1e-6);
        }
        // kp3d[0] = rest[0] + t, and skts invert the joint frames.
        for ((k, r), t) in fr.kp3d[0].iter().zip(avatar_rest[0]).zip(fr.root) {
            assert!((k - (r + t)).abs() < 1e-5);
        }
        let s = fr.skts[15];
        let p = fr.kp3d[15];
        let local: Vec<f32> = (0..3)
            .map(|r| s[r][0] * p[0] + s[r][1] * p[1] + s[r][2] * p[2] + s[r][3])
            .collect();
        assert!(local.iter().all(|v| v.abs() < 1e-5), "{local:?}");
    }
    // The rotations are carried over as they are.
    assert_eq!(out.frames[3].bones, c.bones[3]);
}

#[test]
fn y_up_motion_is_turned_head_down() {
    let rest = synth::rest_pose();
    let mut c = clip(1, HeadDir::PosY, None);
    c.bones[0] = [[0.0; 3]; 24]; // upright in a y-up world
    c.roots[0] = [1.0, 2.0, 3.0];
    let out = retarget(&c, &rest, RootScale::LegRatio).unwrap();
    assert!(out.flipped);
    assert_eq!(out.root_scale, 1.0, "no source skeleton: trajectory kept");
    let fr = &out.frames[0];
    assert_eq!(fr.root, [1.0, -2.0, -3.0]);
    // Head (15) above the pelvis means smaller y in the training convention.
    assert!(fr.kp3d[15][1] < fr.kp3d[0][1] - 0.4, "{:?}", fr.kp3d[15]);
    // Feet below.
    assert!(fr.kp3d[10][1] > fr.kp3d[0][1] + 0.5);
}

#[test]
fn scale_choices_and_bad_input() {
    let rest = synth::rest_pose();
    assert!((leg_length(&scaled(&rest, 2.0)) - 2.0 * leg_length(&rest)).abs() < 1e-9);
    assert_eq!(
        root_scale(RootScale::Factor(0.5), Some(&rest), &rest).unwrap(),
        0.5
    );
    assert!(root_scale(RootScale::Factor(-1.0), None, &rest).is_err());
    assert_eq!("legs".parse::<RootScale>().unwrap(), RootScale::LegRatio);
    assert_eq!("none".parse::<RootScale>().unwrap(), RootScale::Factor(1.0));
    assert_eq!("1.5".parse::<RootScale>().unwrap(), RootScale::Factor(1.5));
    for bad in ["", "0", "-2", "nan", "inf", "feet"] {
        assert!(bad.parse::<RootScale>().is_err(), "{bad}");
    }

    let mut c = clip(3, HeadDir::NegY, None);
    c.roots.pop();
    assert!(retarget(&c, &rest, RootScale::LegRatio).is_err());
    let mut c = clip(3, HeadDir::NegY, None);
    c.bones[1][4][2] = f32::NAN;
    assert!(retarget(&c, &rest, RootScale::LegRatio).is_err());
    let c = clip(0, HeadDir::NegY, None);
    assert!(retarget(&c, &rest, RootScale::LegRatio).is_err());
    // A degenerate target skeleton is refused.
    let c = clip(2, HeadDir::NegY, None);
    assert!(retarget(&c, &[[0.0; 3]; 24], RootScale::LegRatio).is_err());
}

#[test]
fn dataset_rest_pose_counts_only_when_read_from_the_file() {
    let rest = synth::rest_pose();
    let p = 2;
    let make = || {
        let mut ds = Dataset::from_bones(Array3::zeros((p, 24, 3)));
        ds.root_locs = Some(Array2::from_elem((p, 3), 0.5));
        ds
    };
    let mut own = make();
    own.rest_pose = Some(scaled(&rest, 1.1));
    own.derive(None).unwrap();
    let c = MotionClip::from_dataset(&own).unwrap();
    assert_eq!(c.rest, Some(scaled(&rest, 1.1)));
    assert_eq!(c.len(), p);
    assert_eq!(c.roots[1], [0.5; 3]);

    let mut borrowed = make();
    borrowed.derive(Some(&rest)).unwrap();
    assert_eq!(MotionClip::from_dataset(&borrowed).unwrap().rest, None);

    let mut no_root = Dataset::from_bones(Array3::zeros((p, 24, 3)));
    no_root.derive(None).unwrap();
    assert!(MotionClip::from_dataset(&no_root).is_err());
}

#[test]
fn aist_dance_drives_the_synthetic_avatar_in_either_up_convention() {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../pma-data/assets/motion/aist_demo.npz"
    );
    let m = pma_data::motion::read_smpl_npz(std::path::Path::new(path), 60.0).unwrap();
    // The demo clip was captured y-down (root ≈ π about x); a y-up copy is the same motion.
    assert_eq!(m.up, HeadDir::NegY);
    let up = m.to_up(HeadDir::PosY);
    let avatar_rest = scaled(&synth::rest_pose(), 0.9);
    let run = |m: &pma_data::motion::Motion| {
        let c = MotionClip {
            bones: m.bones.clone(),
            roots: m.root.clone(),
            head: m.up,
            rest: Some(synth::rest_pose()),
        };
        retarget(&c, &avatar_rest, RootScale::LegRatio).unwrap()
    };
    let (down, from_up) = (run(&m), run(&up));
    assert!(!down.flipped && from_up.flipped);
    assert!((down.root_scale - 0.9).abs() < 1e-6);
    let want = bone_lengths(&avatar_rest);
    let mut upright = 0;
    for ((fr, fu), src) in down.frames.iter().zip(&from_up.frames).zip(&m.root) {
        for (g, w) in bone_lengths(&fr.kp3d).iter().zip(&want) {
            assert!((g - w).abs() < 1e-5);
        }
        for (r, s) in fr.root.iter().zip(src) {
            assert!((r - 0.9 * s).abs() < 1e-5);
        }
        for (a, b) in fr.kp3d.iter().zip(&fu.kp3d) {
            for k in 0..3 {
                assert!((a[k] - b[k]).abs() < 1e-4, "{a:?} vs {b:?}");
            }
        }
        if fr.kp3d[15][1] < fr.kp3d[0][1] {
            upright += 1;
        }
    }
    assert_eq!(
        upright,
        down.frames.len(),
        "the dancer's head is up (−y) in every frame"
    );
}
