//! Image metrics under the paper's offline evaluation protocol
//! (docs/conventions.md, "Evaluation protocol"). Images are float RGB in
//! [0,1], `[H·W·3]` channels last, row-major; masks are `[H·W]`, nonzero =
//! foreground.
//!
//! * PSNR = −10·log10(MSE), the mean over pixels and the 3 channels, over the
//!   foreground-mask pixels ([`Region::Mask`], the reference's committed H36M
//!   code) or the tight box of the mask ([`Region::Bbox`], the paper's text).
//! * SSIM = scikit-image `structural_similarity` on the tight-box crop with
//!   the reference's call: 7×7 uniform window, sample covariance, K1 0.01,
//!   K2 0.03, per-channel mean without a 3-pixel border, mean over channels,
//!   and `data_range` 2.0 (what scikit-image 0.19 used for float input).
//!
//! Sums are accumulated in f64 in a fixed order, so scores are reproducible
//! bit for bit.

use crate::error::{DataError, Result};

/// scikit-image's default window side.
pub const SSIM_WIN: usize = 7;
/// The reference's effective SSIM data range (scikit-image 0.19, float input).
pub const REFERENCE_DATA_RANGE: f64 = 2.0;

/// Which pixels the PSNR averages over.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Region {
    /// Foreground-mask pixels.
    Mask,
    /// The tight bounding box of the mask.
    Bbox,
}

/// The tight box of a mask: rows `y0..y1`, columns `x0..x1` (exclusive ends),
/// i.e. OpenCV `boundingRect` of the nonzero pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TightBox {
    pub y0: usize,
    pub x0: usize,
    pub y1: usize,
    pub x1: usize,
}

impl TightBox {
    pub fn contains(&self, y: usize, x: usize) -> bool {
        (self.y0..self.y1).contains(&y) && (self.x0..self.x1).contains(&x)
    }
    pub fn height(&self) -> usize {
        self.y1 - self.y0
    }
    pub fn width(&self) -> usize {
        self.x1 - self.x0
    }
}

fn check_len(name: &str, len: usize, want: usize) -> Result<()> {
    if len == want {
        Ok(())
    } else {
        Err(DataError::arg(name, format!("{want} values"), len))
    }
}

/// Tight box of the nonzero pixels of `mask` (`[h·w]`), `None` when empty.
pub fn tight_box(mask: &[u8], h: usize, w: usize) -> Option<TightBox> {
    let mut b: Option<TightBox> = None;
    for y in 0..h {
        for x in 0..w {
            if mask.get(y * w + x).copied().unwrap_or(0) > 0 {
                b = Some(match b {
                    None => TightBox {
                        y0: y,
                        x0: x,
                        y1: y + 1,
                        x1: x + 1,
                    },
                    Some(b) => TightBox {
                        y0: b.y0.min(y),
                        x0: b.x0.min(x),
                        y1: b.y1.max(y + 1),
                        x1: b.x1.max(x + 1),
                    },
                });
            }
        }
    }
    b
}

/// Checks the lengths of a masked comparison (`pred`, `gt`: `[h·w·3]`,
/// `mask`: `[h·w]`) and returns the mask's tight box, `None` when it is empty.
fn masked_box(
    pred: &[f32],
    gt: &[f32],
    mask: &[u8],
    h: usize,
    w: usize,
) -> Result<Option<TightBox>> {
    check_len("pred", pred.len(), 3 * h * w)?;
    check_len("gt", gt.len(), 3 * h * w)?;
    check_len("mask", mask.len(), h * w)?;
    Ok(tight_box(mask, h, w))
}

/// −10·log10 of a mean squared error (+∞ for a perfect match).
pub fn psnr_from_mse(mse: f64) -> f64 {
    -10.0 * mse.log10()
}

/// PSNR over every value of two equally long arrays in [0,1].
pub fn psnr(pred: &[f32], gt: &[f32]) -> Result<f64> {
    check_len("pred", pred.len(), gt.len())?;
    if gt.is_empty() {
        return Err(DataError::arg("gt", "a non-empty image", "0 values"));
    }
    let se: f64 = pred
        .iter()
        .zip(gt)
        .map(|(&p, &g)| {
            let e = p as f64 - g as f64;
            e * e
        })
        .sum();
    Ok(psnr_from_mse(se / gt.len() as f64))
}

/// PSNR over the pixels of `region` (`pred`, `gt`: `[h·w·3]`, `mask`:
/// `[h·w]`); `None` when the mask is empty.
pub fn psnr_masked(
    pred: &[f32],
    gt: &[f32],
    mask: &[u8],
    h: usize,
    w: usize,
    region: Region,
) -> Result<Option<f64>> {
    let Some(b) = masked_box(pred, gt, mask, h, w)? else {
        return Ok(None);
    };
    let (mut se, mut count) = (0f64, 0usize);
    for p in 0..h * w {
        let use_px = match region {
            Region::Mask => mask[p] > 0,
            Region::Bbox => b.contains(p / w, p % w),
        };
        if use_px {
            for c in 0..3 {
                let e = pred[3 * p + c] as f64 - gt[3 * p + c] as f64;
                se += e * e;
            }
            count += 3;
        }
    }
    Ok(Some(psnr_from_mse(se / count as f64)))
}

