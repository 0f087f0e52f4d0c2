//! Numeric choices travel with each avatar (`Avatar::with_numerics`), not with the process:
//! two avatars over the same tensors, one in parity and one with the vectorised sine and
//! without the fused kernels, run interleaved in one process and each computes what it
//! computes alone.

use crate::common::*;
use pma_model::compute::numerics::Numerics;
use pma_model::render::avatar::{Avatar, Mode, Outputs};
use pma_model::render::PassOptions;

fn train_forward(a: &Avatar, case: &GoldenCase) -> Outputs {
    let parity = PassOptions::parity();
    a.forward(
        &case.rays,
        &case.poses,
        &mut Mode::Train(None),
        &parity,
        None,
    )
    .unwrap()
}

fn bits(o: &Outputs) -> Vec<u32> {
    [&o.fine.rgb, &o.fine.weights, &o.raw, &o.raw_coarse]
        .iter()
        .flat_map(|t| flat(t))
        .map(f32::to_bits)
        .collect()
}

#[test]
fn two_avatars_with_different_numerics_share_a_process() {
    let case = GoldenCase::load("golden", false);
    let parity = &case.avatar;
    assert_eq!(parity.numerics(), Numerics::PARITY);
    let rebuild = |k: Numerics| {
        Avatar::from_tensors(parity.config().clone(), parity.tensors(), parity.device())
            .unwrap()
            .with_numerics(k)
    };
    let unfused = rebuild(Numerics {
        fused: false,
        row_ops: false,
        ..Numerics::PARITY
    });
    let fast = rebuild(Numerics {
        fast_sine: true,
        ..Numerics::PARITY
    });

    let p0 = bits(&train_forward(parity, &case));
    let f0 = bits(&train_forward(&fast, &case));
    let u0 = bits(&train_forward(&unfused, &case));
    let p1 = bits(&train_forward(parity, &case));
    let f1 = bits(&train_forward(&fast, &case));

    // Each avatar repeats itself whatever ran in between.
    assert_eq!(p0, p1, "parity changed after a fast-sine pass");
    assert_eq!(f0, f1, "fast sine changed after a parity pass");
    // Fused kernels and row ops are bit-identical to candle's plain ops.
    assert_eq!(p0, u0, "plain ops differ from the fused ones");
    // The vectorised sine really ran: last-bit differences somewhere, small everywhere
    // (1e-4 relative, the golden tolerance).
    let (p, f): (Vec<f32>, Vec<f32>) = (
        p0.iter().map(|b| f32::from_bits(*b)).collect(),
        f0.iter().map(|b| f32::from_bits(*b)).collect(),
    );
    let differ = p.iter().zip(&f).filter(|(a, b)| a != b).count();
    assert!(differ > 0, "fast sine gave parity's bits: it did not run");
    for (a, b) in p.iter().zip(&f) {
        assert!(
            (a - b).abs() <= 1e-4 * a.abs().max(1.0),
            "fast sine {b} vs parity {a}"
        );
    }
}
