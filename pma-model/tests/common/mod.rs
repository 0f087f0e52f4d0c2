//! Shared helpers for the golden-case tests.
#![allow(dead_code)]

use std::collections::HashMap;
use std::path::PathBuf;

use candle_core::{DType, Device, Tensor};
use pma_model::network::checkpoint;
pub use pma_model::render::avatar::PassOptions;
use pma_model::render::avatar::{Avatar, Mode, Outputs, Poses, Rays, Trace};

/// The device the golden cases run on: the CPU, or `PMA_TEST_DEVICE` (e.g. `cuda` for
/// scripts/gpu-check.sh with a `--features cuda` test binary).
pub fn test_device() -> Device {
    match std::env::var("PMA_TEST_DEVICE") {
        Ok(spec) => pma_model::compute::device::parse_device(&spec).expect("PMA_TEST_DEVICE"),
        Err(_) => Device::Cpu,
    }
}

/// The fixtures directory; `PMA_FIXTURES` overrides the build-time path (a test binary run
/// on another machine, scripts/gpu-check.sh).
pub fn fixtures() -> PathBuf {
    match std::env::var_os("PMA_FIXTURES") {
        Some(dir) => PathBuf::from(dir),
        None => PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../fixtures"),
    }
}

/// The tensors of `rel` under fixtures/golden/, on the CPU.
pub fn load_golden(rel: &str) -> HashMap<String, Tensor> {
    let path = fixtures().join("golden").join(rel);
    candle_core::safetensors::load(&path, &Device::Cpu)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The values of `key` in `g`, flattened, as `T`.
pub fn golden_values<T: candle_core::WithDType>(g: &HashMap<String, Tensor>, key: &str) -> Vec<T> {
    g.get(key)
        .unwrap_or_else(|| panic!("golden key {key} missing"))
        .flatten_all()
        .unwrap()
        .to_dtype(T::DTYPE)
        .unwrap()
        .to_vec1()
        .unwrap()
}

pub struct Golden(pub HashMap<String, Tensor>);

impl Golden {
    pub fn has(&self, k: &str) -> bool {
        self.0.contains_key(k)
    }
    pub fn t(&self, k: &str) -> &Tensor {
        self.0
            .get(k)
            .unwrap_or_else(|| panic!("golden array {k} missing"))
    }
    pub fn f32(&self, k: &str) -> Vec<f32> {
        flat(&self.t(k).to_dtype(DType::F32).unwrap())
    }
    pub fn i64_as_f32(&self, k: &str) -> Vec<f32> {
        self.t(k)
            .to_vec1::<i64>()
            .map(|v| v.into_iter().map(|x| x as f32).collect())
            .unwrap_or_else(|_| {
                self.t(k)
                    .flatten_all()
                    .unwrap()
                    .to_vec1::<i64>()
                    .unwrap()
                    .into_iter()
                    .map(|x| x as f32)
                    .collect()
            })
    }
}

pub fn flat(t: &Tensor) -> Vec<f32> {
    flat_as(t)
}

/// Every value of `t`, converted to `T`, in row-major order.
pub fn flat_as<T: candle_core::WithDType>(t: &Tensor) -> Vec<T> {
    t.to_dtype(T::DTYPE)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<T>()
        .unwrap()
}

/// The largest |a_i − b_i| of two equally long slices.
pub fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// The largest |a_i − b_i| of two equally long slices, NaN anywhere counting as infinite.
pub fn max_abs_err(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len(), "length mismatch");
    a.iter()
        .zip(b)
        .map(|(x, y)| {
            if x.is_nan() || y.is_nan() {
                f32::INFINITY
            } else {
                (x - y).abs()
            }
        })
        .fold(0.0, f32::max)
}

/// Rows `ray*S + s` of the subset rays from a [R*S, ...] tensor.
pub fn subset_rows(t: &Tensor, rays: &[usize], s: usize) -> Tensor {
    subset_samples(t, rays, s, 0)
}

/// Same along dim 1 of a [K, R*S, F] tensor.
pub fn subset_rows_dim1(t: &Tensor, rays: &[usize], s: usize) -> Tensor {
    subset_samples(t, rays, s, 1)
}

/// Indices `ray*S + s` of the subset rays' samples, selected along `dim`.
fn subset_samples(t: &Tensor, rays: &[usize], s: usize, dim: usize) -> Tensor {
    let idx: Vec<u32> = rays
        .iter()
        .flat_map(|&r| (0..s).map(move |k| (r * s + k) as u32))
        .collect();
    let idx = Tensor::from_vec(idx.clone(), idx.len(), t.device()).unwrap();
    t.contiguous().unwrap().index_select(&idx, dim).unwrap()
}

/// Per-ray features [R,F] repeated for each of the S samples of the subset rays.
pub fn per_sample(t: &Tensor, rays: &[usize], s: usize) -> Tensor {
    let idx: Vec<u32> = rays
        .iter()
        .flat_map(|&r| std::iter::repeat_n(r as u32, s))
        .collect();
    let idx = Tensor::from_vec(idx.clone(), idx.len(), t.device()).unwrap();
    t.contiguous().unwrap().index_select(&idx, 0).unwrap()
}

