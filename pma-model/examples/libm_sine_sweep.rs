//! Every f32 through `pma_model::compute::libm_sine` against `f32::sin`/`f32::cos` (libm), separately
//! and through the sine-and-cosine pass: prints the flavour in use and the number of
//! differing bit patterns (0 is the claim).
//!
//!     cargo run --release -p pma-model --example libm_sine_sweep

use std::thread;

fn main() {
    println!("flavour: {:?}", pma_model::compute::libm_sine::flavour());
    speed();
    let workers = thread::available_parallelism().map_or(1, |n| n.get()) as u64;
    let total = 1u64 << 32;
    let t0 = std::time::Instant::now();
    let bad: u64 = thread::scope(|s| {
        let handles: Vec<_> = (0..workers)
            .map(|w| {
                s.spawn(move || {
                    let (lo, hi) = (total * w / workers, total * (w + 1) / workers);
                    let mut bad = 0u64;
                    let mut x = Vec::with_capacity(1 << 16);
                    let mut out = vec![0f32; 1 << 16];
                    let mut out_cos = vec![0f32; 1 << 16];
                    let mut b = lo;
                    while b < hi {
                        let e = (b + (1 << 16)).min(hi);
                        x.clear();
                        x.extend((b..e).map(|v| f32::from_bits(v as u32)));
                        for cos in [false, true] {
                            let o = &mut out[..x.len()];
                            pma_model::compute::libm_sine::apply(&x, o, cos);
                            for (v, g) in x.iter().zip(o.iter()) {
                                let want = if cos { v.cos() } else { v.sin() };
                                let same = want.to_bits() == g.to_bits() || (want.is_nan() && g.is_nan());
                                if !same {
                                    if bad < 5 {
                                        eprintln!("differs: x = {v:e} ({:#010x}) cos = {cos}: libm {want:e}, kernel {g:e}", v.to_bits());
                                    }
                                    bad += 1;
                                }
                            }
                        }
                        // The sine-and-cosine pass must give the same bits as the separate ones.
                        let (ps, pc) = (&mut out[..x.len()], &mut out_cos[..x.len()]);
                        pma_model::compute::libm_sine::apply_pair(&x, ps, pc);
                        for ((v, s), c) in x.iter().zip(ps.iter()).zip(pc.iter()) {
                            for (want, g) in [(v.sin(), s), (v.cos(), c)] {
                                let same = want.to_bits() == g.to_bits() || (want.is_nan() && g.is_nan());
                                if !same {
                                    if bad < 5 {
                                        eprintln!("pair differs: x = {v:e} ({:#010x}): libm {want:e}, kernel {g:e}", v.to_bits());
                                    }
                                    bad += 1;
                                }
                            }
                        }
                        b = e;
                    }
                    bad
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).sum()
    });
    println!(
        "{} f32 values × (sin, cos, sin+cos pass): {bad} differ from libm ({:.1} s)",
        total,
        t0.elapsed().as_secs_f64()
    );
    if bad > 0 {
        std::process::exit(1);
    }
}

/// Median time per value of the kernel and of scalar libm over 4M arguments in the
/// network's range (one thread).
fn speed() {
    let x: Vec<f32> = (0..1 << 22)
        .map(|i| (i as f32 * 1.3e-5).sin() * 60.0)
        .collect();
    let mut out = vec![0f32; x.len()];
    let mut time = |f: &mut dyn FnMut(&mut [f32])| {
        let mut t: Vec<f64> = (0..5)
            .map(|_| {
                let t0 = std::time::Instant::now();
                f(&mut out);
                t0.elapsed().as_secs_f64()
            })
            .collect();
        t.sort_by(f64::total_cmp);
        t[2] * 1e9 / x.len() as f64
    };
    let kernel = time(&mut |o| pma_model::compute::libm_sine::apply(&x, o, false));
    let mut cos = vec![0f32; x.len()];
    let pair = time(&mut |o| pma_model::compute::libm_sine::apply_pair(&x, o, &mut cos));
    let libm = time(&mut |o| {
        for (o, v) in o.iter_mut().zip(&x) {
            *o = v.sin();
        }
    });
    println!(
        "sin over 4M values in [-60, 60]: kernel {kernel:.2} ns/value, libm {libm:.2} ns/value; \
         sin and cos in one pass {pair:.2} ns/value"
    );
}
