//! The ray caster's tensor-op path (`render::raycast::device`, what a GPU runs) against the
//! host code, both on the CPU: near/far, coarse samples, importance samples and the sorted
//! merge, on random rays around extreme poses (box hits, grazing rays, cylinder misses,
//! vertical rays) with every combination of the two ray-bound quirks, and on random coarse
//! weights (zeros, spikes, flat rows).
//!
//! Tolerance: the bounds, the coarse samples and their points are the host's f32 operations
//! in the host's order, so they must agree bit for bit, except where the batch mean of a
//! cylinder miss is summed in another order (≤ 1 ulp of the mean). The importance samples
//! interpolate a cdf whose total is summed in another order: its values move by an ulp or
//! two, and inverting it multiplies that by the bin width over the cdf step, up to ~1e3 where
//! the pdf sits at its floor; they are held to the ray caster's golden tolerance, 1e-4 on ray
//! parameters of order 1–10 (and the golden test holds the device path to the reference with
//! it too). The merge must give the host's sorted values; its permutation may differ only
//! between equal values.

use candle_core::{Device, Tensor};
use pma_data::synth;
use pma_model::render::avatar::Avatar;
use pma_model::render::raycast::device::merge_sorted_tensors;
use pma_model::render::raycast::merge_sorted;
use pma_model::tools::stability;
use pma_model::Config;

/// Max abs difference of the importance samples (see the module docs).
const IMPORTANCE_TOL: f32 = 1e-4;

fn host(t: &Tensor) -> Vec<f32> {
    t.flatten_all()
        .unwrap()
        .to_dtype(candle_core::DType::F32)
        .unwrap()
        .to_vec1()
        .unwrap()
}

/// Deterministic values in [lo, hi).
struct Lcg(u64);

impl Lcg {
    fn next(&mut self, lo: f32, hi: f32) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        lo + (hi - lo) * ((self.0 >> 40) as f32 / (1u64 << 24) as f32)
    }
}

/// Max abs difference with equal NaNs counting as equal; the count of bit-identical entries.
fn compare(a: &[f32], b: &[f32]) -> (f32, usize) {
    assert_eq!(a.len(), b.len());
    let mut worst = 0f32;
    let mut same = 0;
    for (x, y) in a.iter().zip(b) {
        if x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan()) {
            same += 1;
            continue;
        }
        let d = if x.is_nan() || y.is_nan() {
            f32::INFINITY
        } else {
            (x - y).abs()
        };
        worst = worst.max(d);
    }
    (worst, same)
}

/// Rays of `n_poses` poses: from around the body (some from inside a joint's box), some
/// vertical, some horizontal, some pointing away from everything.
fn rays(rng: &mut Lcg, n_poses: usize, per_pose: usize, kp3d: &[[f32; 3]]) -> (Vec<f32>, Vec<f32>) {
    let (mut o, mut d) = (Vec::new(), Vec::new());
    for i in 0..n_poses * per_pose {
        let c = kp3d[(i * 7) % 24];
        let mut dir = [
            rng.next(-1.0, 1.0),
            rng.next(-1.0, 1.0),
            rng.next(-1.0, 1.0),
        ];
        let origin = match i % 6 {
            0 => c,
            1 => {
                dir = [0.0, dir[1].signum(), 0.0];
                [c[0] + rng.next(-0.3, 0.3), c[1], c[2] + rng.next(-0.3, 0.3)]
            }
            2 => {
                dir[1] = 0.0;
                [c[0] + rng.next(-3.0, 3.0), c[1], c[2] + rng.next(-3.0, 3.0)]
            }
            3 => {
                // Far out, pointing away: misses the cylinder.
                dir = [1.0, 0.0, 0.0];
                [c[0] + 30.0, c[1], c[2]]
            }
            _ => {
                // From a camera distance towards the body.
                let from = [
                    c[0] + rng.next(-3.0, 3.0),
                    c[1] + rng.next(-1.0, 1.0),
                    c[2] - 3.0,
                ];
                dir = [c[0] - from[0], c[1] - from[1], c[2] - from[2]];
                from
            }
        };
        o.extend_from_slice(&origin);
        d.extend_from_slice(&dir);
    }
    (o, d)
}

