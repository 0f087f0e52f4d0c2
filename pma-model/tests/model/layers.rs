//! Layer-level parity with the torch fixtures in `fixtures/layers` (see the README there).
//!
//! Each fixture case holds the inputs, the torch float32 outputs and the gradients of
//! `loss = sum_k sum(out_k * lossw_k)` w.r.t. the module's parameters and inputs, computed by an
//! independent torch implementation that was itself checked against the official reference's
//! outputs. The modules run on the tiny checkpoint `model_tiny.safetensors`.
//!
//! Tolerance per element: `|rust - torch| <= 5 f32_err + 1e-5 max|torch| + 1e-4 |torch|`, where
//! `f32_err` (manifest) is how far torch float32 is from torch float64 on the same inputs.
//! For well-conditioned arrays of magnitude ~1 this is the usual 1e-5 absolute / 1e-4
//! relative; the `f32_err` term only grows where float32 itself cannot do better (sine
//! arguments of order 1e3-1e4 in the far-outside-range cases), and the `max|torch|` term scales
//! the absolute part with arrays whose natural size is far from 1 (gradients of 1e-6 or 1e5).
//! The factor 5: two float32 implementations with different summation orders differ by more
//! than either differs from float64 where 1-ulp input differences are amplified (x̄ up to ~40
//! through sin(16 W x̄) in the full forward); up to 4x f32_err was measured there.

use std::collections::HashMap;
use std::path::PathBuf;

use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Tensor, Var, D};
use candle_nn::{VarBuilder, VarMap};
use serde_json::Value;

use pma_data::skeleton::Joints;
use pma_model::network::checkpoint;
use pma_model::network::config::Config;
use pma_model::network::encoders::{pose6d, spherical_harmonics, PointEnc};
use pma_model::network::field::{Field, FrameCodes};
use pma_model::network::gnn::{GnnSine, GnnTrace};
use pma_model::network::modulator::{Modulation, Modulator, PoseExtractor};
use pma_model::network::window::{aggregate, spatial_window, WinFun};
use pma_model::render::avatar::{Avatar, Mode, Poses, Rays, Trace};
use pma_model::render::raycast::{merge_raw, merge_sorted, RayCaster};
use pma_model::render::volume::raw2outputs;
use pma_model::train::loss::{training_loss, LossWeights};

/// The parity numerics (the default) for the layers called one by one.
const K: pma_model::compute::numerics::Numerics = pma_model::compute::numerics::Numerics::PARITY;

fn fixture_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../fixtures/layers")
}

fn manifest() -> Value {
    let path = fixture_dir().join("manifest.json");
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_str(&text).expect("manifest.json is JSON")
}

/// One fixture file and its manifest entry.
struct Fixture {
    name: String,
    tensors: HashMap<String, Tensor>,
    cases: Value,
}

fn fixture(name: &str) -> Fixture {
    let m = manifest();
    let entry = m["files"]
        .as_array()
        .expect("manifest files")
        .iter()
        .find(|f| f["file"] == format!("{name}.safetensors"))
        .unwrap_or_else(|| panic!("{name}.safetensors not in the manifest"))
        .clone();
    let path = fixture_dir().join(format!("{name}.safetensors"));
    let tensors = candle_core::safetensors::load(&path, &Device::Cpu)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    Fixture {
        name: name.to_string(),
        tensors,
        cases: entry["cases"].clone(),
    }
}

impl Fixture {
    fn get(&self, case: &str, key: &str) -> Tensor {
        let k = format!("{case}/{key}");
        self.tensors
            .get(&k)
            .unwrap_or_else(|| panic!("{}: no tensor {k}", self.name))
            .clone()
    }

    fn input(&self, case: &str, key: &str) -> Tensor {
        self.get(case, &format!("in/{key}"))
    }

    fn host(&self, case: &str, key: &str) -> Vec<f32> {
        flat_f32(&self.get(case, key))
    }

    fn meta(&self, case: &str, key: &str) -> &Value {
        let v = &self.cases[case]["arrays"][key];
        assert!(
            !v.is_null(),
            "{}: no manifest entry for {case}/{key}",
            self.name
        );
        v
    }

    /// Compare `actual` with the stored `case/key` under the tolerance of the module docs.
    fn check(&self, case: &str, key: &str, actual: &[f32]) {
        let expected = self.host(case, key);
        let meta = self.meta(case, key);
        let f32_err = meta["f32_err"].as_f64().unwrap_or(0.0);
        let max_abs = meta["max_abs"].as_f64().unwrap_or(0.0);
        let what = format!("{}/{case}/{key}", self.name);
        assert_close(&what, actual, &expected, f32_err, max_abs);
    }

    fn check_t(&self, case: &str, key: &str, actual: &Tensor) {
        let expected_shape = self.get(case, key).dims().to_vec();
        assert_eq!(
            actual.elem_count(),
            expected_shape.iter().product::<usize>(),
            "{}/{case}/{key}: shape {:?} vs expected {:?}",
            self.name,
            actual.dims(),
            expected_shape
        );
        self.check(case, key, &flat_f32(actual));
    }

