//! Volume rendering and importance sampling on stiff inputs (docs/numerics.md, "Densities and
//! alpha"): densities from 0 to 1e6, interval lengths from 1e-7 to 1e10, all weight on one
//! sample, no weight at all. Compositing stays in [0,1], transmittance is monotone, gradients
//! are finite, and importance samples are sorted and inside the coarse span.

use candle_core::{DType, Device, Tensor, Var};
use pma_model::render::raycast::RayCaster;
use pma_model::render::volume::raw2outputs;
use pma_model::tools::stability;
use pma_model::Config;
use proptest::prelude::*;

fn caster(cfg: &Config) -> RayCaster {
    let mut t = vec![0f32; 24 * 16];
    for j in 0..24 {
        for k in 0..4 {
            t[j * 16 + 5 * k] = 1.0;
        }
    }
    RayCaster::new(cfg, &t).unwrap()
}

#[test]
fn fixed_stiff_cases_hold_every_invariant() {
    for cfg in [Config::tiny(), Config::paper()] {
        let rows = stability::probe_compositing(&cfg).unwrap();
        print!("{}", stability::Report { rows: rows.clone() }.table());
        assert_eq!(rows.len(), 7);
        for r in rows {
            assert_eq!(r.non_finite, 0, "{r:?}");
            assert_eq!(r.violations, 0, "{r:?}");
        }
    }
}

/// A log-uniform magnitude in [10^lo, 10^hi], or exactly 0.
fn magnitude(lo: f64, hi: f64) -> impl Strategy<Value = f32> {
    prop_oneof![
        1 => Just(0f32),
        6 => (lo..hi).prop_map(|e| 10f64.powf(e) as f32),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    #[test]
    fn compositing_is_bounded_monotone_and_differentiable(
        sigma in prop::collection::vec(magnitude(-6.0, 6.0), 12),
        delta in prop::collection::vec((-7.0f64..10.0).prop_map(|e| 10f64.powf(e) as f32), 11),
        rgb in prop::collection::vec(0f32..=1.0, 36),
        bg in prop::collection::vec(0f32..=1.0, 3),
        dir_len in 0.2f32..5.0,
    ) {
        let m = 12;
        let mut z = vec![0.5f32];
        for d in &delta {
            let next = z.last().unwrap() + d;
            // f32 cannot resolve a 1e-7 step at 1e10: keep the depths strictly ascending.
            z.push(if next > *z.last().unwrap() { next } else { f32::from_bits(z.last().unwrap().to_bits() + 1) });
        }
        let mut raw = Vec::new();
        for k in 0..m {
            raw.extend_from_slice(&[rgb[3 * k], rgb[3 * k + 1], rgb[3 * k + 2], sigma[k]]);
        }
        let dev = Device::Cpu;
        let raw = Var::from_tensor(&Tensor::from_vec(raw, (1, m, 4), &dev).unwrap()).unwrap();
        let zt = Tensor::from_vec(z.clone(), (1, m), &dev).unwrap();
        let d = Tensor::from_vec(vec![0.0, dir_len * 0.6, dir_len * 0.8], (1, 3), &dev).unwrap();
        let bgt = Tensor::from_vec(bg, (1, 3), &dev).unwrap();
        let out = raw2outputs(raw.as_tensor(), &zt, &d, Some(&bgt)).unwrap();
        let v = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let (w, t, acc, c) = (v(&out.weights), v(&out.transmittance), v(&out.acc), v(&out.rgb));
        for x in w.iter().chain(&acc).chain(&t) {
            prop_assert!(x.is_finite() && (-1e-6..=1.0 + 1e-6).contains(x), "{x} in {w:?} {t:?}");
        }
        for x in &c {
            prop_assert!(x.is_finite() && (-1e-5..=1.0 + 1e-5).contains(x), "rgb {c:?}");
        }
        for p in t.windows(2) {
            prop_assert!(p[1] <= p[0] * (1.0 + 1e-6), "transmittance rises: {t:?}");
        }
        let disp = v(&out.disp)[0];
        prop_assert!(disp.is_finite() && disp >= 0.0, "disp {disp}");

        let loss = (out.rgb.sum_all().unwrap() + out.acc.sum_all().unwrap()).unwrap();
        let g = loss.backward().unwrap();
        let g = v(g.get(raw.as_tensor()).unwrap());
        prop_assert!(g.iter().all(|x| x.is_finite()), "gradient {g:?}");

        let cfg = Config { n_samples: m, n_importance: 9, ..Config::tiny() };
        let zi = caster(&cfg).importance_z(&z, &w, None).unwrap();
        for p in zi.windows(2) {
            prop_assert!(p[0] <= p[1], "unsorted importance samples {zi:?}");
        }
        for x in &zi {
            prop_assert!(x.is_finite() && *x >= z[0] && *x <= z[m - 1], "{x} outside {z:?}");
        }
    }
}

/// Half-precision inputs are composited in f32: with the 1e-10 guards rounded to 0 an empty
/// ray's disparity would be 0/0, and a fully opaque sample's log(1 − α) −inf.
#[test]
fn half_precision_compositing_stays_finite() {
    let dev = Device::Cpu;
    for dtype in [DType::F16, DType::BF16] {
        let mut raw = vec![0.5f32; 2 * 8 * 4];
        for k in 0..8 {
            raw[4 * k + 3] = 0.0; // ray 0: empty
            raw[32 + 4 * k + 3] = if k == 3 { 6e4 } else { 0.0 }; // ray 1: one opaque sample
        }
        let raw = Tensor::from_vec(raw, (2, 8, 4), &dev)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let z: Vec<f32> = (0..16).map(|k| 1.0 + 0.1 * (k % 8) as f32).collect();
        let z = Tensor::from_vec(z, (2, 8), &dev)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let d = Tensor::from_vec(vec![0f32, 0.0, 1.0, 0.0, 1.0, 0.0], (2, 3), &dev)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let out = raw2outputs(&raw, &z, &d, None).unwrap();
        let (max, bad) =
            stability::tensor_stats(&[&out.rgb, &out.disp, &out.acc, &out.weights]).unwrap();
        assert_eq!(bad, 0, "{dtype:?}");
        assert!(max.is_finite());
        let acc = out
            .acc
            .to_dtype(DType::F32)
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        assert!(
            acc[0] == 0.0 && (acc[1] - 1.0).abs() < 1e-3,
            "{dtype:?}: {acc:?}"
        );
    }
}
