//! Layer-level parity with the torch fixtures in `fixtures/layers` (see the README there).
//!
//! Each fixture case holds the inputs, the torch float32 outputs and the gradients of
//! `loss = sum_k sum(out_k * lossw_k)` w.r.t. the module's parameters and inputs, computed by an
//! independent torch implementation that was itself checked against the official reference's
//! outputs. The modules run on the tiny checkpoint `model_tiny.safetensors`.
//!
//! Tolerance per element: `|rust - torch| <= 3 f32_err + 1e-5 max|torch| + 1e-4 |torch|`, where
//! `f32_err` (manifest) is how far torch float32 is from torch float64 on the same inputs.
//! For well-conditioned arrays of magnitude ~1 this is the usual 1e-5 absolute / 1e-4
//! relative; the `f32_err` term only grows where float32 itself cannot do better (sine
//! arguments of order 1e3-1e4 in the far-outside-range cases), and the `max|torch|` term scales
//! the absolute part with arrays whose natural size is far from 1 (gradients of 1e-6 or 1e5).

use std::collections::HashMap;
use std::path::PathBuf;

use candle_core::{DType, Device, Tensor, Var};
use serde_json::Value;

use pma_model::checkpoint;
use pma_model::config::Config;
use pma_model::raycast::{merge_raw, merge_sorted, RayCaster};
use pma_model::render::raw2outputs;

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

    #[allow(dead_code)]
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
            let tol = 3.0 * f32_err + 1e-5 * max_abs + 1e-4 * e.abs();
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
        let pts = pma_model::raycast::sample_points(&o, &d, &z, cfg.n_samples).expect("points");
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
        let zi = rc.importance_z(&z, &w).expect("importance_z");
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
        fx.check(case, "out/raycast/near", &coarse.bounds.near);
        fx.check(case, "out/raycast/far", &coarse.bounds.far);
        let hits: Vec<i64> = coarse.bounds.box_hit.iter().map(|&h| h as i64).collect();
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
            .resample(&o, &d, &coarse.z, &r0.weights)
            .expect("resample");
        fx.check_t(case, "out/raycast/z_is", &fine.z);
        fx.check_t(case, "out/raycast/z_vals_merged", &fine.z_all);
        let perm: Vec<i64> = flat_f32(&fine.perm).iter().map(|&p| p as i64).collect();
        fx.check_exact(case, "out/raycast/sorted_idxs", &perm);
        let raw_all =
            merge_raw(&raw0, &fx.get(case, "out/fine/raw"), &fine.perm).expect("merge_raw");
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
