//! `pma render`: render a trained avatar as PNG frames plus an animated GIF.
//!
//! Sources of poses:
//! * `--data DS [--split S]`: the images of a dataset split, each with its own pose;
//! * `--poses POSES.npz`: a motion (e.g. from `pma convert motion`), retargeted onto the avatar
//!   (FK with the avatar's rest pose, head turned to −y, the root trajectory scaled by the
//!   leg-length ratio; see `pma_model::tools::retarget` and `docs/conventions.md`, "Motion files").
//!
//! Cameras (`--camera`):
//! * `dataset`: each image's own camera (needs `--data` without `--poses`);
//! * `orbit`: one turn around the body over the sequence (`--views` frames per turn), at the
//!   training camera's distance and height (`--data`'s camera `--cam`, default the first
//!   image's), or `--distance`; without a dataset, a framing camera in front of the body;
//! * `bullet`: one pose (`--frame`) frozen while the camera turns `--views` times about the
//!   vertical axis through the root (the reference's transposed Ry; see
//!   `pma_model::render::camera_path`);
//! * `follow`: the orbit's starting camera for every frame, moving with the body (retargeted
//!   motion seen from the training camera).
//!
//! Renders are chunked (bounded memory: `--chunk` rays at a time, the GIF is streamed to disk)
//! and show a progress bar over the rays to trace. View directions are normalised before the
//! view encoding, as in training (`--reference-dirs` keeps the reference's raw render-time
//! directions; see `pma_model::render::camera_path`). MP4 is not offered: no pure-Rust H.264 encoder
//! fits, and no ffmpeg is assumed.
//!
//! Output: `OUT/frame_0000.png`…, `OUT/render.gif`, `OUT/render.json` (what was rendered and
//! how long each frame took), and with `--strip N` `OUT/strip.png`: N evenly spread frames side
//! by side.

use std::f64::consts::TAU;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context as _};
use candle_core::Tensor;
use image::codecs::gif::{GifEncoder, Repeat};
use image::{Delay, Frame, RgbImage, RgbaImage};
use pma_data::camera::Camera;
use pma_data::cylinder::{cylinder_from_joints, CylinderParams, HeadDir};
use pma_data::dataset::{Dataset, Profile, ReadOptions};
use pma_data::fsio::AtomicFile;
use pma_data::skeleton::Joints;
use pma_model::eval::{dataset_pose, resolve_split, split_images, spread, Split};
use pma_model::render::avatar::{Avatar, Poses, Rays};
use pma_model::render::camera_path::{
    bullet_time, facing, framing_camera, load_avatar, parse_resolution, Orbit, ViewDirs,
};
use pma_model::render::image::{body_box, render_image, ChunkRender, ImageOptions, RenderedImage};
use pma_model::render::PassOptions;
use pma_model::tools::retarget::{retarget, MotionClip, RootScale};
use serde::Serialize;

