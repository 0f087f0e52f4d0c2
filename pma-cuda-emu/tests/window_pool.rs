//! `window_pool.cu` over emulated grids against pma-model's CPU window pool
//! (`pma_model::compute::fused::window_pool`): the max, and the gradients of q and g.
//!
//! Tolerance: none, bits are compared. The kernels compute every value with the CPU op's
//! f32 operations in its order (max in joint order with the same NaN rule; each gradient
//! of g summed over its pose's points in point order from +0; products and sums rounded
//! separately, never contracted), so any difference is a bug. On a GPU the same holds:
//! `__fmul_rn`/`__fadd_rn` round like the host's f32 operations.

use candle_core::{Device, Tensor, Var};
use pma_cuda_emu::{window_pool, window_pool_grad, Grid, PoolDims};
use pma_model::compute::fused;
use pma_model::compute::numerics::Numerics;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Values on a coarse grid (ties between joints happen) with, when `nan`, a few NaNs.
fn values(rng: &mut ChaCha8Rng, len: usize, nan: bool) -> Vec<f32> {
    (0..len)
        .map(|_| {
            if nan && rng.gen_bool(0.02) {
                f32::NAN
            } else {
                (rng.gen_range(-8i32..=8) as f32) * 0.25 + rng.gen_range(0..2) as f32 * 1e-3
            }
        })
        .collect()
}

/// `a` and `b` have the same bits everywhere; else the first place they differ.
fn same_bits(a: &[f32], b: &[f32], what: &str) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    if let Some(i) = (0..a.len()).find(|&i| a[i].to_bits() != b[i].to_bits()) {
        panic!("{what}: element {i} is {} here, {} on the CPU", a[i], b[i]);
    }
}

/// The CPU op's (max, grad q, grad g) for upstream gradient `up`.
fn cpu(q: &[f32], g: &[f32], w: &[f32], up: &[f32], d: PoolDims) -> [Vec<f32>; 3] {
    let dev = Device::Cpu;
    let qv = Var::from_vec(q.to_vec(), (d.n, d.j, d.h), &dev).unwrap();
    let gv = Var::from_vec(g.to_vec(), (d.p, d.j, d.h), &dev).unwrap();
    let wt = Tensor::from_vec(w.to_vec(), (d.n, d.j), &dev).unwrap();
    let upt = Tensor::from_vec(up.to_vec(), (d.n, d.h), &dev).unwrap();
    let y = fused::window_pool(qv.as_tensor(), gv.as_tensor(), &wt, Numerics::PARITY).unwrap();
    let grads = (&y * &upt).unwrap().sum_all().unwrap().backward().unwrap();
    let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    [
        flat(&y),
        flat(grads.get(&qv).unwrap()),
        flat(grads.get(&gv).unwrap()),
    ]
}

fn check(d: PoolDims, rng: &mut ChaCha8Rng, threads: u32, max_blocks: u32) {
    let q = values(rng, d.n * d.j * d.h, false);
    let g = values(rng, d.p * d.j * d.h, false);
    let w = values(rng, d.n * d.j, true);
    let up = values(rng, d.n * d.h, false);
    let [y_cpu, gq_cpu, gg_cpu] = cpu(&q, &g, &w, &up, d);
    let grid = |elems| Grid::covering(elems, threads, max_blocks);
    let (y, arg) = window_pool(&q, &g, &w, d, grid(d.n * d.h));
    same_bits(&y, &y_cpu, &format!("max, {d:?}"));
    assert!(
        arg.iter().all(|&a| (a as usize) < d.j),
        "arg-max in range, {d:?}"
    );
    let (gq, gg) = window_pool_grad(
        &up,
        &w,
        &arg,
        d,
        grid(d.n * d.j * d.h),
        grid(d.p * d.j * d.h),
    );
    same_bits(&gq, &gq_cpu, &format!("grad q, {d:?}"));
    same_bits(&gg, &gg_cpu, &format!("grad g, {d:?}"));
}

#[test]
fn window_pool_kernels_match_the_cpu_op_bit_for_bit() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    for case in 0..40 {
        // Sizes rarely multiples of the block; some grids too small for one element per
        // thread (the grid-stride loop's other turns), some with idle threads.
        let p = rng.gen_range(1..4);
        let d = PoolDims {
            n: p * rng.gen_range(1..23),
            p,
            j: rng.gen_range(1..26),
            h: rng.gen_range(1..41),
        };
        let threads = [32, 64, 96, 256][case % 4];
        let max_blocks = [1, 3, 65_535][case % 3];
        check(d, &mut rng, threads, max_blocks);
    }
}

#[test]
fn window_pool_kernels_handle_no_points() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    for p in [1, 2] {
        let d = PoolDims {
            n: 0,
            p,
            j: 5,
            h: 7,
        };
        check(d, &mut rng, 64, 4);
    }
}

#[test]
fn a_nan_window_propagates_and_ties_take_the_first_joint() {
    // One point, two joints tied, a NaN window on the third point's second joint.
    let d = PoolDims {
        n: 3,
        p: 1,
        j: 2,
        h: 1,
    };
    let (q, g) = (vec![1.0, 1.0, 0.5, 2.0, 3.0, 4.0], vec![0.0, 0.0]);
    let w = vec![1.0, 1.0, 1.0, 0.5, 1.0, f32::NAN];
    let (y, arg) = window_pool(&q, &g, &w, d, Grid::covering(3, 2, 1));
    assert_eq!(arg, vec![0, 1, 1]);
    assert_eq!(&y[..2], &[1.0, 1.0]);
    assert!(y[2].is_nan());
}
