//! The avatar behind the server and how one frame is rendered.
//!
//! [`Renderer`] owns the avatar and is used by one thread only; the page's per-pass switches
//! ([`crate::pass::PassOptions`]) become the pass options of each frame's render. It
//! reloads the model when its file changes (a training run writing a new checkpoint).
//!
//! A frame is one call of `pma_model::render::image::render_image`, the renderer every
//! command uses, with a chunk renderer that first asks whether the frame is still wanted:
//! a newer request makes the next chunk stop the frame, so it ends within one chunk's time.

use std::path::{Path, PathBuf};
use std::time::{Instant, UNIX_EPOCH};

use candle_core::{Device, Tensor};
use pma_data::camera::Camera;
use pma_data::interrupt::Interrupted;
use pma_model::compute::numerics::Numerics;
use pma_model::error::ModelError;
use pma_model::eval::{quantize, score_image, PsnrRegion};
use pma_model::render::avatar::{Avatar, Rays};
use pma_model::render::camera_path::{load_avatar, look_at, ViewDirs};
use pma_model::render::image::{render_image, ImageOptions, RenderedImage};
use serde::Serialize;

use crate::query::{CamSpec, RenderRequest};
use crate::scene::Scene;
use crate::ViewError;

/// What `pma view` was pointed at.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ModelSource {
    /// A model file.
    File(PathBuf),
    /// A run directory (`pma train --out`), possibly still being written.
    Run(PathBuf),
}

impl ModelSource {
    /// A directory is a run directory, anything else a model file.
    pub fn new(path: &Path) -> Result<ModelSource, ViewError> {
        let refuse = |what: String| Err(ViewError::Input(format!("{}: {what}", path.display())));
        match std::fs::metadata(path) {
            Ok(m) if m.is_dir() => Ok(ModelSource::Run(path.to_path_buf())),
            Ok(m) if m.is_file() => Ok(ModelSource::File(path.to_path_buf())),
            Ok(m) => refuse(format!(
                "{}, expected a model file or a run directory",
                pma_data::fsio::file_type_name(&m.file_type())
            )),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                refuse("no such model file or run directory".into())
            }
            Err(e) => refuse(e.to_string()),
        }
    }

    /// The model file to show now.
    pub fn model_file(&self) -> PathBuf {
        match self {
            ModelSource::File(p) => p.clone(),
            ModelSource::Run(dir) => run_model_file(dir),
        }
    }

    pub fn run_dir(&self) -> Option<&Path> {
        match self {
            ModelSource::Run(dir) => Some(dir),
            ModelSource::File(_) => None,
        }
    }
}

/// The model of run directory `run` that the viewer shows: the newest complete checkpoint
/// (`pma_model::network::run_dir::newest_model`); before the first one, the path where it
/// will be published.
pub fn run_model_file(run: &Path) -> PathBuf {
    pma_model::network::run_dir::newest_model(run)
        .unwrap_or_else(|_| run.join(pma_model::network::run_dir::MODEL_FILE))
}

/// What tells one version of a file from the next: modification time and length.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct Stamp {
    /// Milliseconds since the Unix epoch.
    pub modified_ms: u64,
    pub bytes: u64,
}

/// `path`'s [`Stamp`], `None` when it cannot be read.
pub fn stamp(path: &Path) -> Option<Stamp> {
    let meta = std::fs::metadata(path).ok()?;
    let modified_ms = meta
        .modified()
        .ok()?
        .duration_since(UNIX_EPOCH)
        .ok()?
        .as_millis() as u64;
    Some(Stamp {
        modified_ms,
        bytes: meta.len(),
    })
}

/// The model, and the settings every frame is rendered with.
pub struct Renderer {
    source: ModelSource,
    device: Device,
    dirs: ViewDirs,
    chunk: usize,
    numerics: Numerics,
    avatar: Avatar,
    stamp: Option<Stamp>,
    /// Models loaded so far (1 after [`Renderer::load`]).
    version: u64,
    /// Why the newest model file could not be loaded (the previous model stays).
    reload_error: Option<String>,
}

/// Why a frame was not rendered.
#[derive(Debug)]
pub enum RenderFail {
    /// A newer request arrived.
    Superseded,
    /// Ctrl-C.
    Interrupted,
    /// The request cannot be rendered (HTTP 400).
    Bad(String),
    /// The render failed (HTTP 500).
    Failed(String),
}

/// A rendered frame.
pub struct Frame {
    pub png: Vec<u8>,
    pub stats: FrameStats,
}