use super::{progress, read_dataset, refuse, write_json, write_png, Refused};

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum CameraMode {
    Dataset,
    Orbit,
    Bullet,
    /// The orbit's first camera for every frame, following the body along the ground.
    Follow,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum Background {
    Black,
    White,
}

#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Trained model (`RUN/model.safetensors`, or the run directory: its newest complete model).
    #[arg(long)]
    pub model: PathBuf,
    /// Dataset: a pma-npz file, or a `pma synth` directory holding `<split>.npz`. Supplies poses
    /// (without `--poses`) and the training camera for orbit and bullet time.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Split of `--data` (`novel_view`, `novel_pose`, `train`, `val`). With `--poses` the
    /// dataset lends only its camera: the split's first image's, or the file's first image's
    /// when the file does not hold the split.
    #[arg(long, default_value = "novel_view")]
    pub split: String,
    /// Motion npz (`pma convert motion`), retargeted onto the avatar.
    #[arg(long)]
    pub poses: Option<PathBuf>,
    /// Camera path (default: `dataset` with `--data` alone, `orbit` otherwise).
    #[arg(long, value_enum)]
    pub camera: Option<CameraMode>,
    /// Output size `WxH` (default: the dataset's image size, or 256x256).
    #[arg(long)]
    pub res: Option<String>,
    /// Frames `a:b` (end exclusive; `a:`, `:b` and `k` work too) of the split's images or of
    /// the motion's poses.
    #[arg(long)]
    pub frames: Option<String>,
    /// Bullet time: views per turn (default 24). Orbit: frames per turn (default: all frames).
    #[arg(long)]
    pub views: Option<usize>,
    /// Bullet time: which frame of the range to freeze (default: the first).
    #[arg(long, default_value_t = 0)]
    pub frame: usize,
    /// Camera row of `--data` that orbit and bullet time start from (default: the first
    /// image's camera).
    #[arg(long)]
    pub cam: Option<usize>,
    /// Orbit distance from the body (default: the training camera's).
    #[arg(long)]
    pub distance: Option<f64>,
    #[arg(long, value_enum, default_value = "black")]
    pub background: Background,
    /// Root trajectory scale for `--poses`: `legs` (avatar/motion leg length), `none`, or a
    /// factor.
    #[arg(long, default_value = "legs")]
    pub root_scale: String,
    /// GIF frame rate.
    #[arg(long, default_value_t = 15.0)]
    pub fps: f64,
    /// Rays per network call.
    #[arg(long, default_value_t = 4096)]
    pub chunk: usize,
    /// Feed the reference's raw (unnormalised) render-time ray directions to the view encoding.
    #[arg(long)]
    pub reference_dirs: bool,
    /// PNG frames only.
    #[arg(long)]
    pub no_gif: bool,
    /// Also write `strip.png`: this many evenly spread frames side by side.
    #[arg(long)]
    pub strip: Option<usize>,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
    #[command(flatten)]
    pub pass: PassOptions,
    /// Compute device: cpu, cuda, cuda:N, metal (cuda/metal need a binary built with that
    /// feature).
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// TF32 matrix products on CUDA: faster, changes results (see docs/numerics.md, "Low
    /// precision"); refused on other devices.
    #[arg(long)]
    pub tf32: bool,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
}

/// One pose to render.
struct PoseItem {
    label: String,
    poses: Poses,
    kp3d: Joints,
    bones: Joints,
    /// The dataset image's camera, if the pose comes from one.
    camera: Option<Camera>,
}

/// One output frame.
struct Job<'a> {
    item: &'a PoseItem,
    camera: Camera,
}

#[derive(Serialize)]
struct FrameReport {
    file: String,
    pose: String,
    camera_origin: [f32; 3],
    /// Pixels ray-traced (inside the body's box); the others are background.
    rays: usize,
    seconds: f64,
}

#[derive(Serialize)]
struct Report {
    model: String,
    camera: CameraMode,
    width: usize,
    height: usize,
    view_dirs: &'static str,
    #[serde(skip_serializing_if = "Option::is_none")]
    root_scale: Option<f64>,
    frames: Vec<FrameReport>,
    seconds_per_frame: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    gif: Option<PathBuf>,
}

