//! Frequency histograms: how the power of a render is spread over spatial frequencies,
//! against the ground truth's. A render that is too smooth (the failure the paper's
//! frequency analysis is about) has too little power at high frequencies even when its PSNR
//! is fine; this measures that directly.
//!
//! For one image, on the crop SSIM is scored on (the mask's tight box, grown to 7×7 where
//! the image allows: [`pma_data::metrics::ssim_crop`]):
//!
//! 1. **Luminance** `Y = 0.2126 R + 0.7152 G + 0.0722 B` (BT.709). Sharpness is carried by
//!    luminance; one spectrum per image keeps the histogram free of colour-balance effects.
//! 2. **Mean subtraction**, then a separable **Hann window** `sin²(π(n+½)/N)` along each
//!    axis of the crop. The DFT treats the crop as periodic, so the jump between opposite
//!    crop borders would otherwise leak broadband power into every bin and hide the
//!    render's own high frequencies. Subtracting the mean first keeps the window's own
//!    low-frequency lobe (the mean times the window) out of the lowest bins.
//! 3. **Zero padding** to at least [`MIN_FFT`] samples per axis, then a 2-D DFT (rustfft,
//!    f64). Padding keeps the frequency unit physical (cycles per pixel, whatever the crop
//!    size) and the grid fine enough that every bin holds DFT samples; the window has
//!    already brought the data to zero at the crop border, so padding adds no edge.
//! 4. **Power** `|F(u,v)|²`, binned by the radial frequency
//!    `r = √((u/Nx)² + (v/Ny)²)` (cycles per pixel, `u`, `v` signed) into [`FREQ_BINS`]
//!    equal bins over `[0, ½√2]` (½√2 = both axes at Nyquist). The DC sample is left out.
//!    A bin's value is the **mean** power of its samples (the radially averaged power
//!    spectrum, so the outer bins are not favoured for holding more samples), and the
//!    histogram is **normalised to sum 1**: it describes the shape of the spectrum, not the
//!    image's contrast, which PSNR already scores. A flat crop (no variation) gives all zeros.
//!
//! **Distance** between a render's histogram `p` and the ground truth's `q`: the mean
//! absolute log-ratio over the bins, `D = (1/B) Σ_k |log10(p_k + ε) − log10(q_k + ε)|` with
//! `ε` = [`EPS`], in decades. Power spectra of images fall off by orders of magnitude
//! towards high frequencies, so a linear distance (L1 on `p`, `q`) would be decided by the
//! few low-frequency bins holding nearly all the power; on a log scale a blurred render's
//! missing high frequencies count as much as a wrong low-frequency level. `D = 0` for
//! identical spectra (up to overall contrast) and grows as the render's spectrum departs
//! from the ground truth's, whichever side it is on (too smooth or too noisy). A flat
//! render against a textured ground truth scores about `12 − mean_k |log10 q_k|`, roughly
//! 10: the largest distances come from renders with no structure at all.
//!
//! A split reports the mean of the per-image distances and the per-bin mean of the
//! per-image histograms of render and ground truth (each sums to 1 unless some crops were
//! flat, which add zeros).

use rustfft::num_complex::Complex;
use rustfft::FftPlanner;
use serde::Serialize;

use pma_data::metrics::{crop, ssim_crop, tight_box};

/// Radial bins of a histogram.
pub const FREQ_BINS: usize = 32;
/// Upper end of the radial frequency (cycles per pixel): both axes at Nyquist.
pub const R_MAX: f64 = std::f64::consts::FRAC_1_SQRT_2;
/// Minimum DFT size per axis: a grid step 1/64 below the bin width ½√2/32 puts DFT samples
/// in every bin even for a 7-pixel crop.
pub const MIN_FFT: usize = 64;
/// Floor added to normalised bin values before the log, so a bin without power (a flat
/// crop) gives a finite distance.
pub const EPS: f64 = 1e-12;

/// Luminance deviation from the crop's mean below which the crop counts as flat (8-bit
/// images vary by at least 0.0722/255 where they vary at all).
const FLAT: f64 = 1e-9;

/// The [`FREQ_BINS`]` + 1` bin edges, in cycles per pixel.
pub fn bin_edges() -> Vec<f64> {
    (0..=FREQ_BINS)
        .map(|k| R_MAX * k as f64 / FREQ_BINS as f64)
        .collect()
}

