use candle_core::{DType, Device, Tensor, Var};

use super::*;
use crate::compute::account::{Account, Route as AccountRoute};
use crate::compute::kernel::Route;
use crate::compute::ops::testing::{bits, rand};

/// The window pool of a product computed inside it gives the bits of the product followed
/// by the pool (values, and gradients of e, W and g over two backward passes), on the CPU
/// route and on the CUDA route's emulated kernels.
#[test]
fn window_pool_of_a_product_matches_product_then_pool() {
    let (n, j, h, ce, p) = (12, 5, 7, 4, 3);
    let e = Var::from_tensor(&rand(&[n * j, ce], 71)).unwrap();
    let w = Var::from_tensor(&rand(&[h, ce], 72)).unwrap();
    let g = Var::from_tensor(&rand(&[p, j, h], 73)).unwrap();
    let wp = rand(&[n, j], 74).abs().unwrap();
    let up = rand(&[n, h], 75);
    let run = |fused_op: bool| {
        let k = Numerics::PARITY;
        let y = if fused_op {
            window_pool_of(e.as_tensor(), w.as_tensor(), g.as_tensor(), &wp, k).unwrap()
        } else {
            let q = crate::compute::numerics::matmul(e.as_tensor(), &w.t().unwrap(), k)
                .unwrap()
                .reshape((n, j, h))
                .unwrap();
            window_pool(&q, g.as_tensor(), &wp, k).unwrap()
        };
        let loss = (&y * &up).unwrap().sum_all().unwrap();
        let mut all = vec![bits(&y)];
        for _ in 0..2 {
            let gr = loss.backward().unwrap();
            for v in [&e, &w, &g] {
                all.push(bits(gr.get(v.as_tensor()).unwrap()));
            }
        }
        all
    };
    let two_ops = run(false);
    assert_eq!(run(true), two_ops);
    let account = Account::start(&Device::Cpu, AccountRoute::Cuda).unwrap();
    let counted = run(true);
    let r = account.finish();
    assert_eq!(counted, two_ops);
    // Forward: the product and the pool; the second backward pools again.
    let launches = |op: &str| r.ops.get(op).map_or(0, |c| c.launches);
    assert_eq!(launches("pma-window-pool"), 2, "{:?}", r.ops.keys());
    assert_eq!(launches("pma-window-pool-grad"), 4);
}

/// On the CUDA route's emulated kernels the window pool computes the CPU's values and
/// gradients bit for bit, including a second backward that finds the arg-max used, and
/// counts as its kernels.
#[test]
fn window_pool_on_the_emulated_kernels_keeps_the_cpu_bits() {
    let (n, j, h, p) = (12, 5, 7, 3);
    let q = Var::from_tensor(&rand(&[n, j, h], 1)).unwrap();
    let g = Var::from_tensor(&rand(&[p, j, h], 2)).unwrap();
    let w = rand(&[n, j], 3).abs().unwrap();
    let up = rand(&[n, h], 4);
    let run = || {
        let y = window_pool(q.as_tensor(), g.as_tensor(), &w, Numerics::PARITY).unwrap();
        let loss = (&y * &up).unwrap().sum_all().unwrap();
        let mut out = vec![bits(&y)];
        for _ in 0..2 {
            let gr = loss.backward().unwrap();
            out.push(bits(gr.get(&q).unwrap()));
            out.push(bits(gr.get(&g).unwrap()));
        }
        out
    };
    let cpu = run();
    let account = Account::start(&Device::Cpu, AccountRoute::Cuda).unwrap();
    let counted = run();
    let report = account.finish();
    assert_eq!(cpu, counted);
    let launches = |op: &str| report.ops.get(op).map_or(0, |c| c.launches);
    // Forward once, the arg-max again for the second backward, two gradients each time.
    assert_eq!(launches("pma-window-pool"), 2, "{:?}", report.ops.keys());
    assert_eq!(launches("pma-window-pool-grad"), 4);
}

/// Forward values and gradients equal candle's ops exactly, including rows whose spatial
/// window is 0 for every joint (all-tie rows, where the sign of a zero may differ: the
/// first joint's against candle's pick), with one pose and with three (each block of points
/// pooled with its own pose's g); a second backward pools again.
#[test]
fn window_pool_matches_candles_ops_bit_for_bit() {
    for poses in [1, 3] {
        let (n, j, h) = (39, 24, 16);
        let run = |fused: bool| {
            let q = Var::from_tensor(&rand(&[n, j, h], 1)).unwrap();
            let g = Var::from_tensor(&rand(&[poses, j, h], 2)).unwrap();
            let mut w = rand(&[n, j], 3).abs().unwrap();
            let zero = Tensor::zeros((n / 2, j), DType::F32, &Device::Cpu).unwrap();
            w = Tensor::cat(&[&zero, &w.narrow(0, n / 2, n - n / 2).unwrap()], 0).unwrap();
            let k = Numerics {
                fused,
                ..Numerics::PARITY
            };
            let m = window_pool(q.as_tensor(), g.as_tensor(), &w, k).unwrap();
            let loss = m.sin().unwrap().sum_all().unwrap();
            let values = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let mut all = vec![values(&m)];
            for _ in 0..2 {
                let grads = loss.backward().unwrap();
                all.push(values(grads.get(&q).unwrap()));
                all.push(values(grads.get(&g).unwrap()));
            }
            all
        };
        let (a, b) = (run(true), run(false));
        for (i, (x, y)) in a.iter().zip(&b).enumerate() {
            let differ = x.iter().zip(y).filter(|(u, v)| u != v).count();
            assert_eq!(
                differ,
                0,
                "{poses} poses, value {i}: {differ} of {} differ",
                x.len()
            );
        }
    }
    // The kernels really ran: the CPU route is taken for f32 CPU tensors.
    let t = rand(&[2, 2, 2], 9);
    assert!(matches!(
        crate::compute::kernel::route(true, &MODULE, &[&t]),
        Route::Cpu
    ));
}

#[test]
fn window_pool_propagates_nan_and_falls_back_for_f64() {
    let q = rand(&[3, 4, 5], 7);
    let g = rand(&[1, 4, 5], 8);
    let mut wv = vec![0.5f32; 12];
    wv[5] = f32::NAN;
    let w = Tensor::from_vec(wv, (3, 4), &Device::Cpu).unwrap();
    let m = window_pool(&q, &g, &w, Numerics::PARITY)
        .unwrap()
        .to_vec2::<f32>()
        .unwrap();
    assert!(m[1].iter().all(|v| v.is_nan()), "row 1 has a NaN window");
    assert!(m[0].iter().chain(&m[2]).all(|v| v.is_finite()));
    let m64 = window_pool(
        &q.to_dtype(DType::F64).unwrap(),
        &g.to_dtype(DType::F64).unwrap(),
        &w.to_dtype(DType::F64).unwrap(),
        Numerics::PARITY,
    )
    .unwrap();
    assert_eq!(m64.dtype(), DType::F64);
}

/// Every case of the full check passes on the emulated grid.
#[test]
fn the_full_check_passes_on_the_emulated_grid() {
    crate::compute::ops::testing::full_check_passes(&MODULE);
}