/// What the page shows under a frame.
#[derive(Debug, Clone, Serialize)]
pub struct FrameStats {
    pub width: usize,
    pub height: usize,
    pub pose: usize,
    /// Wall time of the render (pose features, rays, network, compositing), ms.
    pub ms: f64,
    /// Rays traced (pixels inside the body's box).
    pub rays: usize,
    pub rays_per_s: f64,
    /// Samples that went through the network.
    pub samples: u64,
    pub cull_rays: bool,
    pub cull_samples: bool,
    pub occupancy: bool,
    pub early_stop: bool,
    pub cull_joints: bool,
    /// Centre of the body (the camera's turning point).
    pub centre: [f32; 3],
    /// The dataset image this view is, when scored.
    pub image: Option<usize>,
    pub scores: Option<FrameScores>,
    /// Models loaded so far: changes when a new checkpoint is picked up.
    pub model_version: u64,
    pub reload_error: Option<String>,
}

/// `pma eval`'s scores of the frame against its ground truth (`None`: undefined, e.g. LPIPS
/// under its 31×31 minimum).
#[derive(Debug, Clone, Serialize)]
pub struct FrameScores {
    pub psnr: Option<f64>,
    pub ssim: Option<f64>,
    pub lpips: Option<f64>,
}

fn finite(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}

impl Renderer {
    /// Load the model of `source` (`chunk` rays per network call) to compute with
    /// `numerics`.
    pub fn load(
        source: ModelSource,
        device: Device,
        dirs: ViewDirs,
        chunk: usize,
        numerics: Numerics,
    ) -> Result<Renderer, ViewError> {
        let max = pma_model::render::MAX_CHUNK_RAYS;
        if !(1..=max).contains(&chunk) {
            return Err(ViewError::Input(format!(
                "--chunk {chunk} must be in 1..={max}"
            )));
        }
        let file = source.model_file();
        if let (Some(dir), false) = (source.run_dir(), file.exists()) {
            return Err(ViewError::Input(format!(
                "{}: the run has no checkpoint yet ({} appears with its first one)",
                dir.display(),
                file.display()
            )));
        }
        let stamp = stamp(&file);
        let avatar = load_avatar(&file, &device, dirs)?.with_numerics(numerics);
        Ok(Renderer {
            source,
            device,
            dirs,
            chunk,
            numerics,
            avatar,
            stamp,
            version: 1,
            reload_error: None,
        })
    }

    pub fn avatar(&self) -> &Avatar {
        &self.avatar
    }

    pub fn source(&self) -> &ModelSource {
        &self.source
    }

    /// Load the model file again if it changed since the last load. A file that does not
    /// load keeps the previous model and is reported with the next frames.
    pub fn refresh(&mut self) {
        let file = self.source.model_file();
        let now = stamp(&file);
        if now.is_none() || now == self.stamp {
            return;
        }
        self.stamp = now;
        match load_avatar(&file, &self.device, self.dirs).map(|a| a.with_numerics(self.numerics)) {
            Ok(a) => {
                self.avatar = a;
                self.version += 1;
                self.reload_error = None;
            }
            Err(e) => self.reload_error = Some(format!("{}: {e}", file.display())),
        }
    }

