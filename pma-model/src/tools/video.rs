//! Render planning for `pma render`: the poses of a sequence, one camera per output frame,
//! and the frames rendered into PNGs, an animated GIF and a strip.
//!
//! Poses ([`PoseItem`]) come from a dataset's images ([`dataset_items`], each with its own
//! camera) or from a motion retargeted onto the avatar ([`motion_items`]). Cameras
//! ([`CameraMode`], [`shots`]):
//! * `dataset`: each image's own camera;
//! * `orbit`: one turn around the body over the sequence (`views` frames per turn), at the
//!   reference camera's distance and height ([`CameraSource`]);
//! * `bullet`: one pose frozen while the camera turns `views` times about the vertical axis
//!   through the root (the reference's transposed Ry; see [`crate::render::camera_path`]);
//! * `follow`: the orbit's starting camera for every frame, moving with the body along the
//!   ground.
//!
//! [`render_video`] renders in chunks (bounded memory; the GIF is streamed to disk) and
//! reports each frame's rays and time. MP4 is not offered: no pure-Rust H.264 encoder fits,
//! and no ffmpeg is assumed.

use std::f64::consts::TAU;
use std::path::{Path, PathBuf};
use std::time::Instant;

use candle_core::{Device, Tensor};
use image::codecs::gif::{GifEncoder, Repeat};
use image::{Delay, Frame, RgbImage, RgbaImage};
use pma_data::camera::Camera;
use pma_data::cylinder::{cylinder_from_joints, CylinderParams, HeadDir};
use pma_data::dataset::Dataset;
use pma_data::fsio::AtomicFile;
use pma_data::skeleton::Joints;
use serde::Serialize;

use crate::error::{ModelError, Result};
use crate::eval::{dataset_pose, spread, write_png, EvalError};
use crate::render::avatar::{Avatar, Poses, Rays};
use crate::render::camera_path::{bullet_time, facing, framing_camera, Orbit, ViewDirs};
use crate::render::image::{body_box, render_image, ChunkRender, ImageOptions, RenderedImage};
use crate::render::options::PassOptions;
use crate::tools::retarget::{retarget, MotionClip, RootScale};

/// How the camera moves over the frames (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum CameraMode {
    Dataset,
    Orbit,
    Bullet,
    /// The orbit's first camera for every frame, following the body along the ground.
    Follow,
}

/// One pose to render.
#[derive(Debug, Clone)]
pub struct PoseItem {
    /// What the frame shows, for reports (`image 3 (pose 1)`, `motion frame 12`).
    pub label: String,
    pub poses: Poses,
    pub kp3d: Joints,
    pub bones: Joints,
    /// The dataset image's camera, if the pose comes from one.
    pub camera: Option<Camera>,
}

/// One output frame: a pose (an index into the items) and a camera.
#[derive(Debug, Clone)]
pub struct Shot {
    pub item: usize,
    pub camera: Camera,
}

/// Images `images` of `ds`, each with its pose and camera.
pub fn dataset_items(
    avatar: &Avatar,
    ds: &Dataset,
    images: &[usize],
) -> std::result::Result<Vec<PoseItem>, EvalError> {
    images
        .iter()
        .map(|&n| {
            let p = ds.pose_row(n)?;
            let (poses, kp3d) = dataset_pose(ds, p, avatar.device())?;
            Ok(PoseItem {
                label: format!("image {n} (pose {p})"),
                bones: poses.bones[0],
                poses,
                kp3d,
                camera: Some(ds.image_camera(n)?),
            })
        })
        .collect()
}

/// The frames of `clip` retargeted onto `avatar`, labelled from `first_frame` on (the
/// clip's index in its file); also returns the root scale used.
pub fn motion_items(
    avatar: &Avatar,
    clip: &MotionClip,
    first_frame: usize,
    scale: RootScale,
) -> Result<(Vec<PoseItem>, f64)> {
    let out = retarget(clip, avatar.rest_pose(), scale)?;
    let items = out
        .frames
        .iter()
        .enumerate()
        .map(|(k, f)| {
            let (poses, kp3d) = avatar.pose_from_bones(&f.bones, f.root)?;
            Ok(PoseItem {
                label: format!("motion frame {}", first_frame + k),
                poses,
                kp3d,
                bones: f.bones,
                camera: None,
            })
        })
        .collect::<Result<_>>()?;
    Ok((items, out.root_scale))
}

