//! `sine_linear.cu` over emulated grids against pma-model's narrow-input SIREN layer
//! (`pma_model::compute::sine_linear`, run as a CPU run accounted as CUDA runs it): the
//! output and the gradients of x, W, b and the row scales.
//!
//! Tolerance: none on the host, bits are compared. The kernels form the argument and sum
//! the gradients with the CPU op's f32 operations in its order (per block of rows, then over
//! the blocks), rounded separately, and the host build's sinf/cosf are the C library's,
//! whose bits the CPU op reproduces. On a GPU CUDA's sinf/cosf (within 2 ulp) replace them:
//! there the output and the gradients differ from the CPU's through the last bits of the
//! sine and cosine only.

use candle_core::{Device, Tensor, Var};
use pma_cuda_emu::{sine_linear, sine_linear_grad, sine_linear_rows, Grid, SineLinearDims};
use pma_model::compute::account::{Account, Route};
use pma_model::compute::numerics::Numerics;
use pma_model::compute::sine_linear::ROWS_PER_BLOCK;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn same_bits(a: &[f32], b: &[f32], what: &str) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    if let Some(i) = (0..a.len()).find(|&i| a[i].to_bits() != b[i].to_bits()) {
        panic!("{what}: element {i} is {} here, {} on the CPU", a[i], b[i]);
    }
}

/// The CPU op's (output, grad [W|b] as [out, in+1], grad x, grad s) for upstream gradient
/// `up`, on the route a CUDA device takes.
fn cpu(x: &[f32], wb: &[f32], sc: &[f32], up: &[f32], d: SineLinearDims) -> [Vec<f32>; 4] {
    let dev = Device::Cpu;
    let xv = Var::from_vec(x.to_vec(), (d.rows, d.inp), &dev).unwrap();
    let wbt = Tensor::from_vec(wb.to_vec(), (d.out, d.inp + 1), &dev).unwrap();
    let wv = Var::from_tensor(&wbt.narrow(1, 0, d.inp).unwrap()).unwrap();
    let bv = Var::from_tensor(&wbt.narrow(1, d.inp, 1).unwrap().squeeze(1).unwrap()).unwrap();
    let sv = Var::from_vec(sc.to_vec(), d.rows, &dev).unwrap();
    let upt = Tensor::from_vec(up.to_vec(), (d.rows, d.out), &dev).unwrap();
    let account = Account::start(&dev, Route::Cuda).unwrap();
    let y = pma_model::compute::sine_linear::sine_linear(
        xv.as_tensor(),
        wv.as_tensor(),
        bv.as_tensor(),
        Some(sv.as_tensor()),
        Numerics::PARITY,
    )
    .unwrap();
    let grads = (&y * &upt).unwrap().sum_all().unwrap().backward().unwrap();
    let report = account.finish();
    assert!(
        report.ops.contains_key("pma-sine-linear"),
        "the CPU op ran on the CUDA route"
    );
    let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let gw = grads.get(&wv).unwrap();
    let gb = grads.get(&bv).unwrap().unsqueeze(1).unwrap();
    [
        flat(&y),
        flat(&Tensor::cat(&[gw, &gb], 1).unwrap()),
        flat(grads.get(&xv).unwrap()),
        flat(grads.get(&sv).unwrap()),
    ]
}

fn check(d: SineLinearDims, rng: &mut ChaCha8Rng, threads: u32, max_blocks: u32) {
    let mut vals = |len: usize, scale: f32| -> Vec<f32> {
        (0..len)
            .map(|_| rng.gen_range(-1.0f32..1.0) * scale)
            .collect()
    };
    // x̄ within the bone boxes (|x̄| ≲ 1.1), weights and bias scaled by ω = 16, window
    // weights in [0, 1].
    let x = vals(d.rows * d.inp, 1.1);
    let wb = vals(d.out * (d.inp + 1), 16.0);
    let sc: Vec<f32> = vals(d.rows, 1.0).iter().map(|v| v.abs()).collect();
    let up = vals(d.rows * d.out, 1.0);
    let [y_cpu, gwb_cpu, gx_cpu, gs_cpu] = cpu(&x, &wb, &sc, &up, d);
    let y = sine_linear(
        &x,
        &wb,
        &sc,
        d,
        Grid::covering(d.rows * d.out, threads, max_blocks),
    );
    same_bits(&y, &y_cpu, &format!("sine, {d:?}"));
    let n_blocks = d.rows.div_ceil(ROWS_PER_BLOCK);
    let (gwb, g_rows) = sine_linear_grad(
        &up,
        &x,
        &wb,
        &sc,
        d,
        [
            Grid::covering(n_blocks * d.out, threads, max_blocks),
            Grid::covering(d.out * (d.inp + 1), threads, max_blocks),
            Grid::covering(d.rows, threads, max_blocks),
        ],
    );
    same_bits(&gwb, &gwb_cpu, &format!("grad [W|b], {d:?}"));
    let width = d.inp + 1;
    let gx: Vec<f32> = (0..d.rows)
        .flat_map(|r| g_rows[r * width..r * width + d.inp].to_vec())
        .collect();
    let gs: Vec<f32> = (0..d.rows).map(|r| g_rows[r * width + d.inp]).collect();
    same_bits(&gx, &gx_cpu, &format!("grad x, {d:?}"));
    same_bits(&gs, &gs_cpu, &format!("grad s, {d:?}"));
}

#[test]
fn the_kernel_and_the_cpu_op_sum_in_blocks_of_the_same_rows() {
    assert_eq!(sine_linear_rows(), ROWS_PER_BLOCK);
}

#[test]
fn sine_linear_kernels_match_the_cpu_op_bit_for_bit() {
    let mut rng = ChaCha8Rng::seed_from_u64(17);
    for case in 0..24 {
        // Row counts below, at and across block boundaries (1024 rows per partial sum).
        let rows = [1, 5, 1023, 1024, 1025, 2500][case % 6];
        let d = SineLinearDims {
            rows,
            inp: rng.gen_range(1..=4),
            out: rng.gen_range(1..70),
        };
        let threads = [32, 64, 96, 256][case % 4];
        let max_blocks = [1, 3, 65_535][case % 3];
        check(d, &mut rng, threads, max_blocks);
    }
}

#[test]
fn sine_linear_kernels_handle_no_rows() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let d = SineLinearDims {
        rows: 0,
        inp: 3,
        out: 8,
    };
    check(d, &mut rng, 64, 4);
}