    /// Render `req`. `superseded` is asked before every chunk of rays; once it says yes the
    /// frame stops with [`RenderFail::Superseded`].
    // The chunk renderer returns pma-model's error, which carries candle's (large) one.
    #[allow(clippy::result_large_err)]
    pub fn render(
        &mut self,
        scene: &Scene,
        req: &RenderRequest,
        superseded: &(dyn Fn() -> bool + Sync),
    ) -> Result<Frame, RenderFail> {
        let failed = |e: &dyn std::fmt::Display| RenderFail::Failed(e.to_string());
        if req.pose >= scene.pose_count() {
            return Err(RenderFail::Bad(format!(
                "pose {} is past the {} pose(s)",
                req.pose,
                scene.pose_count()
            )));
        }
        if req.pass.occupancy && self.avatar.occupancy().is_none() {
            return Err(RenderFail::Bad(
                "occupancy=1: the model has no occupancy grid (pma train --occupancy or \
                 pma occupancy build adds one)"
                    .into(),
            ));
        }
        let cam = camera(scene, req)?;
        let image = match req.cam {
            CamSpec::Dataset(c) if req.score => scene.image_of(req.pose, c).filter(|_| {
                scene.camera(c).map(|k| (k.width, k.height)) == Some((cam.width, cam.height))
            }),
            _ => None,
        };
        let version = self.version;
        let reload_error = self.reload_error.clone();
        let chunk = self.chunk;
        let device = self.device.clone();
        let avatar = &self.avatar;
        let pass = req.pass.model_options();
        let item = scene.pose(req.pose, avatar).map_err(|e| failed(&e))?;
        let start = Instant::now();
        let rays = std::sync::atomic::AtomicUsize::new(0);
        let result = (|| -> Result<RenderedImage, ModelError> {
            let pose = avatar.pose_features(&item.poses, None)?;
            let chunk_fn = |o: &Tensor, d: &Tensor, bg: &Tensor| {
                if superseded() {
                    return Err(ModelError::Interrupted(Interrupted));
                }
                let n = o.dim(0)?;
                let batch = Rays {
                    origins: o.clone(),
                    dirs: d.clone(),
                    bgs: Some(bg.clone()),
                    framecodes: vec![-1; n],
                };
                let out = avatar.render_chunk(&batch, &item.poses, &pose, &pass)?;
                rays.fetch_add(n, std::sync::atomic::Ordering::Relaxed);
                Ok(out)
            };
            let opts = ImageOptions {
                chunk,
                head: scene.head(),
                device,
                pass: pass.clone(),
            };
            render_image(&chunk_fn, &cam, &item.kp3d, None, &opts)
        })();
        let img = match result {
            Ok(img) => img,
            Err(_) if pma_data::interrupt::requested() => return Err(RenderFail::Interrupted),
            Err(_) if superseded() => return Err(RenderFail::Superseded),
            Err(e) => return Err(failed(&e)),
        };
        let secs = start.elapsed().as_secs_f64();
        let samples = img.stats.points_evaluated;
        let scores = match image {
            Some(n) => Some(score(scene, n, &img).map_err(|e| failed(&e))?),
            None => None,
        };
        let rays = rays.into_inner();
        let png = encode_png(&img).map_err(|e| failed(&e))?;
        Ok(Frame {
            png,
            stats: FrameStats {
                width: img.width,
                height: img.height,
                pose: req.pose,
                ms: secs * 1e3,
                rays,
                rays_per_s: if secs > 0.0 { rays as f64 / secs } else { 0.0 },
                samples,
                cull_rays: req.pass.cull_rays,
                cull_samples: req.pass.cull_samples,
                occupancy: req.pass.occupancy,
                early_stop: req.pass.early_stop,
                cull_joints: req.pass.cull_joints,
                centre: scene.centre(&item.kp3d),
                image,
                scores,
                model_version: version,
                reload_error,
            },
        })
    }
}

/// The camera of `req`, at the requested size.
fn camera(scene: &Scene, req: &RenderRequest) -> Result<Camera, RenderFail> {
    let (w, h) = (req.width, req.height);
    match req.cam {
        CamSpec::Dataset(c) => scene
            .camera(c)
            .map(|cam| cam.resized(w, h))
            .ok_or_else(|| RenderFail::Bad(format!("no dataset camera {c}"))),
        CamSpec::Free {
            eye,
            target,
            fov_deg,
        } => {
            let bad = |e: &dyn std::fmt::Display| RenderFail::Bad(e.to_string());
            let c2w = look_at(eye, target, scene.head().vector()).map_err(|e| bad(&e))?;
            let f = (0.5 * h as f64 / (0.5 * fov_deg.to_radians()).tan()) as f32;
            Camera::new(w, h, f, f, w as f32 / 2.0, h as f32 / 2.0, c2w).map_err(|e| bad(&e))
        }
    }
}

/// PSNR, SSIM and LPIPS of `img` against image `n`, as `pma eval` scores them.
fn score(scene: &Scene, n: usize, img: &RenderedImage) -> Result<FrameScores, ViewError> {
    let (gt, mask, h, w) = scene.ground_truth(n)?;
    let opts = pma_model::eval::EvalOptions::quick(1);
    let s = score_image(
        &quantize(img),
        &gt,
        &mask,
        h,
        w,
        PsnrRegion::Mask,
        opts.ssim_data_range,
    )?;
    Ok(match s {
        Some(s) => FrameScores {
            psnr: finite(s.psnr),
            ssim: finite(s.ssim),
            lpips: finite(s.lpips),
        },
        None => FrameScores {
            psnr: None,
            ssim: None,
            lpips: None,
        },
    })
}

/// 8-bit RGB PNG of values in [0,1] (fast compression: the frame is on the wire at once).
pub fn png_rgb(rgb: &[f32], width: usize, height: usize) -> Result<Vec<u8>, ViewError> {
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    use image::ImageEncoder as _;
    let px: Vec<u8> = rgb
        .iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    let mut out = Vec::new();
    PngEncoder::new_with_quality(&mut out, CompressionType::Fast, FilterType::Adaptive)
        .write_image(
            &px,
            width as u32,
            height as u32,
            image::ExtendedColorType::Rgb8,
        )
        .map_err(|e| ViewError::Failed(format!("encoding a PNG: {e}")))?;
    Ok(out)
}

fn encode_png(img: &RenderedImage) -> Result<Vec<u8>, ViewError> {
    png_rgb(&img.rgb, img.width, img.height)
}
