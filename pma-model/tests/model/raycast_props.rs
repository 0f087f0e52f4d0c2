//! Ray caster on hand-made scenes with known answers: cylinder bounds and the miss fallback,
//! box bounds (scaled, unnormalised directions, edge hits), per-pose grouping, importance
//! sampling of a uniform and a peaked pdf, merge gradients, and input errors.

use candle_core::{Device, Tensor, Var};
use pma_data::skeleton::N_JOINTS;
use pma_model::network::config::Config;
use pma_model::render::raycast::{
    box_sphere_may_hit, cylinder_near_far, fill_cylinder_misses, merge_raw, BoxRay, RayCaster,
};

use crate::common::flat;

/// [`BoxRay::near_far`] of one ray against one part's box.
fn box_near_far(
    world_to_box: &[f32],
    scale: [f32; 3],
    o: [f32; 3],
    d: [f32; 3],
    bound: f64,
) -> Option<(f32, f32)> {
    BoxRay::new(world_to_box, scale, o, d).near_far(scale, bound)
}

fn identity4() -> Vec<f32> {
    (0..16)
        .map(|i| if i % 5 == 0 { 1.0 } else { 0.0 })
        .collect()
}

fn identities(n: usize) -> Vec<f32> {
    (0..n).flat_map(|_| identity4()).collect()
}

/// World-to-joint transform of a joint at `x` on the world x axis (no rotation).
fn translate_x(x: f32) -> Vec<f32> {
    let mut m = identity4();
    m[3] = -x;
    m
}

fn caster(cfg: &Config) -> RayCaster {
    RayCaster::new(cfg, &identities(N_JOINTS)).unwrap()
}

fn close(a: f32, b: f32, tol: f32) -> bool {
    (a - b).abs() <= tol
}

#[test]
fn cylinder_bounds_for_known_rays() {
    // Circle of radius 1 at the origin of the x-z plane.
    let cyl = |_: usize| [0.0f32, 0.0, 1.0];
    let rays_o = [
        -5.0f32, 0.3, 0.0, 0.2, 0.0, 0.0, -5.0, 0.0, 3.0, 0.5, -3.0, 0.5,
    ];
    // Ray 0: along +x through the centre; ray 1: starts inside; ray 2: misses (passes at z = 3);
    // ray 3: vertical (no ground-plane component).
    let rays_d = [
        2.0f32, 0.1, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0,
    ];
    let (near, far) = cylinder_near_far(&rays_o, &rays_d, cyl);
    // Ray 0 enters at x = -1 and leaves at x = 1: distances 4 and 6 along |d_xz| = 2.
    assert!(
        close(near[0], 2.0, 1e-5) && close(far[0], 3.0, 1e-5),
        "{near:?} {far:?}"
    );
    assert!(
        near[1] == 0.0 && close(far[1], 0.8, 1e-5),
        "{near:?} {far:?}"
    );
    assert!(near[2].is_nan() && far[2].is_nan());
    assert!(near[3].is_nan() && far[3].is_nan());

    // Reference fallback: the mean of the rays that hit; quirk off: the config's near/far.
    let (mut n, mut f) = (near.clone(), far.clone());
    fill_cylinder_misses(&mut n, &mut f, 0.0, 100.0, false);
    assert!(close(n[2], 1.0, 1e-6) && close(f[2], 1.9, 1e-5) && n[3] == n[2] && f[3] == f[2]);
    let (mut n, mut f) = (near.clone(), far.clone());
    fill_cylinder_misses(&mut n, &mut f, 0.5, 50.0, true);
    assert_eq!((n[2], f[2], n[3], f[3]), (0.5, 50.0, 0.5, 50.0));
    assert_eq!((n[0], f[0]), (near[0], far[0]));
    // A batch where every ray misses falls back to near0/far0 in both modes.
    let (mut n, mut f) = (vec![f32::NAN; 2], vec![f32::NAN; 2]);
    fill_cylinder_misses(&mut n, &mut f, 0.0, 100.0, false);
    assert_eq!((n, f), (vec![0.0; 2], vec![100.0; 2]));
}

