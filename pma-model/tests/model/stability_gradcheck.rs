//! Finite differences vs autograd in f64, module by module, at normal and at extreme inputs: 6D
//! poses that are far from orthonormal or have collinear columns, bone-frame coordinates a
//! thousand box sizes out, modulation frequencies of ±1e3, densities of 1e4.
//!
//! Every module is built from the `tiny` initialisation cast to f64. For a few entries of each
//! parameter (and of the differentiable inputs) the central difference with step `h` is
//! compared with the autograd gradient; the error is relative to the largest |gradient| of
//! that tensor. Inputs are random, so ReLU kinks and max-pool ties are not hit exactly.

use std::collections::HashMap;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use pma_data::synth;
use pma_model::network::encoders::{spherical_harmonics, PointEnc};
use pma_model::network::field::Field;
use pma_model::network::gnn::GnnSine;
use pma_model::network::init_tensors;
use pma_model::network::modulator::{Modulation, Modulator, PoseExtractor};
use pma_model::network::window::{aggregate, WinFun};
use pma_model::render::volume::raw2outputs;
use pma_model::Config;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// The parity numerics (the default) for the layers called one by one.
const K: pma_model::compute::numerics::Numerics = pma_model::compute::numerics::Numerics::PARITY;

const DEV: Device = Device::Cpu;

struct Setup {
    cfg: Config,
    vars: HashMap<String, Var>,
    vb: VarBuilder<'static>,
    rng: ChaCha8Rng,
}

fn setup() -> Setup {
    let cfg = Config {
        n_framecodes: 3,
        ..Config::tiny()
    };
    let varmap = VarMap::new();
    let mut vars = HashMap::new();
    {
        let mut data = varmap.data().lock().unwrap();
        for (k, t) in init_tensors(&cfg, &synth::rest_pose(), 11, &DEV).unwrap() {
            let v = Var::from_tensor(&t.to_dtype(DType::F64).unwrap()).unwrap();
            vars.insert(k.clone(), v.clone());
            data.insert(k, v);
        }
    }
    let vb = VarBuilder::from_varmap(&varmap, DType::F64, &DEV);
    Setup {
        cfg,
        vars,
        vb,
        rng: ChaCha8Rng::seed_from_u64(5),
    }
}

fn rand_t(rng: &mut ChaCha8Rng, shape: &[usize], lo: f64, hi: f64) -> Tensor {
    let n: usize = shape.iter().product();
    let v: Vec<f64> = (0..n).map(|_| rng.gen_range(lo..hi)).collect();
    Tensor::from_vec(v, shape, &DEV).unwrap()
}

/// Compare d loss / d var with central differences at `probes` random entries; returns the
/// largest error relative to max |autograd gradient| of the var.
fn check(what: &str, var: &Var, loss: &dyn Fn() -> Tensor, h: f64, rng: &mut ChaCha8Rng) -> f64 {
    let l = loss();
    let grads = l.backward().unwrap();
    let ad = grads
        .get(var.as_tensor())
        .unwrap_or_else(|| panic!("{what}: no gradient"))
        .flatten_all()
        .unwrap()
        .to_vec1::<f64>()
        .unwrap();
    assert!(
        ad.iter().all(|x| x.is_finite()),
        "{what}: non-finite gradient"
    );
    let scale = ad.iter().fold(0f64, |m, x| m.max(x.abs()));
    let base = var
        .as_tensor()
        .flatten_all()
        .unwrap()
        .to_vec1::<f64>()
        .unwrap();
    let shape = var.as_tensor().shape().clone();
    let eval = |v: Vec<f64>| -> f64 {
        var.set(&Tensor::from_vec(v, shape.clone(), &DEV).unwrap())
            .unwrap();
        loss().to_scalar::<f64>().unwrap()
    };
    let mut worst = 0f64;
    for _ in 0..4 {
        let k = rng.gen_range(0..base.len());
        let mut plus = base.clone();
        plus[k] += h;
        let mut minus = base.clone();
        minus[k] -= h;
        let fd = (eval(plus) - eval(minus)) / (2.0 * h);
        assert!(fd.is_finite(), "{what}: non-finite difference");
        worst = worst.max((fd - ad[k]).abs() / scale.max(1e-12));
    }
    var.set(&Tensor::from_vec(base, shape, &DEV).unwrap())
        .unwrap();
    println!("{what:<55} max |grad| {scale:>10.3e}  rel err {worst:.2e}");
    worst
}

