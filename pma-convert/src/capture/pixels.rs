//! Capture pixels: masks, sampling masks, undistortion, resizing, background
//! plates, and the streamed output (docs/conventions.md, "ZJU-MoCap capture").

use std::{
    io::{BufWriter, Read, Seek, SeekFrom, Write},
    path::{Path, PathBuf},
};

use glam::{DMat3, DVec3};
use pma_data::{dataset::Dataset, fsio::parent_dir};

use super::{Annots, CaptureCamera, CaptureOptions, ImageRef, Progress};
use crate::{
    dataset::pixels::{start_member, write_archive},
    error::{ConvertError, Result},
};

/// `mask/<image path without extension>.png` and the same under `mask_cihp/`.
fn mask_paths(dir: &Path, rel: &str) -> [PathBuf; 2] {
    let stem = rel.rsplit_once('.').map_or(rel, |(s, _)| s);
    ["mask", "mask_cihp"].map(|m| dir.join(m).join(format!("{stem}.png")))
}

pub(super) fn check_inputs(dir: &Path, rel: &str) -> Result<()> {
    let img = dir.join(rel);
    if !img.is_file() {
        return Err(ConvertError::io(
            img,
            std::io::Error::new(
                std::io::ErrorKind::NotFound,
                "image listed in annots.npy is missing",
            ),
        ));
    }
    let [m, c] = mask_paths(dir, rel);
    if !m.is_file() && !c.is_file() {
        return Err(missing_mask(dir, rel));
    }
    Ok(())
}

fn missing_mask(dir: &Path, rel: &str) -> ConvertError {
    let [m, c] = mask_paths(dir, rel);
    ConvertError::io(
        m,
        std::io::Error::new(
            std::io::ErrorKind::NotFound,
            format!(
                "no mask for image {rel} (neither this file nor {} exists)",
                c.display()
            ),
        ),
    )
}

fn image_err(path: &Path, e: image::ImageError) -> ConvertError {
    match e {
        image::ImageError::IoError(io) => ConvertError::io(path, io),
        other => ConvertError::format(path, format!("cannot decode the image: {other}")),
    }
}

/// The output `(H, W)`: the first image's size, scaled by `res` (floored).
pub(super) fn output_size(dir: &Path, rel: &str, res: Option<f64>) -> Result<(usize, usize)> {
    let p = dir.join(rel);
    let (w, h) = image::image_dimensions(&p).map_err(|e| image_err(&p, e))?;
    let s = res.unwrap_or(1.0);
    let (h, w) = (((h as f64) * s) as usize, ((w as f64) * s) as usize);
    if h == 0 || w == 0 {
        return Err(ConvertError::Usage(format!(
            "--res {s}: {} would become {w}x{h}",
            p.display()
        )));
    }
    Ok((h, w))
}

/// An 8-bit image, interleaved channels.
pub struct Plane {
    pub w: usize,
    pub h: usize,
    pub c: usize,
    pub px: Vec<u8>,
}

fn read_rgb(path: &Path) -> Result<Plane> {
    let img = pma_data::fsio::open_image(path)
        .map_err(|e| image_err(path, e))?
        .to_rgb8();
    let (w, h) = img.dimensions();
    Ok(Plane {
        w: w as usize,
        h: h as usize,
        c: 3,
        px: img.into_raw(),
    })
}

/// A mask file as 0/1 (any non-zero channel is foreground).
fn read_mask(path: &Path) -> Result<Plane> {
    let img = pma_data::fsio::open_image(path).map_err(|e| image_err(path, e))?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let px = match img {
        image::DynamicImage::ImageLuma8(g) => {
            g.into_raw().into_iter().map(|v| (v != 0) as u8).collect()
        }
        other => other
            .to_rgba8()
            .pixels()
            .map(|p| (p[0] != 0 || p[1] != 0 || p[2] != 0) as u8)
            .collect(),
    };
    Ok(Plane { w, h, c: 1, px })
}

/// Square max (dilate) or min (erode) filter of half-width `r`, ignoring
/// pixels outside the image (OpenCV's default morphology border).
pub fn morph(src: &[u8], w: usize, h: usize, r: usize, max: bool) -> Vec<u8> {
    let pick = |a: u8, b: u8| if max { a.max(b) } else { a.min(b) };
    let mut tmp = vec![0u8; w * h];
    for y in 0..h {
        let row = &src[y * w..(y + 1) * w];
        for x in 0..w {
            let (a, b) = (x.saturating_sub(r), (x + r).min(w - 1));
            tmp[y * w + x] = row[a..=b].iter().copied().reduce(pick).unwrap_or(0);
        }
    }
    let mut out = vec![0u8; w * h];
    for y in 0..h {
        let (a, b) = (y.saturating_sub(r), (y + r).min(h - 1));
        for x in 0..w {
            out[y * w + x] = (a..=b).map(|yy| tmp[yy * w + x]).reduce(pick).unwrap_or(0);
        }
    }
    out
}

