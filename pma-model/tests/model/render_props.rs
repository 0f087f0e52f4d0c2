//! `raw2outputs` beyond the golden data: an independent f64 forward reference, a
//! finite-difference gradient check (including near-opaque samples), invariants under stiff
//! densities, and shape errors.

use candle_core::{DType, Device, Tensor, Var};
use pma_model::render::volume::raw2outputs;
use proptest::prelude::*;

/// Straightforward per-ray f64 evaluation of the compositing formulas (docs/numerics.md,
/// "Densities and alpha"), with an explicit cumulative product.
/// raw: [R,M,4], z: [R,M], d: [R,3], bg: [R,3] -> (rgb [R,3], depth, disp, acc, weights [R,M]).
#[allow(clippy::type_complexity)]
fn naive(
    raw: &[f64],
    z: &[f64],
    d: &[f64],
    bg: &[f64],
    m: usize,
) -> (Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>) {
    let n = z.len() / m;
    let (mut rgb, mut depth, mut disp, mut acc, mut weights) =
        (vec![], vec![], vec![], vec![], vec![]);
    for r in 0..n {
        let norm = (d[3 * r].powi(2) + d[3 * r + 1].powi(2) + d[3 * r + 2].powi(2)).sqrt();
        let mut t = 1.0;
        let (mut c, mut dep, mut sum) = ([0.0; 3], 0.0, 0.0);
        for i in 0..m {
            let delta = if i + 1 < m {
                z[r * m + i + 1] - z[r * m + i]
            } else {
                1e10
            } * norm;
            let alpha = 1.0 - (-raw[(r * m + i) * 4 + 3] * delta).exp();
            let w = alpha * t;
            t *= 1.0 - alpha + 1e-10;
            for (k, ck) in c.iter_mut().enumerate() {
                *ck += w * raw[(r * m + i) * 4 + k];
            }
            dep += w * z[r * m + i];
            sum += w;
            weights.push(w);
        }
        let a = sum.min(1.0);
        for (k, ck) in c.iter().enumerate() {
            rgb.push(ck + (1.0 - a) * bg[3 * r + k]);
        }
        let dsp = 1.0 / (dep / (sum + 1e-10)).max(1e-10);
        disp.push(if sum.abs() <= 1e-8 { 0.0 } else { dsp });
        depth.push(dep);
        acc.push(a);
    }
    (rgb, depth, disp, acc, weights)
}

/// Two rays, five samples: ray 0 semi-transparent, ray 1 with a near-opaque sample
/// (σδ ≈ 18, so 1 − α ≈ 1.5e-8) in the middle. The last samples (interval 1e10·|d|) are
/// nearly empty, so acc = Σw < 1 stays away from the min(·, 1) kink.
fn tiny_case() -> (Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>) {
    let sigma = [[0.5, 2.0, 0.0, 1.0, 1e-11], [0.1, 40.0, 3.0, 0.5, 2e-11]];
    let colour =
        |r: usize, i: usize, k: usize| 0.1 + 0.8 * (((r * 7 + i * 3 + k * 5) % 11) as f64 / 10.0);
    let mut raw = vec![];
    for (r, row) in sigma.iter().enumerate() {
        for (i, &s) in row.iter().enumerate() {
            raw.extend([colour(r, i, 0), colour(r, i, 1), colour(r, i, 2), s]);
        }
    }
    let z = vec![1.0, 1.3, 1.7, 2.2, 2.6, 0.8, 1.0, 1.45, 1.5, 2.0];
    let d = vec![0.3, -0.2, 1.1, -0.5, 0.9, 0.4];
    let bg = vec![0.2, 0.7, 0.4, 0.9, 0.1, 0.5];
    (raw, z, d, bg)
}

fn t64(v: &[f64], shape: &[usize]) -> Tensor {
    Tensor::from_vec(v.to_vec(), shape, &Device::Cpu).unwrap()
}