    /// Integer / boolean outputs must match exactly.
    fn check_exact(&self, case: &str, key: &str, actual: &[i64]) {
        let expected: Vec<i64> = self
            .get(case, key)
            .to_dtype(DType::I64)
            .and_then(|t| t.flatten_all())
            .and_then(|t| t.to_vec1())
            .expect("integer fixture");
        assert_eq!(actual, expected.as_slice(), "{}/{case}/{key}", self.name);
    }

    /// Backpropagates the case's loss over `outs` (checked against torch's) and checks the
    /// gradients of the parameters the case lists (read from `vm`) and of `inputs`.
    fn check_backward(
        &self,
        case: &str,
        outs: &[(&str, &Tensor)],
        vm: &VarMap,
        inputs: &[(&str, &Var)],
    ) {
        let loss = self.loss(case, outs);
        self.check_t(case, "out/loss", &loss);
        let grads = loss.backward().unwrap();
        check_grads(self, case, &grads, &var_param(vm), inputs);
    }

    fn option(&self, case: &str, key: &str) -> Value {
        self.cases[case]["options"][key].clone()
    }

    /// The case's scalar loss `sum_k sum(out_k * lossw_k)`; `outs` must name exactly the
    /// case's loss keys, so a test cannot silently drop a term.
    fn loss(&self, case: &str, outs: &[(&str, &Tensor)]) -> Tensor {
        let mut keys: Vec<&str> = self.cases[case]["loss_keys"]
            .as_array()
            .expect("loss_keys")
            .iter()
            .map(|v| v.as_str().unwrap())
            .collect();
        let mut given: Vec<&str> = outs.iter().map(|(k, _)| *k).collect();
        keys.sort_unstable();
        given.sort_unstable();
        assert_eq!(given, keys, "{}/{case}: loss terms", self.name);
        let mut total = Tensor::zeros((), DType::F32, &Device::Cpu).unwrap();
        for (k, out) in outs {
            let w = self.get(case, &format!("lossw/{k}"));
            let w = w
                .reshape(out.dims())
                .unwrap_or_else(|e| panic!("{}/{case}/lossw/{k}: {e}", self.name));
            total = (total + (*out * w).unwrap().sum_all().unwrap()).unwrap();
        }
        total
    }
}

fn flat_f32(t: &Tensor) -> Vec<f32> {
    t.to_dtype(DType::F32)
        .and_then(|t| t.flatten_all())
        .and_then(|t| t.to_vec1())
        .expect("f32 data")
}

fn assert_close(what: &str, actual: &[f32], expected: &[f32], f32_err: f64, max_abs: f64) {
    assert_eq!(
        actual.len(),
        expected.len(),
        "{what}: {} values vs {} expected",
        actual.len(),
        expected.len()
    );
    let mut bad = 0usize;
    // (excess over the tolerance, index, got, expected)
    let mut worst = (0f64, 0usize, 0f64, 0f64);
    for (i, (&a, &e)) in actual.iter().zip(expected).enumerate() {
        let (a, e) = (a as f64, e as f64);
        let excess = if e.is_finite() {
            let tol = 5.0 * f32_err + 1e-5 * max_abs + 1e-4 * e.abs();
            let d = (a - e).abs();
            if d <= tol {
                continue;
            }
            if d.is_nan() {
                f64::INFINITY
            } else {
                d / tol.max(f64::MIN_POSITIVE)
            }
        } else if (a.is_nan() && e.is_nan()) || a == e {
            continue;
        } else {
            f64::INFINITY
        };
        bad += 1;
        if excess >= worst.0 {
            worst = (excess, i, a, e);
        }
    }
    let (_, i, a, e) = worst;
    assert!(
        bad == 0,
        "{what}: {bad} of {} values outside tolerance; worst at flat index {i}: got {a}, expected {e} \
         (f32_err {f32_err:e}, max|ref| {max_abs:e})",
        actual.len()
    );
}

fn tiny_checkpoint() -> checkpoint::Checkpoint {
    let path = fixture_dir().join("model_tiny.safetensors");
    checkpoint::load(&path, &Device::Cpu).unwrap_or_else(|e| panic!("{e}"))
}

fn tiny_config() -> Config {
    tiny_checkpoint().config
}

/// The tiny checkpoint's tensors as variables (so gradients can be read back by name), with
/// some of them replaced, and a builder over them for the modules' `load`.
fn tiny_vars(overrides: &[(&str, &Tensor)]) -> (VarMap, VarBuilder<'static>) {
    let mut tensors = tiny_checkpoint().tensors;
    for (name, t) in overrides {
        assert!(
            tensors.contains_key(*name),
            "override of unknown tensor {name}"
        );
        tensors.insert(name.to_string(), (*t).clone());
    }
    let vm = VarMap::new();
    {
        let mut data = vm.data().lock().unwrap();
        for (name, t) in tensors {
            data.insert(name, Var::from_tensor(&t).unwrap());
        }
    }
    let vb = VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu);
    (vm, vb)
}

/// Gradient of `t`, or zeros where nothing depends on it (torch reports zeros there too).
fn grad_or_zeros(grads: &GradStore, t: &Tensor) -> Tensor {
    grads
        .get(t)
        .cloned()
        .unwrap_or_else(|| t.zeros_like().unwrap())
}

