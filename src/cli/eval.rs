//! `pma eval`: PSNR and SSIM of a trained avatar on a held-out split, under the protocol of
//! spec data.md §8.3 (a): renders on a black background with the mean frame code, written as
//! 8-bit (`uint8(truncate(255·clamp(rgb)))`) and read back; ground truth = image·mask on
//! black; PSNR over the foreground-mask pixels (the reference's committed H36M code; `--psnr-
//! region bbox` uses the tight box instead); SSIM as scikit-image's `structural_similarity`
//! on the tight-box crop (7×7 uniform window, sample covariance, data_range 2.0 as in the
//! reference's scikit-image 0.19).
//!
//! LPIPS is not reported: it needs pretrained AlexNet/VGG weights, which are not bundled and
//! are never downloaded at run time.
//!
//! Output: a table on stdout, `eval.json` (`{"split", "psnr", "ssim", "per_image": [...]}`)
//! and side-by-side PNGs (ground truth | render | error heat map) for a few images.

use std::io::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context as _};
use candle_core::Tensor;
use pma_data::dataset::{Dataset, Profile, ReadOptions};
use pma_model::avatar::{Avatar, Poses};
use pma_model::image::ImageOptions;
use serde::Serialize;

#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Trained model (`RUN/model.safetensors`).
    #[arg(long)]
    pub model: PathBuf,
    /// Dataset: a pma-npz file, or a directory from `pma synth` holding `<split>.npz`.
    #[arg(long)]
    pub data: PathBuf,
    /// Which images to score: `novel_view`, `novel_pose` or `train`. With a single npz that has
    /// `eval_tag`, the images with that tag; without one, every image of the file.
    #[arg(long, default_value = "novel_view")]
    pub split: String,
    /// Output directory for eval.json and the PNGs (default: `eval_<split>` next to the model).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Region of the PSNR: `mask` (foreground pixels, the reference's committed code) or
    /// `bbox` (the tight box of the mask, as the paper's text says).
    #[arg(long, default_value = "mask")]
    pub psnr_region: String,
    /// SSIM data range (2.0 reproduces the reference's scikit-image; 1.0 is the textbook value).
    #[arg(long, default_value_t = 2.0)]
    pub ssim_data_range: f64,
    /// Score at most this many images, evenly spread over the split (default: all).
    #[arg(long)]
    pub max_images: Option<usize>,
    /// Side-by-side PNGs to write (evenly spread).
    #[arg(long, default_value_t = 4)]
    pub pngs: usize,
    /// Rays per render chunk.
    #[arg(long, default_value_t = 4096)]
    pub chunk: usize,
    /// Training data, for the trivial baseline (mean training foreground colour inside the
    /// mask). Default: `train.npz` beside a split file or in the `--data` directory.
    #[arg(long)]
    pub train_data: Option<PathBuf>,
    #[command(flatten)]
    pub cull: super::bench::CullArgs,
    /// Compute device: cpu, cuda, cuda:N, metal (cuda/metal need a binary built with that
    /// feature).
    #[arg(long, default_value = "cpu")]
    pub device: String,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let device = super::device(&args.device)?;
    let mut avatar = Avatar::load(&args.model, &device)
        .with_context(|| format!("loading model {}", args.model.display()))?;
    args.cull.apply(&mut avatar)?;
    let (data_path, split) = resolve_split(&args.data, &args.split)?;
    let data = read_dataset(&data_path, Profile::Eval)?;
    let images = split_images(&data, &split)?;
    let images = spread(&images, args.max_images.unwrap_or(usize::MAX));
    let out = args.out.clone().unwrap_or_else(|| {
        args.model
            .parent()
            .unwrap_or(Path::new("."))
            .join(format!("eval_{}", split.name))
    });
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let baseline = match baseline_source(&args, &data_path) {
        Some(p) => Some(mean_foreground_colour(&read_dataset(&p, Profile::Eval)?)?),
        None => None,
    };
    let opts = EvalOptions {
        region: args.psnr_region.parse()?,
        ssim_data_range: args.ssim_data_range,
        chunk: args.chunk,
        png_dir: Some(out.clone()),
        pngs: args.pngs,
        baseline_colour: baseline,
    };
    let report = evaluate(&avatar, &data, &split.name, &images, &opts, &mut |_, _| {})?;
    print_table(&report);
    let json = out.join("eval.json");
    write_json_atomic(&report, &json)?;
    println!(
        "wrote {} and {} side-by-side PNG(s) to {}",
        json.display(),
        report.pngs.len(),
        out.display()
    );
    Ok(())
}

