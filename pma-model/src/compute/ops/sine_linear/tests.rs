use candle_core::{Device, Tensor, Var};

use super::*;

fn random(shape: &[usize], seed: u64, lo: f32, hi: f32) -> Tensor {
    let n: usize = shape.iter().product();
    let mut s = seed;
    let v: Vec<f32> = (0..n)
        .map(|_| {
            s = s
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            lo + (s >> 40) as f32 / (1u64 << 24) as f32 * (hi - lo)
        })
        .collect();
    Tensor::from_vec(v, shape, &Device::Cpu).unwrap()
}

/// Output and the gradients of x, W, b and the scale for upstream gradient `up`.
fn run(x: &Tensor, w: &Tensor, b: &Tensor, sc: &Tensor, up: &Tensor) -> [Vec<f32>; 5] {
    let [xv, wv, bv, sv] = [x, w, b, sc].map(|t| Var::from_tensor(t).unwrap());
    let y = sine_linear(
        xv.as_tensor(),
        wv.as_tensor(),
        bv.as_tensor(),
        Some(sv.as_tensor()),
        Numerics::PARITY,
    )
    .unwrap();
    let grads = (&y * up).unwrap().sum_all().unwrap().backward().unwrap();
    let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    [
        flat(&y),
        flat(grads.get(&xv).unwrap()),
        flat(grads.get(&wv).unwrap()),
        flat(grads.get(&bv).unwrap()),
        flat(grads.get(&sv).unwrap()),
    ]
}

fn on_emulated_kernels<T>(f: impl FnOnce() -> T) -> (T, crate::compute::account::Report) {
    let acc =
        crate::compute::account::Account::start(&Device::Cpu, crate::compute::account::Route::Cuda)
            .unwrap();
    let out = f();
    (out, acc.finish())
}

/// |a − b| within `tol` times the sum of the magnitudes of the terms of the sum.
fn close(a: &[f32], b: &[f32], mag: impl Fn(usize) -> f32, tol: f32, what: &str) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        assert!(
            (x - y).abs() <= tol * mag(i).max(1.0),
            "{what}[{i}]: {x} vs {y}"
        );
    }
}

/// The op on the CUDA route's emulated kernels against candle's ops (the CPU route): the
/// same values up to the order of the sums. Output within 5e-7 (four f32 ulps) times
/// the argument's magnitude bound Σ|x W| + |b|: the argument's products and bias add
/// round differently from the gemm's, by an ulp or two of an argument up to ~70, and
/// sin' ≤ 1; gradients, sums of up to 3,000 terms, within 1e-5 times the sum of their
/// magnitudes.
#[test]
fn on_the_emulated_kernels_matches_candles_ops() {
    for (rows, inp, out, seed) in [(3000, 3, 64, 1), (1500, 1, 5, 2), (7, 4, 3, 3)] {
        let x = random(&[rows, inp], seed, -1.2, 1.2);
        let w = random(&[out, inp], seed + 10, -16.0, 16.0);
        let b = random(&[out], seed + 20, -16.0, 16.0);
        let sc = random(&[rows], seed + 40, 0.0, 1.0);
        let up = random(&[rows, out], seed + 30, -1.0, 1.0);
        let plain = run(&x, &w, &b, &sc, &up);
        let (fused, report) = on_emulated_kernels(|| run(&x, &w, &b, &sc, &up));
        let launches = |name: &str| report.ops.get(name).map_or(0, |c| c.launches);
        assert_eq!(launches("pma-sine-linear"), 1, "one forward launch");
        assert_eq!(launches("pma-sine-linear-grad"), 2, "W and b: two launches");
        assert_eq!(
            launches("pma-sine-linear-grad-rows"),
            1,
            "x and s: one launch"
        );
        assert_eq!(launches("sin") + launches("cos"), 0);
        // The test's own loss is the one reduction.
        assert_eq!(launches("reduce-sum"), 1);
        let [xs, ups, ws] = [&x, &up, &w].map(|t| t.to_vec2::<f32>().unwrap());
        let (scs, bs) = (sc.to_vec1::<f32>().unwrap(), b.to_vec1::<f32>().unwrap());
        let y_mag = |i: usize| {
            let (r, j) = (i / out, i % out);
            (0..inp).map(|c| (xs[r][c] * ws[j][c]).abs()).sum::<f32>() + bs[j].abs()
        };
        close(&plain[0], &fused[0], y_mag, 5e-7, "y");
        let gx_mag = |i: usize| {
            let (r, c) = (i / inp, i % inp);
            (0..out)
                .map(|j| (ups[r][j] * scs[r] * ws[j][c]).abs())
                .sum()
        };
        close(&plain[1], &fused[1], gx_mag, 1e-5, "grad x");
        let gw_mag = |i: usize| {
            let (j, c) = (i / inp, i % inp);
            (0..rows)
                .map(|r| (ups[r][j] * scs[r] * xs[r][c]).abs())
                .sum()
        };
        close(&plain[2], &fused[2], gw_mag, 1e-5, "grad W");
        let gb_mag = |j: usize| (0..rows).map(|r| (ups[r][j] * scs[r]).abs()).sum();
        close(&plain[3], &fused[3], gb_mag, 1e-5, "grad b");
        let gs_mag = |r: usize| (0..out).map(|j| ups[r][j].abs()).sum();
        close(&plain[4], &fused[4], gs_mag, 1e-5, "grad scale");
    }
}