pub fn run(mut args: Args) -> anyhow::Result<()> {
    check_args(&args)?;
    args.model = super::model_path(&args.model)?;
    let res = args.res.as_deref().map(parse_resolution).transpose()?;
    let device = super::device_tf32(&args.device, args.tf32)?;
    let dirs = if args.reference_dirs {
        ViewDirs::Reference
    } else {
        ViewDirs::Normalized
    };
    let avatar = load_avatar(&args.model, &device, dirs)
        .with_context(|| format!("loading model {}", args.model.display()))?;

    let data = match &args.data {
        Some(d) => Some(SplitData::read(d, &args.split, args.poses.is_some())?),
        None => None,
    };
    let mode = match (args.camera, &args.poses, &data) {
        (Some(m), _, _) => m,
        (None, None, Some(_)) => CameraMode::Dataset,
        _ => CameraMode::Orbit,
    };
    let (items, head, root_scale) = pose_items(&args, &avatar, data.as_ref(), mode)?;
    let jobs = camera_jobs(&args, &items, data.as_ref(), head, mode, res)?;
    let mut files: Vec<String> = (0..jobs.len()).map(frame_file).collect();
    files.extend(["render.gif", "render.json", "strip.png"].map(String::from));
    let data_check = match &args.data {
        Some(d) if d.is_dir() => pma_data::fsio::PathCheck::new().input_dir("--data", d),
        d => pma_data::fsio::PathCheck::new().input_opt("--data", d.as_deref()),
    };
    super::check_paths(
        data_check
            .input("--model", &args.model)
            .input_opt("--poses", args.poses.as_deref())
            .output_dir("--out", &args.out, files),
    )?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let rendered = render_jobs(&args, &avatar, &jobs, head, &device)?;

    let (w, h) = (jobs[0].camera.width, jobs[0].camera.height);
    let report = Report {
        model: args.model.display().to_string(),
        camera: mode,
        width: w,
        height: h,
        view_dirs: match dirs {
            ViewDirs::Normalized => "normalized",
            ViewDirs::Reference => "reference",
        },
        root_scale,
        seconds_per_frame: rendered.frames.iter().map(|f| f.seconds).sum::<f64>()
            / rendered.frames.len() as f64,
        frames: rendered.frames,
        gif: rendered.gif.clone(),
    };
    write_json(&report, &args.out.join("render.json"))?;
    println!(
        "rendered {} frame(s) of {w}x{h} ({:?} camera, {:.2} s/frame) to {}{}",
        report.frames.len(),
        mode,
        report.seconds_per_frame,
        args.out.display(),
        rendered
            .gif
            .map(|g| format!(", animation {}", g.display()))
            .unwrap_or_default()
    );
    Ok(())
}

/// The file of frame `k`.
fn frame_file(k: usize) -> String {
    format!("frame_{k:04}.png")
}

/// The most frames one render writes (`--views`, `--strip`): ten minutes at 60 fps.
const MAX_FRAMES: usize = 36_000;

fn check_args(args: &Args) -> anyhow::Result<()> {
    if !(1..=pma_model::render::MAX_CHUNK_RAYS).contains(&args.chunk) {
        refuse!(
            "--chunk {} must be in 1..={}",
            args.chunk,
            pma_model::render::MAX_CHUNK_RAYS
        );
    }
    if args.views.is_some_and(|v| v > MAX_FRAMES) || args.strip.is_some_and(|v| v > MAX_FRAMES) {
        refuse!("--views and --strip take at most {MAX_FRAMES} frames");
    }
    if !(args.fps.is_finite() && args.fps > 0.0 && args.fps <= 100.0) {
        refuse!("--fps must be in (0, 100], found {}", args.fps);
    }
    if args.views == Some(0) {
        refuse!("--views must be >= 1");
    }
    if args.strip == Some(0) {
        refuse!("--strip must be >= 1");
    }
    Ok(())
}

/// `--data` read for rendering, with the images of `--split`.
struct SplitData {
    data: Dataset,
    images: Vec<usize>,
}

impl SplitData {
    /// With `camera_only` (poses from elsewhere), a file without the split lends its first
    /// image instead of being refused.
    fn read(path: &Path, split: &str, camera_only: bool) -> anyhow::Result<Self> {
        let (file, split) = resolve_split(path, split)?;
        let data = read_dataset(&file, Profile::Render)?;
        let images = match split_images(&data, &file, &split) {
            Ok(images) => images,
            Err(_) if camera_only => split_images(&data, &file, &Split::whole_file(&split.name)?)?,
            Err(e) => return Err(e.into()),
        };
        Ok(Self { data, images })
    }
}