/// Which images of a file form the split.
#[derive(Debug, Clone, PartialEq)]
pub struct Split {
    pub name: String,
    /// `eval_tag` value selecting the images; `None` = every image of the file.
    pub tag: Option<i8>,
}

fn split_tag(name: &str) -> anyhow::Result<i8> {
    Ok(match name {
        "train" => 0,
        "novel_view" => 1,
        "novel_pose" => 2,
        "val" => 3,
        other => bail!("unknown split {other:?}; expected novel_view, novel_pose, train or val"),
    })
}

/// A directory means `DIR/<split>.npz` (the layout `pma synth` writes), whose images are all
/// the split; a file is filtered by its `eval_tag` when it has one.
pub fn resolve_split(data: &Path, split: &str) -> anyhow::Result<(PathBuf, Split)> {
    let tag = split_tag(split)?;
    if data.is_dir() {
        let path = data.join(format!("{split}.npz"));
        if !path.is_file() {
            bail!(
                "{} is a directory without {split}.npz (pass the npz file itself?)",
                data.display()
            );
        }
        return Ok((
            path,
            Split {
                name: split.to_string(),
                tag: None,
            },
        ));
    }
    if !data.is_file() {
        bail!("dataset {} does not exist", data.display());
    }
    Ok((
        data.to_path_buf(),
        Split {
            name: split.to_string(),
            tag: Some(tag),
        },
    ))
}

pub fn read_dataset(path: &Path, profile: Profile) -> anyhow::Result<Dataset> {
    let data = Dataset::read(path, &ReadOptions::new(profile))
        .with_context(|| format!("reading dataset {} ({profile} profile)", path.display()))?;
    for w in &data.warnings {
        eprintln!("warning: {}: {w}", path.display());
    }
    Ok(data)
}

/// Image indices of `split` in `data`.
pub fn split_images(data: &Dataset, split: &Split) -> anyhow::Result<Vec<usize>> {
    let n = data.n_images();
    let images: Vec<usize> = match (&split.tag, &data.eval_tag) {
        (Some(tag), Some(tags)) => (0..n).filter(|&i| tags[i] == *tag).collect(),
        _ => (0..n).collect(),
    };
    if images.is_empty() {
        bail!("{}: no images in split {:?}", data.source, split.name);
    }
    Ok(images)
}

/// At most `k` of `items`, evenly spread, first and last included.
pub fn spread(items: &[usize], k: usize) -> Vec<usize> {
    if k >= items.len() {
        return items.to_vec();
    }
    if k == 0 {
        return Vec::new();
    }
    if k == 1 {
        return vec![items[0]];
    }
    let mut out: Vec<usize> = (0..k)
        .map(|i| items[i * (items.len() - 1) / (k - 1)])
        .collect();
    out.dedup();
    out
}

fn baseline_source(args: &Args, data_path: &Path) -> Option<PathBuf> {
    if let Some(p) = &args.train_data {
        return Some(p.clone());
    }
    let beside = data_path.parent()?.join("train.npz");
    beside.is_file().then_some(beside)
}