/// Check the gradients of every parameter and input the case lists.
fn check_grads(
    fx: &Fixture,
    case: &str,
    grads: &GradStore,
    params: &dyn Fn(&str) -> Tensor,
    inputs: &[(&str, &Var)],
) {
    let listed = |key: &str| -> Vec<String> {
        fx.cases[case][key]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_str().unwrap().to_string())
            .collect()
    };
    for name in listed("params") {
        fx.check_t(
            case,
            &format!("grad/{name}"),
            &grad_or_zeros(grads, &params(&name)),
        );
    }
    let wanted = listed("grad_inputs");
    let mut given: Vec<String> = inputs.iter().map(|(k, _)| k.to_string()).collect();
    given.sort();
    let mut expected = wanted.clone();
    expected.sort();
    assert_eq!(given, expected, "{}/{case}: input gradients", fx.name);
    for (name, var) in inputs {
        fx.check_t(
            case,
            &format!("grad_in/{name}"),
            &grad_or_zeros(grads, var.as_tensor()),
        );
    }
}

fn var_param(vm: &VarMap) -> impl Fn(&str) -> Tensor + '_ {
    move |name: &str| {
        vm.data()
            .lock()
            .unwrap()
            .get(name)
            .unwrap_or_else(|| panic!("no variable {name}"))
            .as_tensor()
            .clone()
    }
}

fn input_var(fx: &Fixture, case: &str, key: &str) -> Var {
    Var::from_tensor(&fx.input(case, key)).unwrap()
}

fn joints(bones: &Tensor) -> Vec<Joints> {
    let (p, j, _) = bones.dims3().unwrap();
    assert_eq!(j, 24);
    let v = flat_f32(bones);
    (0..p)
        .map(|i| {
            let mut out = [[0f32; 3]; 24];
            for (k, o) in out.iter_mut().enumerate() {
                o.copy_from_slice(&v[(i * 24 + k) * 3..(i * 24 + k) * 3 + 3]);
            }
            out
        })
        .collect()
}

// ------------------------------------------------------------------------------------------
// Fixture set and checkpoint
// ------------------------------------------------------------------------------------------

#[test]
fn fixtures_stay_small() {
    let m = manifest();
    let mut total = std::fs::metadata(fixture_dir().join("manifest.json"))
        .unwrap()
        .len();
    total += std::fs::metadata(fixture_dir().join("model_tiny.safetensors"))
        .unwrap()
        .len();
    for f in m["files"].as_array().unwrap() {
        let path = fixture_dir().join(f["file"].as_str().unwrap());
        let len = std::fs::metadata(&path)
            .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
            .len();
        assert_eq!(
            Some(len),
            f["bytes"].as_u64(),
            "{}: size differs from the manifest",
            path.display()
        );
        total += len;
    }
    assert!(
        total < 2_000_000,
        "layer fixtures take {total} bytes; the budget is 2 MB"
    );
}

#[test]
fn tiny_checkpoint_loads_with_its_config() {
    let ckpt = tiny_checkpoint();
    let m = manifest();
    let expected: Config =
        serde_json::from_value(m["checkpoint"]["config"].clone()).expect("config JSON");
    assert_eq!(ckpt.config, expected);
    let gw = ckpt.config.gnn_width;
    assert_eq!(
        ckpt.tensors["graph_net.layers.1.lin.weight"].dims(),
        [24, gw, gw]
    );
    assert_ne!(ckpt.config, Config::paper());
    assert_eq!(ckpt.meta.format_version, Some(1));
    assert_eq!(
        ckpt.tensors.len(),
        checkpoint::tensor_layout(&ckpt.config).len()
    );
}

// ------------------------------------------------------------------------------------------
// Ray caster
// ------------------------------------------------------------------------------------------

fn ray_caster(cfg: &Config) -> RayCaster {
    let ckpt = tiny_checkpoint();
    RayCaster::from_tensor(cfg, &ckpt.tensors["raycast.transforms"]).expect("ray caster")
}

/// The fixtures carry per-ray copies of the pose data (as the reference's data loader); the
/// ray caster takes them once per pose.
fn first_row<const N: usize>(t: &Tensor) -> Vec<f32> {
    flat_f32(&t.get(0).unwrap())[..N].to_vec()
}

#[test]
fn raycast_near_far_and_coarse_samples() {
    let fx = fixture("raycast");
    let cfg = tiny_config();
    let rc = ray_caster(&cfg);
    for case in ["mixed", "all_miss"] {
        let o = flat_f32(&fx.input(case, "rays_o"));
        let d = flat_f32(&fx.input(case, "rays_d"));
        let skts = first_row::<{ 24 * 16 }>(&fx.input(case, "skts"));
        let cyls = first_row::<5>(&fx.input(case, "cyls"));
        let scales = flat_f32(&fx.input(case, "scales"));
        let b = rc
            .near_far(&o, &d, &cyls, &skts, &scales)
            .expect("near_far");
        fx.check(case, "out/near", &b.near);
        fx.check(case, "out/far", &b.far);
        fx.check_exact(
            case,
            "out/box_hit",
            &b.box_hit.iter().map(|&h| h as i64).collect::<Vec<_>>(),
        );
        fx.check_exact(
            case,
            "out/ray_hits_body",
            &b.ray_hits_body
                .iter()
                .map(|&h| h as i64)
                .collect::<Vec<_>>(),
        );
        let z = rc.coarse_z(&b.near, &b.far).expect("coarse_z");
        fx.check(case, "out/z_vals", &z);
        let pts =
            pma_model::render::raycast::sample_points(&o, &d, &z, cfg.n_samples).expect("points");
        fx.check(case, "out/pts", &pts);
    }
}

