//! Evaluation of a trained avatar: PSNR, SSIM and LPIPS on a held-out split, under the protocol of
//! the project's notes (`docs/conventions.md`, "Evaluation protocol"): renders on a black
//! background with the mean frame code, written as 8-bit (`uint8(truncate(255·clamp(rgb)))`)
//! and read back; ground truth = image·mask on black; PSNR over the foreground-mask pixels
//! (the reference's committed H36M code; [`PsnrRegion::Bbox`] uses the tight box instead);
//! SSIM as scikit-image's `structural_similarity` on the tight-box crop (7×7 uniform window,
//! sample covariance, data range 2.0 as in the reference's scikit-image 0.19); LPIPS (AlexNet,
//! v0.1 heads, inputs mapped to [−1,1]) on the same tight-box crop, grown to the 31×31 the
//! network needs where the image allows. PSNR and SSIM live in `pma_data::metrics`, LPIPS in
//! [`crate::eval::lpips`]; [`score_image`] combines them.
//! On the same crop, [`spectrum`] compares the radially binned power spectra of render and
//! ground truth (`freq_distance`).
//!
//! Which images form a split: a directory holds `<split>.npz` (the layout `pma synth`
//! writes), all of whose images are the split; a file is filtered by its `eval_tag`. A file
//! without `eval_tag` does not say which split its images belong to, so it counts only as
//! the split its name gives (`novel_pose.npz`); any other split is refused, never silently
//! replaced by the file's images.
//!
//! Training scores its held-out curve with [`evaluate`]; nothing here depends on training.

use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
use pma_data::dataset::{Dataset, Profile, ReadOptions};
use pma_data::skeleton::Joints;
use serde::Serialize;

use crate::render::avatar::{Avatar, Poses};
use crate::render::image::{ImageOptions, RenderedImage};
use crate::render::options::PassOptions;

pub mod lpips;
mod png;
pub mod spectrum;
mod split;

pub use png::{heat, side_by_side, write_png};
pub use split::{
    held_out_images, read_split, resolve_split, split_images, spread, Split, SplitData,
};

#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    /// A split name other than the four known ones.
    #[error("unknown split {0:?}; expected novel_view, novel_pose, train or val")]
    UnknownSplit(String),

    #[error("unknown PSNR region {0:?}; expected mask or bbox")]
    UnknownRegion(String),

    #[error("dataset {} does not exist", .0.display())]
    NoData(PathBuf),

    /// The dataset path is there but is not a file or directory that can hold one (a FIFO,
    /// a device), or cannot be looked at.
    #[error("dataset {}: {what}", path.display())]
    NotData { path: PathBuf, what: String },

    /// A directory given as the dataset lacks the split's file.
    #[error("{} is a directory without {split}.npz (pass the npz file itself?)", dir.display())]
    NoSplitFile { dir: PathBuf, split: String },

    /// The file holds no image of the split (by its `eval_tag`, or, without one, by its name).
    #[error("{}: no images of split {split:?} ({why})", path.display())]
    SplitNotInFile {
        path: PathBuf,
        split: String,
        why: String,
    },

    /// Keys the protocol needs are missing from a file that passed validation.
    #[error("{source_name}: {what}")]
    Incomplete { source_name: String, what: String },

    /// Every image of the split had an empty mask.
    #[error("{source_name}: no image of split {split:?} could be scored")]
    NothingScored { source_name: String, split: String },

    /// Writing one of the evaluation's files failed.
    #[error(transparent)]
    File(#[from] pma_data::FileError),

    #[error("encoding {}: {source}", path.display())]
    Png {
        path: PathBuf,
        #[source]
        source: ::image::ImageError,
    },

    /// A dataset that cannot be read for the profile it is used with.
    #[error("reading dataset {} ({profile} profile): {source}", path.display())]
    Read {
        path: PathBuf,
        profile: Profile,
        #[source]
        source: Box<pma_data::DataError>,
    },

    // Boxed so `Result<_, EvalError>` stays small.
    #[error(transparent)]
    Model(Box<crate::error::ModelError>),

    #[error(transparent)]
    Data(Box<pma_data::DataError>),

    #[error(transparent)]
    Candle(Box<candle_core::Error>),
}

impl pma_data::ExitKind for EvalError {
    fn kind(&self) -> pma_data::ErrorKind {
        use pma_data::ErrorKind;
        match self {
            EvalError::UnknownSplit(_)
            | EvalError::UnknownRegion(_)
            | EvalError::NoData(_)
            | EvalError::NotData { .. }
            | EvalError::NoSplitFile { .. }
            | EvalError::SplitNotInFile { .. }
            | EvalError::Incomplete { .. }
            | EvalError::NothingScored { .. } => ErrorKind::Refused,
            // The evaluation's own files (PNGs) could not be written.
            EvalError::Png { .. } | EvalError::Candle(_) => ErrorKind::Failure,
            EvalError::File(f) => f.kind(),
            EvalError::Read { source, .. } => source.kind(),
            EvalError::Model(m) => m.kind(),
            EvalError::Data(d) => d.kind(),
        }
    }
}