/// Normalised radial power histogram ([`FREQ_BINS`] values summing to 1, or all zeros for
/// a flat image) of an `[h·w·3]` RGB image, row-major, channels last (see the module docs).
///
/// # Panics
/// If `img.len() != 3·h·w`.
pub fn radial_power_histogram(img: &[f64], h: usize, w: usize) -> Vec<f64> {
    assert_eq!(img.len(), 3 * h * w, "image of {h}x{w}x3");
    let (ny, nx) = (h.max(MIN_FFT), w.max(MIN_FFT));
    let lum: Vec<f64> = img
        .chunks_exact(3)
        .map(|p| 0.2126 * p[0] + 0.7152 * p[1] + 0.0722 * p[2])
        .collect();
    let mean = lum.iter().sum::<f64>() / lum.len().max(1) as f64;
    // The mean's rounding error would otherwise leave a flat crop with a spectrum of noise.
    if lum.iter().all(|v| (v - mean).abs() <= FLAT) {
        return vec![0.0; FREQ_BINS];
    }
    let hann = |n: usize, len: usize| {
        (std::f64::consts::PI * (n as f64 + 0.5) / len as f64)
            .sin()
            .powi(2)
    };
    let (wy, wx): (Vec<f64>, Vec<f64>) = (
        (0..h).map(|y| hann(y, h)).collect(),
        (0..w).map(|x| hann(x, w)).collect(),
    );

    let mut buf = vec![Complex::new(0.0, 0.0); ny * nx];
    for y in 0..h {
        for x in 0..w {
            buf[y * nx + x].re = (lum[y * w + x] - mean) * wy[y] * wx[x];
        }
    }
    let mut planner = FftPlanner::<f64>::new();
    planner.plan_fft_forward(nx).process(&mut buf);
    // Columns as rows of the transpose: `cols[u·ny + v]` = F(v, u).
    let mut cols = vec![Complex::new(0.0, 0.0); ny * nx];
    for v in 0..ny {
        for u in 0..nx {
            cols[u * ny + v] = buf[v * nx + u];
        }
    }
    planner.plan_fft_forward(ny).process(&mut cols);

    let signed = |k: usize, n: usize| {
        if k <= n / 2 {
            k as f64 / n as f64
        } else {
            (k as f64 - n as f64) / n as f64
        }
    };
    let mut sum = [0f64; FREQ_BINS];
    let mut count = [0u64; FREQ_BINS];
    for u in 0..nx {
        let fu = signed(u, nx);
        for v in 0..ny {
            if u == 0 && v == 0 {
                continue;
            }
            let fv = signed(v, ny);
            let r = (fu * fu + fv * fv).sqrt();
            let bin = ((r / R_MAX * FREQ_BINS as f64) as usize).min(FREQ_BINS - 1);
            sum[bin] += cols[u * ny + v].norm_sqr();
            count[bin] += 1;
        }
    }
    let mean_power: Vec<f64> = sum
        .iter()
        .zip(&count)
        .map(|(&s, &c)| if c > 0 { s / c as f64 } else { 0.0 })
        .collect();
    let total: f64 = mean_power.iter().sum();
    if total > 0.0 && total.is_finite() {
        mean_power.iter().map(|p| p / total).collect()
    } else {
        vec![0.0; FREQ_BINS]
    }
}

/// Mean absolute log10-ratio over bins between two histograms (see the module docs).
///
/// # Panics
/// If the lengths differ.
pub fn distance(render: &[f64], gt: &[f64]) -> f64 {
    assert_eq!(render.len(), gt.len(), "histograms of different lengths");
    if render.is_empty() {
        return 0.0;
    }
    render
        .iter()
        .zip(gt)
        .map(|(&p, &q)| ((p + EPS).log10() - (q + EPS).log10()).abs())
        .sum::<f64>()
        / render.len() as f64
}

/// The histograms of one evaluated image and their distance.
#[derive(Debug, Clone)]
pub struct ImageSpectra {
    pub render: Vec<f64>,
    pub gt: Vec<f64>,
    pub distance: f64,
}