/// scikit-image `structural_similarity(a, b, channel_axis=-1, data_range=…)`
/// with its other defaults (see the module docs). `a`, `b`: `[h·w·3]`.
pub fn ssim(a: &[f64], b: &[f64], h: usize, w: usize, data_range: f64) -> Result<f64> {
    check_len("a", a.len(), 3 * h * w)?;
    check_len("b", b.len(), 3 * h * w)?;
    if h < SSIM_WIN || w < SSIM_WIN {
        return Err(DataError::arg(
            "image size",
            "at least 7x7 pixels for the SSIM window",
            format!("{w}x{h}"),
        ));
    }
    if !(data_range.is_finite() && data_range > 0.0) {
        return Err(DataError::arg("data_range", "finite and > 0", data_range));
    }
    let (c1, c2) = ((0.01 * data_range).powi(2), (0.03 * data_range).powi(2));
    let np = (SSIM_WIN * SSIM_WIN) as f64;
    let cov_norm = np / (np - 1.0);
    let pad = (SSIM_WIN - 1) / 2;
    let mut total = 0.0;
    for c in 0..3 {
        let at = |img: &[f64], y: usize, x: usize| img[3 * (y * w + x) + c];
        let (mut sum, mut n) = (0.0, 0usize);
        // Only windows fully inside the image survive scikit-image's border
        // crop, so its padding mode never matters.
        for y in pad..h - pad {
            for x in pad..w - pad {
                let (mut ux, mut uy, mut uxx, mut uyy, mut uxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
                for yy in y - pad..=y + pad {
                    for xx in x - pad..=x + pad {
                        let (p, q) = (at(a, yy, xx), at(b, yy, xx));
                        ux += p;
                        uy += q;
                        uxx += p * p;
                        uyy += q * q;
                        uxy += p * q;
                    }
                }
                let (ux, uy, uxx, uyy, uxy) = (ux / np, uy / np, uxx / np, uyy / np, uxy / np);
                let vx = cov_norm * (uxx - ux * ux);
                let vy = cov_norm * (uyy - uy * uy);
                let vxy = cov_norm * (uxy - ux * uy);
                let s = ((2.0 * ux * uy + c1) * (2.0 * vxy + c2))
                    / ((ux * ux + uy * uy + c1) * (vx + vy + c2));
                sum += s;
                n += 1;
            }
        }
        total += sum / n as f64;
    }
    Ok(total / 3.0)
}

/// The crop SSIM is computed on: the tight box, grown symmetrically (and
/// kept inside the image) to at least 7×7 where the image allows, because
/// scikit-image refuses smaller inputs and a thin limb seen edge-on in a
/// small image would otherwise drop the image.
pub fn ssim_crop(b: TightBox, h: usize, w: usize) -> TightBox {
    grow_crop(b, h, w, SSIM_WIN)
}

/// `b` grown symmetrically (and kept inside the `h`×`w` image) to at least
/// `min`×`min` where the image allows; a side the image cannot supply stays
/// as it is.
pub fn grow_crop(b: TightBox, h: usize, w: usize, min: usize) -> TightBox {
    let grow = |lo: usize, hi: usize, n: usize| -> (usize, usize) {
        if hi - lo >= min || n < min {
            return (lo, hi);
        }
        let lo = lo
            .saturating_sub((min - (hi - lo)).div_ceil(2))
            .min(n - min);
        (lo, lo + min)
    };
    let ((y0, y1), (x0, x1)) = (grow(b.y0, b.y1, h), grow(b.x0, b.x1, w));
    TightBox { y0, x0, y1, x1 }
}

/// `[h·w·3]` f32 → the crop `b` as f64.
pub fn crop(img: &[f32], w: usize, b: TightBox) -> Vec<f64> {
    let mut out = Vec::with_capacity(b.height() * b.width() * 3);
    for y in b.y0..b.y1 {
        for x in b.x0..b.x1 {
            out.extend((0..3).map(|c| img[3 * (y * w + x) + c] as f64));
        }
    }
    out
}

/// SSIM on the tight-box crop of `mask` (grown by [`ssim_crop`]); `None`
/// when the mask is empty.
pub fn ssim_masked(
    pred: &[f32],
    gt: &[f32],
    mask: &[u8],
    h: usize,
    w: usize,
    data_range: f64,
) -> Result<Option<f64>> {
    let Some(b) = masked_box(pred, gt, mask, h, w)? else {
        return Ok(None);
    };
    let b = ssim_crop(b, h, w);
    ssim(
        &crop(pred, w, b),
        &crop(gt, w, b),
        b.height(),
        b.width(),
        data_range,
    )
    .map(Some)
}

/// (PSNR over `region`, SSIM on the tight box) of one image; `None` when the
/// mask is empty (such an image is skipped, not scored).
pub fn score_image(
    pred: &[f32],
    gt: &[f32],
    mask: &[u8],
    h: usize,
    w: usize,
    region: Region,
    data_range: f64,
) -> Result<Option<(f64, f64)>> {
    let Some(psnr) = psnr_masked(pred, gt, mask, h, w, region)? else {
        return Ok(None);
    };
    let ssim = ssim_masked(pred, gt, mask, h, w, data_range)?.unwrap_or(f64::NAN);
    Ok(Some((psnr, ssim)))
}

/// `uint8(truncate(255·clamp(v, 0, 1))) / 255`: what the reference scores
/// after writing renders as 8-bit PNGs.
pub fn quantize(rgb: &[f32]) -> Vec<f32> {
    rgb.iter()
        .map(|&v| ((v.clamp(0.0, 1.0) * 255.0) as u8) as f32 / 255.0)
        .collect()
}