fn host(t: &Tensor) -> Vec<f64> {
    t.flatten_all()
        .unwrap()
        .to_dtype(DType::F64)
        .unwrap()
        .to_vec1()
        .unwrap()
}

#[test]
fn forward_matches_direct_f64_evaluation() {
    let (raw, z, d, bg) = tiny_case();
    let out = raw2outputs(
        &t64(&raw, &[2, 5, 4]),
        &t64(&z, &[2, 5]),
        &t64(&d, &[2, 3]),
        Some(&t64(&bg, &[2, 3])),
    )
    .unwrap();
    let (rgb, depth, disp, acc, weights) = naive(&raw, &z, &d, &bg, 5);
    for (what, got, want) in [
        ("rgb", host(&out.rgb), rgb),
        ("depth", host(&out.depth), depth),
        ("disp", host(&out.disp), disp),
        ("acc", host(&out.acc), acc),
        ("weights", host(&out.weights), weights),
    ] {
        for (g, w) in got.iter().zip(&want) {
            assert!(
                (g - w).abs() <= 1e-12 * (1.0 + w.abs()),
                "{what}: {g} vs {w}"
            );
        }
    }
}

/// Scalar test loss: fixed-coefficient mix of every differentiable output.
fn loss(raw: &Tensor, z: &Tensor, d: &Tensor, bg: &Tensor) -> Tensor {
    let out = raw2outputs(raw, z, d, Some(bg)).unwrap();
    let c_rgb = t64(&[0.3, -1.2, 0.7, 1.1, 0.4, -0.6], &[2, 3]);
    let terms = [
        (out.rgb * c_rgb).unwrap().sum_all().unwrap(),
        (out.depth * 0.37).unwrap().sum_all().unwrap(),
        (out.disp * -0.21).unwrap().sum_all().unwrap(),
        (out.acc * 0.9).unwrap().sum_all().unwrap(),
        (out.weights.sqr().unwrap() * 0.5)
            .unwrap()
            .sum_all()
            .unwrap(),
    ];
    terms
        .iter()
        .skip(1)
        .fold(terms[0].clone(), |a, b| (a + b).unwrap())
}

#[test]
fn gradient_matches_finite_differences() {
    let (raw, z, d, bg) = tiny_case();
    let inputs = [(raw, vec![2, 5, 4]), (z, vec![2, 5]), (d, vec![2, 3])];
    let vars: Vec<Var> = inputs
        .iter()
        .map(|(v, s)| Var::from_tensor(&t64(v, s)).unwrap())
        .collect();
    let bg_t = t64(&bg, &[2, 3]);
    let grads = loss(
        vars[0].as_tensor(),
        vars[1].as_tensor(),
        vars[2].as_tensor(),
        &bg_t,
    )
    .backward()
    .unwrap();
    let analytic: Vec<Vec<f64>> = vars
        .iter()
        .map(|v| host(grads.get(v.as_tensor()).unwrap()))
        .collect();

    let eval = |which: usize, idx: usize, h: f64| -> f64 {
        let args: Vec<Tensor> = inputs
            .iter()
            .enumerate()
            .map(|(k, (v, s))| {
                let mut v = v.clone();
                if k == which {
                    v[idx] += h;
                }
                t64(&v, s)
            })
            .collect();
        loss(&args[0], &args[1], &args[2], &bg_t)
            .to_scalar::<f64>()
            .unwrap()
    };
    let names = ["raw", "z_vals", "rays_d"];
    for (which, (v, _)) in inputs.iter().enumerate() {
        for idx in 0..v.len() {
            // The last samples' tiny σ (times the 1e10 interval) must stay positive, so they
            // get a relative step; a step that small elsewhere would drown in round-off.
            let x = v[idx].abs();
            let h = if x > 0.0 && x < 1e-6 {
                1e-3 * x
            } else {
                1e-6 * (1.0 + x)
            };
            let (up, down) = (eval(which, idx, h), eval(which, idx, -h));
            let fd = (up - down) / (2.0 * h);
            let ad = analytic[which][idx];
            // Central-difference round-off: a few ulp of the loss divided by the step.
            let round_off = 8.0 * f64::EPSILON * up.abs().max(1.0) / h;
            assert!(
                (fd - ad).abs() <= 1e-6 + round_off + 1e-5 * ad.abs(),
                "d loss / d {}[{idx}]: autograd {ad}, finite difference {fd}",
                names[which]
            );
        }
    }
}