#[test]
fn tensor_ops_cast_like_the_host_code() {
    let dev = Device::Cpu;
    let poses = stability::extreme_poses().unwrap();
    let mut rng = Lcg(7);
    for (robust, per_ray) in [(false, false), (true, false), (false, true), (true, true)] {
        let mut cfg = Config::tiny();
        cfg.quirks.robust_ray_bounds = robust;
        cfg.quirks.per_ray_cylinder_fallback = per_ray;
        let a = Avatar::new(cfg, &synth::rest_pose(), 0, &dev).unwrap();
        // Three poses in one batch, 60 rays each.
        let (n_poses, per_pose) = (3, 60);
        let (mut skts, mut cyls) = (Vec::new(), Vec::new());
        let mut kp = Vec::new();
        for (_, bones) in poses.iter().take(n_poses) {
            let (p, kp3d) = a.pose_from_bones(bones, [0.0; 3]).unwrap();
            skts.push(p.skts);
            cyls.push(p.cyls);
            kp.extend_from_slice(&kp3d);
        }
        let skts = Tensor::cat(&skts, 0).unwrap();
        let cyls = Tensor::cat(&cyls, 0).unwrap();
        let (o, d) = rays(&mut rng, n_poses, per_pose, &kp);
        let r = n_poses * per_pose;
        let rays_o = Tensor::from_vec(o.clone(), (r, 3), &dev).unwrap();
        let rays_d = Tensor::from_vec(d.clone(), (r, 3), &dev).unwrap();
        let scales = a.axis_scale().unwrap();
        let caster = a.ray_caster();
        let on_host = caster
            .cast(&rays_o, &rays_d, &cyls, &skts, &scales)
            .unwrap();
        let bounds = on_host.bounds.as_ref().unwrap();
        let misses = bounds.ray_hits_body.iter().filter(|h| !**h).count();
        assert!(
            misses > 10 && misses < r - 10,
            "{misses} of {r} rays miss every box"
        );
        let (near, far) = caster
            .near_far_tensors(&rays_o, &rays_d, &cyls, &skts, &scales)
            .unwrap();
        let on_device = caster
            .cast_tensors(&rays_o, &rays_d, &cyls, &skts, &scales, None)
            .unwrap();
        assert!(on_device.bounds.is_none());
        let case = format!("robust {robust}, per-ray fallback {per_ray}");
        for (what, a, b) in [
            ("near", host(&near), bounds.near.clone()),
            ("far", host(&far), bounds.far.clone()),
            ("z", host(&on_device.z), host(&on_host.z)),
            ("pts", host(&on_device.pts), host(&on_host.pts)),
        ] {
            let (err, same) = compare(&a, &b);
            eprintln!(
                "{case}: {what} max abs diff {err:e}, bit-exact {same}/{}",
                a.len()
            );
            // Only a miss fill (a batch mean) may differ, by its last bit.
            let ulp_of_mean = 1e-6 * b.iter().fold(1f32, |m, v| m.max(v.abs()));
            assert!(err <= ulp_of_mean, "{case}: {what} differs by {err:e}");
        }
    }
}

