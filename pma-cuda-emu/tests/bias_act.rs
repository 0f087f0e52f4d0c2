//! `bias_act.cu` over emulated grids against pma-model's linear-activation ops
//! (`pma_model::compute::linear_act`, run as a CPU run accounted as CUDA runs them): the
//! output, and the gradients of the weight (from the kernel's product gradient, through the
//! same candle product the op uses) and of the bias, for the ReLU and the sine.
//!
//! Tolerance: none on the host, bits are compared. The kernels add, select, multiply and
//! sum with the CPU op's f32 operations in its order (the bias gradient per block of rows,
//! then over the blocks), and the host build's sinf/cosf are the C library's, whose bits the
//! CPU op reproduces. On a GPU the ReLU gives the same bits; the sine's output and
//! gradients differ by CUDA's sinf/cosf (within 2 ulp).

use candle_core::{Device, Tensor, Var};
use pma_cuda_emu::{act_grad, bias_act, bias_act_rows, Grid};
use pma_model::compute::account::{Account, Route};
use pma_model::compute::linear_act::{linear_relu, linear_sine, ROWS_PER_BLOCK};
use pma_model::compute::numerics::Numerics;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn same_bits(a: &[f32], b: &[f32], what: &str) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    if let Some(i) = (0..a.len()).find(|&i| a[i].to_bits() != b[i].to_bits()) {
        panic!("{what}: element {i} is {} here, {} on the CPU", a[i], b[i]);
    }
}

fn flat(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
}

struct Case {
    rows: usize,
    inn: usize,
    out: usize,
    sine: bool,
}

fn check(c: Case, rng: &mut ChaCha8Rng, threads: u32, max_blocks: u32) {
    let Case {
        rows,
        inn,
        out,
        sine,
    } = c;
    let dev = Device::Cpu;
    let mut vals = |len: usize, s: f32| -> Vec<f32> {
        (0..len).map(|_| rng.gen_range(-1.0f32..1.0) * s).collect()
    };
    // Sine layers see ω-scaled weights (ω = 8 in the pose extractor).
    let scale = if sine { 8.0 } else { 1.0 };
    let (x, w, b, up) = (
        vals(rows * inn, 1.0),
        vals(out * inn, scale),
        vals(out, scale),
        vals(rows * out, 1.0),
    );
    let xt = Tensor::from_vec(x, (rows, inn), &dev).unwrap();
    let wv = Var::from_vec(w, (out, inn), &dev).unwrap();
    let bv = Var::from_vec(b.clone(), out, &dev).unwrap();
    let upt = Tensor::from_vec(up.clone(), (rows, out), &dev).unwrap();
    let account = Account::start(&dev, Route::Cuda).unwrap();
    let op = if sine { linear_sine } else { linear_relu };
    let y = op(&xt, wv.as_tensor(), bv.as_tensor(), Numerics::PARITY).unwrap();
    let grads = (&y * &upt).unwrap().sum_all().unwrap().backward().unwrap();
    let report = account.finish();
    let name = if sine {
        "pma-bias-sine"
    } else {
        "pma-bias-relu"
    };
    assert!(report.ops.contains_key(name), "the CPU op ran");
    // The product without the bias, as cuBLAS gives it to the kernel.
    let z = flat(&xt.matmul(&wv.as_tensor().t().unwrap()).unwrap());
    let what = format!("{rows}x{inn}->{out}, sine {sine}");
    let yk = bias_act(
        &z,
        &b,
        sine,
        Grid::covering(rows * out, threads, max_blocks),
    );
    same_bits(&yk, &flat(&y), &format!("y, {what}"));
    let n_blocks = rows.div_ceil(ROWS_PER_BLOCK);
    let kept = if sine { &z } else { &yk };
    let (gz, gb) = act_grad(
        &up,
        kept,
        &b,
        sine,
        Grid::covering(n_blocks * out, threads, max_blocks),
        Grid::covering(out, threads, max_blocks),
    );
    same_bits(
        &gb,
        &flat(grads.get(&bv).unwrap()),
        &format!("grad b, {what}"),
    );
    let gzt = Tensor::from_vec(gz, (rows, out), &dev).unwrap();
    let gw = xt.t().unwrap().matmul(&gzt).unwrap().t().unwrap();
    same_bits(
        &flat(&gw),
        &flat(grads.get(&wv).unwrap()),
        &format!("grad W, {what}"),
    );
}

#[test]
fn the_kernel_and_the_cpu_op_sum_in_blocks_of_the_same_rows() {
    assert_eq!(bias_act_rows(), ROWS_PER_BLOCK);
}

#[test]
fn bias_act_kernels_match_the_cpu_op_bit_for_bit() {
    let mut rng = ChaCha8Rng::seed_from_u64(23);
    for case in 0..24 {
        // Row counts below, at and across block boundaries (256 rows per partial sum).
        let rows = [1, 7, 255, 256, 257, 700][case % 6];
        let (inn, out) = (rng.gen_range(1..20), rng.gen_range(1..40));
        let threads = [32, 64, 96, 256][case % 4];
        let max_blocks = [1, 3, 65_535][case % 3];
        let sine = case % 2 == 1;
        check(
            Case {
                rows,
                inn,
                out,
                sine,
            },
            &mut rng,
            threads,
            max_blocks,
        );
    }
}

#[test]
fn bias_act_kernels_handle_no_rows() {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    for sine in [false, true] {
        let c = Case {
            rows: 0,
            inn: 5,
            out: 8,
            sine,
        };
        check(c, &mut rng, 64, 4);
    }
}