/// Without a scale, and with an x that needs no gradient: no row kernel runs.
#[test]
fn an_untracked_input_and_no_scale_cost_no_row_launch() {
    let x = random(&[10, 3], 4, -1.0, 1.0);
    let w = Var::from_tensor(&random(&[6, 3], 5, -2.0, 2.0)).unwrap();
    let b = random(&[6], 6, -2.0, 2.0);
    let (g, report) = on_emulated_kernels(|| {
        let y = sine_linear(&x, w.as_tensor(), &b, None, Numerics::PARITY).unwrap();
        y.sum_all().unwrap().backward().unwrap()
    });
    assert!(report.ops.contains_key("pma-sine-linear-grad"));
    assert!(!report.ops.contains_key("pma-sine-linear-grad-rows"));
    assert!(g.get(&w).is_some());
}

/// The weight and bias gradients sum per block of [`ROWS_PER_BLOCK`] rows, then over the
/// blocks in order: on a row count that leaves a partial last block, with the argument 0
/// (cos = 1) and a unit scale, against sums formed in that order by hand.
#[test]
fn weight_grads_sum_per_block_then_over_blocks() {
    let rows = ROWS_PER_BLOCK + 37;
    let x: Vec<f32> = (0..rows).map(|r| 1.0 + (r % 7) as f32 * 0.25).collect();
    let grad: Vec<f32> = (0..rows).map(|r| 0.1 + (r % 5) as f32 * 0.3).collect();
    let xt = Tensor::from_vec(x.clone(), (rows, 1), &Device::Cpu).unwrap();
    let w =
        Var::from_tensor(&Tensor::zeros((1, 1), candle_core::DType::F32, &Device::Cpu).unwrap())
            .unwrap();
    let b = Var::from_tensor(&Tensor::zeros(1, candle_core::DType::F32, &Device::Cpu).unwrap())
        .unwrap();
    let up = Tensor::from_vec(grad.clone(), (rows, 1), &Device::Cpu).unwrap();
    let (g, _) = on_emulated_kernels(|| {
        let y = sine_linear(&xt, w.as_tensor(), b.as_tensor(), None, Numerics::PARITY).unwrap();
        (&y * &up).unwrap().sum_all().unwrap().backward().unwrap()
    });
    let flat = |v: &Var| {
        g.get(v)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap()
    };
    let block = |rs: std::ops::Range<usize>| {
        rs.fold((0f32, 0f32), |(w, b), r| (w + grad[r] * x[r], b + grad[r]))
    };
    let (w0, b0) = block(0..ROWS_PER_BLOCK);
    let (w1, b1) = block(ROWS_PER_BLOCK..rows);
    assert_eq!(flat(&w), vec![0.0 + w0 + w1]);
    assert_eq!(flat(&b), vec![0.0 + b0 + b1]);
}

/// Every case of the full check passes on the emulated grid.
#[test]
fn the_full_check_passes_on_the_emulated_grid() {
    crate::compute::ops::testing::full_check_passes(&MODULE);
}