/// Where orbit, follow and bullet time take their first camera from.
#[derive(Debug, Clone, Copy)]
pub enum CameraSource<'a> {
    /// A dataset: its camera row `cam` if given, else the pose's own image camera, else
    /// image `first_image`'s.
    Dataset {
        data: &'a Dataset,
        cam: Option<usize>,
        first_image: usize,
    },
    /// A framing camera in front of the body.
    Framing,
}

/// How [`shots`] places the cameras.
#[derive(Debug, Clone, Copy)]
pub struct CameraPlan<'a> {
    pub mode: CameraMode,
    pub source: CameraSource<'a>,
    /// Output size `(W, H)`; `None`: the reference camera's (256×256 for framing).
    pub res: Option<(usize, usize)>,
    /// Bullet time: views per turn (default 24). Orbit: frames per turn (default: all).
    pub views: Option<usize>,
    /// Bullet time: which item to freeze.
    pub frame: usize,
    /// Orbit distance from the body (default: the reference camera's).
    pub distance: Option<f64>,
    pub head: HeadDir,
}

impl CameraPlan<'_> {
    /// The camera orbit and bullet time start from for `item`.
    fn reference_camera(&self, item: &PoseItem) -> Result<Camera> {
        let cam = match self.source {
            CameraSource::Dataset {
                data, cam: Some(c), ..
            } => data.camera(c)?,
            CameraSource::Dataset {
                data, first_image, ..
            } => match &item.camera {
                Some(c) => c.clone(),
                None => data.image_camera(first_image)?,
            },
            CameraSource::Framing => {
                let (w, h) = self.res.unwrap_or((256, 256));
                framing_camera(&item.kp3d, self.head, facing(&item.bones), w, h)?
            }
        };
        Ok(self.resized(cam))
    }

    fn resized(&self, cam: Camera) -> Camera {
        match self.res {
            Some((w, h)) => cam.resized(w, h),
            None => cam,
        }
    }
}

/// One shot per output frame of `items` as `plan` says (see the module docs).
pub fn shots(plan: &CameraPlan, items: &[PoseItem]) -> Result<Vec<Shot>> {
    let Some(first) = items.first() else {
        return Err(ModelError::Input("no poses to render".into()));
    };
    let head = plan.head;
    Ok(match plan.mode {
        CameraMode::Dataset => items
            .iter()
            .enumerate()
            .map(|(k, it)| {
                let cam = it.camera.clone().ok_or_else(|| {
                    ModelError::Input(format!("{} has no camera of its own", it.label))
                })?;
                Ok(Shot {
                    item: k,
                    camera: plan.resized(cam),
                })
            })
            .collect::<Result<_>>()?,
        CameraMode::Orbit | CameraMode::Follow => {
            let target0 = body_centre(&first.kp3d, head);
            let mut orbit = Orbit::through(&plan.reference_camera(first)?, target0, head)?;
            if let Some(d) = plan.distance {
                orbit = orbit.at_distance(d)?;
            }
            let per_turn = plan.views.unwrap_or(items.len());
            let spin = if plan.mode == CameraMode::Follow {
                0.0
            } else {
                1.0
            };
            items
                .iter()
                .enumerate()
                .map(|(k, it)| {
                    // Follow the body along the ground; keep the first frame's height.
                    let c = body_centre(&it.kp3d, head);
                    let target = [c[0], target0[1], c[2]];
                    let angle = spin * TAU * k as f64 / per_turn as f64;
                    Ok(Shot {
                        item: k,
                        camera: orbit.camera(target, angle)?,
                    })
                })
                .collect::<Result<_>>()?
        }
        CameraMode::Bullet => {
            let it = items.get(plan.frame).ok_or_else(|| {
                ModelError::Input(format!(
                    "bullet time: frame {} is past the {} selected frame(s)",
                    plan.frame,
                    items.len()
                ))
            })?;
            let mut cam = plan.reference_camera(it)?;
            if let Some(d) = plan.distance {
                let target = body_centre(&it.kp3d, head);
                cam = Orbit::through(&cam, target, head)?
                    .at_distance(d)?
                    .camera(target, 0.0)?;
            }
            bullet_time(&cam, it.kp3d[0], plan.views.unwrap_or(24))?
                .into_iter()
                .map(|camera| Shot {
                    item: plan.frame,
                    camera,
                })
                .collect()
        }
    })
}

/// Centre of the render cylinder: ground position of the root, mid-height of the body.
fn body_centre(kp3d: &Joints, head: HeadDir) -> [f32; 3] {
    let c = cylinder_from_joints(kp3d, &CylinderParams::render(head));
    [c[0], 0.5 * (c[3] + c[4]), c[1]]
}

