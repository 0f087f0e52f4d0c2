//! `adam.cu` over emulated grids against pma-model's flat Adam update
//! (`pma_model::train::adam::Adam::step_masked`) over several steps: two parameter groups,
//! a parameter without a gradient, a step masked off on the device, a clipped gradient.
//!
//! Tolerance: none, bits are compared: the kernel performs the tensor-op update's f32
//! operations in its order, each rounded on its own (sqrt and division correctly rounded,
//! as on the GPU with `__fsqrt_rn`/`__fdiv_rn`).

use std::collections::HashMap;

use candle_core::{Device, Tensor, Var};
use pma_cuda_emu::{adam, AdamStep, Grid};
use pma_model::train::adam::{reference_group, Adam};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn same_bits(a: &[f32], b: &[f32], what: &str) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    if let Some(i) = (0..a.len()).find(|&i| a[i].to_bits() != b[i].to_bits()) {
        panic!("{what}: element {i} is {} here, {} on the CPU", a[i], b[i]);
    }
}

fn flat(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1().unwrap()
}

#[test]
fn adam_kernel_matches_the_flat_update_bit_for_bit() {
    let mut rng = ChaCha8Rng::seed_from_u64(17);
    let names = [
        "graph_net.0.weight",
        "pts_linears.0.weight",
        "pts_linears.0.bias",
        "modulator.1.bias",
        "rgb_linear.weight",
    ];
    let (lr_freq, lr_other, betas, eps) = (1e-4, 5e-4, [0.9, 0.999], 1e-8);
    let vars: Vec<(String, Var)> = names
        .iter()
        .map(|n| {
            let len = rng.gen_range(1..300);
            let v: Vec<f32> = (0..len).map(|_| rng.gen_range(-1.0f32..1.0)).collect();
            (n.to_string(), Var::from_vec(v, len, &Device::Cpu).unwrap())
        })
        .collect();
    let by_name: HashMap<&str, &Var> = vars.iter().map(|(n, v)| (n.as_str(), v)).collect();
    let mut opt = Adam::reference(&vars, lr_freq, lr_other, betas, eps).unwrap();
    let order: Vec<String> = opt.param_names().map(str::to_string).collect();
    let lens: Vec<usize> = order
        .iter()
        .map(|n| by_name[n.as_str()].elem_count())
        .collect();
    let slot_of: Vec<u32> = lens
        .iter()
        .enumerate()
        .flat_map(|(s, &l)| std::iter::repeat_n(s as u32, l))
        .collect();
    let n = slot_of.len();
    // (step, no gradient for slot 1, applies, clip factor)
    let plan = [
        (0, false, true, None),
        (1, true, true, None),
        (2, false, false, None),
        (3, false, true, Some(0.37f32)),
        (4, true, true, Some(0.91f32)),
        (5, false, true, None),
    ];
    for (step, hole, ok, coef) in plan {
        let grads: Vec<Option<Tensor>> = lens
            .iter()
            .enumerate()
            .map(|(s, &l)| {
                (!(hole && s == 1)).then(|| {
                    let g: Vec<f32> = (0..l).map(|_| rng.gen_range(-2.0f32..2.0)).collect();
                    Tensor::from_vec(g, l, &Device::Cpu).unwrap()
                })
            })
            .collect();
        let (g, has) = opt.flatten(&grads).unwrap();
        // What the update reads, from the optimizer's state before it.
        let states = opt.states().unwrap();
        let p_old: Vec<f32> = order
            .iter()
            .flat_map(|n| flat(by_name[n.as_str()]))
            .collect();
        let m_old: Vec<f32> = states.iter().flat_map(|(_, s)| flat(&s.exp_avg)).collect();
        let v_old: Vec<f32> = states
            .iter()
            .flat_map(|(_, s)| flat(&s.exp_avg_sq))
            .collect();
        let (mut step_size, mut inv_bias2) = (Vec::new(), Vec::new());
        for ((name, st), &h) in states.iter().zip(&has) {
            // The step number this update gives the slot (the table index on the CPU).
            let t = (st.step + u64::from(h && ok)) as i32;
            let lr = if reference_group(name) == 0 {
                lr_freq
            } else {
                lr_other
            };
            step_size.push((lr / (1.0 - betas[0].powi(t))) as f32);
            inv_bias2.push((1.0 / (1.0 - betas[1].powi(t)).sqrt()) as f32);
        }
        let spec = AdamStep {
            slot_of: slot_of.clone(),
            step_size,
            inv_bias2,
            has: has.clone(),
            ok,
            coef,
            betas,
            eps,
        };
        let grid = Grid::covering(n, [64, 96, 256][step % 3], [2, 65_535][step % 2]);
        let [p, m, v] = adam(&flat(&g), &p_old, &m_old, &v_old, &spec, grid);

        // The CPU update: the clip as the trainer applies it, the flag as a device scalar.
        let g = match coef {
            Some(c) => g
                .broadcast_mul(&Tensor::new(c, &Device::Cpu).unwrap())
                .unwrap(),
            None => g,
        };
        let ok_t = Tensor::new(ok as u8, &Device::Cpu).unwrap();
        opt.step_masked(&g, &has, Some(&ok_t)).unwrap();
        let states = opt.states().unwrap();
        let p_cpu: Vec<f32> = order
            .iter()
            .flat_map(|n| flat(by_name[n.as_str()]))
            .collect();
        let m_cpu: Vec<f32> = states.iter().flat_map(|(_, s)| flat(&s.exp_avg)).collect();
        let v_cpu: Vec<f32> = states
            .iter()
            .flat_map(|(_, s)| flat(&s.exp_avg_sq))
            .collect();
        same_bits(&p, &p_cpu, &format!("parameters, step {step}"));
        same_bits(&m, &m_cpu, &format!("first moments, step {step}"));
        same_bits(&v, &v_cpu, &format!("second moments, step {step}"));
        if !ok {
            same_bits(&p, &p_old, "a masked step changes nothing");
        }
    }
}

#[test]
fn adam_kernel_handles_no_elements() {
    let spec = AdamStep {
        slot_of: vec![],
        step_size: vec![1e-3],
        inv_bias2: vec![1.0],
        has: vec![true],
        ok: true,
        coef: None,
        betas: [0.9, 0.999],
        eps: 1e-8,
    };
    let [p, m, v] = adam(&[], &[], &[], &[], &spec, Grid::covering(0, 64, 4));
    assert!(p.is_empty() && m.is_empty() && v.is_empty());
}