#[test]
fn raycast_mixed_case_covers_every_ray_kind() {
    // Guards the fixture itself: hits, cylinder-only rays and cylinder misses must all occur.
    let fx = fixture("raycast");
    let hits = fx.host("mixed", "out/ray_hits_body");
    assert!(hits.contains(&1.0) && hits.contains(&0.0));
}

#[test]
fn importance_sampling_and_merge() {
    let fx = fixture("raycast");
    let base = tiny_config();
    for (case, sc, sf) in [
        ("importance_tiny", base.n_samples, base.n_importance),
        ("importance_paper", 48, 24),
    ] {
        let cfg = Config {
            n_samples: sc,
            n_importance: sf,
            ..base.clone()
        };
        let rc = ray_caster(&cfg);
        let z = flat_f32(&fx.input(case, "z_vals"));
        let w = flat_f32(&fx.input(case, "weights"));
        let zi = rc.importance_z(&z, &w, None).expect("importance_z");
        fx.check(case, "out/z_samples", &zi);
        let (z_all, perm) = merge_sorted(&z, sc, &zi, sf).expect("merge");
        fx.check(case, "out/z_vals_merged", &z_all);
        fx.check_exact(
            case,
            "out/sorted_idxs",
            &perm.iter().map(|&p| p as i64).collect::<Vec<_>>(),
        );
    }
}

// ------------------------------------------------------------------------------------------
// Volume rendering
// ------------------------------------------------------------------------------------------

#[test]
fn raw2outputs_matches_torch() {
    let fx = fixture("render");
    let case = "mixed";
    let raw = Var::from_tensor(&fx.input(case, "raw")).unwrap();
    let bgs = fx.input(case, "bgs");
    let r = raw2outputs(
        raw.as_tensor(),
        &fx.input(case, "z_vals"),
        &fx.input(case, "rays_d"),
        Some(&bgs),
    )
    .expect("raw2outputs");
    fx.check_t(case, "out/rgb_map", &r.rgb);
    fx.check_t(case, "out/acc_map", &r.acc);
    fx.check_t(case, "out/disp_map", &r.disp);
    fx.check_t(case, "out/depth_map", &r.depth);
    fx.check_t(case, "out/weights", &r.weights);
    fx.check_t(case, "out/alpha", &r.alpha);
    let loss = fx.loss(
        case,
        &[
            ("rgb_map", &r.rgb),
            ("acc_map", &r.acc),
            ("weights", &r.weights),
            ("depth_map", &r.depth),
        ],
    );
    fx.check_t(case, "out/loss", &loss);
    let grads = loss.backward().unwrap();
    fx.check_t(
        case,
        "grad_in/raw",
        grads.get(raw.as_tensor()).expect("gradient of raw"),
    );
}

/// The non-network stages of the full forward (ray casting, both renders, importance sampling
/// and the merge), chained on the stored network outputs of the forward fixture.
#[test]
fn forward_sampling_and_render_stages() {
    let fx = fixture("forward");
    let cfg = tiny_config();
    let rc = ray_caster(&cfg);
    for case in ["one_pose", "two_poses"] {
        let n_poses = fx.host(case, "in/n_unique")[0] as usize;
        let o = fx.input(case, "rays_o");
        let d = fx.input(case, "rays_d");
        let n_rays = o.dims()[0];
        let per_pose = n_rays / n_poses;
        let rows: Vec<u32> = (0..n_poses).map(|p| (p * per_pose) as u32).collect();
        let rows = Tensor::new(rows.as_slice(), &Device::Cpu).unwrap();
        let skts = fx.input(case, "skts").index_select(&rows, 0).unwrap();
        let cyls = fx.input(case, "cyls").index_select(&rows, 0).unwrap();
        let scales = fx.get(case, "out/coarse/axis_scale");
        let coarse = rc.cast(&o, &d, &cyls, &skts, &scales).expect("cast");
        let bounds = coarse.bounds.as_ref().unwrap();
        fx.check(case, "out/raycast/near", &bounds.near);
        fx.check(case, "out/raycast/far", &bounds.far);
        let hits: Vec<i64> = bounds.box_hit.iter().map(|&h| h as i64).collect();
        fx.check_exact(case, "out/raycast/box_hit", &hits);
        fx.check_t(case, "out/raycast/z_vals_coarse", &coarse.z);

        let bgs = fx.input(case, "bgs");
        let raw0 = fx.get(case, "out/render_coarse/raw");
        let r0 = raw2outputs(&raw0, &coarse.z, &d, Some(&bgs)).expect("coarse render");
        for (key, t) in [
            ("rgb_map", &r0.rgb),
            ("acc_map", &r0.acc),
            ("disp_map", &r0.disp),
            ("weights", &r0.weights),
            ("alpha", &r0.alpha),
        ] {
            fx.check_t(case, &format!("out/render_coarse/{key}"), t);
        }

        let fine = rc
            .resample(&o, &d, &coarse.z, &r0.weights, None)
            .expect("resample");
        fx.check_t(case, "out/raycast/z_is", &fine.z);
        fx.check_t(case, "out/raycast/z_vals_merged", &fine.z_all);
        let perm: Vec<i64> = flat_f32(&fine.perm).iter().map(|&p| p as i64).collect();
        fx.check_exact(case, "out/raycast/sorted_idxs", &perm);
        let raw_all =
            merge_raw(&raw0, &fx.get(case, "out/fine/raw"), &fine.perm, K).expect("merge_raw");
        fx.check_t(case, "out/render_fine/raw", &raw_all);
        let r1 = raw2outputs(&raw_all, &fine.z_all, &d, Some(&bgs)).expect("fine render");
        for (key, t) in [
            ("rgb_map", &r1.rgb),
            ("acc_map", &r1.acc),
            ("disp_map", &r1.disp),
            ("weights", &r1.weights),
            ("alpha", &r1.alpha),
        ] {
            fx.check_t(case, &format!("out/render_fine/{key}"), t);
        }
    }
}