/// Step 1: the poses to render (from `--poses`, or the split's images), the head direction
/// and, for a motion, the root scale used.
fn pose_items(
    args: &Args,
    avatar: &Avatar,
    data: Option<&SplitData>,
    mode: CameraMode,
) -> anyhow::Result<(Vec<PoseItem>, HeadDir, Option<f64>)> {
    match (&args.poses, data) {
        (Some(p), _) => {
            if mode == CameraMode::Dataset {
                refuse!("--camera dataset renders a dataset's own images: pass --data without --poses (or use orbit/bullet)");
            }
            let scale: RootScale = args.root_scale.parse()?;
            let (items, s) = motion_items(avatar, p, scale, args.frames.as_deref())?;
            Ok((items, HeadDir::NegY, Some(s)))
        }
        (None, Some(sd)) => {
            let range = parse_range(args.frames.as_deref(), sd.images.len(), "split images")?;
            let items = sd.images[range]
                .iter()
                .map(|&n| dataset_item(avatar, &sd.data, n))
                .collect::<anyhow::Result<Vec<_>>>()?;
            Ok((items, sd.data.head()?, None))
        }
        (None, None) => refuse!("nothing to render: pass --data DS and/or --poses POSES.npz"),
    }
}

/// The camera orbit and bullet time start from: `--cam` of `--data`, the first item's own
/// camera, the split's first image's, or a framing camera in front of the body.
fn reference_camera(
    args: &Args,
    first: &PoseItem,
    data: Option<&SplitData>,
    head: HeadDir,
    res: Option<(usize, usize)>,
) -> anyhow::Result<Camera> {
    let cam = match (data, args.cam) {
        (Some(sd), Some(c)) => sd.data.camera(c)?,
        (Some(sd), None) => match &first.camera {
            Some(c) => c.clone(),
            None => sd.data.image_camera(sd.images[0])?,
        },
        (None, Some(_)) => refuse!("--cam needs --data"),
        (None, None) => {
            let (w, h) = res.unwrap_or((256, 256));
            framing_camera(&first.kp3d, head, facing(&first.bones), w, h)?
        }
    };
    Ok(match res {
        Some((w, h)) => cam.resized(w, h),
        None => cam,
    })
}

/// Step 2: one job (pose and camera) per output frame.
fn camera_jobs<'a>(
    args: &Args,
    items: &'a [PoseItem],
    data: Option<&SplitData>,
    head: HeadDir,
    mode: CameraMode,
    res: Option<(usize, usize)>,
) -> anyhow::Result<Vec<Job<'a>>> {
    Ok(match mode {
        CameraMode::Dataset => items
            .iter()
            .map(|it| {
                let cam = it.camera.clone().expect("dataset items carry cameras");
                Job {
                    item: it,
                    camera: match res {
                        Some((w, h)) => cam.resized(w, h),
                        None => cam,
                    },
                }
            })
            .collect(),
        CameraMode::Orbit | CameraMode::Follow => {
            let first = &items[0];
            let target0 = body_centre(&first.kp3d, head);
            let mut orbit = Orbit::through(
                &reference_camera(args, first, data, head, res)?,
                target0,
                head,
            )?;
            if let Some(d) = args.distance {
                orbit = orbit.at_distance(d)?;
            }
            let per_turn = args.views.unwrap_or(items.len());
            let spin = if mode == CameraMode::Follow { 0.0 } else { 1.0 };
            items
                .iter()
                .enumerate()
                .map(|(k, it)| {
                    // Follow the body along the ground; keep the first frame's height.
                    let c = body_centre(&it.kp3d, head);
                    let target = [c[0], target0[1], c[2]];
                    let angle = spin * TAU * k as f64 / per_turn as f64;
                    Ok(Job {
                        item: it,
                        camera: orbit.camera(target, angle)?,
                    })
                })
                .collect::<anyhow::Result<_>>()?
        }
        CameraMode::Bullet => {
            let it = items.get(args.frame).with_context(|| {
                format!(
                    "--frame {} is past the {} selected frame(s)",
                    args.frame,
                    items.len()
                )
            })?;
            let mut cam = reference_camera(args, it, data, head, res)?;
            if let Some(d) = args.distance {
                let target = body_centre(&it.kp3d, head);
                cam = Orbit::through(&cam, target, head)?
                    .at_distance(d)?
                    .camera(target, 0.0)?;
            }
            bullet_time(&cam, it.kp3d[0], args.views.unwrap_or(24))?
                .into_iter()
                .map(|camera| Job { item: it, camera })
                .collect()
        }
    })
}

