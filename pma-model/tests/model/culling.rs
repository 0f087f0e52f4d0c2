//! Leaving work out (`pma_model::render::cull`): culling at threshold 0 is exactly parity
//! mode on the golden cases in inference, and parity up to the last bits of the far-away
//! constant on the training route (which computes it in a call of its own); culled rays are exactly the background with zero weights while
//! every other ray is untouched; a small sample threshold changes a render by a bounded amount.

use crate::common::*;
use candle_core::{Device, Tensor};
use pma_data::camera::Camera;
use pma_model::network::config::Config;
use pma_model::render::avatar::{Avatar, Mode, Outputs};
use pma_model::render::cull::{SampleFate, WindowTest};
use pma_model::render::image::{render_image, ChunkRender, ImageOptions};
use pma_model::render::{Culling, PassOptions, SampleFill};

fn culling(rays: bool, threshold: Option<f64>) -> PassOptions {
    PassOptions::culled(Culling {
        rays,
        sample_threshold: threshold,
        sample_fill: SampleFill::Network,
    })
}

/// Every output tensor of a forward pass, by name.
pub(crate) fn tensors(o: &Outputs) -> Vec<(&'static str, Vec<f32>)> {
    vec![
        ("fine/rgb", flat(&o.fine.rgb)),
        ("fine/acc", flat(&o.fine.acc)),
        ("fine/disp", flat(&o.fine.disp)),
        ("fine/depth", flat(&o.fine.depth)),
        ("fine/weights", flat(&o.fine.weights)),
        ("fine/alpha", flat(&o.fine.alpha)),
        ("coarse/rgb", flat(&o.coarse.rgb)),
        ("coarse/acc", flat(&o.coarse.acc)),
        ("coarse/disp", flat(&o.coarse.disp)),
        ("coarse/weights", flat(&o.coarse.weights)),
        ("z_coarse", flat(&o.z_coarse)),
        ("z_vals", flat(&o.z_vals)),
        ("raw_coarse", flat(&o.raw_coarse)),
        ("raw", flat(&o.raw)),
    ]
}

pub(crate) fn assert_identical(a: &Outputs, b: &Outputs, what: &str) {
    let mut problems = Vec::new();
    for ((name, x), (_, y)) in tensors(a).into_iter().zip(tensors(b)) {
        assert_eq!(x.len(), y.len(), "{what}: {name} sizes differ");
        let bad = x.iter().zip(&y).filter(|(p, q)| p != q).count();
        let max = max_abs_diff(&x, &y);
        if bad > 0 {
            problems.push(format!(
                "{name} differs in {bad} of {} values (max |diff| {max:e})",
                x.len()
            ));
        }
    }
    assert!(problems.is_empty(), "{what}: {problems:#?}");
}

/// Every output of `b` within `tol` of `a`'s.
pub(crate) fn assert_close(a: &Outputs, b: &Outputs, tol: f32, what: &str) {
    for ((name, x), (_, y)) in tensors(a).into_iter().zip(tensors(b)) {
        assert_eq!(x.len(), y.len(), "{what}: {name} sizes differ");
        let max = max_abs_diff(&x, &y);
        assert!(
            max <= tol,
            "{what}: {name} differs by {max:e} (tolerance {tol:e})"
        );
    }
}

/// How far the training route's threshold-0 culling may move an output from parity: it
/// computes the far-away constant in a call of its own (the trunk once per pose, the colour
/// head per ray), whose products round differently in the last bit from the same point's
/// row inside a larger call (docs/numerics.md, "Empty rays and culling"). Measured on the
/// dense golden case: raw within 4.8e-7, weights within 1.9e-6, alpha within 3.1e-6.
pub(crate) const FAR_CALL_TOLERANCE: f32 = 1e-5;

/// Samples of a pass whose window is 0 for every joint (host test at threshold 0).
fn zero_window_samples(avatar: &Avatar, case: &GoldenCase, pts: &Tensor) -> usize {
    let align = flat(&avatar.tensors()["pts_embedder.transforms"]);
    let test = WindowTest::new(
        &align,
        &flat(&case.poses.skts),
        &flat(&avatar.axis_scale().unwrap()),
        2.0,
        6,
        0.0,
    )
    .unwrap();
    let (r, s, _) = pts.dims3().unwrap();
    test.fates(&flat(pts), r, s, None, None)
        .unwrap()
        .iter()
        .filter(|f| **f == SampleFate::Outside)
        .count()
}