#[test]
fn tensor_ops_resample_and_merge_like_the_host_code() {
    let dev = Device::Cpu;
    let cfg = Config::paper();
    let a = Avatar::new(cfg.clone(), &synth::rest_pose(), 0, &dev).unwrap();
    let caster = a.ray_caster();
    let (sc, sf) = (cfg.n_samples, cfg.n_importance);
    let r = 64;
    let mut rng = Lcg(11);
    let (mut zc, mut w) = (Vec::new(), Vec::new());
    for ray in 0..r {
        let (near, far) = (rng.next(0.5, 3.0), rng.next(3.5, 8.0));
        zc.extend((0..sc).map(|k| near + (far - near) * k as f32 / (sc - 1) as f32));
        let peak = (ray * 5) % sc;
        w.extend((0..sc).map(|k| match ray % 4 {
            0 => 0.0,                                               // empty ray: the floor alone
            1 => (k == peak) as u8 as f32,                          // one opaque sample
            2 => rng.next(0.0, 1.0).powi(4),                        // scattered weights
            _ => (-((k as f32 - peak as f32) / 3.0).powi(2)).exp(), // a smooth bump
        }));
    }
    let z_t = Tensor::from_vec(zc.clone(), (r, sc), &dev).unwrap();
    let w_t = Tensor::from_vec(w.clone(), (r, sc), &dev).unwrap();
    let zf_host = caster.importance_z(&zc, &w, None).unwrap();
    let zf_dev = caster.importance_z_tensors(&z_t, &w_t, None).unwrap();
    let (err, same) = compare(&host(&zf_dev), &zf_host);
    eprintln!(
        "importance z: max abs diff {err:e}, bit-exact {same}/{}",
        zf_host.len()
    );
    assert!(
        err <= IMPORTANCE_TOL,
        "importance samples differ by {err:e}"
    );

    // The merge of the same samples: the host's sorted values; where the permutation
    // differs, the values it swaps are equal.
    let zf_t = Tensor::from_vec(zf_host.clone(), (r, sf), &dev).unwrap();
    let (z_all, perm) = merge_sorted_tensors(&z_t, &zf_t).unwrap();
    let (z_host, perm_host) = merge_sorted(&zc, sc, &zf_host, sf).unwrap();
    assert_eq!(host(&z_all), z_host, "merged values");
    let perm: Vec<u32> = perm.flatten_all().unwrap().to_vec1().unwrap();
    let m = sc + sf;
    let cat = |ray: usize, i: u32| {
        let i = i as usize;
        if i < sc {
            zc[ray * sc + i]
        } else {
            zf_host[ray * sf + i - sc]
        }
    };
    let mut differing = 0;
    for i in 0..r * m {
        let ray = i / m;
        assert_eq!(cat(ray, perm[i]), z_host[i], "perm does not gather z_all");
        if perm[i] != perm_host[i] {
            differing += 1;
            assert_eq!(cat(ray, perm[i]), cat(ray, perm_host[i]), "ray {ray}");
        }
    }
    eprintln!(
        "merge: {differing} of {} indices differ (between equal values)",
        r * m
    );

    // Ties between the sets and within them keep their order in cat(coarse, fine).
    let zc = Tensor::new(&[[1f32, 2.0, 3.0]], &dev).unwrap();
    let zf = Tensor::new(&[[2f32, 2.0, 4.0]], &dev).unwrap();
    let (z_all, perm) = merge_sorted_tensors(&zc, &zf).unwrap();
    assert_eq!(host(&z_all), vec![1.0, 2.0, 2.0, 2.0, 3.0, 4.0]);
    assert_eq!(
        perm.flatten_all().unwrap().to_vec1::<u32>().unwrap(),
        vec![0, 1, 3, 4, 2, 5]
    );
}

