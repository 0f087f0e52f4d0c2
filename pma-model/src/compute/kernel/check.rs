//! An op's kernels against its generic ops (candle's) on random inputs of awkward sizes:
//! the forward's outputs and every input's gradient under one random upstream gradient.
//! Runs before a module's first use on a device ([`super::health::ready`]) and in
//! `pma doctor`, on the device the kernels run on (a GPU, or the CPU of a run that takes the
//! CUDA route: the emulated grid).

use candle_core::{Device, Tensor, Var};

use super::Module;

/// How many cases a check runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Size {
    /// One small case (a module's first use).
    Quick,
    /// Every case: sizes that are not multiples of a block, a grid too small for one thread
    /// per element, no rows (`pma doctor`, the tests).
    Full,
}

/// A module's check: its cases on `device` (whose tensors take the kernels).
pub type CheckFn = fn(&Device, Size) -> crate::error::Result<Vec<Case>>;

/// One compared value of one case.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Case {
    /// The case and the value (`[1030,24,16] grad q`).
    pub what: String,
    /// max |kernel − generic| / max(1, max |generic|).
    pub max_err: f32,
    pub tol: f32,
}

impl Case {
    pub fn passed(&self) -> bool {
        self.max_err <= self.tol
    }
}

/// The relative error of every check: kernels sum in other orders than candle's ops and a
/// GPU's `sinf` is within 2 ulp; a kernel bug is off by far more.
pub const TOL: f32 = 1e-4;

/// Random values in `[lo, hi)` of `shape` on `device` (a fixed generator per seed).
pub fn random(
    shape: &[usize],
    seed: u64,
    (lo, hi): (f32, f32),
    device: &Device,
) -> crate::error::Result<Tensor> {
    let n: usize = shape.iter().product();
    let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let v: Vec<f32> = (0..n)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            lo + (s >> 40) as f32 / (1u64 << 24) as f32 * (hi - lo)
        })
        .collect();
    Ok(Tensor::from_vec(v, shape, device)?)
}

/// The cases `size` asks for: the first alone (a quick check), or all.
pub fn cases<T>(size: Size, all: &[T]) -> &[T] {
    match size {
        Size::Quick => &all[..1.min(all.len())],
        Size::Full => all,
    }
}

/// `op` on `inputs` (each made a variable) through `module`'s kernels and through the
/// generic ops: its output and the gradient of every input under `sum(out · up)`, compared
/// as [`Case`]s named `label out` / `label grad <name>`. With `blocks` > 0 the kernels' grid
/// is capped at that many blocks, said in the label: every thread then walks many elements
/// of its grid-stride loop.
pub fn compare_in(
    blocks: u32,
    module: &'static Module,
    label: &str,
    inputs: &[Tensor],
    names: &[&str],
    up: &Tensor,
    op: impl Fn(&[Tensor]) -> crate::error::Result<Tensor>,
) -> crate::error::Result<Vec<Case>> {
    let run = || -> crate::error::Result<Vec<Tensor>> {
        let vars: Vec<Var> = inputs
            .iter()
            .map(Var::from_tensor)
            .collect::<candle_core::Result<_>>()?;
        let ts: Vec<Tensor> = vars.iter().map(|v| v.as_tensor().clone()).collect();
        let out = op(&ts)?;
        let grads = (&out * up)?.sum_all()?.backward()?;
        let mut values = vec![out];
        for v in &vars {
            values.push(match grads.get(v) {
                Some(g) => g.clone(),
                None => v.as_tensor().zeros_like()?,
            });
        }
        Ok(values)
    };
    let (kernel, label) = match blocks {
        0 => (run()?, label.to_string()),
        _ => (
            super::launch::with_block_limit(blocks, run)?,
            format!("{label} in {blocks} blocks"),
        ),
    };
    let generic = super::health::generic_for(module, run)?;
    kernel
        .iter()
        .zip(&generic)
        .enumerate()
        .map(|(i, (k, g))| {
            let value = match i.checked_sub(1) {
                None => "out".to_string(),
                Some(j) => format!("grad {}", names.get(j).copied().unwrap_or("input")),
            };
            Ok(Case {
                what: format!("{label} {value}"),
                max_err: relative_error(k, g)?,
                tol: TOL,
            })
        })
        .collect()
}

/// max |a − b| / max(1, max |b|) (NaN where either holds a NaN the other does not).
pub fn relative_error(a: &Tensor, b: &Tensor) -> crate::error::Result<f32> {
    let flat = |t: &Tensor| -> candle_core::Result<Vec<f32>> {
        t.flatten_all()?
            .to_dtype(candle_core::DType::F32)?
            .to_vec1::<f32>()
    };
    let (a, b) = (flat(a)?, flat(b)?);
    if a.len() != b.len() {
        return Ok(f32::INFINITY);
    }
    let mut worst = 0f32;
    let mut scale = 1f32;
    for (x, y) in a.iter().zip(&b) {
        if x.is_nan() != y.is_nan() {
            return Ok(f32::NAN);
        }
        if !x.is_nan() {
            worst = worst.max((x - y).abs());
            scale = scale.max(y.abs());
        }
    }
    Ok(worst / scale)
}