fn log_uniform(lo: f64, hi: f64) -> impl Strategy<Value = f64> {
    (lo.ln()..hi.ln()).prop_map(f64::exp)
}

/// One ray batch with stiff densities and extreme intervals, f32 as in production.
#[derive(Debug, Clone)]
struct Stiff {
    m: usize,
    sigma: Vec<f64>,
    deltas: Vec<f64>,
    colours: Vec<f64>,
    d: Vec<f64>,
    bg: Vec<f64>,
}

fn stiff_case() -> impl Strategy<Value = Stiff> {
    (1usize..4, 2usize..12).prop_flat_map(|(r, m)| {
        let sigma = prop::collection::vec(prop_oneof![Just(0.0), log_uniform(1e-6, 1e6)], r * m);
        let deltas = prop::collection::vec(log_uniform(1e-7, 1e10), r * m);
        let colours = prop::collection::vec(0.0..=1.0f64, r * m * 3);
        let d = prop::collection::vec(-2.0..2.0f64, r * 3);
        let bg = prop::collection::vec(0.0..=1.0f64, r * 3);
        (Just(m), sigma, deltas, colours, d, bg).prop_map(|(m, sigma, deltas, colours, d, bg)| {
            Stiff {
                m,
                sigma,
                deltas,
                colours,
                d,
                bg,
            }
        })
    })
}

/// Weights are non-negative and sum to at most 1, transmittance starts at 1 and never
/// increases, acc ∈ [0,1], colours stay in [0,1], nothing is NaN or infinite, and the f32
/// weights stay within 1e-5 of a direct f64 evaluation on the same (f32-rounded) inputs.
fn check_stiff(case: &Stiff) -> Result<(), TestCaseError> {
    let m = case.m;
    let r = case.sigma.len() / m;
    let mut raw = Vec::with_capacity(r * m * 4);
    let mut z = Vec::with_capacity(r * m);
    for ray in 0..r {
        let mut acc_z = 0.0f64;
        for i in 0..m {
            let k = ray * m + i;
            raw.extend_from_slice(&case.colours[3 * k..3 * k + 3]);
            raw.push(case.sigma[k]);
            z.push(acc_z);
            acc_z += case.deltas[k];
        }
    }
    let f = |v: &[f64], s: &[usize]| t64(v, s).to_dtype(DType::F32).unwrap();
    let (raw_t, z_t, d_t, bg_t) = (
        f(&raw, &[r, m, 4]),
        f(&z, &[r, m]),
        f(&case.d, &[r, 3]),
        f(&case.bg, &[r, 3]),
    );
    let out = raw2outputs(&raw_t, &z_t, &d_t, Some(&bg_t)).unwrap();
    let tol = 1e-5;
    let outputs = [
        ("rgb", &out.rgb),
        ("acc", &out.acc),
        ("disp", &out.disp),
        ("weights", &out.weights),
        ("alpha", &out.alpha),
        ("transmittance", &out.transmittance),
        ("depth", &out.depth),
    ];
    for (what, t) in outputs {
        prop_assert!(
            host(t).iter().all(|v| v.is_finite()),
            "{} not finite: {:?}",
            what,
            host(t)
        );
    }
    let (w, tr, a) = (
        host(&out.weights),
        host(&out.transmittance),
        host(&out.alpha),
    );
    for ray in 0..r {
        let row = ray * m..(ray + 1) * m;
        prop_assert!(w[row.clone()].iter().all(|&x| x >= 0.0));
        let sum: f64 = w[row.clone()].iter().sum();
        prop_assert!(sum <= 1.0 + tol, "ray {}: sum of weights {}", ray, sum);
        prop_assert_eq!(tr[ray * m], 1.0);
        let t_row = &tr[row.clone()];
        prop_assert!(
            t_row.windows(2).all(|p| p[1] <= p[0]),
            "transmittance increases: {:?}",
            t_row
        );
        prop_assert!(t_row.iter().all(|&x| (0.0..=1.0).contains(&x)));
        prop_assert!(a[row].iter().all(|&x| (0.0..=1.0).contains(&x)));
    }
    let acc = host(&out.acc);
    prop_assert!(acc.iter().all(|&x| (0.0..=1.0).contains(&x)));
    let rgb = host(&out.rgb);
    prop_assert!(
        rgb.iter().all(|&x| (-tol..=1.0 + tol).contains(&x)),
        "rgb {:?}",
        rgb
    );
    prop_assert!(host(&out.disp).iter().all(|&x| x >= 0.0));

    let (_, _, _, _, w64) = naive(&host(&raw_t), &host(&z_t), &host(&d_t), &host(&bg_t), m);
    let err = w
        .iter()
        .zip(&w64)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max);
    prop_assert!(err <= tol, "weights differ from f64 by {}", err);
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(96))]

    #[test]
    fn invariants_under_stiff_densities(case in stiff_case()) {
        prop_assume!(case.d.chunks(3).all(|d| d.iter().map(|x| x * x).sum::<f64>() > 1e-4));
        check_stiff(&case)?;
    }
}

