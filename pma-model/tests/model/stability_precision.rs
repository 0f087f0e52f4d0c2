//! The golden forward pass in f16, bf16 and f64 against f32: how far half precision moves the
//! rendered colours, and whether it stays finite. The ray caster runs in f32 on the host in
//! every case and compositing in at least f32, so the differences come from the network itself.
//!
//! Measured errors (max |Δ| of the fine rgb over the 64 golden rays) are printed; the bounds
//! below are a few times the measured values, so a regression in the dtype plumbing fails.

use crate::common::*;
use candle_core::DType;
use pma_model::render::avatar::{Mode, Outputs};
use pma_model::tools::stability::tensor_stats;

fn forward(case: &GoldenCase, avatar: &pma_model::render::avatar::Avatar) -> Outputs {
    let mut opts = Mode::Train(None);
    avatar
        .forward(
            &case.rays,
            &case.poses,
            &mut opts,
            &Default::default(),
            None,
        )
        .unwrap()
}

fn max_diff(a: &candle_core::Tensor, b: &candle_core::Tensor) -> f64 {
    let a = flat(a);
    let b = flat(b);
    a.iter()
        .zip(&b)
        .map(|(x, y)| (x - y).abs() as f64)
        .fold(0.0, f64::max)
}

#[test]
fn half_precision_forward_on_the_golden_case() {
    let case = GoldenCase::load("golden/dense", true);
    let reference = forward(&case, &case.avatar);
    let golden_rgb = case.golden.f32("render_fine/rgb_map");
    let f32_err = flat(&reference.fine.rgb)
        .iter()
        .zip(&golden_rgb)
        .map(|(a, b)| (a - b).abs() as f64)
        .fold(0.0, f64::max);
    println!("f32 vs reference rgb: {f32_err:.2e}");
    println!(
        "{:<6} {:>12} {:>12} {:>12} {:>14}",
        "dtype", "rgb fine", "acc fine", "rgb coarse", "sigma (raw)"
    );
    // (dtype, bound on the fine-rgb error)
    for (dtype, bound) in [(DType::F64, 1e-5), (DType::BF16, 2e-2), (DType::F16, 2e-3)] {
        let avatar = case.avatar.with_dtype(dtype).unwrap();
        assert_eq!(avatar.dtype(), dtype);
        let out = forward(&case, &avatar);
        let (_, bad) = tensor_stats(&[&out.fine.rgb, &out.fine.acc, &out.raw]).unwrap();
        assert_eq!(bad, 0, "{dtype:?}: non-finite outputs");
        let rgb = max_diff(&out.fine.rgb, &reference.fine.rgb);
        let acc = max_diff(&out.fine.acc, &reference.fine.acc);
        let rgb0 = max_diff(&out.coarse.rgb, &reference.coarse.rgb);
        let sigma = max_diff(
            &out.raw.narrow(2, 3, 1).unwrap(),
            &reference.raw.narrow(2, 3, 1).unwrap(),
        );
        println!(
            "{:<6} {rgb:>12.3e} {acc:>12.3e} {rgb0:>12.3e} {sigma:>14.3e}",
            format!("{dtype:?}")
        );
        assert!(rgb <= bound, "{dtype:?}: rgb error {rgb:e} > {bound:e}");
        if dtype != DType::F64 {
            // The network really ran in half precision: its outputs carry the dtype, and the
            // error is above what f32 itself reaches against the reference.
            assert_eq!(
                out.raw.dtype(),
                dtype,
                "raw outputs of the {dtype:?} network"
            );
            assert!(
                rgb > f32_err.max(1e-6),
                "{dtype:?}: rgb error {rgb:e} is not above f32's {f32_err:e}"
            );
        }
    }
}
