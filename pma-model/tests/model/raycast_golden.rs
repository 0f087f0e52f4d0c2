//! Ray caster against the reference outputs in fixtures/golden (standard and dense cases).
//!
//! Inputs are the reference's own: rays, one pose's skts and cylinder, the effective axis
//! scales it used and its `raycast.transforms`; importance sampling is fed the reference's
//! coarse weights so that only the ray caster is under test.

use std::collections::HashMap;

use crate::common::{flat, golden_values, load_golden, max_abs_err};
use candle_core::Tensor;
use pma_data::skeleton::N_JOINTS;
use pma_model::network::config::Config;
use pma_model::render::raycast::{merge_sorted, sample_points, RayCaster};

/// Max abs error allowed on every float output (the reference's own float32 results).
const TOL: f32 = 1e-4;

fn f32s(g: &HashMap<String, Tensor>, key: &str) -> Vec<f32> {
    golden_values(g, key)
}

fn ints(g: &HashMap<String, Tensor>, key: &str) -> Vec<i64> {
    golden_values(g, key)
}

fn assert_close(what: &str, got: &[f32], want: &[f32]) {
    let err = max_abs_err(got, want);
    let exact = got
        .iter()
        .zip(want)
        .filter(|(x, y)| x.to_bits() == y.to_bits())
        .count();
    eprintln!(
        "{what}: max abs err {err:e}, bit-exact {exact}/{}",
        want.len()
    );
    assert!(err <= TOL, "{what}: max abs error {err} > {TOL}");
}

/// The reference batch carries per-ray copies of one pose: check that and keep one copy.
fn one_pose(per_ray: &[f32], n_rays: usize) -> Vec<f32> {
    let n = per_ray.len() / n_rays;
    for r in 1..n_rays {
        assert_eq!(
            &per_ray[r * n..(r + 1) * n],
            &per_ray[..n],
            "ray {r} carries a different pose"
        );
    }
    per_ray[..n].to_vec()
}

fn check_case(case: &str) {
    let g = load_golden(&format!("{case}golden.safetensors"));
    let model = load_golden("model.safetensors");
    let cfg = Config::paper();
    let caster = RayCaster::new(&cfg, &f32s(&model, "raycast.transforms")).unwrap();
    let (sc, sf) = (cfg.n_samples, cfg.n_importance);

    let rays_o = f32s(&g, "input/rays_o");
    let rays_d = f32s(&g, "input/rays_d");
    let n_rays = rays_o.len() / 3;
    let skts = one_pose(&f32s(&g, "input/skts"), n_rays);
    let cyls = one_pose(&f32s(&g, "input/cyls"), n_rays);
    let scales = f32s(&g, "coarse/axis_scale");

    let b = caster
        .near_far(&rays_o, &rays_d, &cyls, &skts, &scales)
        .unwrap();
    assert_close(&format!("{case}near"), &b.near, &f32s(&g, "raycast/near"));
    assert_close(&format!("{case}far"), &b.far, &f32s(&g, "raycast/far"));
    let box_hit: Vec<i64> = b.box_hit.iter().map(|&h| h as i64).collect();
    assert_eq!(box_hit, ints(&g, "raycast/box_hit"), "{case}box_hit");
    let hits_body: Vec<i64> = b.ray_hits_body.iter().map(|&h| h as i64).collect();
    assert_eq!(
        hits_body,
        ints(&g, "raycast/ray_hits_body"),
        "{case}ray_hits_body"
    );
    // The fixture's ray kinds: 0 = hits a box; 1 and 2 must not.
    for (r, kind) in ints(&g, "input/ray_kind").into_iter().enumerate() {
        assert_eq!(
            b.ray_hits_body[r],
            kind == 0,
            "{case}ray {r} of kind {kind}"
        );
    }
    assert_eq!(b.box_hit.len(), n_rays * N_JOINTS);

    let z = caster.coarse_z(&b.near, &b.far).unwrap();
    assert_close(
        &format!("{case}z_vals_coarse"),
        &z,
        &f32s(&g, "raycast/z_vals_coarse"),
    );
    let pts = sample_points(&rays_o, &rays_d, &z, sc).unwrap();
    assert_close(
        &format!("{case}pts_coarse"),
        &pts,
        &f32s(&g, "raycast/pts_coarse"),
    );

    // Importance sampling from the reference's own coarse z and weights.
    let z_ref = f32s(&g, "raycast/z_vals_coarse");
    let w_ref = f32s(&g, "render_coarse/weights");
    let z_is = caster.importance_z(&z_ref, &w_ref, None).unwrap();
    let pts_is = sample_points(&rays_o, &rays_d, &z_is, sf).unwrap();
    assert_close(
        &format!("{case}pts_is"),
        &pts_is,
        &f32s(&g, "raycast/pts_is"),
    );

    let (z_all, perm) = merge_sorted(&z_ref, sc, &z_is, sf).unwrap();
    assert_close(
        &format!("{case}z_vals_merged"),
        &z_all,
        &f32s(&g, "raycast/z_vals_merged"),
    );
    let perm: Vec<i64> = perm.into_iter().map(i64::from).collect();
    let want = ints(&g, "raycast/sorted_idxs");
    let m = sc + sf;
    let bad: Vec<usize> = (0..n_rays)
        .filter(|&r| perm[r * m..(r + 1) * m] != want[r * m..(r + 1) * m])
        .collect();
    assert!(bad.is_empty(), "{case}sorted_idxs differ on rays {bad:?}");
}

