//! `bias_relu.cu` over emulated grids against pma-model's linear-ReLU op
//! (`pma_model::compute::linear_relu`, run as a CPU run accounted as CUDA runs it): the
//! output, and the gradients of the weight (from the kernel's product gradient, through the
//! same candle product the op uses) and of the bias.
//!
//! Tolerance: none, bits are compared. The kernels add, select and sum with the CPU op's f32
//! operations in its order (the bias gradient per block of rows, then over the blocks); no
//! library function is involved, so a GPU gives the same bits as well.

use candle_core::{Device, Tensor, Var};
use pma_cuda_emu::{bias_relu, bias_relu_rows, relu_grad, Grid};
use pma_model::compute::account::{Account, Route};
use pma_model::compute::linear_relu::{linear_relu, ROWS_PER_BLOCK};
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

fn check(rows: usize, inn: usize, out: usize, rng: &mut ChaCha8Rng, threads: u32, max_blocks: u32) {
    let dev = Device::Cpu;
    let mut vals =
        |len: usize| -> Vec<f32> { (0..len).map(|_| rng.gen_range(-1.0f32..1.0)).collect() };
    let (x, w, b, up) = (
        vals(rows * inn),
        vals(out * inn),
        vals(out),
        vals(rows * out),
    );
    let xt = Tensor::from_vec(x, (rows, inn), &dev).unwrap();
    let wv = Var::from_vec(w, (out, inn), &dev).unwrap();
    let bv = Var::from_vec(b.clone(), out, &dev).unwrap();
    let upt = Tensor::from_vec(up.clone(), (rows, out), &dev).unwrap();
    let account = Account::start(&dev, Route::Cuda).unwrap();
    let y = linear_relu(&xt, wv.as_tensor(), bv.as_tensor(), Numerics::PARITY).unwrap();
    let grads = (&y * &upt).unwrap().sum_all().unwrap().backward().unwrap();
    let report = account.finish();
    assert!(report.ops.contains_key("pma-bias-relu"), "the CPU op ran");
    // The product without the bias, as cuBLAS gives it to the kernel.
    let z = flat(&xt.matmul(&wv.as_tensor().t().unwrap()).unwrap());
    let yk = bias_relu(&z, &b, Grid::covering(rows * out, threads, max_blocks));
    same_bits(&yk, &flat(&y), &format!("y, {rows}x{inn}->{out}"));
    let n_blocks = rows.div_ceil(ROWS_PER_BLOCK);
    let (gz, gb) = relu_grad(
        &up,
        &yk,
        out,
        Grid::covering(n_blocks * out, threads, max_blocks),
        Grid::covering(out, threads, max_blocks),
    );
    same_bits(&gb, &flat(grads.get(&bv).unwrap()), "grad b");
    let gzt = Tensor::from_vec(gz, (rows, out), &dev).unwrap();
    let gw = xt.t().unwrap().matmul(&gzt).unwrap().t().unwrap();
    same_bits(&flat(&gw), &flat(grads.get(&wv).unwrap()), "grad W");
}

#[test]
fn the_kernel_and_the_cpu_op_sum_in_blocks_of_the_same_rows() {
    assert_eq!(bias_relu_rows(), ROWS_PER_BLOCK);
}

#[test]
fn bias_relu_kernels_match_the_cpu_op_bit_for_bit() {
    let mut rng = ChaCha8Rng::seed_from_u64(23);
    for case in 0..18 {
        // Row counts below, at and across block boundaries (256 rows per partial sum).
        let rows = [1, 7, 255, 256, 257, 700][case % 6];
        let (inn, out) = (rng.gen_range(1..20), rng.gen_range(1..40));
        let threads = [32, 64, 96, 256][case % 4];
        let max_blocks = [1, 3, 65_535][case % 3];
        check(rows, inn, out, &mut rng, threads, max_blocks);
    }
}

#[test]
fn bias_relu_kernels_handle_no_rows() {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    check(0, 5, 8, &mut rng, 64, 4);
}