// ------------------------------------------------------------------------------------------
// GNN, 6D pose embedding, axis scales
// ------------------------------------------------------------------------------------------

#[test]
fn gnn_matches_torch() {
    let fx = fixture("gnn");
    let cfg = tiny_config();
    let (vm, vb) = tiny_vars(&[]);
    let gnn = GnnSine::new(vb.pp("graph_net"), &cfg).unwrap();
    for case in ["normal", "far", "degenerate"] {
        let theta = input_var(&fx, case, "theta");
        let mut trace = GnnTrace::new();
        let g = gnn.forward(theta.as_tensor(), Some(&mut trace)).unwrap();
        fx.check_t(case, "out/gnn_feat", &g);
        assert_eq!(trace.len(), cfg.gnn_graph_layers + cfg.gnn_fc_layers);
        for (l, pre) in trace.iter().enumerate() {
            fx.check_t(case, &format!("out/pre_sin_{l}"), pre);
        }
        fx.check_backward(case, &[("gnn_feat", &g)], &vm, &[("theta", &theta)]);
    }
}

#[test]
fn pose6d_matches_torch() {
    let fx = fixture("gnn");
    let bones = joints(&fx.input("pose6d", "bones"));
    let theta = pose6d(&bones, &Device::Cpu).unwrap();
    fx.check_t("pose6d", "out/pose6d", &theta);
}

#[test]
fn axis_scale_straight_through_floor() {
    check_axis_scale_case("floor");
}

/// Raw scales exactly 0: torch's d|a|/da is 0 there (docs/numerics.md, "Densities and alpha"),
/// so the regulariser does not push such an entry either way.
#[test]
fn axis_scale_gradient_is_zero_at_zero() {
    check_axis_scale_case("zero");
}

fn check_axis_scale_case(case: &str) {
    let fx = fixture("gnn");
    let cfg = tiny_config();
    {
        let raw = fx.input(case, "axis_scale");
        let base = fx.input(case, "base_scale");
        let (vm, vb) = tiny_vars(&[
            ("graph_net.axis_scale", &raw),
            ("graph_net.base_scale", &base),
        ]);
        let gnn = GnnSine::new(vb.pp("graph_net"), &cfg).unwrap();
        let s = gnn.axis_scale().unwrap();
        fx.check_t(case, "out/scale", &s);
        let volume = (pma_model::train::loss::box_volume(&s).unwrap()
            * LossWeights::default().scale)
            .unwrap();
        fx.check_t(case, "out/scale_loss", &volume);
        let loss = fx.loss(case, &[("scale", &s), ("scale_loss", &volume)]);
        let grads = loss.backward().unwrap();
        let a = var_param(&vm)("graph_net.axis_scale");
        fx.check_t(case, "grad_in/axis_scale", &grad_or_zeros(&grads, &a));
    }
}

// ------------------------------------------------------------------------------------------
// Encoders and the spatial window
// ------------------------------------------------------------------------------------------

/// x̄ = x̂ / s with the Rust effective scale; the division itself is the avatar's one-liner.
#[test]
fn normalised_coordinates_and_spatial_window() {
    let fx = fixture("encoders");
    let cfg = tiny_config();
    for case in ["window_normal", "window_extreme"] {
        let (vm, vb) = tiny_vars(&[]);
        let gnn = GnnSine::new(vb.pp("graph_net"), &cfg).unwrap();
        let x_hat = input_var(&fx, case, "x_hat");
        let x_bar = x_hat
            .as_tensor()
            .broadcast_div(&gnn.axis_scale().unwrap())
            .unwrap();
        fx.check_t(case, "out/x_bar", &x_bar);
        let w_p = spatial_window(&x_bar, cfg.window_alpha, cfg.window_beta).unwrap();
        fx.check_t(case, "out/w_p", &w_p);
        fx.check_backward(case, &[("x_bar", &x_bar)], &vm, &[("x_hat", &x_hat)]);
    }
}

#[test]
fn spatial_window_is_detached() {
    // w^p carries no gradient in the reference (docs/reference.md, "Paper versus code"): the
    // window cases above only pass their loss through x̄, so check the detachment directly.
    let fx = fixture("encoders");
    let cfg = tiny_config();
    let x = input_var(&fx, "window_normal", "x_hat");
    let w_p = spatial_window(x.as_tensor(), cfg.window_alpha, cfg.window_beta).unwrap();
    let grads = w_p.sum_all().unwrap().backward().unwrap();
    assert!(grads.get(x.as_tensor()).is_none());
}