const TOL: f64 = 1e-5;

#[test]
fn gnn_and_axis_scale() {
    let mut s = setup();
    let gnn = GnnSine::new(s.vb.pp("graph_net"), &s.cfg).unwrap();
    let rot6d = |bones: &pma_data::skeleton::Joints| {
        let v: Vec<f64> = pma_data::skeleton::pose_to_rot6d(bones)
            .iter()
            .flatten()
            .map(|&x| x as f64)
            .collect();
        Tensor::from_vec(v, (1, 24, 6), &DEV).unwrap()
    };
    let normal = rot6d(&[[0.3, -0.2, 0.1]; 24]);
    let pi = rot6d(&[[std::f32::consts::PI, 0.0, 0.0]; 24]);
    let wild = rand_t(&mut s.rng, &[2, 24, 6], -100.0, 100.0);
    // Collinear columns: (a, k·a) for each joint.
    let a = rand_t(&mut s.rng, &[1, 24, 3], -1.0, 1.0);
    let collinear = Tensor::stack(&[&a, &(&a * 3.0).unwrap()], 3)
        .unwrap()
        .reshape((1, 24, 6))
        .unwrap();
    let out_w = rand_t(&mut s.rng, &[2, 24, s.cfg.gnn_width], -1.0, 1.0);
    for (case, x) in [
        ("normal", normal),
        ("pi", pi),
        ("non-orthonormal x100", wild),
        ("collinear", collinear),
    ] {
        let p = x.dim(0).unwrap();
        let w = out_w.narrow(0, 0, p).unwrap();
        let loss = || {
            (gnn.forward(&x, None).unwrap() * &w)
                .unwrap()
                .sum_all()
                .unwrap()
        };
        for name in [
            "graph_net.layers.0.lin.weight",
            "graph_net.layers.0.adj_w",
            "graph_net.layers.1.bias",
            "graph_net.layers.3.weight",
        ] {
            let e = check(
                &format!("gnn {case}: {name}"),
                &s.vars[name],
                &loss,
                1e-6,
                &mut s.rng,
            );
            assert!(e < TOL, "{case} {name}: {e:e}");
        }
    }
    // The straight-through floor: d s / d a = sign(a) wherever |a| is (above or below it).
    let scale_w = rand_t(&mut s.rng, &[24, 3], -1.0, 1.0);
    let loss = || {
        (gnn.axis_scale().unwrap() * &scale_w)
            .unwrap()
            .sum_all()
            .unwrap()
    };
    let e = check(
        "axis scale (above the floor)",
        &s.vars["graph_net.axis_scale"],
        &loss,
        1e-7,
        &mut s.rng,
    );
    assert!(e < TOL, "{e:e}");
}

