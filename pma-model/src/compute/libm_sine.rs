//! libm's own `sinf`/`cosf`, vectorised: the parity-mode sine at vector speed.
//!
//! Parity mode must produce the bits candle gets from `f32::sin`/`f32::cos`, one scalar libm
//! call per value, which `perf` puts at ~15 % of a paper-config training step. glibc (2.28 on)
//! computes these with a fixed double-precision recipe: one multiply-subtract by π/2 for
//! |x| < 120 (the quadrant from a scaled truncation), then a degree-7 sine or degree-8 cosine
//! polynomial on the remainder, rounded once to f32. The recipe is arithmetic only, so running
//! it lane-wise over a slice gives the same bits, and the compiler vectorises it.
//!
//! glibc builds the recipe twice: with fused multiply-adds (picked on CPUs with FMA) and
//! without. Which one (if either) this process's libm is, is settled once, at first use,
//! by comparing both against `f32::sin`/`f32::cos` on a fixed set of arguments that covers
//! every branch, the branch edges and the sign and quadrant cases. A libm that matches neither
//! (musl, macOS, an older glibc) keeps the scalar libm calls, so parity never depends on the
//! check passing. Arguments outside the fast range (|x| ≥ 120, inf, NaN) always go to libm.
//! `cargo run --release -p pma-model --example libm_sine_sweep` compares every f32.

use std::mem::MaybeUninit;
use std::sync::OnceLock;

/// An output slot: the kernels only write, so outputs may start uninitialised.
type Out = MaybeUninit<f32>;

/// 2/π · 2^24: the quadrant lands in bits 24 and up after truncation.
const HPI_INV: f64 = f64::from_bits(0x4164_5f30_6dc9_c883);
/// π/2 rounded to double.
const HPI: f64 = f64::from_bits(0x3ff9_21fb_5444_2d18);
/// Cosine polynomial 1 + c1·x² + … + c4·x⁸.
const C: [f64; 5] = [
    1.0,
    f64::from_bits(0xbfdf_ffff_fd0c_621c),
    f64::from_bits(0x3fa5_5553_e106_8f19),
    f64::from_bits(0xbf56_c087_e89a_359d),
    f64::from_bits(0x3ef9_9343_027b_f8c3),
];
/// Sine polynomial x + s1·x³ + s2·x⁵ + s3·x⁷.
const S: [f64; 3] = [
    f64::from_bits(0xbfc5_5554_5995_a603),
    f64::from_bits(0x3f81_1076_0523_0bc4),
    f64::from_bits(0xbf29_94eb_3774_cf24),
];
/// glibc compares the top 12 bits of |x|: below 0x398 (|x| < 2^-12) sin x = x and cos x = 1;
/// from 0x42f (|x| ≥ 120, and NaN) the fast reduction no longer applies. Both edges have
/// zero low bits, so plain comparisons of |x| are the same tests.
const TINY: f32 = 1.0 / 4096.0;
const LARGE: f32 = 120.0;

/// Which build of the recipe this process's libm matches.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Flavour {
    /// glibc's FMA build (multiply-adds fused, one rounding each).
    Fused,
    /// glibc's plain build (separate multiply and add).
    Plain,
    /// Neither: every value goes to libm.
    Libm,
}

/// The flavour in use, decided on first call.
pub fn flavour() -> Flavour {
    static F: OnceLock<Flavour> = OnceLock::new();
    *F.get_or_init(|| {
        let args = check_arguments();
        [Flavour::Fused, Flavour::Plain]
            .into_iter()
            .find(|&f| agrees(f, &args))
            .unwrap_or(Flavour::Libm)
    })
}

#[inline(always)]
fn madd<const FMA: bool>(a: f64, b: f64, c: f64) -> f64 {
    if FMA {
        a.mul_add(b, c)
    } else {
        a * b + c
    }
}

