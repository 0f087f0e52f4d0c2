//! An opt-in vectorised sine for the SIREN and modulated layers (`--fast-sine`).
//!
//! candle evaluates `sin` (and `cos` in its backward) with one scalar libm call per value, a
//! large share of a paper-config pass on the CPU (`perf record`). Here the argument is reduced
//! by π/2 in f64 and sin/cos of the remainder come from Taylor polynomials in f64 (truncation
//! < 5e-17 on [-π/4, π/4]), written as straight-line lane-wise code the compiler vectorises
//! (AVX2 where the CPU has it). The result is the correctly rounded f32 sine up to rare
//! last-bit ties, so it can differ from the libm result in the last bit: it is an explicit
//! option, never the parity default, and its error against parity is measured (`pma bench`,
//! `throughput --fast-sine`).
//!
//! The reduction is exact enough while |x| ≤ 2^26 (see `PIO2_1`); larger and non-finite
//! arguments go to libm.

use candle_core::{CpuStorage, CustomOp1, DType, Layout, Shape, Tensor};

use crate::error::Result;

/// `sin(x)`: the vectorised kernel (`fast`, f32 CPU tensors) or, in parity mode, libm's bits
/// at vector speed ([`crate::compute::libm_sine`]); other devices and dtypes take candle's
/// `sin`, as do a CPU run accounted as CUDA ([`crate::compute::account`]) and parity mode
/// under `--generic-kernels`.
pub fn sin(x: &Tensor, fast: bool) -> Result<Tensor> {
    let libm_op = !fast && crate::compute::kernel::health::generic();
    if x.device().is_cpu()
        && x.dtype() == DType::F32
        && !crate::compute::account::emulates_cuda()
        && !libm_op
    {
        let x = x.contiguous()?;
        let cos = crate::compute::kernel::storage::Kept::new(x.track_op());
        Ok(x.apply_op1(Sine { fast, cos })?)
    } else {
        Ok(x.sin()?)
    }
}

/// sin (`shift` 0) or cos (`shift` 1) of every value: the vectorised kernel (`fast`) or
/// libm's values ([`crate::compute::libm_sine`]).
pub(crate) fn trig(x: &[f32], shift: u64, fast: bool) -> Vec<f32> {
    if fast {
        sin_or_cos(x, shift)
    } else {
        crate::compute::libm_sine::map(x, shift == 1)
    }
}

/// sin and cos of every value in one pass (libm's bits, or the vectorised kernel's).
pub(crate) fn trig_pair(x: &[f32], fast: bool) -> (Vec<f32>, Vec<f32>) {
    if fast {
        (sin_or_cos(x, 0), sin_or_cos(x, 1))
    } else {
        crate::compute::libm_sine::map_pair(x)
    }
}

const LIMIT: f64 = 67_108_864.0; // 2^26
/// 1.5 · 2^52: adding it rounds an f64 of magnitude < 2^51 to an integer, and the integer's
/// low bits land in the low mantissa bits (the quadrant), without a float→int conversion.
const ROUNDER: f64 = 6_755_399_441_055_744.0;
const TWO_OVER_PI: f64 = std::f64::consts::FRAC_2_PI;
/// π/2 = P1 + P2 + P3 (Cody–Waite): P1 and P2 carry 27 significant bits each, so n·P1 and
/// n·P2 are exact f64 products for |n| < 2^26 and the remainder keeps its accuracy even
/// next to a multiple of π, where sin(x) itself is tiny.
const PIO2_1: f64 = 1.570_796_325_802_803;
const PIO2_2: f64 = 9.920_935_739_593_517e-10;
const PIO2_3: f64 = 5.721_188_726_109_832e-18;

/// sin(r) and cos(r) for |r| ≤ π/4 (+ a hair), Horner form of the Taylor series.
#[inline(always)]
fn sin_cos_reduced(r: f64) -> (f64, f64) {
    let z = r * r;
    let s = r + r
        * z
        * (-1.0 / 6.0
            + z * (1.0 / 120.0
                + z * (-1.0 / 5040.0
                    + z * (1.0 / 362_880.0
                        + z * (-1.0 / 39_916_800.0
                            + z * (1.0 / 6_227_020_800.0 + z * (-1.0 / 1_307_674_368_000.0)))))));
    let c = 1.0
        + z * (-0.5
            + z * (1.0 / 24.0
                + z * (-1.0 / 720.0
                    + z * (1.0 / 40_320.0
                        + z * (-1.0 / 3_628_800.0
                            + z * (1.0 / 479_001_600.0
                                + z * (-1.0 / 87_178_291_200.0
                                    + z * (1.0 / 20_922_789_888_000.0))))))));
    (s, c)
}