#[test]
fn bone_aligned_embedding_through_the_avatar() {
    let fx = fixture("encoders");
    let case = "embed";
    let ckpt = tiny_checkpoint();
    let cfg = ckpt.config.clone();
    let avatar = Avatar::from_tensors(cfg.clone(), ckpt.tensors, &Device::Cpu).unwrap();
    let pts = input_var(&fx, case, "pts");
    let (r, s, _) = pts.as_tensor().dims3().unwrap();
    let skts = fx.input(case, "skts").narrow(0, 0, 1).unwrap();
    // The embedding does not depend on the pose's bones (only on skts); any bones will do.
    let poses = Poses {
        bones: vec![[[0.0; 3]; 24]],
        skts,
        cyls: Tensor::zeros((1, 5), DType::F32, &Device::Cpu).unwrap(),
    };
    let pose = avatar.pose_features(&poses, None).unwrap();
    let view_dim = cfg.sh_degree * cfg.sh_degree + cfg.framecode_ch;
    let view = Tensor::zeros((r * s, view_dim), DType::F32, &Device::Cpu).unwrap();
    let mut trace = Trace::default();
    avatar
        .network()
        .eval_points(
            &pose,
            0,
            &pts.as_tensor().reshape((r * s, 3)).unwrap(),
            &view,
            Some((&mut trace, "p")),
        )
        .unwrap();
    let t = |k: &str| trace.tensors[&format!("p/{k}")].clone();
    fx.check_t(case, "out/pts_jt", &t("pts_jt"));
    fx.check_t(case, "out/pts_t", &t("pts_t"));
    fx.check_t(case, "out/x_bar", &t("x_bar"));
    fx.check_t(case, "out/w_p", &t("w_p"));
    // view_dir_root (also in this case's loss) depends on neither pts nor the axis scales, so
    // the x̄ term alone carries the gradients checked here.
    let lw = fx.get(case, "lossw/x_bar");
    let loss = (t("x_bar") * lw).unwrap().sum_all().unwrap();
    let grads = loss.backward().unwrap();
    let params: HashMap<String, Var> = avatar.trainable().into_iter().collect();
    fx.check_t(
        case,
        "grad/graph_net.axis_scale",
        &grad_or_zeros(&grads, params["graph_net.axis_scale"].as_tensor()),
    );
    fx.check_t(case, "grad_in/pts", &grad_or_zeros(&grads, pts.as_tensor()));
}

#[test]
fn point_encoders_match_torch() {
    let fx = fixture("encoders");
    let cfg = tiny_config();
    for case in ["point_enc_normal", "point_enc_far"] {
        let (vm, vb) = tiny_vars(&[]);
        let enc_pose =
            PointEnc::new(vb.pp("pts_enc_pose"), cfg.point_enc_dim, cfg.sin_w0_pose).unwrap();
        let enc_point =
            PointEnc::new(vb.pp("pts_enc_point"), cfg.point_enc_dim, cfg.sin_w0_point).unwrap();
        let x_bar = input_var(&fx, case, "x_bar");
        let e = enc_pose.forward(x_bar.as_tensor(), K).unwrap();
        let z = enc_point.forward(x_bar.as_tensor(), K).unwrap();
        fx.check_t(case, "out/pts_enc_pose", &e);
        fx.check_t(case, "out/pts_enc_point", &z);
        fx.check_backward(
            case,
            &[("pts_enc_pose", &e), ("pts_enc_point", &z)],
            &vm,
            &[("x_bar", &x_bar)],
        );
    }
}

#[test]
fn spherical_harmonics_match_torch() {
    let fx = fixture("encoders");
    for case in ["sh_unit", "sh_non_unit"] {
        let dirs = input_var(&fx, case, "dirs");
        let sh = spherical_harmonics(dirs.as_tensor(), 4).unwrap();
        fx.check_t(case, "out/sh", &sh);
        let loss = fx.loss(case, &[("sh", &sh)]);
        let grads = loss.backward().unwrap();
        fx.check_t(
            case,
            "grad_in/dirs",
            &grad_or_zeros(&grads, dirs.as_tensor()),
        );
    }
}

// ------------------------------------------------------------------------------------------
// Feature window
// ------------------------------------------------------------------------------------------

#[test]
fn window_matches_torch() {
    let fx = fixture("window");
    let cfg = tiny_config();
    for case in ["normal", "zero_rows", "large"] {
        let (vm, vb) = tiny_vars(&[]);
        let win = WinFun::new(vb.pp("win_fun"), &cfg).unwrap();
        let g_feat = input_var(&fx, case, "gnn_feat");
        let e = input_var(&fx, case, "pts_enc_pose");
        let w_p = fx.input(case, "w_p");
        let g = win.project_pose(g_feat.as_tensor(), K).unwrap();
        fx.check_t(case, "out/win_layer_pose", &g);
        // All poses in one call: each pose's g applies to its block of points.
        let out = win.forward(&g, e.as_tensor(), &w_p, None, K).unwrap();
        let (w, f_m) = (out.w.clone(), aggregate(&out.w, &g).unwrap());
        fx.check_t(case, "out/win_maxpool", &out.pooled);
        fx.check_t(case, "out/win_logits", &out.logits);
        fx.check_t(case, "out/w_f", &out.w_f);
        fx.check_t(case, "out/w", &w);
        fx.check_t(case, "out/f_m", &f_m);
        fx.check_backward(
            case,
            &[("w", &w), ("f_m", &f_m)],
            &vm,
            &[("gnn_feat", &g_feat), ("pts_enc_pose", &e)],
        );
    }
}