#[test]
fn box_bounds_scale_and_direction_length() {
    let id = identity4();
    // Unit half-extents enlarged by 1.1: the ray along +x from x = -5 crosses x = ±1.1.
    let (n, f) = box_near_far(&id, [1.0; 3], [-5.0, 0.2, -0.3], [1.0, 0.0, 0.0], 1.1).unwrap();
    assert!(close(n, 3.9, 1e-5) && close(f, 6.1, 1e-5), "{n} {f}");
    // Half-extent 2 along x: faces at ±2.2.
    let (n, f) = box_near_far(
        &id,
        [2.0, 1.0, 1.0],
        [-5.0, 0.2, -0.3],
        [1.0, 0.0, 0.0],
        1.1,
    )
    .unwrap();
    assert!(close(n, 2.8, 1e-5) && close(f, 7.2, 1e-5), "{n} {f}");
    // Ray parameters, not distances: doubling |d| halves them.
    let (n, f) = box_near_far(&id, [1.0; 3], [-5.0, 0.2, -0.3], [2.0, 0.0, 0.0], 1.1).unwrap();
    assert!(close(n, 1.95, 1e-5) && close(f, 3.05, 1e-5), "{n} {f}");
    // A miss.
    assert!(box_near_far(&id, [1.0; 3], [-5.0, 2.0, 0.0], [1.0, 0.0, 0.0], 1.1).is_none());
    // Through two opposite edges: four valid face hits, so the box does not count (hazard 7).
    assert!(box_near_far(&id, [1.0; 3], [-5.0, -5.0, 0.0], [1.0, 1.0, 0.0], 1.1).is_none());
    // A rotated and translated frame: joint at (0, 0, 10), box axes swapped (x <-> z).
    let m = [
        0.0f32, 0., 1., -10., 0., 1., 0., 0., 1., 0., 0., 0., 0., 0., 0., 1.,
    ];
    let (n, f) = box_near_far(&m, [0.5, 1.0, 2.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 1.1).unwrap();
    // Along world z the box extends ±0.5·1.1 around z = 10.
    assert!(close(n, 9.45, 1e-5) && close(f, 10.55, 1e-5), "{n} {f}");
}

/// The cheap pre-tests (the box frame's sphere and the world-space sphere before it) never
/// reject a ray either exact box test finds crossing, including rays aimed at corners and
/// edges and rays that just graze past, for rotated, translated and stretched boxes; and they
/// reject many rays that pass well away (else they save nothing).
#[test]
fn the_box_pre_test_passes_every_crossing_ray() {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let mut u = move || rng.gen::<f32>();
    let bound = 1.1f64;
    let (mut crossing, mut far_rejected, mut far_total) = (0, 0, 0);
    let mut sphere_rejected = 0;
    for case in 0..20_000 {
        // A rotation about a random axis (Rodrigues), a translation and per-axis scales.
        let (ax, ang) = ([u() - 0.5, u() - 0.5, u() - 0.5], 6.3 * u());
        let n = (ax[0] * ax[0] + ax[1] * ax[1] + ax[2] * ax[2])
            .sqrt()
            .max(1e-3);
        let k = [ax[0] / n, ax[1] / n, ax[2] / n];
        let (c, s) = (ang.cos(), ang.sin());
        let mut m = vec![0f32; 16];
        for i in 0..3 {
            for j in 0..3 {
                let cross = match (i, j) {
                    (0, 1) => -k[2],
                    (0, 2) => k[1],
                    (1, 0) => k[2],
                    (1, 2) => -k[0],
                    (2, 0) => -k[1],
                    (2, 1) => k[0],
                    _ => 0.0,
                };
                m[4 * i + j] = c * f32::from(i == j) + s * cross + (1.0 - c) * k[i] * k[j];
            }
            m[4 * i + 3] = 2.0 * (u() - 0.5);
        }
        m[15] = 1.0;
        let scale = [0.05 + 0.3 * u(), 0.05 + 0.3 * u(), 0.05 + 0.3 * u()];
        // A target in box-normalised coordinates: a corner, an edge, a face, or outside.
        let lim = bound as f32;
        let pick = |v: f32| if v < 0.5 { -lim } else { lim };
        let target_n = match case % 4 {
            0 => [pick(u()), pick(u()), pick(u())],
            1 => [pick(u()), pick(u()), lim * (2.0 * u() - 1.0)],
            2 => [pick(u()), lim * (2.0 * u() - 1.0), lim * (2.0 * u() - 1.0)],
            _ => [
                4.0 * (u() - 0.5) * lim,
                4.0 * (u() - 0.5) * lim,
                4.0 * (u() - 0.5) * lim,
            ],
        };
        // Back to the world: x = Rᵀ(s ⊙ x̂ − t).
        let local = [
            target_n[0] * scale[0] - m[3],
            target_n[1] * scale[1] - m[7],
            target_n[2] * scale[2] - m[11],
        ];
        let target: [f32; 3] =
            std::array::from_fn(|j| (0..3).map(|i| m[4 * i + j] * local[i]).sum());
        let o = [3.0 * (u() - 0.5), 3.0 * (u() - 0.5), 3.0 + 2.0 * u()];
        // Every eighth camera 100× farther away, where f32 rounding in the pre-tests grows.
        let o = match case % 8 == 5 {
            true => o.map(|v| 100.0 * v),
            false => o,
        };
        // Unnormalised directions, as image rays have them.
        let len = 0.5 + u();
        let d = [
            (target[0] - o[0]) * len,
            (target[1] - o[1]) * len,
            (target[2] - o[2]) * len,
        ];
        let ray = BoxRay::new(&m, scale, o, d);
        let may = ray.may_hit(bound);
        let sphere = box_sphere_may_hit(&m, scale, o, d, bound);
        let hits = [ray.near_far(scale, bound), ray.near_far_robust(bound)];
        if hits.iter().any(Option::is_some) {
            crossing += 1;
            assert!(may, "case {case}: a crossing ray was rejected ({hits:?})");
            assert!(
                sphere,
                "case {case}: the world sphere rejected a crossing ray"
            );
        }
        if case % 4 == 3 && target_n.iter().any(|v| v.abs() > 1.9 * lim) {
            far_total += 1;
            far_rejected += usize::from(!may);
            sphere_rejected += usize::from(!sphere);
        }
    }
    println!(
        "{crossing} crossing rays; {far_rejected} of {far_total} far-off rays rejected \
         ({sphere_rejected} by the world sphere)"
    );
    assert!(
        crossing > 10_000,
        "too few crossing rays to mean anything: {crossing}"
    );
    assert!(
        far_rejected * 2 > far_total,
        "the pre-test rejects only {far_rejected} of {far_total} rays aimed well off the box"
    );
    assert!(
        sphere_rejected * 4 > far_total,
        "the world sphere rejects only {sphere_rejected} of {far_total} rays aimed well off the box"
    );
}

#[test]
fn near_far_groups_rays_by_pose_and_reports_hits() {
    let cfg = Config::paper();
    let rc = caster(&cfg);
    // Pose 0: every part at the origin; pose 1: every part at x = 10.
    let mut skts = identities(N_JOINTS);
    skts.extend((0..N_JOINTS).flat_map(|_| translate_x(10.0)));
    let cyls = [0.0f32, 0.0, 20.0, 0.0, 0.0, 0.0, 0.0, 20.0, 0.0, 0.0];
    let scales = vec![1.0f32; N_JOINTS * 3];
    // Two rays per pose: the same ray along +x, and one passing far above every box.
    let rays_o = [-5.0f32, 0., 0., -30., 50., 0., -5., 0., 0., -30., 50., 0.];
    let rays_d = [1.0f32, 0., 0., 1., 0., 0., 1., 0., 0., 1., 0., 0.];
    let b = rc
        .near_far(&rays_o, &rays_d, &cyls, &skts, &scales)
        .unwrap();
    assert!(
        close(b.near[0], 3.9, 1e-5) && close(b.far[0], 6.1, 1e-5),
        "{:?} {:?}",
        b.near,
        b.far
    );
    assert!(
        close(b.near[2], 13.9, 1e-5) && close(b.far[2], 16.1, 1e-5),
        "{:?} {:?}",
        b.near,
        b.far
    );
    assert_eq!(b.ray_hits_body, vec![true, false, true, false]);
    assert!(b.box_hit[..N_JOINTS].iter().all(|&h| h));
    assert!(b.box_hit[N_JOINTS..2 * N_JOINTS].iter().all(|&h| !h));
    // The rays above the boxes keep their cylinder bounds: radius 20 around the origin (the
    // cylinder's height is not used), so x runs from -20 to 20, i.e. t from 10 to 50.
    for r in [1, 3] {
        assert!(
            close(b.near[r], 10.0, 1e-4) && close(b.far[r], 50.0, 1e-4),
            "ray {r}: {} {}",
            b.near[r],
            b.far[r]
        );
    }
}

#[test]
fn coarse_z_spans_near_to_far_evenly() {
    let cfg = Config::paper();
    let z = caster(&cfg).coarse_z(&[2.0, 0.5], &[6.0, 0.5]).unwrap();
    let s = cfg.n_samples;
    assert_eq!(z.len(), 2 * s);
    assert_eq!((z[0], z[s - 1]), (2.0, 6.0));
    for k in 0..s {
        assert!(
            close(z[k], 2.0 + 4.0 * k as f32 / (s - 1) as f32, 2e-6),
            "z[{k}] = {}",
            z[k]
        );
        assert_eq!(z[s + k], 0.5);
    }
}

#[test]
fn importance_samples_follow_the_pdf() {
    let cfg = Config::paper();
    let rc = caster(&cfg);
    let (sc, sf) = (cfg.n_samples, cfg.n_importance);
    let zc = rc.coarse_z(&[2.0, 2.0], &[6.0, 6.0]).unwrap();
    // Ray 0: zero weights -> flat blurred pdf -> samples evenly from the first to the last
    // bin midpoint. Ray 1: all weight on sample 20 -> samples crowd around z[20].
    let mut w = vec![0.0f32; 2 * sc];
    w[sc + 20] = 1.0;
    let zf = rc.importance_z(&zc, &w, None).unwrap();
    assert_eq!(zf.len(), 2 * sf);
    let step = 4.0 / (sc - 1) as f32;
    let (lo, hi) = (2.0 + 0.5 * step, 6.0 - 0.5 * step);
    for (m, &z) in zf[..sf].iter().enumerate() {
        let want = lo + (hi - lo) * m as f32 / (sf - 1) as f32;
        assert!(close(z, want, 1e-4), "uniform sample {m}: {z} vs {want}");
    }
    let near_peak = zf[sf..]
        .iter()
        .filter(|&&z| (z - zc[20]).abs() <= 1.5 * step)
        .count();
    assert!(
        near_peak >= sf / 2,
        "only {near_peak} of {sf} samples near the peak: {:?}",
        &zf[sf..]
    );
    for row in zf.chunks(sf) {
        assert!(
            row.windows(2).all(|p| p[0] <= p[1]),
            "not ascending: {row:?}"
        );
        assert!(row.iter().all(|&z| (lo..=hi).contains(&z)));
    }
}

#[test]
fn merge_raw_routes_gradients_to_both_passes() {
    let dev = Device::Cpu;
    let coarse = Var::from_tensor(&Tensor::new(&[[[1f32], [3.], [5.]]], &dev).unwrap()).unwrap();
    let fine = Var::from_tensor(&Tensor::new(&[[[2f32], [4.]]], &dev).unwrap()).unwrap();
    let perm = Tensor::new(&[[0u32, 3, 1, 4, 2]], &dev).unwrap();
    let merged = merge_raw(
        coarse.as_tensor(),
        fine.as_tensor(),
        &perm,
        pma_model::compute::numerics::Numerics::PARITY,
    )
    .unwrap();
    let values: Vec<f32> = merged.flatten_all().unwrap().to_vec1().unwrap();
    assert_eq!(values, vec![1., 2., 3., 4., 5.]);
    let weights = Tensor::new(&[[[10f32], [20.], [30.], [40.], [50.]]], &dev).unwrap();
    let grads = (merged * weights)
        .unwrap()
        .sum_all()
        .unwrap()
        .backward()
        .unwrap();
    let gc = flat(grads.get(coarse.as_tensor()).unwrap());
    let gf = flat(grads.get(fine.as_tensor()).unwrap());
    assert_eq!((gc, gf), (vec![10., 30., 50.], vec![20., 40.]));
}

#[test]
fn bad_inputs_are_errors() {
    let cfg = Config::paper();
    let rc = caster(&cfg);
    let skts = identities(N_JOINTS);
    let cyls = [0.0f32, 0.0, 1.0, 0.0, 0.0];
    let scales = vec![1.0f32; N_JOINTS * 3];
    let o = [0.0f32, 0.0, -5.0, 0.0, 0.0, -5.0, 0.0, 0.0, -5.0];
    let d = [0.0f32, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0];
    assert!(rc.near_far(&o, &d, &cyls, &skts, &scales).is_ok());
    let err = |r: Result<_, pma_model::error::ModelError>| {
        r.map(|_: pma_model::render::raycast::RayBounds| ())
            .unwrap_err()
            .to_string()
    };
    // 3 rays cannot be split into 2 poses.
    let two = identities(2 * N_JOINTS);
    assert!(err(rc.near_far(&o, &d, &[cyls, cyls].concat(), &two, &scales)).contains("3 rays"));
    assert!(err(rc.near_far(&o[..8], &d, &cyls, &skts, &scales)).contains("rays_o"));
    assert!(err(rc.near_far(&o, &d, &cyls[..3], &skts, &scales)).contains("cyls"));
    let mut zero = scales.clone();
    zero[7] = 0.0;
    assert!(err(rc.near_far(&o, &d, &cyls, &skts, &zero)).contains("joint 2 axis 1"));
    let mut nan_d = d;
    nan_d[4] = f32::NAN;
    assert!(err(rc.near_far(&o, &nan_d, &cyls, &skts, &scales)).contains("rays_d"));
    let mut zero_d = d;
    zero_d[3..6].fill(0.0);
    assert!(err(rc.near_far(&o, &zero_d, &cyls, &skts, &scales)).contains("ray 1"));
    let w_nan = vec![f32::NAN; cfg.n_samples];
    let zc = rc.coarse_z(&[1.0], &[2.0]).unwrap();
    assert!(rc.importance_z(&zc, &w_nan, None).is_err());
    assert!(rc.importance_z(&zc, &w_nan[1..], None).is_err());
    assert!(RayCaster::new(&cfg, &identities(23)).is_err());
    let few = Config {
        n_samples: 2,
        ..Config::paper()
    };
    assert!(RayCaster::new(&few, &identities(N_JOINTS)).is_err());
    // Tensor entry point: wrong shapes are named.
    let t = |v: &[f32], s: &[usize]| Tensor::from_vec(v.to_vec(), s, &Device::Cpu).unwrap();
    let msg = rc
        .cast(
            &t(&o, &[3, 3]),
            &t(&d, &[3, 3]),
            &t(&cyls, &[1, 5]),
            &t(&skts, &[24, 4, 4]),
            &t(&scales, &[24, 3]),
        )
        .unwrap_err()
        .to_string();
    assert!(msg.contains("skts"), "{msg}");
}