/// Pixels of `shot` that are ray-traced (inside the body's box); the others are
/// background.
pub fn shot_rays(shot: &Shot, items: &[PoseItem], head: HeadDir) -> usize {
    let b = body_box(&shot.camera, &items[shot.item].kp3d, head);
    b.width() * b.height()
}

/// The file of frame `k`.
pub fn frame_file(k: usize) -> String {
    format!("frame_{k:04}.png")
}

/// Where and how [`render_video`] writes.
#[derive(Debug, Clone)]
pub struct VideoOptions {
    /// Directory of `frame_NNNN.png`, `render.gif` and `strip.png`.
    pub out: PathBuf,
    /// Background colour (RGB in [0, 1]).
    pub background: [f32; 3],
    /// Rays per network call.
    pub chunk: usize,
    pub head: HeadDir,
    pub device: Device,
    /// GIF frame rate; no GIF when `None`.
    pub gif_fps: Option<f64>,
    /// `strip.png` of this many evenly spread frames side by side.
    pub strip: Option<usize>,
    /// What the passes may leave out (parity by default).
    pub pass: PassOptions,
}

/// One frame of `render.json`.
#[derive(Debug, Clone, Serialize)]
pub struct FrameReport {
    pub file: String,
    pub pose: String,
    pub camera_origin: [f32; 3],
    /// Pixels ray-traced (inside the body's box); the others are background.
    pub rays: usize,
    pub seconds: f64,
}

/// What [`render_video`] wrote.
#[derive(Debug, Clone)]
pub struct Rendered {
    pub frames: Vec<FrameReport>,
    pub gif: Option<PathBuf>,
}

/// `render.json`: what was rendered and how long each frame took.
#[derive(Debug, Clone, Serialize)]
pub struct VideoReport {
    pub model: String,
    pub camera: CameraMode,
    pub width: usize,
    pub height: usize,
    pub view_dirs: &'static str,
    /// The factor applied to a motion's root trajectory.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub root_scale: Option<f64>,
    pub frames: Vec<FrameReport>,
    pub seconds_per_frame: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gif: Option<PathBuf>,
}

impl VideoReport {
    /// The report of `rendered`, frames of `width`×`height` from `model`.
    pub fn new(
        model: &Path,
        camera: CameraMode,
        (width, height): (usize, usize),
        dirs: ViewDirs,
        root_scale: Option<f64>,
        rendered: Rendered,
    ) -> Self {
        let n = rendered.frames.len().max(1) as f64;
        Self {
            model: model.display().to_string(),
            camera,
            width,
            height,
            view_dirs: match dirs {
                ViewDirs::Normalized => "normalized",
                ViewDirs::Reference => "reference",
            },
            root_scale,
            seconds_per_frame: rendered.frames.iter().map(|f| f.seconds).sum::<f64>() / n,
            frames: rendered.frames,
            gif: rendered.gif,
        }
    }
}

/// How far [`render_video`] is; both methods do nothing by default.
pub trait VideoProgress: Send {
    /// Frame `k` of `n` starts.
    fn frame(&mut self, _k: usize, _n: usize) {}
    /// `n` more rays were traced.
    fn rays(&mut self, _n: u64) {}
}

#[derive(Debug, thiserror::Error)]
pub enum VideoError {
    // Boxed: the wrapped errors are large.
    #[error("rendering frame {frame} ({label}): {source}")]
    Frame {
        frame: usize,
        label: String,
        #[source]
        source: Box<ModelError>,
    },

    #[error("{what} {}: {source}", path.display())]
    Io {
        what: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },

    #[error("encoding a GIF frame: {0}")]
    Gif(#[source] Box<image::ImageError>),

    #[error("{}: the GIF could not be completed (disk full?)", .0.display())]
    GifIncomplete(PathBuf),

    #[error(transparent)]
    Png(Box<EvalError>),
}

impl From<EvalError> for VideoError {
    fn from(e: EvalError) -> Self {
        Self::Png(Box::new(e))
    }
}

impl pma_data::ExitKind for VideoError {
    fn kind(&self) -> pma_data::ErrorKind {
        match self {
            Self::Frame { source, .. } => source.kind(),
            Self::Png(e) => e.kind(),
            Self::Io { .. } | Self::Gif(_) | Self::GifIncomplete(_) => pma_data::ErrorKind::Failure,
        }
    }
}

/// Render every shot into `frame_NNNN.png` in `opts.out`, and the GIF and the strip if
/// asked for.
pub fn render_video(
    avatar: &Avatar,
    items: &[PoseItem],
    shots: &[Shot],
    opts: &VideoOptions,
    progress: &mut dyn VideoProgress,
) -> std::result::Result<Rendered, VideoError> {
    let Some(first) = shots.first() else {
        return Ok(Rendered {
            frames: Vec::new(),
            gif: None,
        });
    };
    let (w, h) = (first.camera.width, first.camera.height);
    let background: Vec<f32> = (0..w * h).flat_map(|_| opts.background).collect();
    let image_opts = ImageOptions {
        chunk: opts.chunk,
        head: opts.head,
        device: opts.device.clone(),
        pass: opts.pass.clone(),
    };
    let gif_path = opts.out.join("render.gif");
    let mut gif = match opts.gif_fps {
        Some(fps) => Some(GifStream::create(&gif_path, fps)?),
        None => None,
    };
    let strip_frames: Vec<usize> = opts
        .strip
        .map(|n| spread(&(0..shots.len()).collect::<Vec<_>>(), n))
        .unwrap_or_default();
    let mut strip = Vec::with_capacity(strip_frames.len());
    let mut frames = Vec::with_capacity(shots.len());
    for (k, shot) in shots.iter().enumerate() {
        progress.frame(k, shots.len());
        let item = &items[shot.item];
        let t = Instant::now();
        let img = render_shot(
            avatar,
            item,
            &shot.camera,
            &background,
            &image_opts,
            progress,
        )
        .map_err(|source| VideoError::Frame {
            frame: k,
            label: item.label.clone(),
            source: Box::new(source),
        })?;
        let seconds = t.elapsed().as_secs_f64();
        let rgb = to_rgb8(&img);
        let file = frame_file(k);
        write_png(&rgb, &opts.out.join(&file))?;
        if let Some(g) = gif.as_mut() {
            g.push(&rgb)?;
        }
        if strip_frames.contains(&k) {
            strip.push(rgb);
        }
        frames.push(FrameReport {
            file,
            pose: item.label.clone(),
            camera_origin: shot.camera.origin(),
            rays: shot_rays(shot, items, opts.head),
            seconds,
        });
    }
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
        write_png(&img, &opts.out.join("strip.png"))?;
    }
    crate::compute::profile::print_render(shots.len());
    Ok(Rendered { frames, gif })
}

// The renderer closure returns this crate's error, which carries candle's (large) one.
#[allow(clippy::result_large_err)]
fn render_shot(
    avatar: &Avatar,
    item: &PoseItem,
    camera: &Camera,
    background: &[f32],
    opts: &ImageOptions,
    progress: &mut dyn VideoProgress,
) -> Result<RenderedImage> {
    // Chunks may run on several workers at once; each reports its rays when done.
    let progress = std::sync::Mutex::new(progress);
    let pose = avatar.pose_features(&item.poses, None)?;
    let renderer = |o: &Tensor, d: &Tensor, bg: &Tensor| -> Result<ChunkRender> {
        let rays = Rays {
            origins: o.clone(),
            dirs: d.clone(),
            bgs: Some(bg.clone()),
            framecodes: vec![-1; o.dim(0)?],
        };
        let out = avatar.render_chunk(&rays, &item.poses, &pose, &opts.pass)?;
        if let Ok(mut p) = progress.lock() {
            p.rays(o.dim(0)? as u64);
        }
        Ok(out)
    };
    render_image(&renderer, camera, &item.kp3d, Some(background), opts)
}

