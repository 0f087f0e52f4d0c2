//! `pma metrics A.png B.png [--mask M.png]`: PSNR, SSIM and LPIPS of two images, scored by
//! the same code as `pma eval` (`pma_model::eval::score_image`), so renders from any tool
//! can be compared with pma's numbers.
//!
//! Without a mask every pixel counts: PSNR over the whole image, SSIM and LPIPS on the whole
//! image. With a mask (a PNG, foreground = gray level ≥ 128) the evaluation protocol
//! applies: PSNR over the mask (or its tight box with `--psnr-region bbox`), SSIM and LPIPS
//! on the mask's tight box. Unreadable files and images of different sizes are refused
//! (exit status 2).

use std::path::{Path, PathBuf};

use pma_model::eval::{score_image, PsnrRegion};

use super::Refused;

#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// The image to score (e.g. a render).
    pub a: PathBuf,
    /// The reference image (e.g. ground truth), same size.
    pub b: PathBuf,
    /// Foreground mask (PNG, same size; gray level ≥ 128 = foreground).
    #[arg(long)]
    pub mask: Option<PathBuf>,
    /// Region of the PSNR with a mask: `mask` (foreground pixels) or `bbox` (its tight box).
    #[arg(long, default_value = "mask")]
    pub psnr_region: String,
    /// SSIM data range (2.0 reproduces the reference's scikit-image; 1.0 is the textbook value).
    #[arg(long, default_value_t = 2.0)]
    pub ssim_data_range: f64,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    super::check_paths(
        pma_data::fsio::PathCheck::new()
            .input("image", &args.a)
            .input("reference", &args.b)
            .input_opt("--mask", args.mask.as_deref()),
    )?;
    let region: PsnrRegion = args.psnr_region.parse().map_err(Refused::new)?;
    let (a, (w, h)) = read_rgb(&args.a)?;
    let (b, size_b) = read_rgb(&args.b)?;
    if size_b != (w, h) {
        return Err(Refused::new(format!(
            "{} is {w}x{h} but {} is {}x{}: the images must have the same size",
            args.a.display(),
            args.b.display(),
            size_b.0,
            size_b.1
        ))
        .into());
    }
    let mask = match &args.mask {
        Some(p) => {
            let img = open(p)?.to_luma8();
            if img.dimensions() != (w as u32, h as u32) {
                return Err(Refused::new(format!(
                    "mask {} is {}x{} but the images are {w}x{h}",
                    p.display(),
                    img.width(),
                    img.height()
                ))
                .into());
            }
            img.into_raw()
                .into_iter()
                .map(|v| (v >= 128) as u8)
                .collect()
        }
        None => vec![1u8; w * h],
    };
    let scores = score_image(&a, &b, &mask, h, w, region, args.ssim_data_range)
        .map_err(|e| Refused::new(format!("scoring {w}x{h} images: {e}")))?
        .ok_or_else(|| Refused::new("the mask has no foreground pixel"))?;
    let what = match (&args.mask, region) {
        (None, _) => "all pixels",
        (Some(_), PsnrRegion::Mask) => "mask pixels",
        (Some(_), PsnrRegion::Bbox) => "mask's tight box",
    };
    println!("PSNR   {:.4} dB ({what})", scores.psnr);
    println!("SSIM   {:.4}", scores.ssim);
    if scores.lpips.is_nan() {
        println!(
            "LPIPS  n/a (needs at least {0}x{0} pixels)",
            pma_model::eval::lpips::MIN_SIDE
        );
    } else {
        println!("LPIPS  {:.4}", scores.lpips);
    }
    Ok(())
}

fn open(path: &Path) -> anyhow::Result<image::DynamicImage> {
    pma_data::fsio::open_image(path)
        .map_err(|e| Refused::new(format!("cannot read image {}: {e}", path.display())).into())
}

/// `[h·w·3]` RGB in [0,1] (alpha dropped) and (width, height).
fn read_rgb(path: &Path) -> anyhow::Result<(Vec<f32>, (usize, usize))> {
    let img = open(path)?.to_rgb8();
    let size = (img.width() as usize, img.height() as usize);
    Ok((
        img.into_raw()
            .into_iter()
            .map(|v| v as f32 / 255.0)
            .collect(),
        size,
    ))
}