#[test]
fn empty_rays_show_the_background_with_zero_disparity() {
    let raw = Tensor::zeros((2, 4, 4), DType::F32, &Device::Cpu).unwrap();
    let z = Tensor::new(&[[1f32, 2., 3., 4.], [1., 1.5, 2., 2.5]], &Device::Cpu).unwrap();
    let d = Tensor::new(&[[0f32, 0., -1.], [0.5, 0.5, -1.]], &Device::Cpu).unwrap();
    let bg = Tensor::new(&[[0.25f32, 0.5, 0.75], [1., 0., 1.]], &Device::Cpu).unwrap();
    let out = raw2outputs(&raw, &z, &d, Some(&bg)).unwrap();
    assert_eq!(host(&out.rgb), host(&bg));
    assert_eq!(host(&out.acc), vec![0.0, 0.0]);
    assert_eq!(host(&out.disp), vec![0.0, 0.0]);
    let black = raw2outputs(&raw, &z, &d, None).unwrap();
    assert_eq!(host(&black.rgb), vec![0.0; 6]);
}

#[test]
fn rejects_mismatched_shapes() {
    let dev = Device::Cpu;
    let raw = Tensor::zeros((2, 4, 4), DType::F32, &dev).unwrap();
    let z = Tensor::zeros((2, 4), DType::F32, &dev).unwrap();
    let d = Tensor::ones((2, 3), DType::F32, &dev).unwrap();
    let bad_raw = Tensor::zeros((2, 4, 3), DType::F32, &dev).unwrap();
    let bad_z = Tensor::zeros((2, 5), DType::F32, &dev).unwrap();
    let bad_d = Tensor::ones((3, 3), DType::F32, &dev).unwrap();
    let bad_bg = Tensor::ones((2, 4), DType::F32, &dev).unwrap();
    assert!(raw2outputs(&bad_raw, &z, &d, None).is_err());
    assert!(raw2outputs(&raw, &bad_z, &d, None).is_err());
    assert!(raw2outputs(&raw, &z, &bad_d, None).is_err());
    let msg = raw2outputs(&raw, &z, &d, Some(&bad_bg))
        .unwrap_err()
        .to_string();
    assert!(msg.contains("bgs"), "error does not name the tensor: {msg}");
}