/// What step 3 wrote.
struct Rendered {
    frames: Vec<FrameReport>,
    gif: Option<PathBuf>,
}

/// Step 3: render every job into `frame_NNNN.png`, the GIF and the strip.
fn render_jobs(
    args: &Args,
    avatar: &Avatar,
    jobs: &[Job],
    head: HeadDir,
    device: &candle_core::Device,
) -> anyhow::Result<Rendered> {
    let (w, h) = (jobs[0].camera.width, jobs[0].camera.height);
    let rays = |j: &Job| {
        let b = body_box(&j.camera, &j.item.kp3d, head);
        b.width() * b.height()
    };
    let total: u64 = jobs.iter().map(|j| rays(j) as u64).sum();
    let bar = progress::bar(args.quiet, total, "rays");
    let bg = match args.background {
        Background::Black => [0.0f32; 3],
        Background::White => [1.0; 3],
    };
    let background: Vec<f32> = (0..w * h).flat_map(|_| bg).collect();
    let opts = ImageOptions {
        chunk: args.chunk,
        head,
        device: device.clone(),
        pass: args.pass.clone(),
    };
    let gif_path = args.out.join("render.gif");
    let mut gif = if args.no_gif {
        None
    } else {
        Some(GifStream::create(&gif_path, args.fps)?)
    };
    let strip_frames: Vec<usize> = args
        .strip
        .map(|n| spread(&(0..jobs.len()).collect::<Vec<_>>(), n))
        .unwrap_or_default();
    let mut strip = Vec::with_capacity(strip_frames.len());
    let mut frames = Vec::with_capacity(jobs.len());
    for (k, job) in jobs.iter().enumerate() {
        bar.set_message(format!("frame {}/{}", k + 1, jobs.len()));
        let t = Instant::now();
        let img = render_job(avatar, job, &background, &opts, &bar)
            .with_context(|| format!("rendering frame {k} ({})", job.item.label))?;
        let seconds = t.elapsed().as_secs_f64();
        let rgb = to_rgb8(&img);
        let file = frame_file(k);
        write_png(&rgb, &args.out.join(&file))?;
        if let Some(g) = gif.as_mut() {
            g.push(&rgb)?;
        }
        if strip_frames.contains(&k) {
            strip.push(rgb);
        }
        frames.push(FrameReport {
            file,
            pose: job.item.label.clone(),
            camera_origin: job.camera.origin(),
            rays: rays(job),
            seconds,
        });
    }
    bar.finish_and_clear();
    let gif = match gif {
        Some(g) => {
            g.finish()?;
            Some(gif_path)
        }
        None => None,
    };
    if !strip.is_empty() {
        let mut img = RgbImage::new(w as u32 * strip.len() as u32, h as u32);
        for (i, f) in strip.iter().enumerate() {
            image::imageops::replace(&mut img, f, (i * w) as i64, 0);
        }
        write_png(&img, &args.out.join("strip.png"))?;
    }
    Ok(Rendered { frames, gif })
}