pub struct GoldenCase {
    pub golden: Golden,
    pub avatar: Avatar,
    pub rays: Rays,
    pub poses: Poses,
}

impl GoldenCase {
    /// dir: "golden" or "golden/dense" under fixtures/.
    pub fn load(dir: &str, sigma_override: bool) -> Self {
        let dev = test_device();
        let base = fixtures().join(dir);
        let golden =
            Golden(candle_core::safetensors::load(base.join("golden.safetensors"), &dev).unwrap());
        let ck = checkpoint::load(&fixtures().join("golden/model.safetensors"), &dev).unwrap();
        let mut tensors = ck.tensors;
        if sigma_override {
            let o = candle_core::safetensors::load(base.join("sigma_override.safetensors"), &dev)
                .unwrap();
            for (k, v) in o {
                assert!(
                    tensors.contains_key(&k),
                    "override {k} is not a model tensor"
                );
                tensors.insert(k, v);
            }
        }
        let avatar = Avatar::from_tensors(ck.config, tensors, &dev).unwrap();
        let (rays, poses) = golden_batch(&golden, &dev);
        Self {
            golden,
            avatar,
            rays,
            poses,
        }
    }

    pub fn subset_rays(&self) -> Vec<usize> {
        self.golden
            .t("input/subset_rays")
            .to_vec1::<i64>()
            .unwrap()
            .into_iter()
            .map(|x| x as usize)
            .collect()
    }

    /// Train-mode forward with density noise off, as the golden run (parity).
    pub fn forward(&self, trace: Option<&mut Trace>) -> Outputs {
        self.forward_with(&PassOptions::parity(), trace)
    }

    /// [`Self::forward`] leaving out what `opts` says.
    pub fn forward_with(&self, opts: &PassOptions, trace: Option<&mut Trace>) -> Outputs {
        let mut mode = Mode::Train(None);
        self.avatar
            .forward(&self.rays, &self.poses, &mut mode, opts, trace)
            .unwrap()
    }
}

/// The golden batch: per-ray copies of one pose, reduced to one pose as the reference's
/// striding does (N_unique = 1).
pub fn golden_batch(g: &Golden, dev: &Device) -> (Rays, Poses) {
    let bones = g.t("input/bones").get(0).unwrap().to_vec2::<f32>().unwrap();
    let mut joints = [[0f32; 3]; 24];
    for (d, s) in joints.iter_mut().zip(bones) {
        d.copy_from_slice(&s);
    }
    let poses = Poses {
        bones: vec![joints],
        skts: g
            .t("input/skts")
            .narrow(0, 0, 1)
            .unwrap()
            .to_device(dev)
            .unwrap(),
        cyls: g
            .t("input/cyls")
            .narrow(0, 0, 1)
            .unwrap()
            .to_device(dev)
            .unwrap(),
    };
    let rays = Rays {
        origins: g.t("input/rays_o").clone(),
        dirs: g.t("input/rays_d").clone(),
        bgs: Some(g.t("input/bgs").clone()),
        framecodes: g.t("input/cam_idxs").to_vec1::<i64>().unwrap(),
    };
    (rays, poses)
}

/// Collects per-array max errors and fails at the end with every violation listed.
#[derive(Default)]
pub struct Report {
    rows: Vec<(String, f32, f32, bool)>,
}

impl Report {
    /// Passes when |a−b| ≤ 1e-4·max(1, |b|) element-wise.
    pub fn cmp(&mut self, name: &str, ours: &[f32], reference: &[f32]) {
        assert_eq!(
            ours.len(),
            reference.len(),
            "{name}: {} values vs reference {}",
            ours.len(),
            reference.len()
        );
        let mut max_abs = 0f32;
        let mut max_scaled = 0f32;
        for (a, b) in ours.iter().zip(reference) {
            let d = (a - b).abs();
            let d = if d.is_nan() { f32::INFINITY } else { d };
            max_abs = max_abs.max(d);
            max_scaled = max_scaled.max(d / b.abs().max(1.0));
        }
        self.rows
            .push((name.to_string(), max_abs, max_scaled, max_scaled <= 1e-4));
    }

    pub fn finish(self, case: &str) {
        println!(
            "{:<40} {:>12} {:>12}",
            format!("[{case}] array"),
            "max abs",
            "max scaled"
        );
        for (n, a, s, ok) in &self.rows {
            println!(
                "{n:<40} {a:>12.3e} {s:>12.3e} {}",
                if *ok { "" } else { "FAIL" }
            );
        }
        let bad: Vec<_> = self
            .rows
            .iter()
            .filter(|r| !r.3)
            .map(|r| format!("{} ({:.3e})", r.0, r.2))
            .collect();
        assert!(bad.is_empty(), "{case}: arrays beyond tolerance: {bad:?}");
    }
}
