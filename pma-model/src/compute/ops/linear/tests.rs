use candle_core::{DType, Device, Tensor, Var};

use super::*;
use crate::compute::account::{Account, Report, Route as AccountRoute};
use crate::compute::ops::testing::{bits, rand};

fn on_emulated_kernels<T>(f: impl FnOnce() -> T) -> (T, Report) {
    let acc = Account::start(&Device::Cpu, AccountRoute::Cuda).unwrap();
    let out = f();
    (out, acc.finish())
}

/// The one-op linear layer gives the product-then-bias-add bits, forward and backward
/// (twice over the same graph), on the CPU route and on the CUDA route, where it counts as
/// the product and the bias add it launches.
#[test]
fn linear_matches_product_and_bias_add_bit_for_bit() {
    let empty = linear(
        &Tensor::zeros((0, 4), DType::F32, &Device::Cpu).unwrap(),
        &rand(&[2, 4], 60),
        &rand(&[2], 59),
        Numerics::PARITY,
    )
    .unwrap();
    assert_eq!(empty.dims(), [0, 2]);
    for (rows, inn, out) in [(37, 5, 9), (1, 3, 64), (300, 3, 2)] {
        let x = Var::from_tensor(&rand(&[rows, inn], 61)).unwrap();
        let w = Var::from_tensor(&rand(&[out, inn], 62)).unwrap();
        let b = Var::from_tensor(&rand(&[out], 63)).unwrap();
        let up = rand(&[rows, out], 64);
        let run = |fused: bool| {
            let k = Numerics {
                fused,
                ..Numerics::PARITY
            };
            let y = linear(x.as_tensor(), w.as_tensor(), b.as_tensor(), k).unwrap();
            let loss = (&y * &up).unwrap().sum_all().unwrap();
            let mut all = vec![bits(&y)];
            for _ in 0..2 {
                let g = loss.backward().unwrap();
                for v in [&x, &w, &b] {
                    all.push(bits(g.get(v.as_tensor()).unwrap()));
                }
            }
            all
        };
        let plain = run(false);
        assert_eq!(run(true), plain, "[{rows},{inn}] x [{out},{inn}]");
        let (counted, r) = on_emulated_kernels(|| run(true));
        assert_eq!(counted, plain);
        // Forward: the product and the bias add, as two launches.
        let op = |n: &str| r.ops.get(n).copied().unwrap_or_default();
        assert_eq!(op("matmul").flops, 2 * (rows * out * inn) as u64 * 5);
        assert!(op("add").launches >= 1);
    }
}

/// The bias add gives candle's broadcast add's bits, values and gradients.
#[test]
fn bias_add_matches_candles_broadcast_add() {
    let y = Var::from_tensor(&rand(&[39, 9], 4)).unwrap();
    let b = Var::from_tensor(&rand(&[9], 5)).unwrap();
    let run = |fused: bool| {
        let k = Numerics {
            fused,
            ..Numerics::PARITY
        };
        let z = add_bias(y.as_tensor(), b.as_tensor(), k).unwrap();
        let g = (z.sqr().unwrap() * 0.5)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        [bits(&z), bits(g.get(&y).unwrap()), bits(g.get(&b).unwrap())]
    };
    assert_eq!(run(true), run(false));
}

/// Output and the gradients of x, W and b for upstream gradient `up`.
fn run_act(x: &Tensor, w: &Tensor, b: &Tensor, up: &Tensor, act: Act) -> [Vec<f32>; 4] {
    let [xv, wv, bv] = [x, w, b].map(|t| Var::from_tensor(t).unwrap());
    let y = linear_act(
        xv.as_tensor(),
        wv.as_tensor(),
        bv.as_tensor(),
        act,
        Numerics::PARITY,
    )
    .unwrap();
    let g = (&y * up).unwrap().sum_all().unwrap().backward().unwrap();
    let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    [
        flat(&y),
        flat(g.get(&xv).unwrap()),
        flat(g.get(&wv).unwrap()),
        flat(g.get(&bv).unwrap()),
    ]
}