#[test]
fn standard_case_matches_reference() {
    check_case("");
}

#[test]
fn dense_case_matches_reference() {
    check_case("dense/");
}

/// A golden batch's rays, the transforms and cylinders of its one pose, and the coarse
/// axis scales, as the tensor entry points take them.
struct RayInputs {
    rays_o: Tensor,
    rays_d: Tensor,
    skts: Tensor,
    cyls: Tensor,
    scales: Tensor,
}

impl RayInputs {
    fn of(g: &HashMap<String, Tensor>) -> Self {
        Self {
            rays_o: g["input/rays_o"].clone(),
            rays_d: g["input/rays_d"].clone(),
            skts: g["input/skts"].narrow(0, 0, 1).unwrap(),
            cyls: g["input/cyls"].narrow(0, 0, 1).unwrap(),
            scales: g["coarse/axis_scale"].clone(),
        }
    }
}

#[test]
fn tensor_entry_points_match_host_code() {
    let g = load_golden("dense/golden.safetensors");
    let model = load_golden("model.safetensors");
    let cfg = Config::paper();
    let caster = RayCaster::from_tensor(&cfg, model.get("raycast.transforms").unwrap()).unwrap();
    let r = RayInputs::of(&g);
    let n_rays = r.rays_o.dims()[0];
    let coarse = caster
        .cast(&r.rays_o, &r.rays_d, &r.cyls, &r.skts, &r.scales)
        .unwrap();
    assert_eq!(coarse.z.dims(), [n_rays, cfg.n_samples]);
    assert_eq!(coarse.pts.dims(), [n_rays, cfg.n_samples, 3]);
    let pts: Vec<f32> = coarse.pts.flatten_all().unwrap().to_vec1().unwrap();
    assert!(max_abs_err(&pts, &f32s(&g, "raycast/pts_coarse")) <= TOL);

    let fine = caster
        .resample(
            &r.rays_o,
            &r.rays_d,
            &g["raycast/z_vals_coarse"],
            &g["render_coarse/weights"],
            None,
        )
        .unwrap();
    let pts_is: Vec<f32> = fine.pts.flatten_all().unwrap().to_vec1().unwrap();
    assert!(max_abs_err(&pts_is, &f32s(&g, "raycast/pts_is")) <= TOL);
    let perm: Vec<u32> = fine.perm.flatten_all().unwrap().to_vec1().unwrap();
    let want: Vec<u32> = ints(&g, "raycast/sorted_idxs")
        .into_iter()
        .map(|v| v as u32)
        .collect();
    assert_eq!(perm, want);

    // merge_raw applied to the z values themselves must reproduce the merged list.
    let zc = g["raycast/z_vals_coarse"].unsqueeze(2).unwrap();
    let zf = fine.z.unsqueeze(2).unwrap();
    let merged = pma_model::render::raycast::merge_raw(
        &zc,
        &zf,
        &fine.perm,
        pma_model::compute::numerics::Numerics::PARITY,
    )
    .unwrap()
    .squeeze(2)
    .unwrap();
    let merged: Vec<f32> = merged.flatten_all().unwrap().to_vec1().unwrap();
    let z_all: Vec<f32> = fine.z_all.flatten_all().unwrap().to_vec1().unwrap();
    assert_eq!(merged, z_all);
    assert!(max_abs_err(&z_all, &f32s(&g, "raycast/z_vals_merged")) <= TOL);
}

