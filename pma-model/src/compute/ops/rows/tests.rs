use candle_core::{Device, Var};

use super::*;

fn bits(t: &Tensor) -> Vec<u32> {
    t.flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap()
        .iter()
        .map(|v| v.to_bits())
        .collect()
}

/// d/dx of `sum(y ⊙ up)`: the gradient `up` pulled back through whatever made `y`.
fn grad_of(y: &Tensor, up: &Tensor, x: &Var) -> Tensor {
    let g = (y * up).unwrap().sum_all().unwrap().backward().unwrap();
    g.get(x).unwrap().clone()
}

/// Values with mixed magnitudes, so that a different summation order shows in the bits.
fn values(len: usize, seed: u32) -> Vec<f32> {
    (0..len as u32)
        .map(|i| {
            let h = (i.wrapping_mul(2_654_435_761) ^ seed).wrapping_mul(40_503);
            let u = (h >> 8) as f32 / (1u32 << 24) as f32 - 0.5;
            u * [1.0, 1e-3, 37.0, 1e4][(h & 3) as usize]
        })
        .collect()
}

#[test]
fn select_rows_matches_index_select_bitwise() {
    let dev = Device::Cpu;
    let (n, c, m) = (7, 5, 40);
    let x = Var::from_vec(values(n * c, 1), (n, c), &dev).unwrap();
    // Many rays per code, repeats in any order (like a chunk's frame codes).
    let ids: Vec<u32> = (0..m as u32).map(|i| (i * 5 + i / 3) % n as u32).collect();
    let ids = Tensor::from_vec(ids, m, &dev).unwrap();
    let up = Tensor::from_vec(values(m * c, 2), (m, c), &dev).unwrap();

    let plain = x.as_tensor().index_select(&ids, 0).unwrap();
    let ours = select_rows(x.as_tensor(), &ids, Numerics::PARITY).unwrap();
    assert_eq!(bits(&ours), bits(&plain));
    let (a, b) = (grad_of(&ours, &up, &x), grad_of(&plain, &up, &x));
    assert_eq!(bits(&a), bits(&b));
    // The gradient really accumulates: a row picked k times gets k contributions.
    assert!(bits(&a).iter().any(|&v| v != 0));
}

#[test]
fn gather_rows_matches_gather_bitwise() {
    let dev = Device::Cpu;
    let (b, n, c) = (6, 9, 4);
    let x = Var::from_vec(values(b * n * c, 3), (b, n, c), &dev).unwrap();
    // A permutation per row (merge_raw) for some rows, repeats for others.
    let ids: Vec<u32> = (0..b)
        .flat_map(|r| {
            (0..n).map(move |i| match r % 2 {
                0 => ((i * 4 + r) % n) as u32,
                _ => ((i * i + r) % 3) as u32,
            })
        })
        .collect();
    let ids = Tensor::from_vec(ids, (b, n), &dev).unwrap();
    let up = Tensor::from_vec(values(b * n * c, 4), (b, n, c), &dev).unwrap();

    let idx = ids.unsqueeze(2).unwrap().broadcast_as((b, n, c)).unwrap();
    let plain = x.as_tensor().gather(&idx.contiguous().unwrap(), 1).unwrap();
    let ours = gather_rows(x.as_tensor(), &ids, Numerics::PARITY).unwrap();
    assert_eq!(bits(&ours), bits(&plain));
    assert_eq!(
        bits(&grad_of(&ours, &up, &x)),
        bits(&grad_of(&plain, &up, &x))
    );
}

#[test]
fn bad_index_is_an_error() {
    let x = Tensor::zeros((3, 2), DType::F32, &Device::Cpu).unwrap();
    let ids = Tensor::new(&[0u32, 3], &Device::Cpu).unwrap();
    let e = select_rows(&x, &ids, Numerics::PARITY)
        .unwrap_err()
        .to_string();
    assert!(e.contains("index 3 out of range for 3 rows"), "{e}");
    let ids = Tensor::new(&[[0u32, 1]], &Device::Cpu).unwrap();
    assert!(gather_rows(
        &x.reshape((1, 3, 2)).unwrap(),
        &ids.repeat((2, 1)).unwrap(),
        Numerics::PARITY
    )
    .is_err());
}

/// CUDA against the CPU (skipped without a GPU): values identical, gradients equal up to
/// the order of the atomic additions.
#[test]
fn cuda_matches_cpu() {
    let Ok(cuda) = Device::new_cuda(0) else {
        return;
    };
    let (b, n, c, m) = (3, 11, 128, 300);
    let run = |dev: &Device| {
        let x = Var::from_vec(values(b * n * c, 5), (b, n, c), dev).unwrap();
        let ids: Vec<u32> = (0..b * m).map(|i| ((i * 7 + i / 5) % n) as u32).collect();
        let ids = Tensor::from_vec(ids, (b, m), dev).unwrap();
        let up = Tensor::from_vec(values(b * m * c, 6), (b, m, c), dev).unwrap();
        let y = gather_rows(x.as_tensor(), &ids, Numerics::PARITY).unwrap();
        let gx = grad_of(&y, &up, &x).to_device(&Device::Cpu).unwrap();
        (y.to_device(&Device::Cpu).unwrap(), gx)
    };
    let (y_cpu, g_cpu) = run(&Device::Cpu);
    let (y_gpu, g_gpu) = run(&cuda);
    assert_eq!(bits(&y_gpu), bits(&y_cpu));
    let max_abs = |t: &Tensor| {
        t.abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap()
    };
    let (diff, scale) = (max_abs(&(g_gpu - &g_cpu).unwrap()), max_abs(&g_cpu));
    assert!(
        diff <= 1e-5 * scale.max(1.0),
        "max |cuda - cpu| {diff} (scale {scale})"
    );
}

/// Every case of the full check passes on the emulated grid.
#[test]
fn the_full_check_passes_on_the_emulated_grid() {
    crate::compute::ops::testing::full_check_passes(&MODULE);
}