// ------------------------------------------------------------------------------------------
// Pose extractor and modulator
// ------------------------------------------------------------------------------------------

#[test]
fn pose_extractor_matches_torch() {
    let fx = fixture("modulator");
    let cfg = tiny_config();
    for case in ["pose_extractor_normal", "pose_extractor_far"] {
        let (vm, vb) = tiny_vars(&[]);
        let pe = PoseExtractor::new(vb.pp("pose_extractor"), &cfg).unwrap();
        let modulator = Modulator::new(vb.pp("modulator"), &cfg).unwrap();
        let f_m = input_var(&fx, case, "f_m");
        let m = pe.forward(f_m.as_tensor(), K).unwrap();
        let theta = Tensor::stack(&m.freq, 0).unwrap();
        let phi = Tensor::stack(&m.phase, 0).unwrap();
        fx.check_t(case, "out/theta", &theta);
        fx.check_t(case, "out/phi", &phi);
        fx.check_t(case, "out/gamma", &modulator.gamma(&theta).unwrap());
        fx.check_backward(
            case,
            &[("theta", &theta), ("phi", &phi)],
            &vm,
            &[("f_m", &f_m)],
        );
    }
}

#[test]
fn modulator_matches_torch() {
    let fx = fixture("modulator");
    let cfg = tiny_config();
    // Θ, Φ as separate tensors (plain ops) and as views of one head output (the fused
    // FiLM-sine kernel the full model uses).
    for (case, fused) in ["normal", "extreme", "negative"]
        .into_iter()
        .flat_map(|c| [(c, false), (c, true)])
    {
        let (vm, vb) = tiny_vars(&[]);
        let modulator = Modulator::new(vb.pp("modulator"), &cfg).unwrap();
        let x_tilde = input_var(&fx, case, "x_tilde");
        let theta = input_var(&fx, case, "theta");
        let phi = input_var(&fx, case, "phi");
        let split = |t: &Tensor| (0..cfg.n_pm).map(|k| t.get(k).unwrap()).collect::<Vec<_>>();
        let (freq, phase) = (split(theta.as_tensor()), split(phi.as_tensor()));
        let m = if fused {
            let (k, w) = (cfg.n_pm, cfg.freq_dim);
            let o = Tensor::cat(&freq.iter().chain(&phase).collect::<Vec<_>>(), 1).unwrap();
            Modulation {
                freq: (0..k).map(|i| o.narrow(1, i * w, w).unwrap()).collect(),
                phase: (0..k)
                    .map(|i| o.narrow(1, (k + i) * w, w).unwrap())
                    .collect(),
                head: Some(o),
            }
        } else {
            Modulation {
                freq,
                phase,
                head: None,
            }
        };
        fx.check_t(
            case,
            "out/gamma",
            &modulator.gamma(theta.as_tensor()).unwrap(),
        );
        let s = modulator.forward(x_tilde.as_tensor(), &m, None, K).unwrap();
        fx.check_t(case, "out/S", &s);
        fx.check_backward(
            case,
            &[("S", &s)],
            &vm,
            &[("x_tilde", &x_tilde), ("theta", &theta), ("phi", &phi)],
        );
    }
}

// ------------------------------------------------------------------------------------------
// Density trunk, heads and frame codes
// ------------------------------------------------------------------------------------------

#[test]
fn field_and_frame_codes_match_torch() {
    let fx = fixture("field");
    let cfg = tiny_config();
    for case in ["train_codes", "mean_code", "far"] {
        let training = fx
            .option(case, "training")
            .as_bool()
            .expect("training option");
        let (vm, vb) = tiny_vars(&[]);
        let field = Field::new(vb.clone(), &cfg).unwrap();
        let codes = FrameCodes::new(vb.pp("framecodes"), &cfg).unwrap();
        let s = input_var(&fx, case, "S");
        let idx: Vec<i64> = fx.input(case, "frame_idx").to_vec1().unwrap();
        let code = codes.lookup(&idx, training, K).unwrap();
        fx.check_t(case, "out/framecode", &code);
        let sh = spherical_harmonics(&fx.input(case, "view_dirs"), cfg.sh_degree).unwrap();
        fx.check_t(case, "out/sh", &sh);
        let out = field
            .forward(
                s.as_tensor(),
                &Tensor::cat(&[&sh, &code], D::Minus1).unwrap(),
                K,
                true,
            )
            .unwrap();
        let density = out.sigma_raw.relu().unwrap();
        fx.check_t(
            case,
            "out/density_l0_pre_relu",
            out.l0_pre.as_ref().unwrap(),
        );
        fx.check_t(case, "out/density_feat", &out.feature);
        fx.check_t(case, "out/sigma_raw", &out.sigma_raw);
        fx.check_t(case, "out/density", &density);
        fx.check_t(case, "out/feature_linear", &out.feature_linear);
        fx.check_t(case, "out/view_l0_pre_relu", out.view_pre.as_ref().unwrap());
        fx.check_t(case, "out/rgb_logits", &out.rgb_logits);
        fx.check_t(case, "out/rgb", &out.rgb);
        if fx.cases[case]["loss_keys"].as_array().unwrap().is_empty() {
            continue;
        }
        fx.check_backward(
            case,
            &[
                ("sigma_raw", &out.sigma_raw),
                ("density", &density),
                ("rgb", &out.rgb),
            ],
            &vm,
            &[("S", &s)],
        );
    }
}