/// The sampling mask of a 0/1 mask: dilated three times by a 5×5 square
/// (one 13×13 square), and with `erode_border` the band where a 5×5 dilation
/// and erosion differ set to 100 (the boundary marker).
pub fn sampling_mask(mask: &[u8], w: usize, h: usize, erode_border: bool) -> Vec<u8> {
    let mut s = morph(mask, w, h, 6, true);
    if erode_border {
        let d = morph(mask, w, h, 2, true);
        let e = morph(mask, w, h, 2, false);
        for i in 0..s.len() {
            if d[i].wrapping_sub(e[i]) == 1 {
                s[i] = 100;
            }
        }
    }
    s
}

/// OpenCV's fixed-point remap: source position in 1/32 pixel, as integer
/// pixel and a 5+5-bit fraction.
#[derive(Clone, Copy, Debug)]
pub struct MapEntry {
    pub sx: i32,
    pub sy: i32,
    pub frac: u16,
}

/// The undistortion map of `cv2.undistort(img, K, D)` (the new camera matrix
/// is K): for each output pixel, the distorted source position.
pub fn undistort_map(k: &[[f64; 3]; 3], d: &[f64; 5], w: usize, h: usize) -> Vec<MapEntry> {
    let km = DMat3::from_cols_array_2d(k).transpose();
    let ir = km.inverse();
    let (fx, fy, u0, v0) = (k[0][0], k[1][1], k[0][2], k[1][2]);
    let [k1, k2, p1, p2, k3] = *d;
    let mut out = Vec::with_capacity(w * h);
    for i in 0..h {
        for j in 0..w {
            let q = ir * DVec3::new(j as f64, i as f64, 1.0);
            let (x, y) = (q.x / q.z, q.y / q.z);
            let (x2, y2) = (x * x, y * y);
            let r2 = x2 + y2;
            let xy2 = 2.0 * x * y;
            let kr = 1.0 + ((k3 * r2 + k2) * r2 + k1) * r2;
            let u = fx * (x * kr + p1 * xy2 + p2 * (r2 + 2.0 * x2)) + u0;
            let v = fy * (y * kr + p1 * (r2 + 2.0 * y2) + p2 * xy2) + v0;
            let iu = (u * 32.0).round_ties_even() as i32;
            let iv = (v * 32.0).round_ties_even() as i32;
            out.push(MapEntry {
                sx: iu >> 5,
                sy: iv >> 5,
                frac: (((iv & 31) << 5) | (iu & 31)) as u16,
            });
        }
    }
    out
}

/// Bilinear remap with 15-bit fixed-point weights and a zero border, as
/// OpenCV's `remap(INTER_LINEAR, BORDER_CONSTANT)` on 8-bit images.
pub fn remap(src: &Plane, map: &[MapEntry]) -> Vec<u8> {
    let (w, h, c) = (src.w as i32, src.h as i32, src.c);
    let mut out = vec![0u8; map.len() * c];
    for (o, m) in out.chunks_exact_mut(c).zip(map) {
        let tx = (m.frac & 31) as i32;
        let ty = (m.frac >> 5) as i32;
        let wt = [
            (32 - tx) * (32 - ty) * 32,
            tx * (32 - ty) * 32,
            (32 - tx) * ty * 32,
            tx * ty * 32,
        ];
        let taps = [
            (m.sx, m.sy),
            (m.sx + 1, m.sy),
            (m.sx, m.sy + 1),
            (m.sx + 1, m.sy + 1),
        ];
        for (ch, o) in o.iter_mut().enumerate() {
            let mut acc = 0i32;
            for (&(x, y), &wk) in taps.iter().zip(&wt) {
                if x >= 0 && x < w && y >= 0 && y < h {
                    acc += src.px[(y as usize * src.w + x as usize) * c + ch] as i32 * wk;
                }
            }
            *o = ((acc + (1 << 14)) >> 15).clamp(0, 255) as u8;
        }
    }
    out
}