/// `a:b`, `a:`, `:b` or `k` over `n` items; `None` = all.
fn parse_range(s: Option<&str>, n: usize, what: &str) -> anyhow::Result<Range<usize>> {
    let Some(s) = s else {
        if n == 0 {
            refuse!("no {what} to render");
        }
        return Ok(0..n);
    };
    let num = |t: &str, default: usize| -> anyhow::Result<usize> {
        let t = t.trim();
        if t.is_empty() {
            return Ok(default);
        }
        t.parse()
            .map_err(|_| Refused::new(format!("--frames {s:?}: {t:?} is not a frame index")).into())
    };
    let r = match s.split_once(':') {
        Some((a, b)) => num(a, 0)?..num(b, n)?,
        None => {
            let k = num(s, usize::MAX)?;
            k..k.saturating_add(1)
        }
    };
    if r.start >= r.end || r.end > n {
        refuse!("--frames {s:?} selects nothing within the {n} {what} (use a:b with a < b <= {n})");
    }
    Ok(r)
}

fn dataset_item(avatar: &Avatar, ds: &Dataset, n: usize) -> anyhow::Result<PoseItem> {
    let p = ds.pose_row(n)?;
    let (poses, kp3d) = dataset_pose(ds, p, avatar.device())?;
    Ok(PoseItem {
        label: format!("image {n} (pose {p})"),
        bones: poses.bones[0],
        poses,
        kp3d,
        camera: Some(ds.image_camera(n)?),
    })
}

/// The motion file's poses, retargeted onto the avatar; also returns the root scale used.
fn motion_items(
    avatar: &Avatar,
    path: &Path,
    scale: RootScale,
    frames: Option<&str>,
) -> anyhow::Result<(Vec<PoseItem>, f64)> {
    let (clip, _) = read_motion(avatar, path)?;
    let range = parse_range(frames, clip.len(), "motion frames")?;
    let clip = MotionClip {
        bones: clip.bones[range.clone()].to_vec(),
        roots: clip.roots[range.clone()].to_vec(),
        ..clip
    };
    let out = retarget(&clip, avatar.rest_pose(), scale)
        .with_context(|| format!("retargeting {}", path.display()))?;
    let items = out
        .frames
        .iter()
        .enumerate()
        .map(|(k, f)| {
            let (poses, kp3d) = avatar.pose_from_bones(&f.bones, f.root)?;
            Ok(PoseItem {
                label: format!("motion frame {}", range.start + k),
                poses,
                kp3d,
                bones: f.bones,
                camera: None,
            })
        })
        .collect::<anyhow::Result<_>>()?;
    Ok((items, out.root_scale))
}

/// A motion (or any pma-npz) file's pose rows. Kinematics that the file leaves out use the
/// avatar's rest pose (see `docs/conventions.md`, "pma-npz v1").
pub fn read_motion(avatar: &Avatar, path: &Path) -> anyhow::Result<(MotionClip, Dataset)> {
    let mut opts = ReadOptions::new(Profile::Motion);
    opts.rest_pose = Some(*avatar.rest_pose());
    let ds =
        Dataset::read(path, &opts).with_context(|| format!("reading motion {}", path.display()))?;
    for w in &ds.warnings {
        eprintln!("warning: {}: {w}", path.display());
    }
    let clip = MotionClip::from_dataset(&ds)?;
    if clip.rest.is_none() {
        eprintln!(
            "note: {} has no rest_pose of its own: its root trajectory is kept as is",
            path.display()
        );
    }
    Ok((clip, ds))
}

/// Centre of the render cylinder: ground position of the root, mid-height of the body.
fn body_centre(kp3d: &Joints, head: HeadDir) -> [f32; 3] {
    let c = cylinder_from_joints(kp3d, &CylinderParams::render(head));
    [c[0], 0.5 * (c[3] + c[4]), c[1]]
}