/// The recipe's shared part for one value in the fast range: the sine and cosine
/// polynomials of the remainder and the quadrant. Written without integer conversions or
/// branches so that it vectorises: glibc's quadrant `((int32) (x·hpi_inv) + 2^23) >> 24` is
/// `floor((trunc(x·hpi_inv) + 2^23) / 2^24)`, exact in f64, and its low two bits come from
/// `n − 4·floor(n/4)`.
#[inline(always)]
fn reduced<const FMA: bool>(y: f32) -> (f64, f64, f64) {
    let x = y as f64;
    let n = (((x * HPI_INV).trunc() + 8_388_608.0) * (1.0 / 16_777_216.0)).floor();
    let xr = madd::<FMA>(-n, HPI, x);
    let q = n - 4.0 * (n * 0.25).floor();
    let x2 = xr * xr;
    let x4 = x2 * x2;
    let c2 = madd::<FMA>(x2, C[4], C[3]);
    let c1 = madd::<FMA>(x2, C[1], C[0]);
    let x6 = x4 * x2;
    let c = madd::<FMA>(x6, c2, madd::<FMA>(x4, C[2], c1));
    let x3 = xr * x2;
    let s1 = madd::<FMA>(x2, S[2], S[1]);
    let x7 = x3 * x2;
    let s = madd::<FMA>(x7, s1, madd::<FMA>(x3, S[0], xr));
    (s, c, q)
}

/// sin (`cos` false) or cos (`cos` true) of `y` from [`reduced`]'s polynomials and quadrant.
#[inline(always)]
fn pick(y: f32, s: f64, c: f64, q: f64, cos: bool) -> f32 {
    // glibc negates the sine's argument in quadrants 1 and 2 and the cosine's coefficients
    // in quadrants 2 and 3. Both polynomials are odd or even under those negations and
    // rounding is symmetric, so the negation can move onto the result, exactly.
    let odd = (q == 1.0 || q == 3.0) != cos;
    let flip = if odd { q >= 2.0 } else { q == 1.0 || q == 2.0 };
    let v = if odd { c } else { s };
    let v = if flip { -v } else { v } as f32;
    if y.abs() < TINY {
        if cos {
            1.0
        } else {
            y
        }
    } else {
        v
    }
}

/// sin (`cos` false) or cos (`cos` true) of one value in the fast range by the recipe.
#[inline(always)]
fn lane<const FMA: bool>(y: f32, cos: bool) -> f32 {
    let (s, c, q) = reduced::<FMA>(y);
    pick(y, s, c, q, cos)
}

/// |v| ≥ 120 or NaN: libm's slow reduction.
#[inline(always)]
fn outside(v: f32) -> bool {
    v.abs() >= LARGE || v.is_nan()
}

/// Where a pass writes: one function (`cos` false: sine, true: cosine), or both.
enum Outs<'a> {
    One(&'a mut [Out], bool),
    /// Sine and cosine together: the recipe computes both polynomials anyway, so the
    /// cosine costs one more select and store.
    Both(&'a mut [Out], &'a mut [Out]),
}

#[inline(always)]
fn body<const FMA: bool>(x: &[f32], outs: Outs) {
    let mut large = 0u32;
    // One loop per case, so each stays a plain vectorisable loop.
    match outs {
        Outs::One(out, cos) => {
            // `cos` as a constant in each loop, so the unused selects fold away.
            large = if cos {
                fill(x, out, |v| lane::<FMA>(v, true))
            } else {
                fill(x, out, |v| lane::<FMA>(v, false))
            };
            if large != 0 {
                libm_where(x, Outs::One(out, cos), outside);
            }
        }
        Outs::Both(sin, cos) => {
            for ((os, oc), &v) in sin.iter_mut().zip(cos.iter_mut()).zip(x) {
                let (s, c, q) = reduced::<FMA>(v);
                os.write(pick(v, s, c, q, false));
                oc.write(pick(v, s, c, q, true));
                large |= u32::from(outside(v));
            }
            if large != 0 {
                libm_where(x, Outs::Both(sin, cos), outside);
            }
        }
    }
}