/// Histograms of `pred` and `gt` (`[h·w·3]` in [0,1]) on the crop SSIM is scored on (the
/// mask's tight box, grown to 7×7 where the image allows); `None` when the mask is empty.
///
/// # Panics
/// If the lengths do not match `h`, `w` (the evaluation has checked them when scoring).
pub fn image_spectra(
    pred: &[f32],
    gt: &[f32],
    mask: &[u8],
    h: usize,
    w: usize,
) -> Option<ImageSpectra> {
    let b = ssim_crop(tight_box(mask, h, w)?, h, w);
    let (ch, cw) = (b.height(), b.width());
    let render = radial_power_histogram(&crop(pred, w, b), ch, cw);
    let gt = radial_power_histogram(&crop(gt, w, b), ch, cw);
    let distance = distance(&render, &gt);
    Some(ImageSpectra {
        render,
        gt,
        distance,
    })
}

/// The frequency-histogram part of a split's report (flattened into `eval.json`).
#[derive(Debug, Clone, Serialize)]
pub struct FreqSummary {
    /// Mean over images of the render-to-ground-truth distance.
    #[serde(rename = "freq_distance")]
    pub distance: f64,
    /// Bin edges in cycles per pixel ([`FREQ_BINS`]` + 1`).
    #[serde(rename = "freq_bin_edges")]
    pub bin_edges: Vec<f64>,
    /// Per-bin mean over images of the renders' normalised histograms.
    #[serde(rename = "freq_hist_render")]
    pub hist_render: Vec<f64>,
    /// The same for the ground truth.
    #[serde(rename = "freq_hist_gt")]
    pub hist_gt: Vec<f64>,
}

/// Sums per-image spectra, in a fixed order, into a [`FreqSummary`].
#[derive(Debug, Clone)]
pub struct FreqAccumulator {
    render: Vec<f64>,
    gt: Vec<f64>,
    distance: f64,
    n: usize,
}

impl Default for FreqAccumulator {
    fn default() -> Self {
        Self {
            render: vec![0.0; FREQ_BINS],
            gt: vec![0.0; FREQ_BINS],
            distance: 0.0,
            n: 0,
        }
    }
}

impl FreqAccumulator {
    pub fn add(&mut self, s: &ImageSpectra) {
        for (acc, v) in self.render.iter_mut().zip(&s.render) {
            *acc += v;
        }
        for (acc, v) in self.gt.iter_mut().zip(&s.gt) {
            *acc += v;
        }
        self.distance += s.distance;
        self.n += 1;
    }