/// The tensor-op path (what a GPU runs, here on the CPU) against the reference, at the same
/// tolerance: near/far, coarse samples, importance samples from the reference's weights,
/// and the merge (whose permutation may differ from torch's only between equal values).
#[test]
fn device_path_matches_reference() {
    let model = load_golden("model.safetensors");
    let cfg = Config::paper();
    let caster = RayCaster::from_tensor(&cfg, model.get("raycast.transforms").unwrap()).unwrap();
    let m = cfg.n_samples + cfg.n_importance;
    for case in ["", "dense/"] {
        let g = load_golden(&format!("{case}golden.safetensors"));
        let r = RayInputs::of(&g);
        let n_rays = r.rays_o.dims()[0];
        let (near, far) = caster
            .near_far_tensors(&r.rays_o, &r.rays_d, &r.cyls, &r.skts, &r.scales)
            .unwrap();
        assert_close(
            &format!("{case}device near"),
            &flat(&near),
            &f32s(&g, "raycast/near"),
        );
        assert_close(
            &format!("{case}device far"),
            &flat(&far),
            &f32s(&g, "raycast/far"),
        );
        let coarse = caster
            .cast_tensors(&r.rays_o, &r.rays_d, &r.cyls, &r.skts, &r.scales, None)
            .unwrap();
        assert_close(
            &format!("{case}device pts_coarse"),
            &flat(&coarse.pts),
            &f32s(&g, "raycast/pts_coarse"),
        );
        let fine = caster
            .resample_tensors(
                &r.rays_o,
                &r.rays_d,
                &g["raycast/z_vals_coarse"],
                &g["render_coarse/weights"],
                None,
            )
            .unwrap();
        assert_close(
            &format!("{case}device pts_is"),
            &flat(&fine.pts),
            &f32s(&g, "raycast/pts_is"),
        );
        let z_all = flat(&fine.z_all);
        assert_close(
            &format!("{case}device z_vals_merged"),
            &z_all,
            &f32s(&g, "raycast/z_vals_merged"),
        );
        let perm: Vec<u32> = fine.perm.flatten_all().unwrap().to_vec1().unwrap();
        let want = ints(&g, "raycast/sorted_idxs");
        let (sc, sf) = (cfg.n_samples, cfg.n_importance);
        let (zc, zf) = (f32s(&g, "raycast/z_vals_coarse"), flat(&fine.z));
        let value = |ray: usize, idx: usize| match idx < sc {
            true => zc[ray * sc + idx],
            false => zf[ray * sf + idx - sc],
        };
        let differing = (0..n_rays * m)
            .filter(|&i| perm[i] as i64 != want[i])
            .inspect(|&i| {
                // Only (nearly) equal samples may be ordered differently.
                let ray = i / m;
                let (a, b) = (value(ray, perm[i] as usize), value(ray, want[i] as usize));
                assert!((a - b).abs() <= TOL, "{case}merge position {i}: {a} vs {b}");
            })
            .count();
        eprintln!("{case}device merge: {differing} indices differ from torch's order");
    }
}