/// sin(x) (`shift` 0) or cos(x) = sin(x + π/2) (`shift` 1, exact: a quadrant step).
#[inline(always)]
fn lane(x: f32, shift: u64) -> f32 {
    let xd = x as f64;
    let t = xd * TWO_OVER_PI + ROUNDER;
    let q = t.to_bits().wrapping_add(shift);
    let n = t - ROUNDER;
    let r = ((xd - n * PIO2_1) - n * PIO2_2) - n * PIO2_3;
    let (s, c) = sin_cos_reduced(r);
    let v = if q & 1 == 0 { s } else { c };
    let v = if q & 2 == 0 { v } else { -v };
    v as f32
}

#[inline(always)]
fn kernel_body(x: &[f32], out: &mut [f32], shift: u64) {
    for (o, &v) in out.iter_mut().zip(x) {
        *o = lane(v, shift);
    }
    // Arguments the reduction does not cover (huge or non-finite) take libm's answer.
    for (o, &v) in out.iter_mut().zip(x) {
        let covered = (v as f64).abs() <= LIMIT; // false for NaN as well
        if !covered {
            *o = if shift == 0 { v.sin() } else { v.cos() };
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn kernel_avx2(x: &[f32], out: &mut [f32], shift: u64) {
    kernel_body(x, out, shift)
}

/// sin (`shift` 0) or cos (`shift` 1) of every value. Every code path computes the same
/// IEEE operations (no contraction into FMA), so results do not depend on the CPU.
pub fn sin_or_cos(x: &[f32], shift: u64) -> Vec<f32> {
    let mut out = vec![0f32; x.len()];
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked above).
        unsafe { kernel_avx2(x, &mut out, shift) };
        return out;
    }
    kernel_body(x, &mut out, shift);
    out
}

/// `sin`, whose backward multiplies by cos of the same flavour: kept by the forward when
/// the graph tracks gradients (libm's recipe yields both for the price of one), else
/// computed by [`Cosine`].
struct Sine {
    fast: bool,
    cos: crate::compute::kernel::storage::Kept<Vec<f32>>,
}
struct Cosine {
    fast: bool,
}

impl CustomOp1 for Sine {
    fn name(&self) -> &'static str {
        "pma-sin"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
        let x = crate::compute::kernel::storage::f32_slice(s, l, "sine")?;
        let sin = if self.cos.wanted() {
            let (sin, cos) = trig_pair(x, self.fast);
            self.cos.put(cos);
            sin
        } else {
            trig(x, 0, self.fast)
        };
        Ok((CpuStorage::F32(sin), l.shape().clone()))
    }

    fn bwd(
        &self,
        arg: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<Option<Tensor>> {
        // candle's own rule for sin, `grad · cos(arg)`, so parity mode keeps its bits. The
        // kept cosine is used once (a second backward over the graph recomputes it).
        let cos = match self.cos.take() {
            Some(c) if c.len() == arg.elem_count() => {
                Tensor::from_vec(c, arg.shape(), arg.device())?
            }
            _ => arg.contiguous()?.apply_op1(Cosine { fast: self.fast })?,
        };
        Ok(Some(grad.mul(&cos)?))
    }
}

impl CustomOp1 for Cosine {
    fn name(&self) -> &'static str {
        "pma-cos"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
        let x = crate::compute::kernel::storage::f32_slice(s, l, "sine")?;
        Ok((CpuStorage::F32(trig(x, 1, self.fast)), l.shape().clone()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};

    /// Max error in units of the f32 spacing at the exact (f64) value.
    fn max_ulps(x: &[f32], shift: u64) -> f64 {
        let got = sin_or_cos(x, shift);
        x.iter()
            .zip(&got)
            .map(|(&v, &g)| {
                let exact = if shift == 0 {
                    (v as f64).sin()
                } else {
                    (v as f64).cos()
                };
                let ulp = f32::EPSILON as f64 * exact.abs().max(f32::MIN_POSITIVE as f64);
                (g as f64 - exact).abs() / ulp
            })
            .fold(0.0, f64::max)
    }

    fn grid(lo: f32, hi: f32, n: usize) -> Vec<f32> {
        (0..n)
            .map(|i| lo + (hi - lo) * (i as f32 / (n - 1) as f32))
            .collect()
    }

    #[test]
    fn sine_and_cosine_are_within_one_ulp_over_the_network_range() {
        // SIREN/modulated pre-activations in trained models stay within ±1e3; extreme
        // modulation frequencies (the stability suite's γ = 1e4) reach ±1e5.
        for (lo, hi) in [(-4.0, 4.0), (-1e3, 1e3), (-1e5, 1e5), (1e7, 6e7)] {
            let x = grid(lo, hi, 200_001);
            for shift in [0, 1] {
                let e = max_ulps(&x, shift);
                assert!(e <= 1.0, "[{lo}, {hi}] shift {shift}: {e} ulp");
            }
        }
    }

    #[test]
    fn at_least_as_close_as_libm_and_handles_special_values() {
        // Where the two differ (about 1 % of values, libm's sinf is not correctly rounded),
        // this kernel is the one nearer the exact value, or equally near.
        let x = grid(-200.0, 200.0, 1_000_001);
        let got = sin_or_cos(&x, 0);
        let (mut differ, mut libm_closer) = (0, 0);
        for (&v, &g) in x.iter().zip(&got) {
            let l = v.sin();
            if l != g {
                differ += 1;
                let exact = (v as f64).sin();
                if (l as f64 - exact).abs() < (g as f64 - exact).abs() {
                    libm_closer += 1;
                }
            }
        }
        println!("{differ} of {} differ from libm", x.len());
        assert_eq!(libm_closer, 0, "libm nearer on {libm_closer} of {differ}");
        assert!(
            differ * 20 < x.len(),
            "{differ} of {} differ from libm",
            x.len()
        );
        let special = [
            0.0f32,
            -0.0,
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            1e30,
            -3e9,
        ];
        let s = sin_or_cos(&special, 0);
        assert_eq!(s[0].to_bits(), 0f32.to_bits());
        assert!(s[2].is_nan() && s[3].is_nan() && s[4].is_nan());
        assert_eq!(s[5], 1e30f32.sin());
        assert_eq!(s[6], (-3e9f32).sin());
        let c = sin_or_cos(&special, 1);
        assert_eq!(c[0], 1.0);
        assert_eq!(c[5], 1e30f32.cos());
    }

    #[test]
    fn tensor_op_and_gradient_follow_sine() {
        let dev = Device::Cpu;
        let xs = grid(-30.0, 30.0, 1001);
        let x = Var::from_vec(xs.clone(), 1001, &dev).unwrap();
        // The op itself. With the cosine kept by the forward and without it (recomputed by the backward).
        for keep in [false, true] {
            let cos = crate::compute::kernel::storage::Kept::new(keep);
            let y = x.as_tensor().apply_op1(Sine { fast: true, cos }).unwrap();
            let g = y.sum_all().unwrap().backward().unwrap();
            let y = y.to_vec1::<f32>().unwrap();
            let dx = g.get(x.as_tensor()).unwrap().to_vec1::<f32>().unwrap();
            for ((v, s), d) in xs.iter().zip(&y).zip(&dx) {
                assert!((s - v.sin()).abs() <= 1.2e-7, "sin({v}) = {s}");
                assert!((d - v.cos()).abs() <= 1.2e-7, "cos({v}) = {d}");
            }
        }
        // Not fast (parity): libm's sine and cosine, bit for bit, forward and back. A second
        // backward over the same graph finds the kept cosine used and recomputes it.
        let y = sin(x.as_tensor(), false).unwrap();
        let loss = y.sum_all().unwrap();
        for pass in 0..2 {
            let g = loss.backward().unwrap();
            let dx = g.get(x.as_tensor()).unwrap().to_vec1::<f32>().unwrap();
            let y = y.to_vec1::<f32>().unwrap();
            for ((v, s), d) in xs.iter().zip(&y).zip(&dx) {
                assert_eq!(s.to_bits(), v.sin().to_bits(), "sin({v})");
                assert_eq!(d.to_bits(), v.cos().to_bits(), "cos({v}), pass {pass}");
            }
        }
    }
}