/// Mean colour (in [0,1]) of the foreground pixels of every image: the trivial baseline
/// predicts it inside the ground-truth mask and black elsewhere.
pub fn mean_foreground_colour(data: &Dataset) -> anyhow::Result<[f64; 3]> {
    let mut sum = [0f64; 3];
    let mut count = 0u64;
    for n in 0..data.n_images() {
        let (Some(img), Some(mask)) = (data.image(n), data.mask(n)) else {
            bail!("{}: image {n} has no pixels or mask", data.source);
        };
        for (px, m) in img.outer_iter().zip(mask.outer_iter()) {
            if m[0] > 0 {
                for c in 0..3 {
                    sum[c] += px[c] as f64 / 255.0;
                }
                count += 1;
            }
        }
    }
    if count == 0 {
        bail!("{}: no foreground pixels to average", data.source);
    }
    Ok(sum.map(|s| s / count as f64))
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum PsnrRegion {
    Mask,
    Bbox,
}

impl std::str::FromStr for PsnrRegion {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> anyhow::Result<Self> {
        match s {
            "mask" => Ok(Self::Mask),
            "bbox" => Ok(Self::Bbox),
            other => bail!("unknown PSNR region {other:?}; expected mask or bbox"),
        }
    }
}

#[derive(Debug, Clone)]
pub struct EvalOptions {
    pub region: PsnrRegion,
    pub ssim_data_range: f64,
    pub chunk: usize,
    /// Where side-by-side PNGs go (`None`: no PNGs).
    pub png_dir: Option<PathBuf>,
    pub pngs: usize,
    /// Colour of the trivial baseline; `None` skips it.
    pub baseline_colour: Option<[f64; 3]>,
}

impl EvalOptions {
    /// Protocol defaults, no files.
    #[cfg(feature = "train")]
    pub fn quick(chunk: usize) -> Self {
        Self {
            region: PsnrRegion::Mask,
            ssim_data_range: 2.0,
            chunk,
            png_dir: None,
            pngs: 0,
            baseline_colour: None,
        }
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct ImageScore {
    /// Image index in the dataset file.
    pub index: usize,
    pub psnr: f64,
    pub ssim: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub baseline_psnr: Option<f64>,
}

#[derive(Debug, Clone, Serialize)]
pub struct EvalReport {
    pub split: String,
    pub psnr: f64,
    pub ssim: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub baseline_psnr: Option<f64>,
    pub psnr_region: PsnrRegion,
    pub ssim_data_range: f64,
    pub lpips: Option<f64>,
    pub lpips_note: &'static str,
    pub images: usize,
    pub render_s: f64,
    pub per_image: Vec<ImageScore>,
    pub pngs: Vec<PathBuf>,
}

pub const LPIPS_NOTE: &str =
    "LPIPS not computed: it needs pretrained AlexNet/VGG weights, which pma does not bundle or download";

/// Render and score `images` of `data` (see the module docs for the protocol). `progress`
/// receives (done, total).
pub fn evaluate(
    avatar: &Avatar,
    data: &Dataset,
    split: &str,
    images: &[usize],
    opts: &EvalOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> anyhow::Result<EvalReport> {
    let png_set: Vec<usize> = if opts.png_dir.is_some() {
        spread(images, opts.pngs)
    } else {
        Vec::new()
    };
    let (h, w) = (data.height(), data.width());
    let start = std::time::Instant::now();
    let mut per_image = Vec::with_capacity(images.len());
    let mut pngs = Vec::new();
    for (k, &n) in images.iter().enumerate() {
        let rendered = render_dataset_image(avatar, data, n, opts.chunk)?;
        let pred = quantize(&rendered);
        let (gt, mask) = ground_truth(data, n)?;
        let Some(scores) = score(&pred, &gt, &mask, h, w, opts)? else {
            eprintln!(
                "warning: {}: image {n} has an empty mask; skipped (spec data.md §10.23)",
                data.source
            );
            continue;
        };
        let baseline_psnr = match opts.baseline_colour {
            Some(c) => {
                let base: Vec<f32> = mask
                    .iter()
                    .flat_map(|&m| if m > 0 { c.map(|v| v as f32) } else { [0.0; 3] })
                    .collect();
                score(&quantize_f32(&base), &gt, &mask, h, w, opts)?.map(|s| s.0)
            }
            None => None,
        };
        per_image.push(ImageScore {
            index: n,
            psnr: scores.0,
            ssim: scores.1,
            baseline_psnr,
        });
        if let (Some(dir), true) = (&opts.png_dir, png_set.contains(&n)) {
            let path = dir.join(format!("{split}_{n:04}.png"));
            write_png_atomic(&side_by_side(&gt, &pred, h, w), &path)?;
            pngs.push(path);
        }
        progress(k + 1, images.len());
    }
    if per_image.is_empty() {
        bail!(
            "{}: no image of split {split:?} could be scored",
            data.source
        );
    }
    let mean = |f: &dyn Fn(&ImageScore) -> f64| {
        per_image.iter().map(f).sum::<f64>() / per_image.len() as f64
    };
    let baseline_psnr =
        if per_image.iter().all(|s| s.baseline_psnr.is_some()) && opts.baseline_colour.is_some() {
            Some(mean(&|s| s.baseline_psnr.unwrap_or(f64::NAN)))
        } else {
            None
        };
    Ok(EvalReport {
        split: split.to_string(),
        psnr: mean(&|s| s.psnr),
        ssim: mean(&|s| s.ssim),
        baseline_psnr,
        psnr_region: opts.region,
        ssim_data_range: opts.ssim_data_range,
        lpips: None,
        lpips_note: LPIPS_NOTE,
        images: per_image.len(),
        render_s: start.elapsed().as_secs_f64(),
        per_image,
        pngs,
    })
}

/// Render image `n` of `data` with its pose and camera, black background, mean frame code
/// (spec data.md §8.4: index −1 for unseen frames).
pub fn render_dataset_image(
    avatar: &Avatar,
    data: &Dataset,
    n: usize,
    chunk: usize,
) -> anyhow::Result<pma_model::image::RenderedImage> {
    let device = avatar.device().clone();
    let p = data.pose_row(n)?;
    let cam = data.image_camera(n)?;
    let (Some(skts), Some(cyls), Some(kp3d)) = (&data.skts, &data.cyls, data.pose_kp3d(p)) else {
        bail!(
            "{}: pose {p} lacks skts/cyls/kp3d (derived on import; is the file valid?)",
            data.source
        );
    };
    let skts: Vec<f32> = skts
        .outer_iter()
        .nth(p)
        .map(|m| m.iter().copied().collect())
        .unwrap_or_default();
    let cyl: Vec<f32> = cyls.row(p).to_vec();
    let poses = Poses {
        bones: vec![data.pose_bones(p)],
        skts: Tensor::from_vec(skts, (1, 24, 4, 4), &device)?,
        cyls: Tensor::from_vec(cyl, (1, 5), &device)?,
    };
    let opts = ImageOptions {
        chunk,
        head: data.head()?,
        device,
    };
    Ok(avatar.render_image(&poses, &kp3d, &cam, None, &opts)?)
}

/// `uint8(truncate(255·clamp(rgb, 0, 1))) / 255`, what the reference scores after writing PNGs.
pub fn quantize(img: &pma_model::image::RenderedImage) -> Vec<f32> {
    quantize_f32(&img.rgb)
}

fn quantize_f32(rgb: &[f32]) -> Vec<f32> {
    pma_data::metrics::quantize(rgb)
}

/// Ground truth of image `n` composited on black ([H·W·3] in [0,1]) and its mask ([H·W]).
pub fn ground_truth(data: &Dataset, n: usize) -> anyhow::Result<(Vec<f32>, Vec<u8>)> {
    let (Some(img), Some(mask)) = (data.image(n), data.mask(n)) else {
        bail!(
            "{}: image {n} has no pixels or mask (eval profile)",
            data.source
        );
    };
    let mask: Vec<u8> = mask.outer_iter().map(|m| (m[0] > 0) as u8).collect();
    let gt = img
        .outer_iter()
        .zip(&mask)
        .flat_map(|(px, &m)| [0, 1, 2].map(|c| if m > 0 { px[c] as f32 / 255.0 } else { 0.0 }))
        .collect();
    Ok((gt, mask))
}

/// (PSNR, SSIM) of `pred` against `gt` ([H·W·3] in [0,1]); `None` when the mask is empty.
/// The protocol lives in `pma_data::metrics`.
fn score(
    pred: &[f32],
    gt: &[f32],
    mask: &[u8],
    h: usize,
    w: usize,
    opts: &EvalOptions,
) -> anyhow::Result<Option<(f64, f64)>> {
    let region = match opts.region {
        PsnrRegion::Mask => pma_data::metrics::Region::Mask,
        PsnrRegion::Bbox => pma_data::metrics::Region::Bbox,
    };
    Ok(pma_data::metrics::score_image(
        pred,
        gt,
        mask,
        h,
        w,
        region,
        opts.ssim_data_range,
    )?)
}

/// Inclusive-exclusive tight box `(y0, x0, y1, x1)` of the nonzero mask pixels (OpenCV
/// `boundingRect`), or `None` for an empty mask.
#[cfg(test)]
fn tight_box(mask: &[u8], h: usize, w: usize) -> Option<(usize, usize, usize, usize)> {
    pma_data::metrics::tight_box(mask, h, w).map(|b| (b.y0, b.x0, b.y1, b.x1))
}

/// scikit-image `structural_similarity` as the reference called it (spec data.md §8.3 a);
/// see `pma_data::metrics::ssim`. a, b: [h·w·3] channels last.
#[cfg(test)]
fn ssim_skimage(a: &[f64], b: &[f64], h: usize, w: usize, data_range: f64) -> anyhow::Result<f64> {
    Ok(pma_data::metrics::ssim(a, b, h, w, data_range)?)
}

/// [GT | render | error heat map], upscaled so small images stay readable.
pub fn side_by_side(gt: &[f32], pred: &[f32], h: usize, w: usize) -> image::RgbImage {
    let k = 256usize.div_ceil(h.max(1)).clamp(1, 8) as u32;
    let gap = 4u32;
    let (pw, ph) = (w as u32 * k, h as u32 * k);
    let mut out = image::RgbImage::from_pixel(3 * pw + 2 * gap, ph, image::Rgb([255, 255, 255]));
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
                    out.put_pixel(px, py, image::Rgb(g));
                    out.put_pixel(pw + gap + px, py, image::Rgb(p));
                    out.put_pixel(2 * (pw + gap) + px, py, image::Rgb(e));
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

pub fn print_table(report: &EvalReport) {
    println!("split {} ({} images)", report.split, report.images);
    println!("{:>6}  {:>8}  {:>7}", "image", "PSNR", "SSIM");
    for s in &report.per_image {
        println!("{:>6}  {:>8.3}  {:>7.4}", s.index, s.psnr, s.ssim);
    }
    println!("{:>6}  {:>8.3}  {:>7.4}", "mean", report.psnr, report.ssim);
    if let Some(b) = report.baseline_psnr {
        println!("baseline (mean training colour inside the mask): PSNR {b:.3}");
    }
    println!(
        "LPIPS: n/a ({})",
        LPIPS_NOTE.trim_start_matches("LPIPS not computed: ")
    );
}

/// Encode `img` as PNG and replace `path` atomically.
pub fn write_png_atomic(img: &image::RgbImage, path: &Path) -> anyhow::Result<()> {
    let mut bytes = Vec::new();
    img.write_to(
        &mut std::io::Cursor::new(&mut bytes),
        image::ImageFormat::Png,
    )
    .with_context(|| format!("encoding {}", path.display()))?;
    write_atomic(path, &bytes)
}

/// Serialise `value` as pretty JSON and replace `path` atomically.
pub fn write_json_atomic<T: serde::Serialize>(value: &T, path: &Path) -> anyhow::Result<()> {
    let mut text = serde_json::to_string_pretty(value)?;
    text.push('\n');
    write_atomic(path, text.as_bytes())
}

/// Temporary file in the target directory, then rename: readers never see a partial file.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let mut tmp = tempfile::NamedTempFile::new_in(dir)
        .with_context(|| format!("creating a file in {}", dir.display()))?;
    tmp.write_all(bytes)
        .with_context(|| format!("writing {}", path.display()))?;
    tmp.as_file()
        .sync_all()
        .with_context(|| format!("writing {}", path.display()))?;
    // Temporary files are created 0600; reports and images are ordinary files.
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        tmp.as_file()
            .set_permissions(std::fs::Permissions::from_mode(0o644))
            .with_context(|| format!("writing {}", path.display()))?;
    }
    tmp.persist(path)
        .with_context(|| format!("replacing {}", path.display()))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spread_picks_evenly_with_ends() {
        let v: Vec<usize> = (10..20).collect();
        assert_eq!(spread(&v, 3), vec![10, 14, 19]);
        assert_eq!(spread(&v, 1), vec![10]);
        assert_eq!(spread(&v, 0), Vec::<usize>::new());
        assert_eq!(spread(&v, 50), v);
    }

    #[test]
    fn heat_ramp_is_monotone_in_brightness() {
        let lum = |c: [u8; 3]| c.iter().map(|&v| v as u32).sum::<u32>();
        let mut last = 0;
        for i in 0..=20 {
            let l = lum(heat(i as f32 / 20.0));
            assert!(l >= last, "{i}");
            last = l;
        }
        assert_eq!(heat(f32::NAN), heat(1.0));
    }

    #[test]
    fn ssim_is_one_for_identical_images_and_drops_with_noise() {
        let (h, w) = (12, 10);
        let a: Vec<f64> = (0..h * w * 3)
            .map(|i| ((i * 37) % 101) as f64 / 100.0)
            .collect();
        assert!((ssim_skimage(&a, &a, h, w, 2.0).unwrap() - 1.0).abs() < 1e-12);
        let b: Vec<f64> = a
            .iter()
            .enumerate()
            .map(|(i, v)| v + if i % 2 == 0 { 0.2 } else { -0.2 })
            .collect();
        let s = ssim_skimage(&a, &b, h, w, 2.0).unwrap();
        assert!(s < 0.95, "{s}");
        // A smaller data range makes the same error count more.
        assert!(ssim_skimage(&a, &b, h, w, 1.0).unwrap() < s);
        assert!(ssim_skimage(&a, &b, 6, w, 2.0).is_err());
    }

    /// A hand-computed case: constant images a, b in one 7×7 window (all variances 0), so
    /// SSIM = (2ab + C1) / (a² + b² + C1).
    #[test]
    fn ssim_constant_windows_reduce_to_the_luminance_term() {
        let (a, b) = (0.5f64, 0.25f64);
        let c1 = (0.01f64 * 2.0).powi(2);
        let want = (2.0 * a * b + c1) / (a * a + b * b + c1);
        let got = ssim_skimage(&vec![a; 7 * 7 * 3], &vec![b; 7 * 7 * 3], 7, 7, 2.0).unwrap();
        assert!((got - want).abs() < 1e-12, "{got} vs {want}");
    }

    #[test]
    fn psnr_regions_and_empty_masks() {
        let (h, w) = (8, 8);
        let mut mask = vec![0u8; h * w];
        for y in 1..8 {
            for x in 0..7 {
                if (x + y) % 3 != 0 {
                    mask[y * w + x] = 1;
                }
            }
        }
        let gt = vec![0.5f32; h * w * 3];
        // Error 0.1 on foreground pixels only: mask PSNR = 20 dB, box PSNR higher.
        let pred: Vec<f32> = (0..h * w * 3)
            .map(|i| if mask[i / 3] > 0 { 0.6 } else { 0.5 })
            .collect();
        let mut opts = EvalOptions {
            region: PsnrRegion::Mask,
            ssim_data_range: 2.0,
            chunk: 16,
            png_dir: None,
            pngs: 0,
            baseline_colour: None,
        };
        let (p_mask, _) = score(&pred, &gt, &mask, h, w, &opts).unwrap().unwrap();
        assert!((p_mask - 20.0).abs() < 1e-4, "{p_mask}");
        opts.region = PsnrRegion::Bbox;
        let (p_box, _) = score(&pred, &gt, &mask, h, w, &opts).unwrap().unwrap();
        assert!(p_box > p_mask);
        assert!(score(&pred, &gt, &vec![0; h * w], h, w, &opts)
            .unwrap()
            .is_none());
        assert_eq!(tight_box(&mask, h, w), Some((1, 0, 8, 7)));
    }

    #[test]
    fn quantization_truncates_like_the_reference() {
        assert_eq!(
            quantize_f32(&[1.001, -0.001, 0.5, 0.99999]),
            vec![1.0, 0.0, 127.0 / 255.0, 254.0 / 255.0]
        );
    }
}