#[test]
fn point_encoders_window_and_aggregation() {
    let mut s = setup();
    let cfg = s.cfg.clone();
    let enc = PointEnc::new(
        s.vb.pp("pts_enc_point"),
        cfg.point_enc_dim,
        cfg.sin_w0_point,
    )
    .unwrap();
    let win = WinFun::new(s.vb.pp("win_fun"), &cfg).unwrap();
    for (case, span) in [("normal", 1.0), ("1e3 box sizes out", 1e3)] {
        let x = Var::from_tensor(&rand_t(&mut s.rng, &[5, 24, 3], -span, span)).unwrap();
        let w = rand_t(&mut s.rng, &[5, 24, cfg.point_enc_dim], -1.0, 1.0);
        let loss = || {
            (enc.forward(x.as_tensor(), K).unwrap() * &w)
                .unwrap()
                .sum_all()
                .unwrap()
        };
        // sin(16(w·x + b)) at |x| ~ 1e3 has curvature ~ (16e3)²: a smaller step.
        let h = if span > 1.0 { 1e-9 } else { 1e-6 };
        for (n, v) in [
            ("input x_bar", &x),
            ("weight", &s.vars["pts_enc_point.sin_lin0.layer.weight"]),
        ] {
            let e = check(
                &format!("point encoder {case}: {n}"),
                v,
                &loss,
                h,
                &mut s.rng,
            );
            assert!(e < 1e-4, "{case} {n}: {e:e}");
        }
    }
    let g = Var::from_tensor(&rand_t(&mut s.rng, &[1, 24, cfg.win_hidden], -1.0, 1.0)).unwrap();
    let e = Var::from_tensor(&rand_t(&mut s.rng, &[6, 24, cfg.point_enc_dim], -1.0, 1.0)).unwrap();
    let w_p = rand_t(&mut s.rng, &[6, 24], 0.0, 1.0);
    let out_w = rand_t(&mut s.rng, &[6, cfg.win_hidden], -1.0, 1.0);
    let loss = || {
        let w = win
            .forward(g.as_tensor(), e.as_tensor(), &w_p, None, K)
            .unwrap();
        let f_m = aggregate(&w.w, g.as_tensor()).unwrap();
        (f_m * &out_w).unwrap().sum_all().unwrap()
    };
    for (n, v) in [
        ("input g", &g),
        ("input e", &e),
        ("layer_point", &s.vars["win_fun.layer_point.layer.weight"]),
        ("sin_lin1", &s.vars["win_fun.sin_lin1.layer.weight"]),
        ("last_layer", &s.vars["win_fun.last_layer.layer.bias"]),
    ] {
        let err = check(
            &format!("window + aggregation: {n}"),
            v,
            &loss,
            1e-6,
            &mut s.rng,
        );
        assert!(err < TOL, "{n}: {err:e}");
    }
}

#[test]
fn pose_extractor_and_modulator_at_huge_frequencies() {
    let mut s = setup();
    let cfg = s.cfg.clone();
    let ext = PoseExtractor::new(s.vb.pp("pose_extractor"), &cfg).unwrap();
    let f_m = Var::from_tensor(&rand_t(&mut s.rng, &[4, cfg.win_hidden], -1.0, 1.0)).unwrap();
    let w = rand_t(&mut s.rng, &[4, 2 * cfg.n_pm * cfg.freq_dim], -1.0, 1.0);
    let loss = || {
        let m = ext.forward(f_m.as_tensor(), K).unwrap();
        let all: Vec<Tensor> = m.freq.iter().chain(&m.phase).cloned().collect();
        (Tensor::cat(&all, 1).unwrap() * &w)
            .unwrap()
            .sum_all()
            .unwrap()
    };
    for (n, v) in [
        ("input f_m", &f_m),
        ("head", &s.vars["pose_extractor.sin_lin1.layer.weight"]),
    ] {
        let e = check(&format!("pose extractor: {n}"), v, &loss, 1e-6, &mut s.rng);
        assert!(e < TOL, "{n}: {e:e}");
    }

    let modu = Modulator::new(s.vb.pp("modulator"), &cfg).unwrap();
    let x = rand_t(&mut s.rng, &[3, 24 * cfg.point_enc_dim], -1.0, 1.0);
    let out_w = rand_t(&mut s.rng, &[3, cfg.n_pm * cfg.freq_dim], -1.0, 1.0);
    // Θ such that γ = 15Θ + 30 is about 30 (normal), 1e3 and −1e3 (extreme).
    for (case, gamma) in [("gamma 30", 30.0), ("gamma 1e3", 1e3), ("gamma -1e3", -1e3)] {
        let theta = (gamma - 30.0) / 15.0;
        let freq: Vec<Var> = (0..cfg.n_pm)
            .map(|_| {
                Var::from_tensor(&rand_t(
                    &mut s.rng,
                    &[3, cfg.freq_dim],
                    theta - 0.1,
                    theta + 0.1,
                ))
                .unwrap()
            })
            .collect();
        let phase: Vec<Tensor> = (0..cfg.n_pm)
            .map(|_| rand_t(&mut s.rng, &[3, cfg.freq_dim], -1.0, 1.0))
            .collect();
        let loss = || {
            let m = Modulation {
                freq: freq.iter().map(|v| v.as_tensor().clone()).collect(),
                phase: phase.clone(),
                head: None,
            };
            (modu.forward(&x, &m, None, K).unwrap() * &out_w)
                .unwrap()
                .sum_all()
                .unwrap()
        };
        let h = if gamma == 30.0 { 1e-6 } else { 1e-8 };
        for (n, v) in [
            ("theta of layer 1", &freq[1]),
            ("layer 0 weight", &s.vars["modulator.sin_lin0.layer.weight"]),
            ("layer 1 bias", &s.vars["modulator.sin_lin1.layer.bias"]),
        ] {
            let e = check(&format!("modulator {case}: {n}"), v, &loss, h, &mut s.rng);
            assert!(e < 1e-4, "{case} {n}: {e:e}");
        }
    }
}