    /// Means over the added images (NaN distance and zero histograms when none was added).
    pub fn finish(self) -> FreqSummary {
        let n = self.n as f64;
        let mean = |v: Vec<f64>| -> Vec<f64> {
            if self.n == 0 {
                v
            } else {
                v.into_iter().map(|s| s / n).collect()
            }
        };
        FreqSummary {
            distance: if self.n == 0 {
                f64::NAN
            } else {
                self.distance / n
            },
            bin_edges: bin_edges(),
            hist_render: mean(self.render),
            hist_gt: mean(self.gt),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Stripes and a checkerboard at several scales: power over the whole band.
    fn textured(h: usize, w: usize) -> Vec<f64> {
        let mut img = Vec::with_capacity(h * w * 3);
        for y in 0..h {
            for x in 0..w {
                let checker = ((x / 2 + y / 2) % 2) as f64;
                let stripes = (x as f64 * 0.9 + y as f64 * 0.3).sin() * 0.5 + 0.5;
                let coarse = ((x / 9 + y / 7) % 2) as f64;
                img.extend([
                    0.5 * checker + 0.3 * coarse + 0.2 * stripes,
                    0.4 * checker + 0.4 * stripes + 0.2 * coarse,
                    0.3 * checker + 0.3 * stripes + 0.4 * coarse,
                ]);
            }
        }
        img
    }

    /// Separable Gaussian blur with clamped borders.
    fn blur(img: &[f64], h: usize, w: usize, sigma: f64) -> Vec<f64> {
        let r = (3.0 * sigma).ceil() as isize;
        let k: Vec<f64> = (-r..=r)
            .map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp())
            .collect();
        let ks: f64 = k.iter().sum();
        let pass = |src: &[f64], horizontal: bool| -> Vec<f64> {
            let mut out = vec![0.0; src.len()];
            for y in 0..h as isize {
                for x in 0..w as isize {
                    for c in 0..3 {
                        let mut s = 0.0;
                        for (j, kv) in k.iter().enumerate() {
                            let d = j as isize - r;
                            let (yy, xx) = if horizontal {
                                (y, (x + d).clamp(0, w as isize - 1))
                            } else {
                                ((y + d).clamp(0, h as isize - 1), x)
                            };
                            s += kv * src[3 * (yy as usize * w + xx as usize) + c];
                        }
                        out[3 * (y as usize * w + x as usize) + c] = s / ks;
                    }
                }
            }
            out
        };
        pass(&pass(img, true), false)
    }

    #[test]
    fn blur_moves_power_to_low_frequencies() {
        let (h, w) = (48, 40);
        let sharp = textured(h, w);
        let blurred = blur(&sharp, h, w, 1.5);
        let hs = radial_power_histogram(&sharp, h, w);
        let hb = radial_power_histogram(&blurred, h, w);
        assert_eq!(hs.len(), FREQ_BINS);
        assert!((hs.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        assert!((hb.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        // Above a quarter cycle per pixel a σ = 1.5 blur removes orders of magnitude.
        let high = |p: &[f64]| p[FREQ_BINS / 2..].iter().sum::<f64>();
        assert!(
            high(&hb) < 0.01 * high(&hs),
            "{} vs {}",
            high(&hb),
            high(&hs)
        );
        let d_sharp = distance(&hs, &hs);
        let d_blur = distance(&hb, &hs);
        assert_eq!(d_sharp, 0.0);
        assert!(d_blur > 0.5, "{d_blur}");
        // Symmetric, and a stronger blur is further away.
        assert!((distance(&hs, &hb) - d_blur).abs() < 1e-12);
        let hb2 = radial_power_histogram(&blur(&sharp, h, w, 3.0), h, w);
        assert!(distance(&hb2, &hs) > d_blur);
    }

    #[test]
    fn contrast_and_offset_do_not_change_the_histogram() {
        let (h, w) = (20, 33);
        let a = textured(h, w);
        let b: Vec<f64> = a.iter().map(|v| 0.5 * v + 0.2).collect();
        let (ha, hb) = (
            radial_power_histogram(&a, h, w),
            radial_power_histogram(&b, h, w),
        );
        assert!(distance(&ha, &hb) < 1e-9, "{}", distance(&ha, &hb));
    }

    #[test]
    fn every_bin_holds_samples_and_flat_images_give_zeros() {
        // Noise has power at every frequency: a zero bin would mean a bin without samples.
        let (h, w) = (7, 7);
        let noise: Vec<f64> = (0..h * w * 3)
            .map(|i| ((i * 7919 + 13) % 101) as f64 / 100.0)
            .collect();
        let p = radial_power_histogram(&noise, h, w);
        assert!(p.iter().all(|&v| v > 0.0), "{p:?}");
        let flat = radial_power_histogram(&vec![0.3; h * w * 3], h, w);
        assert!(flat.iter().all(|&v| v == 0.0));
        assert!(distance(&flat, &p) > 1.0);
        assert_eq!(bin_edges().len(), FREQ_BINS + 1);
        assert!((bin_edges()[FREQ_BINS] - R_MAX).abs() < 1e-15);
    }

    #[test]
    fn image_spectra_use_the_mask_crop_and_accumulate() {
        let (h, w) = (30, 30);
        let tex = textured(h, w);
        let mut mask = vec![0u8; h * w];
        for y in 5..25 {
            for x in 8..22 {
                mask[y * w + x] = 1;
            }
        }
        let img: Vec<f32> = tex.iter().map(|&v| v as f32).collect();
        // Outside the crop the render may be anything: it is not looked at.
        let mut other = img.clone();
        other[..3 * w].iter_mut().for_each(|v| *v = 1.0 - *v);
        let s = image_spectra(&other, &img, &mask, h, w).unwrap();
        assert_eq!(s.distance, 0.0);
        assert!(image_spectra(&img, &img, &vec![0; h * w], h, w).is_none());
        let mut acc = FreqAccumulator::default();
        acc.add(&s);
        acc.add(&s);
        let sum = acc.finish();
        assert_eq!(sum.distance, 0.0);
        assert!((sum.hist_gt.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        assert_eq!(sum.hist_render, sum.hist_gt);
    }
}
