//! `pma render`: render a trained avatar as PNG frames plus an animated GIF. Poses come from
//! a dataset split (`--data`, each image with its own pose) or a motion retargeted onto the
//! avatar (`--poses`; `pma_model::tools::retarget`); `pma_model::tools::video` plans a camera
//! per frame (`--camera dataset|orbit|bullet|follow`, see its docs) and writes the frames.
//! View directions are normalised before the view encoding, as in training
//! (`--reference-dirs` keeps the reference's raw ones; see `pma_model::render::camera_path`).
//!
//! Output: `OUT/frame_0000.png`…, `OUT/render.gif`, `OUT/render.json` (what was rendered and
//! how long each frame took), and with `--strip N` `OUT/strip.png`: N evenly spread frames side
//! by side.

use std::ops::Range;
use std::path::PathBuf;

use anyhow::Context as _;
use pma_data::cylinder::HeadDir;
use pma_data::dataset::Profile;
use pma_model::eval::{read_split, SplitData};
use pma_model::render::avatar::Avatar;
use pma_model::render::camera_path::parse_resolution;
use pma_model::render::PassOptions;
use pma_model::tools::retarget::{MotionClip, RootScale};
use pma_model::tools::video::{
    dataset_items, frame_file, motion_items, render_video, shot_rays, shots, CameraMode,
    CameraPlan, CameraSource, PoseItem, VideoOptions, VideoProgress, VideoReport,
};

use super::{progress, read_motion, refuse, write_json, Refused};

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
    #[command(flatten)]
    pub device: super::DeviceArgs,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(mut args: Args) -> anyhow::Result<()> {
    check_args(&args)?;
    args.model = super::model_path(&args.model)?;
    let res = args.res.as_deref().map(parse_resolution).transpose()?;
    let device = args.device.open()?;
    let dirs = super::view_dirs(args.reference_dirs);
    let avatar = super::load_model(&args.model, &device, dirs)?;

    let data = match &args.data {
        Some(d) => {
            let sd = read_split(d, &args.split, Profile::Render, args.poses.is_some())?;
            for w in &sd.data.warnings {
                eprintln!("warning: {}: {w}", sd.file.display());
            }
            Some(sd)
        }
        None => None,
    };
    let mode = match (args.camera, &args.poses, &data) {
        (Some(m), _, _) => m,
        (None, None, Some(_)) => CameraMode::Dataset,
        _ => CameraMode::Orbit,
    };
    let (items, head, root_scale) = pose_items(&args, &avatar, data.as_ref(), mode)?;
    if args.cam.is_some() && data.is_none() {
        refuse!("--cam needs --data");
    }
    if mode == CameraMode::Bullet && args.frame >= items.len() {
        anyhow::bail!(
            "--frame {} is past the {} selected frame(s)",
            args.frame,
            items.len()
        );
    }
    let plan = CameraPlan {
        mode,
        source: match &data {
            Some(sd) => CameraSource::Dataset {
                data: &sd.data,
                cam: args.cam,
                first_image: sd.images[0],
            },
            None => CameraSource::Framing,
        },
        res,
        views: args.views,
        frame: args.frame,
        distance: args.distance,
        head,
    };
    let shots = shots(&plan, &items)?;
    let mut files: Vec<String> = (0..shots.len()).map(frame_file).collect();
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
    pma_data::fsio::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let opts = VideoOptions {
        out: args.out.clone(),
        background: match args.background {
            Background::Black => [0.0; 3],
            Background::White => [1.0; 3],
        },
        chunk: args.chunk,
        head,
        device,
        gif_fps: (!args.no_gif).then_some(args.fps),
        strip: args.strip,
        pass: args.pass.clone(),
    };
    let total: u64 = shots
        .iter()
        .map(|s| shot_rays(s, &items, head) as u64)
        .sum();
    let mut bar = RaysBar(progress::bar(args.quiet, total, "rays"));
    let rendered = render_video(&avatar, &items, &shots, &opts, &mut bar)?;
    bar.0.finish_and_clear();

    let (w, h) = (shots[0].camera.width, shots[0].camera.height);
    let report = VideoReport::new(&args.model, mode, (w, h), dirs, root_scale, rendered);
    write_json(&report, &args.out.join("render.json"))?;
    println!(
        "rendered {} frame(s) of {w}x{h} ({:?} camera, {:.2} s/frame) to {}{}",
        report.frames.len(),
        mode,
        report.seconds_per_frame,
        args.out.display(),
        report
            .gif
            .as_ref()
            .map(|g| format!(", animation {}", g.display()))
            .unwrap_or_default()
    );
    Ok(())
}

/// The progress bar over the rays to trace.
struct RaysBar(indicatif::ProgressBar);

impl VideoProgress for RaysBar {
    fn frame(&mut self, k: usize, n: usize) {
        self.0.set_message(format!("frame {}/{n}", k + 1));
    }

    fn rays(&mut self, n: u64) {
        self.0.inc(n);
    }
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

/// The poses to render (from `--poses`, or the split's images), the head direction and, for
/// a motion, the root scale used.
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
            let clip = read_motion(avatar, p)?;
            let range = parse_range(args.frames.as_deref(), clip.len(), "motion frames")?;
            let clip = MotionClip {
                bones: clip.bones[range.clone()].to_vec(),
                roots: clip.roots[range.clone()].to_vec(),
                ..clip
            };
            let (items, s) = motion_items(avatar, &clip, range.start, scale)
                .with_context(|| format!("retargeting {}", p.display()))?;
            Ok((items, HeadDir::NegY, Some(s)))
        }
        (None, Some(sd)) => {
            let range = parse_range(args.frames.as_deref(), sd.images.len(), "split images")?;
            let items = dataset_items(avatar, &sd.data, &sd.images[range])?;
            Ok((items, sd.data.head()?, None))
        }
        (None, None) => refuse!("nothing to render: pass --data DS and/or --poses POSES.npz"),
    }
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