fn inference(case: &GoldenCase, opts: &PassOptions) -> Outputs {
    case.avatar
        .forward(&case.rays, &case.poses, &mut Mode::Infer, opts, None)
        .unwrap()
}

fn threshold_zero_is_parity(dir: &str, sigma_override: bool) {
    let case = GoldenCase::load(dir, sigma_override);
    let parity = case.forward(None);
    let parity_inf = inference(&case, &PassOptions::parity());
    let culled_coarse = zero_window_samples(&case.avatar, &case, &parity.z_coarse_pts(&case));
    let cull = culling(false, Some(0.0));
    let culled = case.forward_with(&cull, None);
    let evaluated = culled.stats.points_evaluated;
    let total = parity.raw.dims()[0] * parity.raw.dims()[1];
    println!(
        "[{dir}] {culled_coarse} coarse samples have a zero window; network points {evaluated} of {total}"
    );
    assert!(
        culled_coarse > 0,
        "{dir}: no sample has a zero window, the test would not exercise culling"
    );
    assert!(
        (evaluated as usize) < total,
        "{dir}: culling evaluated {evaluated} points, parity {total}"
    );
    assert_close(&parity, &culled, FAR_CALL_TOLERANCE, dir);
    // Inference (chunked, detached; one shared constant row when its density is 0): every
    // rendered output is identical; raw colours of zero-density culled samples may differ.
    let culled_inf = inference(&case, &cull);
    for (a, b, name) in [
        (&parity_inf.fine.rgb, &culled_inf.fine.rgb, "rgb"),
        (
            &parity_inf.fine.weights,
            &culled_inf.fine.weights,
            "weights",
        ),
        (&parity_inf.fine.disp, &culled_inf.fine.disp, "disp"),
        (&parity_inf.coarse.rgb, &culled_inf.coarse.rgb, "rgb0"),
    ] {
        assert_eq!(flat(a), flat(b), "{dir}: inference {name} differs");
    }
}

trait CoarsePts {
    fn z_coarse_pts(&self, case: &GoldenCase) -> Tensor;
}

impl CoarsePts for Outputs {
    /// Coarse sample points o + z·d: [R,Sc,3].
    fn z_coarse_pts(&self, case: &GoldenCase) -> Tensor {
        let z = self.z_coarse.unsqueeze(2).unwrap();
        case.rays
            .origins
            .unsqueeze(1)
            .unwrap()
            .broadcast_add(
                &z.broadcast_mul(&case.rays.dirs.unsqueeze(1).unwrap())
                    .unwrap(),
            )
            .unwrap()
    }
}

#[test]
fn threshold_zero_equals_parity_on_the_golden_case() {
    threshold_zero_is_parity("golden", false);
}

#[test]
fn threshold_zero_equals_parity_on_the_dense_golden_case() {
    threshold_zero_is_parity("golden/dense", true);
}

#[test]
fn culled_rays_are_background_and_hitting_rays_are_unchanged() {
    let case = GoldenCase::load("golden/dense", true);
    let parity = case.forward(None);
    let culled = case.forward_with(&culling(true, None), None);
    let hits = &parity.bounds.as_ref().unwrap().ray_hits_body;
    let n_miss = hits.iter().filter(|h| !**h).count();
    assert!(
        n_miss > 0 && n_miss < hits.len(),
        "the golden batch should mix hitting and missing rays ({n_miss} miss)"
    );
    let bgs = flat(case.rays.bgs.as_ref().unwrap());
    let (rgb_p, rgb_c) = (flat(&parity.fine.rgb), flat(&culled.fine.rgb));
    let m = parity.fine.weights.dims()[1];
    let sc = parity.coarse.weights.dims()[1];
    let (w_p, w_c) = (flat(&parity.fine.weights), flat(&culled.fine.weights));
    let (w0_p, w0_c) = (flat(&parity.coarse.weights), flat(&culled.coarse.weights));
    let (acc_c, disp_c, depth_c) = (
        flat(&culled.fine.acc),
        flat(&culled.fine.disp),
        flat(&culled.fine.depth),
    );
    let (acc_p, disp_p) = (flat(&parity.fine.acc), flat(&parity.fine.disp));
    let mut changed = 0;
    for (r, &hit) in hits.iter().enumerate() {
        if hit {
            assert_eq!(rgb_c[3 * r..3 * r + 3], rgb_p[3 * r..3 * r + 3], "ray {r}");
            assert_eq!(w_c[r * m..(r + 1) * m], w_p[r * m..(r + 1) * m], "ray {r}");
            assert_eq!(w0_c[r * sc..(r + 1) * sc], w0_p[r * sc..(r + 1) * sc]);
            assert_eq!((acc_c[r], disp_c[r]), (acc_p[r], disp_p[r]), "ray {r}");
        } else {
            assert_eq!(rgb_c[3 * r..3 * r + 3], bgs[3 * r..3 * r + 3], "ray {r}");
            assert!(w_c[r * m..(r + 1) * m].iter().all(|&w| w == 0.0), "ray {r}");
            assert!(w0_c[r * sc..(r + 1) * sc].iter().all(|&w| w == 0.0));
            assert_eq!(
                (acc_c[r], disp_c[r], depth_c[r]),
                (0.0, 0.0, 0.0),
                "ray {r}"
            );
            if rgb_p[3 * r..3 * r + 3] != rgb_c[3 * r..3 * r + 3] {
                changed += 1;
            }
        }
    }
    // With the dense override the parity network puts density on these rays, so the
    // comparison above would catch a culled ray that was still evaluated.
    assert!(changed > 0, "no culled ray differs from parity");
}

