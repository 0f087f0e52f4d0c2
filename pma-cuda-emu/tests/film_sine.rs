//! `film_sine.cu` over emulated grids against pma-model's CPU FiLM-sine layer
//! (`pma_model::compute::fused::FilmHead`, parity numerics): the layer's output, the
//! gradient of its input and of the head's two blocks.
//!
//! Tolerance: none on the host, bits are compared. The kernels form the argument and the
//! gradients with the CPU op's f32 operations in its order, rounded separately, and the
//! host build's sinf/cosf are the C library's, whose bits the CPU op reproduces. On a GPU
//! CUDA's sinf/cosf (within 2 ulp) replace them: there the output and the gradients differ
//! from the CPU's in the last bits of the sine and cosine, nothing else.

use candle_core::{Device, Tensor, Var};
use pma_cuda_emu::{film_sine, film_sine_grad, FilmDims, Grid};
use pma_model::compute::fused::FilmHead;
use pma_model::compute::numerics::Numerics;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn same_bits(a: &[f32], b: &[f32], what: &str) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    if let Some(i) = (0..a.len()).find(|&i| a[i].to_bits() != b[i].to_bits()) {
        panic!("{what}: element {i} is {} here, {} on the CPU", a[i], b[i]);
    }
}

/// The CPU layer's (output, grad pre, grad o) for upstream gradient `up`.
fn cpu(pre: &[f32], o: &[f32], up: &[f32], d: FilmDims) -> [Vec<f32>; 3] {
    let dev = Device::Cpu;
    let w = 2 * d.n_layers * d.f;
    let pv = Var::from_vec(pre.to_vec(), (d.n, d.f), &dev).unwrap();
    let ov = Var::from_vec(o.to_vec(), (d.n, w), &dev).unwrap();
    let upt = Tensor::from_vec(up.to_vec(), (d.n, d.f), &dev).unwrap();
    let head = FilmHead::new(
        ov.as_tensor(),
        d.n_layers,
        (d.mul as f64, d.add as f64),
        Numerics::PARITY,
    );
    let y = head.layer(pv.as_tensor(), d.k).unwrap();
    let grads = (&y * &upt).unwrap().sum_all().unwrap().backward().unwrap();
    let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    [
        flat(&y),
        flat(grads.get(&pv).unwrap()),
        flat(grads.get(&ov).unwrap()),
    ]
}

fn check(d: FilmDims, rng: &mut ChaCha8Rng, threads: u32, max_blocks: u32) {
    let w = 2 * d.n_layers * d.f;
    let mut vals = |len: usize, scale: f32| -> Vec<f32> {
        (0..len)
            .map(|_| rng.gen_range(-1.0f32..1.0) * scale)
            .collect()
    };
    // Arguments up to a few hundred, as γ = 15Θ + 30 makes them.
    let pre = vals(d.n * d.f, 3.0);
    let o = vals(d.n * w, 1.0);
    let up = vals(d.n * d.f, 1.0);
    let [y_cpu, gp_cpu, go_cpu] = cpu(&pre, &o, &up, d);
    let grid = Grid::covering(d.n * d.f, threads, max_blocks);
    for keep in [true, false] {
        let (y, cos) = film_sine(&pre, &o, d, keep, grid);
        same_bits(&y, &y_cpu, &format!("sine, {d:?}"));
        // The head gradient starts at zero, as the CPU op's: the kernel writes layer k's
        // blocks only.
        let mut g_o = vec![0f32; o.len()];
        let g_pre = film_sine_grad(&up, &pre, &o, cos.as_deref(), &mut g_o, d, grid);
        same_bits(
            &g_pre,
            &gp_cpu,
            &format!("grad pre (cos kept: {keep}), {d:?}"),
        );
        same_bits(&g_o, &go_cpu, &format!("grad o (cos kept: {keep}), {d:?}"));
    }
}

#[test]
fn film_sine_kernels_match_the_cpu_op_bit_for_bit() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    for case in 0..30 {
        let n_layers = rng.gen_range(1..4);
        let d = FilmDims {
            n: rng.gen_range(1..50),
            f: rng.gen_range(1..37),
            k: rng.gen_range(0..n_layers),
            n_layers,
            mul: 15.0,
            add: 30.0,
        };
        let threads = [32, 64, 96, 256][case % 4];
        let max_blocks = [1, 3, 65_535][case % 3];
        check(d, &mut rng, threads, max_blocks);
    }
}

#[test]
fn film_sine_kernels_handle_no_rows() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let d = FilmDims {
        n: 0,
        f: 8,
        k: 1,
        n_layers: 3,
        mul: 15.0,
        add: 30.0,
    };
    check(d, &mut rng, 64, 4);
}