impl EvalError {
    /// The user asked for something the input does not have (a split, a file): a problem
    /// with the command or its input rather than a failure of the evaluation.
    pub fn is_bad_input(&self) -> bool {
        matches!(
            self,
            Self::UnknownSplit(_)
                | Self::UnknownRegion(_)
                | Self::NoData(_)
                | Self::NotData { .. }
                | Self::NoSplitFile { .. }
                | Self::SplitNotInFile { .. }
        )
    }

    /// Whether the evaluation stopped because an interruption was requested.
    pub fn is_interrupted(&self) -> bool {
        pma_data::interrupt::caused(self)
    }

    fn incomplete(data: &Dataset, what: String) -> Self {
        Self::Incomplete {
            source_name: data.source.clone(),
            what,
        }
    }
}

crate::error::interrupted_as_model!(EvalError);

crate::error::boxed_from!(
    EvalError:
    Model(crate::error::ModelError),
    Data(pma_data::DataError),
    Candle(candle_core::Error),
);

pub type Result<T> = std::result::Result<T, EvalError>;

/// Read a dataset for `profile`. Its warnings are in `Dataset::warnings` for the caller to
/// show.
pub fn read_dataset(path: &Path, profile: Profile) -> Result<Dataset> {
    Dataset::read(path, &ReadOptions::new(profile)).map_err(|e| EvalError::Read {
        path: path.to_path_buf(),
        profile,
        source: Box::new(e),
    })
}