/// A small synthetic case: an untrained cpu-small avatar (with visible density) on the
/// synthetic figure's rest pose, a 40×40 view, rays not culled. Bound: a culled sample has
/// w = w^p·w^f ≤ t on every joint, and the network sees w only through x̃ = w·z (|z| ≤ 1) and
/// f^m = Σ_j w_j g_j, so its raw output moves by at most L·t (first order); each of the S
/// samples of a ray has compositing weight ≤ 1, so the colour moves by at most S·L·t. We
/// take L = 1e-2 (at t = 1e-2 this init measures 7.8e-6 in total, i.e. L ≈ 3e-5 per sample;
/// the bound leaves two orders of magnitude for other platforms) plus 1e-6 for the ulp-level
/// effect of changed call sizes on gemm.
/// An untrained cpu-small avatar with visible density, the synthetic figure's rest pose and
/// a camera on it of `res`×`res` pixels. Untrained, the density head is ≤ 0 almost everywhere and every
/// render is black; the dense golden case's override (σ weights ×50, bias 2) gives the
/// network visible density.
fn visible_avatar(
    res: usize,
) -> (
    Avatar,
    pma_model::render::avatar::Poses,
    pma_data::skeleton::Joints,
    Camera,
) {
    let dev = Device::Cpu;
    let rest = pma_data::synth::rest_pose();
    let cfg = Config::cpu_small();
    let mut tensors = pma_model::network::init_tensors(&cfg, &rest, 3, &dev).unwrap();
    let w = (tensors["sigma_linear.weight"].clone() * 50.0).unwrap();
    tensors.insert("sigma_linear.weight".into(), w);
    tensors.insert(
        "sigma_linear.bias".into(),
        Tensor::new(&[2f32], &dev).unwrap(),
    );
    let avatar = Avatar::from_tensors(cfg, tensors, &dev).unwrap();
    let (poses, kp3d) = avatar.pose_from_bones(&[[0.0; 3]; 24], [0.0; 3]).unwrap();
    let c2w = [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, -0.2],
        [0.0, 0.0, 1.0, 3.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let f = res as f32;
    let cam = Camera::new(res, res, f, f, f / 2.0, f / 2.0, c2w).unwrap();
    (avatar, poses, kp3d, cam)
}

#[test]
fn small_sample_threshold_changes_the_render_by_a_bounded_amount() {
    let (avatar, poses, kp3d, cam) = visible_avatar(40);
    let cfg = avatar.config();
    let samples = (cfg.n_samples + cfg.n_importance) as f64;
    let parity = avatar
        .render_image(&poses, &kp3d, &cam, None, &ImageOptions::default())
        .unwrap();
    let mut prev = 0.0;
    for t in [1e-6, 1e-4, 1e-2] {
        let opts = ImageOptions {
            pass: culling(false, Some(t)),
            ..Default::default()
        };
        let img = avatar
            .render_image(&poses, &kp3d, &cam, None, &opts)
            .unwrap();
        let points = img.stats.points_evaluated;
        let max = parity
            .rgb
            .iter()
            .zip(&img.rgb)
            .map(|(a, b)| (a - b).abs() as f64)
            .fold(0.0, f64::max);
        let bound = 1e-2 * t * samples + 1e-6;
        println!("t {t:e}: max |Δrgb| {max:.3e} (bound {bound:.3e}), {points} network points");
        assert!(max <= bound, "t {t}: max |Δrgb| {max} > {bound}");
        assert!(max >= prev * 0.5 || max < 1e-6, "error should grow with t");
        prev = max;
    }
    // The comparison can fail: at 1e-2 the culled samples do move the render.
    assert!(prev > 0.0, "culling at 1e-2 left the render bit-identical");
}

/// Network calls grouped by the joints their samples need (`cull_joints`) leave out only
/// joints whose window is exactly 0 at every point of the call: the image is the one of the
/// same pass without the grouping up to float summation order (1e-5: the first modulated
/// layer's and f^m's sums skip exact zeros), the same samples run the network, and the calls
/// carry far fewer joints (a count).
#[test]
fn calls_grouped_by_joints_render_the_same_image() {
    // Enough pixels for several calls per pass.
    let (avatar, poses, kp3d, cam) = visible_avatar(96);
    for t in [0.0, 0.6] {
        let render = |cull_joints: bool| {
            let opts = ImageOptions {
                pass: PassOptions {
                    cull_joints,
                    ..culling(true, Some(t))
                },
                ..Default::default()
            };
            avatar
                .render_image(&poses, &kp3d, &cam, None, &opts)
                .unwrap()
        };
        let (all, grouped) = (render(false), render(true));
        let max = all
            .rgb
            .iter()
            .zip(&grouped.rgb)
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        let (a, g) = (all.stats, grouped.stats);
        println!(
            "t {t}: max |Δrgb| {max:.2e}; joint rows {} of {} ({} network points)",
            g.joint_rows, a.joint_rows, g.points_evaluated
        );
        assert!(
            all.acc.iter().any(|&v| v > 0.1),
            "t {t}: the image shows no body"
        );
        assert!(max <= 1e-5, "t {t}: grouping moved the image by {max}");
        assert_eq!(
            (a.coarse_evaluated, a.fine_evaluated),
            (g.coarse_evaluated, g.fine_evaluated),
            "t {t}: the grouping changed which samples ran"
        );
        assert_eq!(
            a.joint_rows,
            24 * a.points_evaluated,
            "t {t}: ungrouped calls carry all joints"
        );
        assert!(
            (g.joint_rows as f64) < 0.6 * a.joint_rows as f64,
            "t {t}: grouped calls carry {} of {} joint rows",
            g.joint_rows,
            a.joint_rows
        );
    }
}

/// With ray culling an image chunk composites and resamples only the rays that cross a bone
/// box (`Avatar::render_chunk`); the others are exactly the background with acc and disp 0.
/// The image, and every count, equals that of the whole chunk's forward pass, bit for bit:
/// culled rays add no sample to a network call and compositing is per ray.
#[test]
// The renderer closure returns the crate's error, which carries candle's (large) one.
#[allow(clippy::result_large_err)]
fn rays_that_cross_no_box_are_left_out_of_the_chunk_exactly() {
    let (avatar, poses, kp3d, cam) = visible_avatar(64);
    let (w, h) = (cam.width, cam.height);
    // A background that differs per pixel, so a culled ray given another's would show.
    let bg: Vec<f32> = (0..w * h)
        .flat_map(|p| [(p % w) as f32 / w as f32, (p / w) as f32 / h as f32, 0.25])
        .collect();
    let early_joints = PassOptions {
        early_stop: Some(0.01),
        cull_joints: true,
        ..culling(true, Some(0.6))
    };
    for pass in [culling(true, None), culling(true, Some(0.6)), early_joints] {
        let opts = ImageOptions {
            // Several chunks, some with rays of both kinds.
            chunk: 700,
            pass: pass.clone(),
            ..Default::default()
        };
        let left_out = avatar
            .render_image(&poses, &kp3d, &cam, Some(&bg), &opts)
            .unwrap();
        let pose = avatar.pose_features(&poses, None).unwrap();
        let whole_chunk = |o: &Tensor, d: &Tensor, b: &Tensor| {
            let rays = pma_model::render::avatar::Rays {
                origins: o.clone(),
                dirs: d.clone(),
                bgs: Some(b.clone()),
                framecodes: vec![-1; o.dim(0)?],
            };
            let out = avatar.forward_with_pose(&rays, &poses, &pose, &mut Mode::Infer, &pass)?;
            Ok(ChunkRender {
                rgb: out.fine.rgb,
                acc: out.fine.acc,
                disp: out.fine.disp,
                stats: out.stats,
            })
        };
        let whole = render_image(&whole_chunk, &cam, &kp3d, Some(&bg), &opts).unwrap();
        let s = left_out.stats;
        let rays = s.samples / (avatar.config().n_samples + avatar.config().n_importance) as u64;
        println!("{pass:?}: {} of {rays} rays culled", s.rays_culled);
        assert!(
            s.rays_culled > 0 && s.rays_culled < rays,
            "the image needs rays of both kinds: {} of {rays} culled",
            s.rays_culled
        );
        assert!(
            left_out.acc.iter().any(|&a| a > 0.1),
            "the image shows no body"
        );
        assert_eq!(left_out.stats, whole.stats, "counts differ");
        for (name, a, b) in [
            ("rgb", &left_out.rgb, &whole.rgb),
            ("acc", &left_out.acc, &whole.acc),
            ("disp", &left_out.disp, &whole.disp),
        ] {
            let differ = a.iter().zip(b).filter(|(x, y)| x.to_bits() != y.to_bits());
            assert_eq!(differ.count(), 0, "{name} differs from the whole chunk's");
        }
    }
}

/// The network on a joint subset: exact (to 1e-5) when every left-out joint's window is 0 at
/// every point, and visibly wrong when a joint with a non-zero window is left out, so the
/// image test above would catch a grouping that dropped a needed joint.
#[test]
fn a_joint_subset_call_is_exact_only_without_live_joints() {
    let (avatar, poses, _, _) = visible_avatar(40);
    let net = avatar.network();
    let pose = avatar.pose_features(&poses, None).unwrap();
    // Points around the left knee (joint 4) of the rest pose.
    let knee = avatar.rest_pose()[4];
    let pts: Vec<f32> = (0..64)
        .flat_map(|i| {
            let f = i as f32 / 64.0;
            [
                knee[0] + 0.04 * (f * 7.0).sin(),
                knee[1] + 0.1 * (f - 0.5),
                knee[2] + 0.04 * (f * 5.0).cos(),
            ]
        })
        .collect();
    let n = pts.len() / 3;
    let test = WindowTest::new(
        &flat(&avatar.tensors()["pts_embedder.transforms"]),
        &flat(&poses.skts),
        &flat(&avatar.axis_scale().unwrap()),
        2.0,
        6,
        0.0,
    )
    .unwrap();
    let samples: Vec<usize> = (0..n).collect();
    let union = test
        .live_joints(&pts, n, 1, &samples)
        .unwrap()
        .iter()
        .fold(0u32, |a, b| a | b);
    let live: Vec<u32> = (0..24).filter(|j| union >> j & 1 == 1).collect();
    assert!(live.contains(&4) && live.len() < 12, "live joints {live:?}");
    let dev = Device::Cpu;
    let pts = Tensor::from_vec(pts, (n, 3), &dev).unwrap();
    let d = Tensor::from_vec([0f32, 0.0, -1.0].repeat(n), (n, 3), &dev).unwrap();
    let view = avatar
        .network()
        .view_features(&d, &vec![-1; n], false)
        .unwrap();
    let eval = |joints: Option<&[u32]>| {
        let (rgb, sigma) = net
            .eval_joints(&pose, 0..1, &pts, &view, joints, None)
            .unwrap();
        [flat(&rgb), flat(&sigma)].concat()
    };
    let diff = |a: &[f32], b: &[f32]| {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0f32, f32::max)
    };
    let full = eval(None);
    let exact = diff(&full, &eval(Some(&live)));
    let without_knee: Vec<u32> = live.iter().copied().filter(|&j| j != 4).collect();
    let wrong = diff(&full, &eval(Some(&without_knee)));
    println!("live joints {live:?}: max |Δ| {exact:.2e} with them, {wrong:.2e} without the knee");
    assert!(
        exact <= 1e-5,
        "subset of the live joints moved the outputs by {exact}"
    );
    assert!(
        wrong > 1e-3,
        "leaving out a live joint changed the outputs by only {wrong}"
    );
    // Bad subsets are refused.
    for bad in [&[][..], &[5, 4][..], &[3, 24][..]] {
        assert!(
            net.eval_joints(&pose, 0..1, &pts, &view, Some(bad), None)
                .is_err(),
            "{bad:?}"
        );
    }
}