/// `out[i] = f(x[i])`; nonzero when some argument is outside the fast range.
#[inline(always)]
fn fill(x: &[f32], out: &mut [Out], f: impl Fn(f32) -> f32) -> u32 {
    let mut large = 0u32;
    for (o, &v) in out.iter_mut().zip(x) {
        o.write(f(v));
        large |= u32::from(outside(v));
    }
    large
}

/// libm's values for the arguments where `pick` holds.
fn libm_where(x: &[f32], outs: Outs, pick: impl Fn(f32) -> bool) {
    match outs {
        Outs::One(out, cos) => {
            for (o, &v) in out.iter_mut().zip(x).filter(|(_, &v)| pick(v)) {
                o.write(if cos { v.cos() } else { v.sin() });
            }
        }
        Outs::Both(sin, cos) => {
            let all = sin.iter_mut().zip(cos.iter_mut()).zip(x);
            for ((os, oc), &v) in all.filter(|(_, &v)| pick(v)) {
                os.write(v.sin());
                oc.write(v.cos());
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn body_fma_avx2(x: &[f32], outs: Outs) {
    body::<true>(x, outs)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn body_plain_avx2(x: &[f32], outs: Outs) {
    body::<false>(x, outs)
}

fn run(f: Flavour, x: &[f32], outs: Outs) {
    #[cfg(target_arch = "x86_64")]
    {
        let avx2 = std::is_x86_feature_detected!("avx2");
        let fma = std::is_x86_feature_detected!("fma");
        match f {
            // SAFETY: the CPU has the features the functions are compiled for (checked).
            Flavour::Fused if avx2 && fma => return unsafe { body_fma_avx2(x, outs) },
            Flavour::Plain if avx2 => return unsafe { body_plain_avx2(x, outs) },
            _ => {}
        }
    }
    match f {
        Flavour::Fused => body::<true>(x, outs),
        Flavour::Plain => body::<false>(x, outs),
        Flavour::Libm => libm_where(x, outs, |_| true),
    }
}

/// `out[i] = sin(x[i])` (`cos` false) or `cos(x[i])`, bit-identical to `f32::sin`/`f32::cos`.
pub fn apply(x: &[f32], out: &mut [f32], cos: bool) {
    run(flavour(), x, Outs::One(as_out(out), cos))
}

/// An initialised slice as output slots (the kernels only write valid f32 into them).
fn as_out(v: &mut [f32]) -> &mut [Out] {
    // SAFETY: MaybeUninit<f32> has f32's layout, and only initialised values are written.
    unsafe { &mut *(v as *mut [f32] as *mut [Out]) }
}

/// A vector of `n` values written by `fill`, without zeroing it first.
fn filled(n: usize, fill: impl FnOnce(&mut [Out])) -> Vec<f32> {
    let mut v = Vec::with_capacity(n);
    fill(&mut v.spare_capacity_mut()[..n]);
    // SAFETY: `fill` wrote all n slots (every kernel writes each output it is given).
    unsafe { v.set_len(n) };
    v
}

/// `sin[i] = sin(x[i])` and `cos[i] = cos(x[i])` in one pass, the same bits as [`apply`].
pub fn apply_pair(x: &[f32], sin: &mut [f32], cos: &mut [f32]) {
    assert!(
        sin.len() == x.len() && cos.len() == x.len(),
        "apply_pair: lengths differ"
    );
    run(flavour(), x, Outs::Both(as_out(sin), as_out(cos)))
}

/// [`apply_pair`] into new vectors: (sin, cos).
pub fn map_pair(x: &[f32]) -> (Vec<f32>, Vec<f32>) {
    let n = x.len();
    let mut cos = Vec::with_capacity(n);
    let sin = filled(n, |s| {
        run(
            flavour(),
            x,
            Outs::Both(s, &mut cos.spare_capacity_mut()[..n]),
        )
    });
    // SAFETY: run wrote all n cosines.
    unsafe { cos.set_len(n) };
    (sin, cos)
}

/// [`apply`] into a new vector.
pub fn map(x: &[f32], cos: bool) -> Vec<f32> {
    filled(x.len(), |o| run(flavour(), x, Outs::One(o, cos)))
}

/// The arguments the flavour check compares on: the edges of every branch (tiny, fast range,
/// libm), zeros and subnormals, neighbours of multiples of π/4 (quadrant changes), a dense
/// grid over the network's range and bit patterns spread over the whole fast range.
fn check_arguments() -> Vec<f32> {
    let mut v = vec![
        0.0f32,
        -0.0,
        f32::MIN_POSITIVE,
        1e-40,
        0.75,
        120.0,
        119.99999,
    ];
    for edge in [0x3980_0000u32, 0x3f40_0000, 0x42f0_0000, 0x3f49_0fdb] {
        for d in 0..16u32 {
            v.push(f32::from_bits(edge + d));
            v.push(f32::from_bits(edge - 1 - d));
        }
    }
    for k in 1..153 {
        let m = k as f32 * std::f32::consts::FRAC_PI_4;
        for d in -4i32..=4 {
            v.push(f32::from_bits((m.to_bits() as i32 + d) as u32));
        }
    }
    v.extend((0..20_001).map(|i| -100.0 + i as f32 * 0.01));
    // A multiplicative walk over the bit patterns below 120.
    let mut b = 0x1234_5677u32;
    for _ in 0..40_000 {
        b = b.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
        v.push(f32::from_bits(b % 0x42f0_0000));
    }
    let neg: Vec<f32> = v.iter().map(|x| -x).collect();
    v.extend(neg);
    v
}

fn agrees(f: Flavour, args: &[f32]) -> bool {
    let mut out = vec![0f32; args.len()];
    [false, true].into_iter().all(|cos| {
        run(f, args, Outs::One(as_out(&mut out), cos));
        args.iter().zip(&out).all(|(&a, &o)| {
            let want = if cos { a.cos() } else { a.sin() };
            want.to_bits() == o.to_bits()
        })
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Both flavours against libm on arguments the start-up check does not use (a different
    /// walk), and, where glibc's FMA build is the libm (x86-64 Linux with FMA), that the
    /// vector kernel is the one in use, so a wrong kernel cannot hide behind the fallback.
    #[test]
    fn matches_libm_bit_for_bit() {
        let mut b = 0x9e37_79b9u32;
        let xs: Vec<f32> = (0..200_000)
            .map(|_| {
                b = b.wrapping_mul(22_695_477).wrapping_add(1);
                f32::from_bits(b)
            })
            .filter(|x| !x.is_nan())
            .collect();
        for cos in [false, true] {
            let got = map(&xs, cos);
            for (x, g) in xs.iter().zip(&got) {
                let want = if cos { x.cos() } else { x.sin() };
                assert_eq!(g.to_bits(), want.to_bits(), "x = {x:e} cos = {cos}");
            }
        }
        let glibc_fma = cfg!(all(
            target_arch = "x86_64",
            target_os = "linux",
            target_env = "gnu"
        )) && {
            #[cfg(target_arch = "x86_64")]
            let has = std::is_x86_feature_detected!("fma");
            #[cfg(not(target_arch = "x86_64"))]
            let has = false;
            has
        };
        if glibc_fma {
            assert_eq!(flavour(), Flavour::Fused);
        }
        let (mut ps, mut pc) = (vec![0f32; xs.len()], vec![0f32; xs.len()]);
        apply_pair(&xs, &mut ps, &mut pc);
        let (ms, mc) = map_pair(&xs);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(
            bits(&ms),
            bits(&ps),
            "map_pair's sines differ from apply_pair's"
        );
        assert_eq!(
            bits(&mc),
            bits(&pc),
            "map_pair's cosines differ from apply_pair's"
        );
        for (i, x) in xs.iter().enumerate() {
            assert_eq!(ps[i].to_bits(), x.sin().to_bits(), "pair sin x = {x:e}");
            assert_eq!(pc[i].to_bits(), x.cos().to_bits(), "pair cos x = {x:e}");
        }
        assert!(map(&[f32::NAN], false)[0].is_nan());
        assert!(map(&[f32::INFINITY], true)[0].is_nan());
    }
}