// ------------------------------------------------------------------------------------------
// Full forward and the training loss
// ------------------------------------------------------------------------------------------

#[test]
fn full_forward_and_training_gradients() {
    let fx = fixture("forward");
    let ckpt = tiny_checkpoint();
    let cfg = ckpt.config.clone();
    let avatar = Avatar::from_tensors(cfg.clone(), ckpt.tensors, &Device::Cpu).unwrap();
    for case in ["one_pose", "two_poses"] {
        assert_eq!(fx.option(case, "density_noise_std").as_f64(), Some(0.0));
        let n_poses = fx.host(case, "in/n_unique")[0] as usize;
        let origins = fx.input(case, "rays_o");
        let n_rays = origins.dim(0).unwrap();
        let per_pose = n_rays / n_poses;
        let rows: Vec<u32> = (0..n_poses).map(|p| (p * per_pose) as u32).collect();
        let rows = Tensor::new(rows.as_slice(), &Device::Cpu).unwrap();
        let pick = |key: &str| fx.input(case, key).index_select(&rows, 0).unwrap();
        let poses = Poses {
            bones: joints(&pick("bones")),
            skts: pick("skts"),
            cyls: pick("cyls"),
        };
        let rays = Rays {
            origins,
            dirs: fx.input(case, "rays_d"),
            bgs: Some(fx.input(case, "bgs")),
            framecodes: fx.input(case, "cam_idxs").to_vec1().unwrap(),
        };
        let mut opts = Mode::Train(None);
        let mut trace = Trace::default();
        let out = avatar
            .forward(
                &rays,
                &poses,
                &mut opts,
                &Default::default(),
                Some(&mut trace),
            )
            .unwrap();

        let bounds = out.bounds.as_ref().unwrap();
        fx.check(case, "out/raycast/near", &bounds.near);
        fx.check(case, "out/raycast/far", &bounds.far);
        let hits: Vec<i64> = bounds.box_hit.iter().map(|&h| h as i64).collect();
        fx.check_exact(case, "out/raycast/box_hit", &hits);
        fx.check_t(case, "out/raycast/z_vals_coarse", &out.z_coarse);
        fx.check_t(case, "out/raycast/z_vals_merged", &out.z_vals);
        let perm: Vec<i64> = flat_f32(&trace.tensors["raycast/sorted_idxs"])
            .iter()
            .map(|&p| p as i64)
            .collect();
        fx.check_exact(case, "out/raycast/sorted_idxs", &perm);
        for key in [
            "coarse/pose6d",
            "coarse/gnn_feat",
            "coarse/axis_scale",
            "coarse/x_bar",
            "coarse/w_p",
            "coarse/w",
            "coarse/f_m",
            "coarse/modulator_out",
            "coarse/sigma_raw",
            "coarse/rgb_logits",
            "fine/sigma_raw",
            "fine/rgb_logits",
        ] {
            let t = trace
                .tensors
                .get(key)
                .unwrap_or_else(|| panic!("trace has no {key}"));
            fx.check_t(case, &format!("out/{key}"), t);
        }
        // The trace holds one SH row per ray; the fixture one per coarse sample.
        let sh = trace.tensors["view_features"]
            .narrow(1, 0, cfg.sh_degree * cfg.sh_degree)
            .unwrap();
        let sh = sh
            .unsqueeze(1)
            .unwrap()
            .repeat((1, cfg.n_samples, 1))
            .unwrap();
        fx.check_t(case, "out/coarse/view_sh", &sh);
        fx.check_t(case, "out/render_coarse/raw", &out.raw_coarse);
        fx.check_t(case, "out/render_fine/raw", &out.raw);
        for (stage, r) in [("render_coarse", &out.coarse), ("render_fine", &out.fine)] {
            fx.check_t(case, &format!("out/{stage}/rgb_map"), &r.rgb);
            fx.check_t(case, &format!("out/{stage}/acc_map"), &r.acc);
            fx.check_t(case, &format!("out/{stage}/disp_map"), &r.disp);
            fx.check_t(case, &format!("out/{stage}/weights"), &r.weights);
            fx.check_t(case, &format!("out/{stage}/alpha"), &r.alpha);
        }

        let w = LossWeights::default();
        let loss = training_loss(&out, &fx.input(case, "target_s"), &w).unwrap();
        fx.check_t(case, "out/loss_fine", &loss.fine);
        fx.check_t(case, "out/loss_coarse", &loss.coarse);
        fx.check_t(case, "out/loss_scale", &(&loss.scale * w.scale).unwrap());
        fx.check_t(case, "out/loss", &loss.total);
        let grads = loss.total.backward().unwrap();
        let params: HashMap<String, Var> = avatar.trainable().into_iter().collect();
        assert_eq!(
            params.len(),
            fx.cases[case]["params"].as_array().unwrap().len()
        );
        check_grads(
            &fx,
            case,
            &grads,
            &|name: &str| params[name].as_tensor().clone(),
            &[],
        );
    }
}