// The renderer closure returns `pma_model`'s error, which carries candle's (large) one.
#[allow(clippy::result_large_err)]
fn render_job(
    avatar: &Avatar,
    job: &Job,
    background: &[f32],
    opts: &ImageOptions,
    bar: &indicatif::ProgressBar,
) -> anyhow::Result<RenderedImage> {
    let poses = &job.item.poses;
    let mut renderer =
        |o: &Tensor, d: &Tensor, bg: &Tensor| -> pma_model::error::Result<ChunkRender> {
            let rays = Rays {
                origins: o.clone(),
                dirs: d.clone(),
                bgs: Some(bg.clone()),
                framecodes: vec![-1; o.dim(0)?],
            };
            let out = avatar.render_rays(&rays, poses, &opts.pass)?;
            bar.inc(o.dim(0)? as u64);
            Ok(ChunkRender {
                rgb: out.fine.rgb,
                acc: out.fine.acc,
                disp: out.fine.disp,
                stats: out.stats,
            })
        };
    Ok(render_image(
        &mut renderer,
        &job.camera,
        &job.item.kp3d,
        Some(background),
        opts,
    )?)
}

fn to_rgb8(img: &RenderedImage) -> RgbImage {
    let px: Vec<u8> = img
        .rgb
        .iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    RgbImage::from_raw(img.width as u32, img.height as u32, px).expect("H·W·3 values")
}

/// A GIF written frame by frame into a temporary file beside its destination, renamed into
/// place when complete: memory stays bounded and readers never see a partial animation.
struct GifStream {
    encoder: GifEncoder<std::io::BufWriter<pma_data::fsio::Writer<std::fs::File>>>,
    file: AtomicFile,
    delay: Delay,
}

impl GifStream {
    fn create(path: &Path, fps: f64) -> anyhow::Result<Self> {
        let err = || format!("writing {}", path.display());
        let file = AtomicFile::create(path).with_context(err)?;
        let handle = file.owned_writer().with_context(err)?;
        let mut encoder = GifEncoder::new_with_speed(std::io::BufWriter::new(handle), 10);
        encoder.set_repeat(Repeat::Infinite).with_context(err)?;
        Ok(Self {
            encoder,
            file,
            delay: Delay::from_numer_denom_ms(1000, fps.round().max(1.0) as u32),
        })
    }

    fn push(&mut self, rgb: &RgbImage) -> anyhow::Result<()> {
        let rgba = RgbaImage::from_fn(rgb.width(), rgb.height(), |x, y| {
            let p = rgb.get_pixel(x, y).0;
            image::Rgba([p[0], p[1], p[2], 255])
        });
        self.encoder
            .encode_frame(Frame::from_parts(rgba, 0, 0, self.delay))
            .context("encoding a GIF frame")
    }

    fn finish(self) -> anyhow::Result<()> {
        let path = self.file.path().to_path_buf();
        let err = || format!("writing {}", path.display());
        // Dropping the encoder writes the GIF trailer and flushes the buffer, both without
        // reporting errors: check that the file ends with the trailer byte instead.
        drop(self.encoder);
        let mut f = self.file.file();
        use std::io::{Read as _, Seek as _, SeekFrom};
        f.seek(SeekFrom::End(-1)).with_context(err)?;
        let mut last = [0u8; 1];
        f.read_exact(&mut last).with_context(err)?;
        if last[0] != 0x3B {
            bail!(
                "{}: the GIF could not be completed (disk full?)",
                path.display()
            );
        }
        self.file
            .commit()
            .with_context(|| format!("replacing {}", path.display()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_ranges() {
        assert_eq!(parse_range(None, 5, "x").unwrap(), 0..5);
        assert_eq!(parse_range(Some("1:3"), 5, "x").unwrap(), 1..3);
        assert_eq!(parse_range(Some("2:"), 5, "x").unwrap(), 2..5);
        assert_eq!(parse_range(Some(":2"), 5, "x").unwrap(), 0..2);
        assert_eq!(parse_range(Some("4"), 5, "x").unwrap(), 4..5);
        for bad in ["3:3", "4:2", "0:6", "5", "a:b", "-1:2"] {
            assert!(parse_range(Some(bad), 5, "x").is_err(), "{bad}");
        }
        assert!(parse_range(None, 0, "x").is_err());
    }
}