/// The far-away call of the training route (`Network::eval_shared`): one point per pose
/// seen along many rays gives each ray what the per-point call gives that point with the
/// ray's view (up to the last bits, [`FAR_CALL_TOLERANCE`]). Its gradients are checked
/// against parity's in `train_culling.rs`.
#[test]
fn a_shared_point_call_gives_each_ray_the_per_point_output() {
    let case = GoldenCase::load("golden", false);
    let net = case.avatar.network();
    let pose = case.avatar.pose_features(&case.poses, None).unwrap();
    let n_poses = pose.g.dim(0).unwrap();
    let dev = pose.g.device().clone();
    let v = net.config().sh_degree * net.config().sh_degree
        + if net.config().use_framecodes {
            net.config().framecode_ch
        } else {
            0
        };
    // One point per pose, six rays per pose with views of their own.
    let rays = 6 * n_poses;
    let pts: Vec<f32> = (0..n_poses)
        .flat_map(|p| [0.05 * p as f32, 0.1, -0.02])
        .collect();
    let pts = Tensor::from_vec(pts, (n_poses, 3), &dev).unwrap();
    let view: Vec<f32> = (0..rays * v)
        .map(|i| ((i * 37 % 101) as f32 / 101.0) - 0.5)
        .collect();
    let view = Tensor::from_vec(view, (rays, v), &dev).unwrap();
    let pose_of: Vec<u32> = (0..rays).map(|r| (r / 6) as u32).collect();
    let rows = Tensor::from_vec(pose_of.clone(), rays, &dev).unwrap();
    let (rgb, sigma) = net
        .eval_shared(&pose, 0..n_poses, &pts, &view, &rows)
        .unwrap();
    assert_eq!(rgb.dims(), &[rays, 3]);
    assert_eq!(sigma.dims(), &[rays, 1]);
    // The per-point call: each ray's point repeated, in equal blocks per pose.
    let repeated = pts.index_select(&rows, 0).unwrap();
    let (want_rgb, want_sigma) = net
        .eval_poses(&pose, 0..n_poses, &repeated, &view, None)
        .unwrap();
    for (got, want, name) in [(&rgb, &want_rgb, "rgb"), (&sigma, &want_sigma, "sigma")] {
        let worst = max_abs_diff(&flat(got), &flat(want));
        assert!(worst <= FAR_CALL_TOLERANCE, "{name} differs by {worst:e}");
    }
    // Rays of one pose share its density; views set their colours apart.
    let s = flat(&sigma);
    assert!(s[..6].iter().all(|&x| x.to_bits() == s[0].to_bits()));
    let c = flat(&rgb);
    assert!(c[0..3] != c[3..6], "two views of one point got one colour");
}

