//! The synthetic scene: deterministic for a seed, valid cameras, non-empty exact masks that
//! agree with the projected skeleton, sampling masks that contain the masks.

use pma_data::cylinder::{cylinder_box, cylinder_from_joints, CylinderParams, HeadDir};
use pma_data::dataset::{Dataset, Profile, ReadOptions};
use pma_data::synth::{plan, render_split, ScenePlan, SynthConfig};

fn cfg(seed: u64) -> SynthConfig {
    SynthConfig {
        novel_pose_dance: 2,
        seed,
        ..SynthConfig::small(32, 3, 3)
    }
}

fn splits(p: &ScenePlan) -> Vec<Dataset> {
    p.splits
        .iter()
        .map(|s| render_split(p, s, &mut || {}).unwrap())
        .collect()
}

#[test]
fn same_seed_same_pixels_other_seed_other_pixels() {
    let a = splits(&plan(&cfg(5)).unwrap());
    let b = splits(&plan(&cfg(5)).unwrap());
    let c = splits(&plan(&cfg(6)).unwrap());
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x.imgs, y.imgs);
        assert_eq!(x.masks, y.masks);
        assert_eq!(x.c2ws, y.c2ws);
        assert_eq!(x.kp3d, y.kp3d);
    }
    assert_ne!(a[0].imgs, c[0].imgs, "the seed changed nothing");
    // The motion does not depend on the seed.
    assert_eq!(a[0].bones, c[0].bones);
}

#[test]
fn splits_follow_the_protocol_and_validate() {
    let p = plan(&cfg(0)).unwrap();
    let ds = splits(&p);
    assert_eq!(
        p.splits.iter().map(|s| s.name).collect::<Vec<_>>(),
        ["train", "novel_view", "novel_pose"]
    );
    // Held-out cameras are disjoint from training cameras.
    assert!(p.test_cams.iter().all(|c| !p.train_cams.contains(c)));
    assert_eq!(ds[0].n_images(), 3 * 3);
    assert_eq!(ds[1].n_images(), 2);
    assert_eq!(ds[2].n_images(), 3 * 3);
    for (d, profile) in ds
        .iter()
        .zip([Profile::Train, Profile::Eval, Profile::Eval])
    {
        let mut d = d.clone();
        d.validate(&ReadOptions::new(profile)).unwrap();
        assert!(d.warnings.is_empty(), "{:?}", d.warnings);
    }
    for cam in &p.cameras {
        cam.validate().unwrap();
    }
}

#[test]
fn masks_agree_with_the_projected_geometry() {
    let p = plan(&cfg(1)).unwrap();
    let res = p.config.res;
    for d in splits(&p) {
        let kp3d = d.kp3d.as_ref().unwrap();
        for n in 0..d.n_images() {
            let cam = d.image_camera(n).unwrap();
            let pr = d.pose_row(n).unwrap();
            let mask = d.mask(n).unwrap();
            let sampling = d.sampling_mask(n).unwrap();
            let fg: Vec<usize> = (0..res * res).filter(|&i| mask[[i, 0]] > 0).collect();
            assert!(!fg.is_empty(), "{}: image {n} has an empty mask", d.source);
            assert!(
                mask.iter().all(|&v| v <= 1),
                "{}: image {n} mask not binary",
                d.source
            );
            // Sampling masks are the masks dilated.
            assert!(fg.iter().all(|&i| sampling[[i, 0]] > 0));
            // Every mask pixel lies inside the projected render-box cylinder.
            let kp: [[f32; 3]; 24] =
                std::array::from_fn(|j| std::array::from_fn(|k| kp3d[[pr, j, k]]));
            let rcyl = cylinder_from_joints(&kp, &CylinderParams::render(HeadDir::NegY));
            let bx = cylinder_box(&rcyl, &cam, None).expect("person in front of the camera");
            let outside = fg
                .iter()
                .filter(|&&i| !bx.contains(i % res, i / res))
                .count();
            assert_eq!(
                outside, 0,
                "{}: image {n}: {outside} mask pixels outside {bx:?}",
                d.source
            );
            // Joints project onto the silhouette (they sit inside the body parts).
            let mut on = 0;
            let mut seen = 0;
            for joint in kp {
                let Some([u, v]) = cam.project(joint) else {
                    continue;
                };
                let (x, y) = (u.round() as i64, v.round() as i64);
                if !(0..res as i64).contains(&x) || !(0..res as i64).contains(&y) {
                    continue;
                }
                seen += 1;
                let hit = (-1i64..=1).any(|dy| {
                    (-1i64..=1).any(|dx| {
                        let (xx, yy) = (x + dx, y + dy);
                        (0..res as i64).contains(&xx)
                            && (0..res as i64).contains(&yy)
                            && mask[[(yy * res as i64 + xx) as usize, 0]] > 0
                    })
                });
                on += hit as usize;
            }
            assert!(
                seen >= 20,
                "{}: image {n}: only {seen} joints in view",
                d.source
            );
            assert_eq!(
                on, seen,
                "{}: image {n}: joints off the silhouette",
                d.source
            );
        }
    }
}