/// Stratified samples ([`Jitter`]): the device route draws the host's places and casts the
/// host's samples (bit for bit but for a cylinder miss's batch mean, as above); every
/// coarse sample stays in its stratum between the midpoints to its even neighbours, the
/// samples stay ascending, and nearly all of them move; the importance samples' CDF places
/// lie one in each of Sf equal parts of [0, 1] and resample like the host's; a seed repeats
/// its places and another seed draws others.
#[test]
fn stratified_samples_stay_in_their_strata_on_both_routes() {
    use pma_model::render::raycast::Jitter;
    let dev = Device::Cpu;
    let poses = stability::extreme_poses().unwrap();
    let cfg = Config::paper();
    let (sc, sf) = (cfg.n_samples, cfg.n_importance);
    let a = Avatar::new(cfg, &synth::rest_pose(), 0, &dev).unwrap();
    let (n_poses, per_pose) = (2, 50);
    let (mut skts, mut cyls, mut kp) = (Vec::new(), Vec::new(), Vec::new());
    for (_, bones) in poses.iter().take(n_poses) {
        let (p, kp3d) = a.pose_from_bones(bones, [0.0; 3]).unwrap();
        skts.push(p.skts);
        cyls.push(p.cyls);
        kp.extend_from_slice(&kp3d);
    }
    let skts = Tensor::cat(&skts, 0).unwrap();
    let cyls = Tensor::cat(&cyls, 0).unwrap();
    let (o, d) = rays(&mut Lcg(5), n_poses, per_pose, &kp);
    let r = n_poses * per_pose;
    let rays_o = Tensor::from_vec(o, (r, 3), &dev).unwrap();
    let rays_d = Tensor::from_vec(d, (r, 3), &dev).unwrap();
    let scales = a.axis_scale().unwrap();
    let caster = a.ray_caster();
    let args = (&rays_o, &rays_d, &cyls, &skts, &scales);
    let cast = |j: Option<Jitter>| {
        caster
            .cast_placed(args.0, args.1, args.2, args.3, args.4, None, j)
            .unwrap()
    };
    let j = Jitter { seed: 42 };
    let even = host(&cast(None).z);
    let jittered = cast(Some(j));
    let z = host(&jittered.z);

    // Device route: the same samples and places.
    let on_device = caster
        .cast_tensors(args.0, args.1, args.2, args.3, args.4, Some(j))
        .unwrap();
    let ulp_of_mean = 1e-6 * z.iter().fold(1f32, |m, v| m.max(v.abs()));
    for (what, x, y) in [
        ("z", host(&on_device.z), z.clone()),
        ("pts", host(&on_device.pts), host(&jittered.pts)),
    ] {
        let (err, _) = compare(&x, &y);
        assert!(err <= ulp_of_mean, "jittered {what} differs by {err:e}");
    }
    let u_host = jittered.fine_u.clone().expect("no fine places");
    assert_eq!(on_device.fine_u.as_ref(), Some(&u_host));
    assert!(cast(None).fine_u.is_none());

    // In their strata, in the order of the even samples (a ray that misses the cylinder
    // can have its bounds the other way round), and moved.
    let mut moved = 0;
    for (ray, (e, z)) in even.chunks_exact(sc).zip(z.chunks_exact(sc)).enumerate() {
        let up = e[0] <= e[sc - 1];
        for k in 0..sc {
            let a = if k == 0 {
                e[0]
            } else {
                0.5 * (e[k - 1] + e[k])
            };
            let b = if k + 1 == sc {
                e[sc - 1]
            } else {
                0.5 * (e[k] + e[k + 1])
            };
            let (lo, hi) = (a.min(b), a.max(b));
            assert!(
                lo <= z[k] && z[k] <= hi,
                "ray {ray} sample {k}: {} outside its stratum [{lo}, {hi}]",
                z[k]
            );
            assert!(
                k == 0 || (z[k - 1] <= z[k]) == up || z[k - 1] == z[k],
                "ray {ray}: out of order at {k}"
            );
            moved += (z[k] != e[k]) as usize;
        }
    }
    assert!(
        moved * 10 > r * sc * 9,
        "only {moved} of {} samples moved",
        r * sc
    );
    for (i, &u) in u_host.iter().enumerate() {
        let m = (i % sf) as f32;
        assert!(
            m / sf as f32 <= u && u <= (m + 1.0) / sf as f32,
            "fine place {i}: {u} outside part {m} of {sf}"
        );
    }

    // The importance samples at those places, on both routes, and not at linspace's.
    let weights = Tensor::from_vec(
        (0..r * sc)
            .map(|i| ((i * 7919) % 13) as f32 / 13.0)
            .collect::<Vec<_>>(),
        (r, sc),
        &dev,
    )
    .unwrap();
    let u = jittered.fine_u.as_deref();
    let fine = caster
        .resample(&rays_o, &rays_d, &jittered.z, &weights, u)
        .unwrap();
    let fine_dev = caster
        .resample_tensors(&rays_o, &rays_d, &jittered.z, &weights, u)
        .unwrap();
    let (err, _) = compare(&host(&fine_dev.z), &host(&fine.z));
    assert!(
        err <= IMPORTANCE_TOL,
        "jittered importance samples differ by {err:e}"
    );
    let at_even = caster
        .resample(&rays_o, &rays_d, &jittered.z, &weights, None)
        .unwrap();
    let (shift, _) = compare(&host(&fine.z), &host(&at_even.z));
    assert!(
        shift > 1e-3,
        "the fine places did not move the importance samples"
    );

    // A seed repeats; another draws other places.
    assert_eq!(host(&cast(Some(j)).z), z);
    assert_ne!(host(&cast(Some(Jitter { seed: 43 })).z), z);
}