/// The op on the CUDA route's kernels against candle's ops (the CPU route): output and the
/// gradients of x and W bit for bit (the same product, bias add and activation, the sine
/// and cosine the C library's, which the CPU's libm recipe reproduces, and the same
/// products backward on the same gradient; no ReLU input is exactly 0 here); the bias
/// gradient sums per block of 256 rows, then over blocks, so within 1e-5 times the sum of
/// the magnitudes. Counted as its kernels: no comparison, cast, sine, cosine, product or
/// reduction of candle's beyond the loss's.
#[test]
fn on_the_emulated_kernels_matches_candles_ops() {
    for act in [Act::Relu, Act::Sine] {
        for (rows, inn, out, seed) in [(1000, 7, 33, 1), (256, 3, 4, 2), (3, 5, 2, 3)] {
            let x = rand(&[rows, inn], seed);
            let w = (rand(&[out, inn], seed + 10) * 8.0).unwrap();
            let b = (rand(&[out], seed + 20) * 4.0).unwrap();
            let up = rand(&[rows, out], seed + 30);
            let plain = run_act(&x, &w, &b, &up, act);
            let (fused, report) = on_emulated_kernels(|| run_act(&x, &w, &b, &up, act));
            let launches = |name: &str| report.ops.get(name).map_or(0, |c| c.launches);
            let (fwd, bwd) = match act {
                Act::Relu => ("pma-bias-relu", "pma-relu-grad"),
                Act::Sine => ("pma-bias-sine", "pma-sine-grad"),
            };
            assert_eq!(launches(fwd), 1);
            assert_eq!(launches(bwd) + launches("pma-bias-grad"), 2);
            for name in ["relu", "sin", "cos", "cmp-ge", "to-dtype", "add"] {
                assert_eq!(launches(name), 0, "{name}");
            }
            // The test's own loss (y·up summed) is the one reduction and every product.
            assert_eq!(launches("reduce-sum"), 1);
            assert_eq!(launches("mul"), 3);
            for (i, what) in ["y", "grad x", "grad W"].iter().enumerate() {
                assert_eq!(plain[i], fused[i], "{what} ({act:?})");
            }
            let ups = up.to_vec2::<f32>().unwrap();
            for (j, (a, c)) in plain[3].iter().zip(&fused[3]).enumerate() {
                let mag: f32 = (0..rows).map(|r| ups[r][j].abs()).sum();
                assert!(
                    (a - c).abs() <= 1e-5 * mag.max(1.0),
                    "grad b[{j}] ({act:?}): {a} vs {c}"
                );
            }
        }
    }
}

/// The ReLU kernel's gradient passes where the output is positive only (PyTorch's rule): at
/// an input of exactly 0 it is 0, where candle's ReLU passes it.
#[test]
fn the_gradient_stops_where_the_output_is_zero() {
    let x = rand(&[4, 2], 1);
    let w = Tensor::zeros((3, 2), DType::F32, &Device::Cpu).unwrap();
    let b = Tensor::zeros(3, DType::F32, &Device::Cpu).unwrap();
    let up = Tensor::ones((4, 3), DType::F32, &Device::Cpu).unwrap();
    let candle = run_act(&x, &w, &b, &up, Act::Relu);
    let (kernel, _) = on_emulated_kernels(|| run_act(&x, &w, &b, &up, Act::Relu));
    assert_eq!(kernel[0], vec![0.0; 12]);
    assert_eq!(
        kernel[3],
        vec![0.0; 3],
        "no gradient through an output of exactly 0"
    );
    assert_eq!(candle[3], vec![4.0; 3], "candle's ReLU passes it at 0");
}

/// The bias gradient sums per block of [`ROWS_PER_BLOCK`] rows, then over the blocks in
/// order: on a row count that leaves a partial last block, against sums formed in that
/// order by hand.
#[test]
fn the_bias_gradient_sums_per_block_then_over_blocks() {
    let rows = 2 * ROWS_PER_BLOCK + 3;
    let grad: Vec<f32> = (0..rows).map(|r| 0.1 + (r % 9) as f32 * 0.37).collect();
    let x = Tensor::zeros((rows, 1), DType::F32, &Device::Cpu).unwrap();
    let w = Tensor::zeros((1, 1), DType::F32, &Device::Cpu).unwrap();
    let b = Tensor::ones(1, DType::F32, &Device::Cpu).unwrap();
    let up = Tensor::from_vec(grad.clone(), (rows, 1), &Device::Cpu).unwrap();
    let (got, _) = on_emulated_kernels(|| run_act(&x, &w, &b, &up, Act::Relu));
    let block = |rs: std::ops::Range<usize>| rs.fold(0f32, |s, r| s + grad[r]);
    let want = 0.0
        + block(0..ROWS_PER_BLOCK)
        + block(ROWS_PER_BLOCK..2 * ROWS_PER_BLOCK)
        + block(2 * ROWS_PER_BLOCK..rows);
    assert_eq!(got[3], vec![want]);
}

/// A sine layer keeps its product for the backward only when the graph tracks gradients:
/// an inference pass holds nothing.
#[test]
fn a_sine_keeps_its_product_only_for_a_backward() {
    let (x, w, b) = (rand(&[300, 4], 1), rand(&[8, 4], 2), rand(&[8], 3));
    let (y, untracked) = on_emulated_kernels(|| linear_sine(&x, &w, &b, Numerics::PARITY).unwrap());
    drop(y);
    let wv = Var::from_tensor(&w).unwrap();
    let (y, tracked) =
        on_emulated_kernels(|| linear_sine(&x, wv.as_tensor(), &b, Numerics::PARITY).unwrap());
    drop(y);
    // The kept product is one more [300, 8] f32 buffer alive at the peak.
    assert_eq!(
        tracked.peak_live_bytes,
        untracked.peak_live_bytes + 300 * 8 * 4
    );
}

/// Every case of the full check passes on the emulated grid.
#[test]
fn the_full_check_passes_on_the_emulated_grid() {
    crate::compute::ops::testing::full_check_passes(&MODULE);
}