#[test]
fn field_view_encoding_and_compositing() {
    let mut s = setup();
    let cfg = s.cfg.clone();
    let field = Field::new(s.vb.clone(), &cfg).unwrap();
    let n = 5;
    let sdim = cfg.n_pm * cfg.freq_dim;
    let vdim = cfg.sh_degree * cfg.sh_degree + cfg.framecode_ch;
    let input = Var::from_tensor(&rand_t(&mut s.rng, &[n, sdim], -1.0, 1.0)).unwrap();
    let view = rand_t(&mut s.rng, &[n, vdim], -1.0, 1.0);
    let w = rand_t(&mut s.rng, &[n, 4], -1.0, 1.0);
    let loss = || {
        let o = field.forward(input.as_tensor(), &view, K, false).unwrap();
        (Tensor::cat(&[&o.rgb, &o.sigma_raw], 1).unwrap() * &w)
            .unwrap()
            .sum_all()
            .unwrap()
    };
    for (name, v) in [
        ("input S", &input),
        ("pts_linears.0", &s.vars["pts_linears.0.weight"]),
        ("sigma_linear", &s.vars["sigma_linear.weight"]),
        ("views_linears.0", &s.vars["views_linears.0.weight"]),
        ("rgb_linear", &s.vars["rgb_linear.bias"]),
    ] {
        let e = check(&format!("field: {name}"), v, &loss, 1e-6, &mut s.rng);
        assert!(e < TOL, "{name}: {e:e}");
    }

    for (case, len) in [("unit", 1.0), ("length 50", 50.0)] {
        let d = Var::from_tensor(&rand_t(&mut s.rng, &[4, 3], -len, len)).unwrap();
        let w = rand_t(&mut s.rng, &[4, 16], -1.0, 1.0);
        let loss = || {
            (spherical_harmonics(d.as_tensor(), 4).unwrap() * &w)
                .unwrap()
                .sum_all()
                .unwrap()
        };
        let e = check(
            &format!("spherical harmonics {case}"),
            &d,
            &loss,
            1e-6,
            &mut s.rng,
        );
        assert!(e < TOL, "{case}: {e:e}");
    }

    // Compositing: moderate densities, and stiff ones (σδ up to ~1e3).
    for (case, hi) in [("sigma 0..2", 2.0), ("sigma 0..1e4", 1e4)] {
        let m = 6;
        let raw = Var::from_tensor(&rand_t(&mut s.rng, &[3, m, 4], 0.0, 1.0)).unwrap();
        let sig = rand_t(&mut s.rng, &[3, m, 1], 0.0, hi);
        let raw_in = || {
            let r = raw.as_tensor();
            Tensor::cat(
                &[
                    &r.narrow(2, 0, 3).unwrap(),
                    &(r.narrow(2, 3, 1).unwrap() * &sig).unwrap(),
                ],
                2,
            )
            .unwrap()
        };
        let z = Tensor::from_vec(
            (0..3 * m)
                .map(|k| 1.0 + 0.1 * (k % m) as f64)
                .collect::<Vec<_>>(),
            (3, m),
            &DEV,
        )
        .unwrap();
        let d = rand_t(&mut s.rng, &[3, 3], 0.5, 1.0);
        let bg = rand_t(&mut s.rng, &[3, 3], 0.0, 1.0);
        let w = rand_t(&mut s.rng, &[3, 3], -1.0, 1.0);
        let loss = || {
            let o = raw2outputs(&raw_in(), &z, &d, Some(&bg)).unwrap();
            ((o.rgb * &w).unwrap().sum_all().unwrap() + o.acc.sum_all().unwrap()).unwrap()
        };
        let h = if hi > 2.0 { 1e-9 } else { 1e-6 };
        let e = check(&format!("compositing {case}"), &raw, &loss, h, &mut s.rng);
        assert!(e < 1e-4, "{case}: {e:e}");
    }
}
