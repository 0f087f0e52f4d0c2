use candle_core::{Device, Tensor, Var};

use super::*;
use crate::compute::account::{Account, Route as AccountRoute};
use crate::compute::ops::linear::add_bias;
use crate::compute::ops::testing::{bits, rand};

/// The FiLM-sine layer gives candle's values and gradients bit for bit, with libm's sine and
/// with the vectorised one, for every layer of a 3-layer head, including large frequencies
/// and arguments.
#[test]
fn film_sine_matches_candles_ops_bit_for_bit() {
    let (n, kk, f) = (29, 3, 8);
    for fast in [false, true] {
        for k in 0..kk {
            let run = |fused: bool| {
                let pre = Var::from_tensor(&(rand(&[n, f], 11) * 3.0).unwrap()).unwrap();
                let o = Var::from_tensor(&(rand(&[n, 2 * kk * f], 12) * 40.0).unwrap()).unwrap();
                let y = FilmHead::with(o.as_tensor(), kk, (15.0, 30.0), fast, fused)
                    .layer(pre.as_tensor(), k)
                    .unwrap();
                // Distinct weights per element, so every gradient entry is tested.
                let wts = rand(&[n, f], 13);
                let grads = (&y * &wts).unwrap().sum_all().unwrap().backward().unwrap();
                [
                    bits(&y),
                    bits(grads.get(&pre).unwrap()),
                    bits(grads.get(&o).unwrap()),
                ]
            };
            let (a, b) = (run(true), run(false));
            assert_eq!(a, b, "fast={fast} k={k}");
            assert!(a[2].iter().any(|&v| f32::from_bits(v) != 0.0));
        }
    }
}

/// A whole stack with its shared head gradient against candle's ops, bit for bit: values
/// and the gradients of the input, the head and every linear layer. A second backward pass
/// over the same graph (the shared gradient already handed over, the kept cosines used)
/// gives the same bits again.
#[test]
fn film_stack_shares_one_head_gradient_bit_for_bit() {
    let (n, kk, f) = (23, 3, 8);
    let run = |fused: bool| {
        let x = Var::from_tensor(&rand(&[n, f], 21)).unwrap();
        let o = Var::from_tensor(&(rand(&[n, 2 * kk * f], 22) * 4.0).unwrap()).unwrap();
        let vars: Vec<(Var, Var)> = (0..kk as u64)
            .map(|k| {
                let w = Var::from_tensor(&rand(&[f, f], 30 + k)).unwrap();
                let b = Var::from_tensor(&rand(&[f], 40 + k)).unwrap();
                (w, b)
            })
            .collect();
        // What the network's linear layer computes: x Wᵀ, then the bias.
        let linear = |k: usize, h: &Tensor| {
            let (w, b) = &vars[k];
            add_bias(
                &h.matmul(&w.as_tensor().t()?)?,
                b.as_tensor(),
                Numerics::PARITY,
            )
        };
        let head = FilmHead::with(o.as_tensor(), kk, (15.0, 30.0), false, fused);
        let outs = head.stack(x.as_tensor(), linear).unwrap();
        let y = Tensor::cat(&outs, 1).unwrap();
        let wts = rand(&[n, kk * f], 23);
        let loss = (&y * &wts).unwrap().sum_all().unwrap();
        let mut passes = Vec::new();
        for _ in 0..2 {
            let g = loss.backward().unwrap();
            let mut all = vec![bits(&y), bits(g.get(&x).unwrap()), bits(g.get(&o).unwrap())];
            for (w, b) in &vars {
                all.push(bits(g.get(w).unwrap()));
                all.push(bits(g.get(b).unwrap()));
            }
            passes.push(all);
        }
        passes
    };
    let (a, b) = (run(true), run(false));
    let names = [
        "values",
        "grad x",
        "grad head",
        "w0",
        "b0",
        "w1",
        "b1",
        "w2",
        "b2",
    ];
    for pass in 0..2 {
        for (i, name) in names.iter().enumerate() {
            assert_eq!(a[pass][i], b[pass][i], "{name}, backward pass {pass}");
        }
    }
    // Every layer's block of the head gradient is there (none lost to the sharing).
    let head: Vec<f32> = a[0][2].iter().map(|&u| f32::from_bits(u)).collect();
    for block in 0..2 * kk {
        let nonzero = (0..n).any(|r| {
            head[r * 2 * kk * f + block * f..][..f]
                .iter()
                .any(|v| *v != 0.0)
        });
        assert!(nonzero, "head gradient block {block} is empty");
    }
}

/// A stack on the CUDA route's emulated kernels gives the CPU's bits and counts
/// `film_sine.cu`'s launches and bytes: one kernel per layer each way, the head gradient's
/// memset once, no plain ops and nothing uploaded.
#[test]
fn film_stack_on_the_emulated_kernels_keeps_the_cpu_bits() {
    let (n, kk, f) = (19, 3, 8);
    let x = Var::from_tensor(&rand(&[n, f], 51)).unwrap();
    let o = Var::from_tensor(&(rand(&[n, 2 * kk * f], 52) * 4.0).unwrap()).unwrap();
    let wts = rand(&[n, kk * f], 53);
    let run = || {
        let head = FilmHead::new(o.as_tensor(), kk, (15.0, 30.0), Numerics::PARITY);
        let outs = head.stack(x.as_tensor(), |_, h| Ok(h.clone())).unwrap();
        let y = Tensor::cat(&outs, 1).unwrap();
        let g = (&y * &wts).unwrap().sum_all().unwrap().backward().unwrap();
        [bits(&y), bits(g.get(&x).unwrap()), bits(g.get(&o).unwrap())]
    };
    let cpu = run();
    let account = Account::start(&Device::Cpu, AccountRoute::Cuda).unwrap();
    let counted = run();
    let report = account.finish();
    assert_eq!(cpu, counted);
    let op = |name: &str| report.ops.get(name).copied().unwrap_or_default();
    let nf = (n * f * 4) as u64;
    let fwd = op("pma-film-sine");
    assert_eq!((fwd.ops, fwd.launches), (kk as u64, kk as u64));
    // Pre and the layer's Θ, Φ blocks in; the sine out (the backward recomputes the
    // cosine, as on CUDA).
    assert_eq!(fwd.bytes_read, kk as u64 * 3 * nf);
    assert_eq!(fwd.bytes_written, kk as u64 * nf);
    let bwd = op("pma-film-sine-grad");
    assert_eq!((bwd.ops, bwd.launches), (kk as u64, kk as u64 + 1));
    assert_eq!(bwd.bytes_read, kk as u64 * 4 * nf);
    let head = (n * 2 * kk * f * 4) as u64;
    assert_eq!(bwd.bytes_written, kk as u64 * 3 * nf + head);
    assert_eq!(op("pma-film-head-grad").launches, 0);
    for plain in ["sin", "cos", "affine"] {
        assert_eq!(
            op(plain).ops,
            0,
            "plain op `{plain}` in {:?}",
            report.ops.keys()
        );
    }
    assert_eq!(report.total.uploads, 0);
    // The head gradient was alive with the activations.
    assert!(report.peak_live_bytes >= head);
}

/// Every case of the full check passes on the emulated grid.
#[test]
fn the_full_check_passes_on_the_emulated_grid() {
    crate::compute::ops::testing::full_check_passes(&MODULE);
}
