use candle_core::{Device, Tensor};

use super::*;
use crate::compute::ops::testing::bits;

/// The CPU's one-pass update gives the bits of the tensor-op update for every case a step
/// has: gradients with signed zeros, tiny and large values, a clip factor, slots without a
/// gradient, and an update that does not apply.
#[test]
fn the_host_update_is_the_tensor_update_bit_for_bit() {
    let dev = Device::Cpu;
    let sizes = [12usize, 5, 4];
    let n: usize = sizes.iter().sum();
    let special = [0.0f32, -0.0, 1e-30, -3e-8, 7.5, -1e6, 2.0e-3, -0.25];
    let flat = |step: usize, scale: f32| -> Tensor {
        let v: Vec<f32> = (0..n)
            .map(|i| special[(i + 3 * step) % special.len()] * scale)
            .collect();
        Tensor::from_vec(v, n, &dev).unwrap()
    };
    let mut inputs = check::Inputs {
        // Each case sets its own.
        g: flat(0, 1.0),
        params: sizes
            .iter()
            .enumerate()
            .map(|(k, &len)| {
                let v: Vec<f32> = (0..len)
                    .map(|i| ((i * 5 + k) % 9) as f32 * 0.3 - 1.2)
                    .collect();
                Tensor::from_vec(v, len, &dev).unwrap()
            })
            .collect(),
        m: flat(1, 0.01),
        v: flat(2, 0.001).abs().unwrap(),
        slot_of: slot_index(&sizes, &dev).unwrap(),
        step_size: Tensor::new(&[1e-3 / (1.0 - 0.9f64.powi(4)), 5e-4, 5e-4 / 0.3], &dev).unwrap(),
        bias2_sqrt: Tensor::new(&[0.063f64, 0.0447, 0.5], &dev).unwrap(),
    };
    let on = Tensor::new(1u8, &dev).unwrap();
    let off = Tensor::new(0u8, &dev).unwrap();
    let clip = Tensor::new(0.37f32, &dev).unwrap();
    let cases: [(&[bool], Option<&Tensor>, Option<&Tensor>); 5] = [
        (&[true, true, true], None, None),
        (&[true, false, true], None, Some(&clip)),
        (&[true, true, true], Some(&on), Some(&clip)),
        (&[false, true, true], Some(&on), None),
        (&[true, true, true], Some(&off), None),
    ];
    for (c, (has, apply, coef)) in cases.into_iter().enumerate() {
        inputs.g = flat(4 + c, 1.0 + c as f32 * 0.1);
        let u = inputs.update(has, apply, coef);
        let host = cpu::update(&u).unwrap();
        let plain = generic(&u).unwrap();
        for (what, a, b) in [
            ("p", &host.0, &plain.0),
            ("m", &host.1, &plain.1),
            ("v", &host.2, &plain.2),
        ] {
            assert_eq!(bits(a), bits(b), "case {c}: {what}");
        }
        let moved = bits(&host.0) != bits(&flat_params(&u).unwrap());
        assert_eq!(
            moved,
            apply.is_none_or(|a| a.to_scalar::<u8>().unwrap() != 0),
            "case {c}"
        );
    }
}

/// Every case of the full check passes on the emulated grid.
#[test]
fn the_full_check_passes_on_the_emulated_grid() {
    crate::compute::ops::testing::full_check_passes(&MODULE);
}
