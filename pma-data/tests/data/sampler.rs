//! The training ray sampler (docs/conventions.md, "Ray sampler"): seeded determinism, the
//! image-major contiguous layout, distinct sorted pixels inside the sampling mask, permutation
//! coverage, background noise only off the silhouette, and an exact continuation after restore.

use pma_data::dataset::Dataset;
use pma_data::sampler::Sampler;
use pma_data::synth::{plan, render_split, SynthConfig};

fn tiny() -> Dataset {
    let cfg = SynthConfig::small(16, 2, 3);
    let p = plan(&cfg).unwrap();
    render_split(&p, &p.splits[0], &mut || {}).unwrap()
}

#[test]
fn batches_are_deterministic_per_seed() {
    let ds = tiny();
    let mut a = Sampler::for_dataset(&ds, 64, 4, true, 7).unwrap();
    let mut b = Sampler::for_dataset(&ds, 64, 4, true, 7).unwrap();
    let mut c = Sampler::for_dataset(&ds, 64, 4, true, 8).unwrap();
    let mut differs = false;
    for _ in 0..5 {
        let (x, y, z) = (
            a.next_batch(&ds).unwrap(),
            b.next_batch(&ds).unwrap(),
            c.next_batch(&ds).unwrap(),
        );
        assert_eq!(x, y);
        differs |= x != z;
    }
    assert!(differs, "another seed drew the same batches");
}

#[test]
fn layout_pixels_and_colours_follow_the_spec() {
    let ds = tiny();
    let (h, w) = (ds.height(), ds.width());
    let (k, imgs) = (16, 4);
    let mut s = Sampler::for_dataset(&ds, k * imgs, imgs, true, 1).unwrap();
    let n = ds.n_images();
    let mut seen = vec![0usize; n];
    let epochs = 3;
    for _ in 0..(epochs * n).div_ceil(imgs) {
        let b = s.next_batch(&ds).unwrap();
        assert_eq!(b.len(), k * imgs);
        assert!(b.images.windows(2).all(|p| p[0] <= p[1]), "{:?}", b.images);
        for (i, &img) in b.images.iter().enumerate() {
            seen[img] += 1;
            assert_eq!(b.pose_rows[i], ds.pose_row(img).unwrap());
            let rays = i * k..(i + 1) * k;
            // Contiguous per image: the frame code is the image index.
            assert!(b.framecodes[rays.clone()].iter().all(|&f| f == img as i64));
            let px = &b.pixels[rays.clone()];
            assert!(px.windows(2).all(|p| p[0] < p[1]), "not sorted/distinct");
            let sm = ds.sampling_mask(img).unwrap();
            let (mask, rgb) = (ds.mask(img).unwrap(), ds.image(img).unwrap());
            let cam = ds.image_camera(img).unwrap();
            for (r, &p) in rays.zip(px) {
                assert!(
                    p < h * w && sm[[p, 0]] > 0,
                    "pixel {p} outside the sampling mask"
                );
                let d = cam.ray_dir(p % w, p / w, true);
                for c in 0..3 {
                    assert_eq!(b.dirs[3 * r + c], d[c]);
                    let t = b.targets[3 * r + c];
                    let bg = b.bgs[3 * r + c];
                    if mask[[p, 0]] > 0 {
                        assert_eq!(t, rgb[[p, c]] as f32 / 255.0);
                        assert_eq!(bg, 0.0);
                    } else {
                        assert!((0.0..1.0).contains(&bg));
                        assert_eq!(t, bg);
                    }
                }
            }
        }
    }
    // Whole permutations: every image drawn once per epoch (± the batch straddling the end).
    let total: usize = seen.iter().sum();
    for (i, &c) in seen.iter().enumerate() {
        assert!(
            c + 1 >= total / n && c <= total / n + 1,
            "image {i} drawn {c} times"
        );
    }
}

#[test]
fn background_is_black_without_perturbation() {
    let ds = tiny();
    let mut s = Sampler::for_dataset(&ds, 32, 2, false, 3).unwrap();
    let b = s.next_batch(&ds).unwrap();
    assert!(b.bgs.iter().all(|&v| v == 0.0));
}

#[test]
fn restore_continues_exactly() {
    let ds = tiny();
    let mut a = Sampler::for_dataset(&ds, 32, 4, true, 11).unwrap();
    for _ in 0..3 {
        a.next_batch(&ds).unwrap();
    }
    let (rng, perm, cursor) = (a.rng().clone(), a.permutation().to_vec(), a.cursor());
    let mut b = Sampler::for_dataset(&ds, 32, 4, true, 999).unwrap();
    b.restore(rng, perm, cursor).unwrap();
    for _ in 0..4 {
        assert_eq!(a.next_batch(&ds).unwrap(), b.next_batch(&ds).unwrap());
    }
    let rng = a.rng().clone();
    assert!(b.restore(rng.clone(), vec![0, 1], 0).is_err());
    assert!(b.restore(rng, (0..ds.n_images()).collect(), 99).is_err());
}

#[test]
fn bad_settings_are_errors() {
    let ds = tiny();
    assert!(Sampler::for_dataset(&ds, 30, 4, true, 0).is_err());
    assert!(Sampler::for_dataset(&ds, 32, 0, true, 0).is_err());
    assert!(Sampler::for_dataset(&ds, 2 * 16 * 16 + 2, 2, true, 0).is_err());
    // A sampler built for another dataset refuses this one.
    let mut s = Sampler::new(3, 256, 8, 2, true, 0).unwrap();
    assert!(s.next_batch(&ds).is_err());
}