/// Mean colour (in [0,1]) of the foreground pixels of every image: the trivial baseline
/// predicts it inside the ground-truth mask and black elsewhere.
pub fn mean_foreground_colour(data: &Dataset) -> Result<[f64; 3]> {
    let mut sum = [0f64; 3];
    let mut count = 0u64;
    for n in 0..data.n_images() {
        let (Some(img), Some(mask)) = (data.image(n), data.mask(n)) else {
            return Err(EvalError::incomplete(
                data,
                format!("image {n} has no pixels or mask"),
            ));
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
        return Err(EvalError::incomplete(
            data,
            "no foreground pixels to average".into(),
        ));
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
    type Err = EvalError;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "mask" => Ok(Self::Mask),
            "bbox" => Ok(Self::Bbox),
            other => Err(EvalError::UnknownRegion(other.to_string())),
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
    /// What the renders may leave out (parity by default).
    pub pass: PassOptions,
}

impl EvalOptions {
    /// Protocol defaults, no files.
    pub fn quick(chunk: usize) -> Self {
        Self {
            region: PsnrRegion::Mask,
            ssim_data_range: 2.0,
            chunk,
            png_dir: None,
            pngs: 0,
            baseline_colour: None,
            pass: PassOptions::default(),
        }
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct ImageScore {
    /// Image index in the dataset file.
    pub index: usize,
    pub psnr: f64,
    pub ssim: f64,
    /// NaN (`null` in JSON) when the image is smaller than LPIPS's 31×31 minimum.
    pub lpips: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub baseline_psnr: Option<f64>,
    /// Frequency-histogram distance of the render to the ground truth ([`spectrum`]).
    pub freq_distance: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct EvalReport {
    pub split: String,
    pub psnr: f64,
    pub ssim: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub baseline_psnr: Option<f64>,
    pub lpips: f64,
    pub psnr_region: PsnrRegion,
    pub ssim_data_range: f64,
    pub images: usize,
    pub render_s: f64,
    pub per_image: Vec<ImageScore>,
    pub pngs: Vec<PathBuf>,
    /// `freq_distance`, `freq_bin_edges`, `freq_hist_render`, `freq_hist_gt`.
    #[serde(flatten)]
    pub freq: spectrum::FreqSummary,
    /// Images left out because their mask is empty (no pixels to score).
    #[serde(skip)]
    pub empty_masks: Vec<usize>,
}

/// Render and score `images` of `data` (see the module docs for the protocol). `progress`
/// receives (done, total).
pub fn evaluate(
    avatar: &Avatar,
    data: &Dataset,
    split: &str,
    images: &[usize],
    opts: &EvalOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<EvalReport> {
    let png_set: Vec<usize> = if opts.png_dir.is_some() {
        spread(images, opts.pngs)
    } else {
        Vec::new()
    };
    let (h, w) = (data.height(), data.width());
    let start = std::time::Instant::now();
    let mut per_image = Vec::with_capacity(images.len());
    let mut pngs = Vec::new();
    let mut empty_masks = Vec::new();
    let mut freq = spectrum::FreqAccumulator::default();
    for (k, &n) in images.iter().enumerate() {
        crate::interrupt::check()?;
        let rendered = render_dataset_image(avatar, data, n, opts.chunk, &opts.pass)?;
        let pred = quantize(&rendered);
        let (gt, mask) = ground_truth(data, n)?;
        let Some(scores) = score(&pred, &gt, &mask, h, w, opts)? else {
            empty_masks.push(n);
            continue;
        };
        let baseline_psnr = match opts.baseline_colour {
            Some(c) => {
                let base: Vec<f32> = mask
                    .iter()
                    .flat_map(|&m| if m > 0 { c.map(|v| v as f32) } else { [0.0; 3] })
                    .collect();
                pma_data::metrics::psnr_masked(
                    &pma_data::metrics::quantize(&base),
                    &gt,
                    &mask,
                    h,
                    w,
                    opts.region.into(),
                )?
            }
            None => None,
        };
        let spectra = spectrum::image_spectra(&pred, &gt, &mask, h, w);
        let freq_distance = spectra.as_ref().map_or(f64::NAN, |s| s.distance);
        spectra.iter().for_each(|s| freq.add(s));
        per_image.push(ImageScore {
            index: n,
            psnr: scores.psnr,
            ssim: scores.ssim,
            lpips: scores.lpips,
            baseline_psnr,
            freq_distance,
        });
        if let (Some(dir), true) = (&opts.png_dir, png_set.contains(&n)) {
            let path = dir.join(format!("{split}_{n:04}.png"));
            write_png(&side_by_side(&gt, &pred, h, w), &path)?;
            pngs.push(path);
        }
        progress(k + 1, images.len());
    }
    if per_image.is_empty() {
        return Err(EvalError::NothingScored {
            source_name: data.source.clone(),
            split: split.to_string(),
        });
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
        lpips: mean(&|s| s.lpips),
        psnr_region: opts.region,
        ssim_data_range: opts.ssim_data_range,
        images: per_image.len(),
        render_s: start.elapsed().as_secs_f64(),
        per_image,
        pngs,
        freq: freq.finish(),
        empty_masks,
    })
}

/// A split scored by [`score_split_file`], with what reading its file said.
#[derive(Debug, Clone)]
pub struct ScoredSplit {
    pub report: EvalReport,
    /// The file as messages name it ([`Dataset::source`]).
    pub source: String,
    /// The dataset's warnings, for the caller to show.
    pub warnings: Vec<pma_data::dataset::Warning>,
}

/// Read `path`, all of whose images are the split `split` (the layout `pma synth` writes,
/// see [`Split::whole_file`]), and score at most `max_images` of them evenly spread over it
/// (0 = all) with [`evaluate`].
pub fn score_split_file(
    avatar: &Avatar,
    path: &Path,
    split: &str,
    max_images: usize,
    opts: &EvalOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<ScoredSplit> {
    let data = read_dataset(path, Profile::Eval)?;
    let limit = match max_images {
        0 => usize::MAX,
        n => n,
    };
    let images = spread(
        &split_images(&data, path, &Split::whole_file(split)?)?,
        limit,
    );
    let report = evaluate(avatar, &data, split, &images, opts, progress)?;
    Ok(ScoredSplit {
        report,
        source: data.source,
        warnings: data.warnings,
    })
}

/// Pose row `p` of `data` as model input, with its posed joints (for the render box).
pub fn dataset_pose(data: &Dataset, p: usize, device: &Device) -> Result<(Poses, Joints)> {
    let (Some(skts), Some(cyls), Some(kp3d)) = (&data.skts, &data.cyls, data.pose_kp3d(p)) else {
        return Err(EvalError::incomplete(
            data,
            format!("pose {p} lacks skts/cyls/kp3d (derived on import; is the file valid?)"),
        ));
    };
    let skts: Vec<f32> = skts
        .outer_iter()
        .nth(p)
        .map(|m| m.iter().copied().collect())
        .unwrap_or_default();
    let poses = Poses {
        bones: vec![data.pose_bones(p)],
        skts: Tensor::from_vec(skts, (1, 24, 4, 4), device)?,
        cyls: Tensor::from_vec(cyls.row(p).to_vec(), (1, 5), device)?,
    };
    Ok((poses, kp3d))
}

/// Render image `n` of `data` with its pose and camera, black background, mean frame code
/// (frame-code index −1, as for frames the model has not seen), leaving out what `pass` says.
pub fn render_dataset_image(
    avatar: &Avatar,
    data: &Dataset,
    n: usize,
    chunk: usize,
    pass: &PassOptions,
) -> Result<RenderedImage> {
    let device = avatar.device().clone();
    let p = data.pose_row(n)?;
    let cam = data.image_camera(n)?;
    let (poses, kp3d) = dataset_pose(data, p, &device)?;
    let opts = ImageOptions {
        chunk,
        head: data.head()?,
        device,
        pass: pass.clone(),
    };
    Ok(avatar.render_image(&poses, &kp3d, &cam, None, &opts)?)
}

/// `uint8(truncate(255·clamp(rgb, 0, 1))) / 255`, what the reference scores after writing PNGs.
pub fn quantize(img: &RenderedImage) -> Vec<f32> {
    pma_data::metrics::quantize(&img.rgb)
}

/// Ground truth of image `n` composited on black ([H·W·3] in [0,1]) and its mask ([H·W]).
pub fn ground_truth(data: &Dataset, n: usize) -> Result<(Vec<f32>, Vec<u8>)> {
    let (Some(img), Some(mask)) = (data.image(n), data.mask(n)) else {
        return Err(EvalError::incomplete(
            data,
            format!("image {n} has no pixels or mask (eval profile)"),
        ));
    };
    let mask: Vec<u8> = mask.outer_iter().map(|m| (m[0] > 0) as u8).collect();
    let gt = img
        .outer_iter()
        .zip(&mask)
        .flat_map(|(px, &m)| [0, 1, 2].map(|c| if m > 0 { px[c] as f32 / 255.0 } else { 0.0 }))
        .collect();
    Ok((gt, mask))
}

impl From<PsnrRegion> for pma_data::metrics::Region {
    fn from(r: PsnrRegion) -> Self {
        match r {
            PsnrRegion::Mask => Self::Mask,
            PsnrRegion::Bbox => Self::Bbox,
        }
    }
}

/// The protocol's scores of one image.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Scores {
    pub psnr: f64,
    pub ssim: f64,
    /// NaN when the image is smaller than [`crate::eval::lpips::MIN_SIDE`] on a side.
    pub lpips: f64,
}

/// PSNR over `region`, SSIM and LPIPS on the tight box of `mask` (see the module docs) of
/// `pred` against `gt` (`[h·w·3]` in [0,1]; `mask`: `[h·w]`, nonzero = foreground); `None`
/// when the mask is empty. `pma eval`, training's held-out curve and `pma metrics` all score
/// through here.
pub fn score_image(
    pred: &[f32],
    gt: &[f32],
    mask: &[u8],
    h: usize,
    w: usize,
    region: PsnrRegion,
    ssim_data_range: f64,
) -> Result<Option<Scores>> {
    let Some((psnr, ssim)) =
        pma_data::metrics::score_image(pred, gt, mask, h, w, region.into(), ssim_data_range)?
    else {
        return Ok(None);
    };
    let lpips = crate::eval::lpips::Lpips::shared()?
        .distance_masked(pred, gt, mask, h, w)?
        .unwrap_or(f64::NAN);
    Ok(Some(Scores { psnr, ssim, lpips }))
}

fn score(
    pred: &[f32],
    gt: &[f32],
    mask: &[u8],
    h: usize,
    w: usize,
    opts: &EvalOptions,
) -> Result<Option<Scores>> {
    score_image(pred, gt, mask, h, w, opts.region, opts.ssim_data_range)
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

    fn ssim_skimage(a: &[f64], b: &[f64], h: usize, w: usize, data_range: f64) -> Result<f64> {
        Ok(pma_data::metrics::ssim(a, b, h, w, data_range)?)
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
        let mut opts = EvalOptions::quick(16);
        let p_mask = score(&pred, &gt, &mask, h, w, &opts).unwrap().unwrap().psnr;
        assert!((p_mask - 20.0).abs() < 1e-4, "{p_mask}");
        opts.region = PsnrRegion::Bbox;
        let p_box = score(&pred, &gt, &mask, h, w, &opts).unwrap().unwrap().psnr;
        assert!(p_box > p_mask);
        assert!(score(&pred, &gt, &vec![0; h * w], h, w, &opts)
            .unwrap()
            .is_none());
        let b = pma_data::metrics::tight_box(&mask, h, w).map(|b| (b.y0, b.x0, b.y1, b.x1));
        assert_eq!(b, Some((1, 0, 8, 7)));
    }

    #[test]
    fn quantization_truncates_like_the_reference() {
        assert_eq!(
            pma_data::metrics::quantize(&[1.001, -0.001, 0.5, 0.99999]),
            vec![1.0, 0.0, 127.0 / 255.0, 254.0 / 255.0]
        );
    }
}