/// Area-average downscale (OpenCV's `INTER_AREA` for shrinking): each output
/// pixel averages the source area it covers, with fractional edge weights.
pub fn resize_area(src: &Plane, w: usize, h: usize) -> Plane {
    let sx = src.w as f64 / w as f64;
    let sy = src.h as f64 / h as f64;
    let spans = |n: usize, s: f64, len: usize| -> Vec<Vec<(usize, f64)>> {
        (0..n)
            .map(|o| {
                let (a, b) = (o as f64 * s, ((o + 1) as f64 * s).min(len as f64));
                let mut v = Vec::new();
                let mut i = a.floor() as usize;
                while (i as f64) < b && i < len {
                    let cov = (b.min(i as f64 + 1.0) - a.max(i as f64)).max(0.0);
                    if cov > 1e-12 {
                        v.push((i, cov));
                    }
                    i += 1;
                }
                v
            })
            .collect()
    };
    let xs = spans(w, sx, src.w);
    let ys = spans(h, sy, src.h);
    let c = src.c;
    let mut px = vec![0u8; w * h * c];
    for (oy, yspan) in ys.iter().enumerate() {
        for (ox, xspan) in xs.iter().enumerate() {
            for ch in 0..c {
                let (mut acc, mut area) = (0.0, 0.0);
                for &(y, wy) in yspan {
                    for &(x, wx) in xspan {
                        acc += src.px[(y * src.w + x) * c + ch] as f64 * wy * wx;
                        area += wy * wx;
                    }
                }
                px[(oy * w + ox) * c + ch] = (acc / area).round().clamp(0.0, 255.0) as u8;
            }
        }
    }
    Plane { w, h, c, px }
}

/// Nearest-neighbour resize (OpenCV's `INTER_NEAREST`: source `floor(x·W/w)`).
pub fn resize_nearest(src: &Plane, w: usize, h: usize) -> Plane {
    let c = src.c;
    let mut px = Vec::with_capacity(w * h * c);
    for y in 0..h {
        let yy = ((y as f64 * src.h as f64 / h as f64).floor() as usize).min(src.h - 1);
        for x in 0..w {
            let xx = ((x as f64 * src.w as f64 / w as f64).floor() as usize).min(src.w - 1);
            px.extend_from_slice(&src.px[(yy * src.w + xx) * c..(yy * src.w + xx + 1) * c]);
        }
    }
    Plane { w, h, c, px }
}

/// One processed image: `(rgb, mask, sampling mask)` at the output size.
pub fn process_image(
    dir: &Path,
    rel: &str,
    cam: &CaptureCamera,
    out: (usize, usize),
    size_in: &mut Option<(usize, usize)>,
    erode_border: bool,
) -> Result<(Vec<u8>, Vec<u8>, Vec<u8>)> {
    let ipath = dir.join(rel);
    let img = read_rgb(&ipath)?;
    let expect = *size_in.get_or_insert((img.w, img.h));
    if (img.w, img.h) != expect {
        return Err(ConvertError::mismatch(
            &ipath,
            "image size",
            format!("{}x{} (as the first image)", expect.0, expect.1),
            format!("{}x{}", img.w, img.h),
        ));
    }
    let mut mask: Option<Vec<u8>> = None;
    for mp in mask_paths(dir, rel) {
        if !mp.is_file() {
            continue;
        }
        let m = read_mask(&mp)?;
        if (m.w, m.h) != (img.w, img.h) {
            return Err(ConvertError::mismatch(
                &mp,
                "mask size",
                format!("{}x{} (as its image)", img.w, img.h),
                format!("{}x{}", m.w, m.h),
            ));
        }
        mask = Some(match mask {
            Some(a) => a.iter().zip(&m.px).map(|(x, y)| x | y).collect(),
            None => m.px,
        });
    }
    let Some(mask) = mask else {
        return Err(missing_mask(dir, rel));
    };
    let smask = sampling_mask(&mask, img.w, img.h, erode_border);
    let map = undistort_map(&cam.k, &cam.d, img.w, img.h);
    let plane = |px: Vec<u8>| Plane {
        w: img.w,
        h: img.h,
        c: 1,
        px,
    };
    let mut rgb = Plane {
        px: remap(&img, &map),
        ..img
    };
    let mut m = plane(remap(&plane(mask), &map));
    for v in &mut m.px {
        *v = (*v >= 1) as u8;
    }
    let mut s = plane(remap(&plane(smask), &map));
    let (h, w) = out;
    if (rgb.w, rgb.h) != (w, h) {
        rgb = resize_area(&rgb, w, h);
        m = resize_nearest(&m, w, h);
        s = resize_nearest(&s, w, h);
    }
    Ok((rgb.px, m.px, s.px))
}

/// Median of `v` as `np.median(...).astype(uint8)`: the mean of the two
/// middle values, truncated, for an even count.
fn median_u8(v: &mut [u8]) -> u8 {
    let n = v.len();
    let (_, hi, _) = v.select_nth_unstable(n / 2);
    let hi = *hi;
    if n % 2 == 1 {
        return hi;
    }
    let lo = *v[..n / 2].iter().max().expect("n >= 2");
    ((lo as u16 + hi as u16) / 2) as u8
}

