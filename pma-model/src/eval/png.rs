//! Side-by-side pictures of an evaluation: ground truth | render | error heat map.

use std::path::Path;

use super::{EvalError, Result};

/// [GT | render | error heat map], upscaled so small images stay readable.
pub fn side_by_side(gt: &[f32], pred: &[f32], h: usize, w: usize) -> ::image::RgbImage {
    let k = 256usize.div_ceil(h.max(1)).clamp(1, 8) as u32;
    let gap = 4u32;
    let (pw, ph) = (w as u32 * k, h as u32 * k);
    let mut out =
        ::image::RgbImage::from_pixel(3 * pw + 2 * gap, ph, ::image::Rgb([255, 255, 255]));
    let byte = |v: f32| (v.clamp(0.0, 1.0) * 255.0) as u8;
    for y in 0..h {
        for x in 0..w {
            let i = 3 * (y * w + x);
            let g = [byte(gt[i]), byte(gt[i + 1]), byte(gt[i + 2])];
            let p = [byte(pred[i]), byte(pred[i + 1]), byte(pred[i + 2])];
            let err = (0..3).map(|c| (pred[i + c] - gt[i + c]).abs()).sum::<f32>() / 3.0;
            let e = heat(err / 0.25);
            for dy in 0..k {
                for dx in 0..k {
                    let (px, py) = (x as u32 * k + dx, y as u32 * k + dy);
                    out.put_pixel(px, py, ::image::Rgb(g));
                    out.put_pixel(pw + gap + px, py, ::image::Rgb(p));
                    out.put_pixel(2 * (pw + gap) + px, py, ::image::Rgb(e));
                }
            }
        }
    }
    out
}

/// Black → purple → orange → yellow-white colour ramp for t in [0,1] (clamped).
pub fn heat(t: f32) -> [u8; 3] {
    const STOPS: [[f32; 3]; 5] = [
        [0.0, 0.0, 0.02],
        [0.32, 0.07, 0.5],
        [0.8, 0.2, 0.35],
        [0.98, 0.6, 0.1],
        [1.0, 1.0, 0.85],
    ];
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        1.0
    };
    let s = t * (STOPS.len() - 1) as f32;
    let i = (s.floor() as usize).min(STOPS.len() - 2);
    let f = s - i as f32;
    let c = |k: usize| STOPS[i][k] + (STOPS[i + 1][k] - STOPS[i][k]) * f;
    [0, 1, 2].map(|k| (c(k) * 255.0).round() as u8)
}

/// Encode `img` as PNG and replace `path` atomically.
pub fn write_png(img: &::image::RgbImage, path: &Path) -> Result<()> {
    let mut bytes = Vec::new();
    img.write_to(
        &mut std::io::Cursor::new(&mut bytes),
        ::image::ImageFormat::Png,
    )
    .map_err(|source| EvalError::Png {
        path: path.to_path_buf(),
        source,
    })?;
    pma_data::fsio::write_atomic(path, &bytes)
        .map_err(|e| pma_data::FileError::write(path, e).into())
}