/// 8-bit RGB of a render (rounded, as the frames are shown).
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
    fn create(path: &Path, fps: f64) -> std::result::Result<Self, VideoError> {
        let io = |source| VideoError::Io {
            what: "writing",
            path: path.to_path_buf(),
            source,
        };
        let file = AtomicFile::create(path).map_err(io)?;
        let handle = file.owned_writer().map_err(io)?;
        let mut encoder = GifEncoder::new_with_speed(std::io::BufWriter::new(handle), 10);
        encoder
            .set_repeat(Repeat::Infinite)
            .map_err(|e| VideoError::Gif(Box::new(e)))?;
        Ok(Self {
            encoder,
            file,
            delay: Delay::from_numer_denom_ms(1000, fps.round().max(1.0) as u32),
        })
    }

    fn push(&mut self, rgb: &RgbImage) -> std::result::Result<(), VideoError> {
        let rgba = RgbaImage::from_fn(rgb.width(), rgb.height(), |x, y| {
            let p = rgb.get_pixel(x, y).0;
            image::Rgba([p[0], p[1], p[2], 255])
        });
        self.encoder
            .encode_frame(Frame::from_parts(rgba, 0, 0, self.delay))
            .map_err(|e| VideoError::Gif(Box::new(e)))
    }

    fn finish(self) -> std::result::Result<(), VideoError> {
        let path = self.file.path().to_path_buf();
        let io = |what| {
            let path = path.clone();
            move |source| VideoError::Io { what, path, source }
        };
        // Dropping the encoder writes the GIF trailer and flushes the buffer, both without
        // reporting errors: check that the file ends with the trailer byte instead.
        drop(self.encoder);
        let mut f = self.file.file();
        use std::io::{Read as _, Seek as _, SeekFrom};
        f.seek(SeekFrom::End(-1)).map_err(io("writing"))?;
        let mut last = [0u8; 1];
        f.read_exact(&mut last).map_err(io("writing"))?;
        if last[0] != 0x3B {
            return Err(VideoError::GifIncomplete(path));
        }
        self.file.commit().map_err(io("replacing"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::DType;

    fn item(k: usize, camera: Option<Camera>) -> PoseItem {
        let dev = Device::Cpu;
        PoseItem {
            label: format!("pose {k}"),
            poses: Poses {
                bones: vec![[[0.0; 3]; 24]],
                skts: Tensor::zeros((1, 24, 4, 4), DType::F32, &dev).unwrap(),
                cyls: Tensor::zeros((1, 5), DType::F32, &dev).unwrap(),
            },
            kp3d: pma_data::synth::figure::rest_pose(),
            bones: [[0.0; 3]; 24],
            camera,
        }
    }

    fn plan(mode: CameraMode, views: Option<usize>, frame: usize) -> CameraPlan<'static> {
        CameraPlan {
            mode,
            source: CameraSource::Framing,
            res: Some((32, 24)),
            views,
            frame,
            distance: None,
            head: HeadDir::NegY,
        }
    }

    #[test]
    fn orbit_turns_once_per_views_around_the_body() {
        let items: Vec<PoseItem> = (0..4).map(|k| item(k, None)).collect();
        let s = shots(&plan(CameraMode::Orbit, Some(4), 0), &items).unwrap();
        assert_eq!(s.iter().map(|s| s.item).collect::<Vec<_>>(), [0, 1, 2, 3]);
        assert!(s
            .iter()
            .all(|s| (s.camera.width, s.camera.height) == (32, 24)));
        // The same pose every frame: the cameras circle one vertical axis, a quarter turn
        // apart, so the first and third stand opposite each other.
        let c = body_centre(&items[0].kp3d, HeadDir::NegY);
        let off = |k: usize| {
            let o = s[k].camera.origin();
            [(o[0] - c[0]) as f64, (o[2] - c[2]) as f64]
        };
        let r0 = off(0)[0].hypot(off(0)[1]);
        for k in 1..4 {
            assert!(
                (off(k)[0].hypot(off(k)[1]) - r0).abs() < 1e-4 * r0,
                "frame {k}"
            );
        }
        assert!((off(0)[0] + off(2)[0]).abs() < 1e-4 * r0);
        assert!((off(0)[1] + off(2)[1]).abs() < 1e-4 * r0);
        // Follow keeps the first camera (the pose does not move here).
        let f = shots(&plan(CameraMode::Follow, Some(4), 0), &items).unwrap();
        assert!(f.iter().all(|s| s.camera.origin() == f[0].camera.origin()));
    }

    #[test]
    fn bullet_time_freezes_one_pose_and_bad_plans_are_refused() {
        let items: Vec<PoseItem> = (0..3).map(|k| item(k, None)).collect();
        let s = shots(&plan(CameraMode::Bullet, Some(6), 2), &items).unwrap();
        assert_eq!(s.len(), 6);
        assert!(s.iter().all(|s| s.item == 2));
        // Errors, not panics: a frozen frame past the poses, dataset cameras the poses do
        // not have, no poses at all.
        assert!(shots(&plan(CameraMode::Bullet, None, 3), &items).is_err());
        assert!(shots(&plan(CameraMode::Dataset, None, 0), &items).is_err());
        assert!(shots(&plan(CameraMode::Orbit, None, 0), &[]).is_err());
    }
}