#[allow(clippy::too_many_arguments)]
pub(super) fn write_capture(
    dir: &Path,
    annots: &Annots,
    refs: &[ImageRef],
    ds: &Dataset,
    output: &Path,
    opts: &CaptureOptions,
    (h, w): (usize, usize),
    progress: Progress,
) -> Result<()> {
    let odir = parent_dir(output);
    let hw = h * w;
    let per = 5 * hw;
    let n = refs.len();
    let used: Vec<usize> = {
        let mut c: Vec<usize> = refs.iter().map(|r| r.cam).collect();
        c.sort_unstable();
        c.dedup();
        c
    };
    let total = (2 * n + used.len()) as u64;
    let mut done = 0u64;
    progress(done, total);

    // Pass 1: every processed image into a scratch file (rgb, mask, sampling mask).
    let mut tmp = tempfile::tempfile_in(odir).map_err(|e| ConvertError::write(odir, e))?;
    let terr = |e| ConvertError::write(odir, e);
    {
        let mut bw = BufWriter::new(&mut tmp);
        let mut size_in = None;
        for r in refs {
            pma_data::interrupt::check()?;
            let (rgb, m, s) = process_image(
                dir,
                &r.rel,
                &annots.cams[r.cam],
                (h, w),
                &mut size_in,
                opts.erode_border,
            )?;
            bw.write_all(&rgb).map_err(terr)?;
            bw.write_all(&m).map_err(terr)?;
            bw.write_all(&s).map_err(terr)?;
            done += 1;
            progress(done, total);
        }
        bw.flush().map_err(terr)?;
    }

    // Background plates: per camera and pixel, the median over the images
    // where the pixel is background; black where it never is.
    let n_cams = annots.cams.len();
    let mut bkgds = vec![0u8; n_cams * hw * 3];
    for &c in &used {
        pma_data::interrupt::check()?;
        let imgs: Vec<usize> = (0..n).filter(|&i| refs[i].cam == c).collect();
        // Rows per block so that the block of every image fits in ~64 MB.
        let rows = (64 << 20) / (imgs.len() * w * 4).max(1);
        let rows = rows.clamp(1, h);
        let mut rgb_blk = vec![0u8; imgs.len() * rows * w * 3];
        let mut m_blk = vec![0u8; imgs.len() * rows * w];
        let mut vals: Vec<u8> = Vec::with_capacity(imgs.len());
        let mut r0 = 0;
        while r0 < h {
            let r1 = (r0 + rows).min(h);
            let nr = r1 - r0;
            for (k, &i) in imgs.iter().enumerate() {
                let base = (i * per) as u64;
                tmp.seek(SeekFrom::Start(base + (r0 * w * 3) as u64))
                    .map_err(terr)?;
                tmp.read_exact(&mut rgb_blk[k * rows * w * 3..k * rows * w * 3 + nr * w * 3])
                    .map_err(terr)?;
                tmp.seek(SeekFrom::Start(base + (3 * hw + r0 * w) as u64))
                    .map_err(terr)?;
                tmp.read_exact(&mut m_blk[k * rows * w..k * rows * w + nr * w])
                    .map_err(terr)?;
            }
            for p in 0..nr * w {
                for ch in 0..3 {
                    vals.clear();
                    for k in 0..imgs.len() {
                        if m_blk[k * rows * w + p] < 1 {
                            vals.push(rgb_blk[(k * rows * w + p) * 3 + ch]);
                        }
                    }
                    if !vals.is_empty() {
                        bkgds[(c * hw + r0 * w + p) * 3 + ch] = median_u8(&mut vals);
                    }
                }
            }
            r0 = r1;
        }
        done += 1;
        progress(done, total);
    }

    // The archive: scene members from the data layer's writer, then pixels.
    let oerr = |e| ConvertError::write(output, e);
    write_archive(ds, output, opts.compression, |zip| {
        let mut buf = vec![0u8; 3 * hw];
        for (key, off, len, ch) in [
            ("imgs", 0, 3 * hw, 3),
            ("masks", 3 * hw, hw, 1),
            ("sampling_masks", 4 * hw, hw, 1),
        ] {
            start_member(zip, output, key, &[n, hw, ch], opts.compression)?;
            for i in 0..n {
                pma_data::interrupt::check()?;
                tmp.seek(SeekFrom::Start((i * per + off) as u64))
                    .map_err(terr)?;
                tmp.read_exact(&mut buf[..len]).map_err(terr)?;
                zip.write_all(&buf[..len]).map_err(oerr)?;
                if key == "imgs" {
                    done += 1;
                    progress(done, total);
                }
            }
        }
        start_member(zip, output, "bkgds", &[n_cams, hw, 3], opts.compression)?;
        zip.write_all(&bkgds).map_err(oerr)?;
        Ok(())
    })
}