/// The density-only call (the grid's refreshes) gives the bits of the full call's density,
/// on the golden model, for every pose.
#[test]
fn a_density_only_call_gives_the_full_calls_density_bit_for_bit() {
    let case = GoldenCase::load("golden", false);
    let net = case.avatar.network();
    let pose = case.avatar.pose_features(&case.poses, None).unwrap();
    let dev = pose.g.device().clone();
    let v = net.config().sh_degree * net.config().sh_degree
        + if net.config().use_framecodes {
            net.config().framecode_ch
        } else {
            0
        };
    let n = 40;
    let pts: Vec<f32> = (0..n * 3)
        .map(|i| ((i * 53 % 97) as f32 / 97.0 - 0.5) * 0.6)
        .collect();
    let pts = Tensor::from_vec(pts, (n, 3), &dev).unwrap();
    let view = Tensor::ones((n, v), candle_core::DType::F32, &dev).unwrap();
    for p in 0..pose.g.dim(0).unwrap() {
        let (_, want) = net.eval_points(&pose, p, &pts, &view, None).unwrap();
        let got = net.eval_density(&pose, p, &pts).unwrap();
        assert_eq!(got.dims(), &[n, 1]);
        let (got, want) = (flat(&got), flat(&want));
        assert!(
            want.iter().any(|&s| s != want[0]),
            "a constant density tests nothing"
        );
        let same = got
            .iter()
            .zip(&want)
            .all(|(a, b)| a.to_bits() == b.to_bits());
        assert!(same, "pose {p}: {got:?} against {want:?}");
    }
}
