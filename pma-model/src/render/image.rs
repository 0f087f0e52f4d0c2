//! Whole-image rendering with bounded memory (docs/conventions.md, "Evaluation protocol").
//!
//! Only pixels inside the 2-D box of the body's render cylinder (E = 0.25, a = 1.6, b = 1.1,
//! bottom-right bound exclusive) are ray-traced, row by row, in chunks; every other pixel keeps
//! the background (acc and disp 0). Ray directions are not normalised (camera-space z = −1), as
//! in the reference render path; whether the SH view encoding normalises them is the model's
//! `normalize_view_dirs` quirk switch.
//!
//! Memory: this module holds the output images (rgb, acc, disp: 20 B per pixel), the list of
//! box pixels (8 B per pixel), together 7 MiB at 512×512, and the rays of one chunk (36 B per
//! ray); nothing else grows with the resolution or the number of chunks.
//! The peak is set by the chunk renderer, which sees at most `chunk` rays per CPU worker at a
//! time (chunks run side by side on the workers; one at a time on a GPU). For the
//! PM-Avatar network its largest live tensors are the [C·S, 24, 128] f32 window features,
//! C·S·12 KiB each (S = 48 coarse or 24 fine samples per ray): 2.8 GiB for C = 5120 rays in
//! the coarse pass, 0.56 GiB for C = 1024. A renderer that evaluates all of a chunk's points at
//! once therefore needs C ≲ 1024 to stay within 4 GiB at any resolution; one that splits the
//! points itself can use the reference's 5120.
//!
//! The image does not depend on the chunk size, with one reference quirk as exception: rays
//! that miss the ray caster's cylinder get the mean near/far of their chunk (as in the
//! reference, whose chunks are 5120 rays); `Quirks::per_ray_cylinder_fallback` removes that.

use candle_core::{Device, Tensor};
use pma_data::camera::Camera;
use pma_data::cylinder::{cylinder_box, cylinder_from_joints, CylinderParams, HeadDir, PixelBox};
use pma_data::skeleton::Joints;

use crate::compute::host::host_f32_shaped;
use crate::error::{ModelError, Result};
use crate::network::PoseFeatures;
use crate::render::avatar::{Avatar, Mode, Rays};
use crate::render::batch::{Outputs, Poses};
use crate::render::options::{PassOptions, PassStats};
use crate::render::raycast::CoarseSamples;

/// Rays per chunk of the reference render path.
pub const DEFAULT_CHUNK: usize = 5120;

/// What a chunk renderer returns for C rays.
#[derive(Debug, Clone)]
pub struct ChunkRender {
    /// rgb: [C,3] colour already composited over the per-ray background.
    pub rgb: Tensor,
    /// acc: [C]
    pub acc: Tensor,
    /// disp: [C]
    pub disp: Tensor,
    /// What the chunk's pass evaluated (zeros for renderers that do not count).
    pub stats: PassStats,
}

/// Renders one chunk of rays of a single pose (e.g. the avatar's ray renderer behind a
/// closure). Chunks of one image may be rendered at the same time on the CPU workers.
pub trait ChunkRenderer: Sync {
    /// rays_o, rays_d: [C,3] (rays_d unnormalised, camera-space z = −1); bgs: [C,3] background
    /// colour of each ray's pixel.
    fn render_chunk(&self, rays_o: &Tensor, rays_d: &Tensor, bgs: &Tensor) -> Result<ChunkRender>;
}

impl<F> ChunkRenderer for F
where
    F: Fn(&Tensor, &Tensor, &Tensor) -> Result<ChunkRender> + Sync,
{
    fn render_chunk(&self, rays_o: &Tensor, rays_d: &Tensor, bgs: &Tensor) -> Result<ChunkRender> {
        self(rays_o, rays_d, bgs)
    }
}

/// Options of [`render_image`].
#[derive(Debug, Clone)]
pub struct ImageOptions {
    /// Rays per renderer call (≥ 1). See the module docs for the memory it implies.
    pub chunk: usize,
    /// Head direction of the pose data (the render box needs the cylinder's top side).
    pub head: HeadDir,
    /// Device the ray tensors are created on.
    pub device: Device,
    /// What the avatar's passes may leave out ([`Avatar::render_image`]; a chunk renderer of
    /// [`render_image`] makes its own choice).
    pub pass: PassOptions,
}

impl Default for ImageOptions {
    fn default() -> Self {
        Self {
            chunk: DEFAULT_CHUNK,
            head: HeadDir::NegY,
            device: Device::Cpu,
            pass: PassOptions::default(),
        }
    }
}

/// A rendered image, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderedImage {
    pub height: usize,
    pub width: usize,
    /// rgb: [H,W,3]; the background outside the body box.
    pub rgb: Vec<f32>,
    /// acc: [H,W]; 0 outside the body box.
    pub acc: Vec<f32>,
    /// disp: [H,W]; 0 outside the body box.
    pub disp: Vec<f32>,
    /// What the passes of the image evaluated, summed over its chunks.
    pub stats: PassStats,
}

/// Pixels to ray-trace for a pose seen by `cam`: the 2-D box of the render cylinder of
/// kp3d: [24,3]. When part of the cylinder lies behind the camera its projection is
/// meaningless (the reference does not handle it), so the whole image is returned instead:
/// slower, never wrong.
pub fn body_box(cam: &Camera, kp3d: &Joints, head: HeadDir) -> PixelBox {
    let cyl = cylinder_from_joints(kp3d, &CylinderParams::render(head));
    cylinder_box(&cyl, cam, None).unwrap_or(PixelBox {
        x0: 0,
        y0: 0,
        x1: cam.width as i64,
        y1: cam.height as i64,
    })
}

/// Render the full image of one pose. `renderer` holds the pose; kp3d: [24,3] its joints
/// (world); background: [H,W,3] or `None` for black.
pub fn render_image<R: ChunkRenderer + ?Sized>(
    renderer: &R,
    cam: &Camera,
    kp3d: &Joints,
    background: Option<&[f32]>,
    opts: &ImageOptions,
) -> Result<RenderedImage> {
    let (h, w) = (cam.height, cam.width);
    if opts.chunk == 0 {
        return Err(ModelError::Input(
            "render_image: chunk must be >= 1 ray".into(),
        ));
    }
    cam.validate()?;
    if let Some((j, k)) = kp3d
        .iter()
        .enumerate()
        .find_map(|(j, k)| k.iter().any(|v| !v.is_finite()).then_some((j, k)))
    {
        return Err(ModelError::Input(format!(
            "render_image: kp3d joint {j} is {k:?}"
        )));
    }
    let mut rgb = match background {
        Some(bg) if bg.len() != h * w * 3 => {
            return Err(ModelError::shape(
                "background",
                [h, w, 3],
                format!("{} values", bg.len()),
            ));
        }
        Some(bg) => bg.to_vec(),
        None => vec![0f32; h * w * 3],
    };
    let mut acc = vec![0f32; h * w];
    let mut disp = vec![0f32; h * w];

    let pbox = body_box(cam, kp3d, opts.head);
    // Row-major order inside the box, like the reference's masked ray list.
    let pixels: Vec<usize> = (pbox.y0.max(0)..pbox.y1.min(h as i64))
        .flat_map(|y| {
            (pbox.x0.max(0)..pbox.x1.min(w as i64)).map(move |x| y as usize * w + x as usize)
        })
        .collect();
    let origin = cam.origin();
    let chunks: Vec<&[usize]> = pixels.chunks(opts.chunk).collect();
    // Whole chunks on the CPU workers: a pass that leaves work out has a small network share
    // per chunk and long host stretches (casting, the window test, compositing) that one
    // chunk at a time would leave a core idle through. A chunk's rays and their results do
    // not depend on which worker runs it, so neither does the image.
    let workers = crate::compute::parallel::workers_on(&opts.device);
    let outs = crate::compute::parallel::map_ordered(workers, chunks.len(), |i| {
        crate::interrupt::check()?;
        // A chunk is a timeline of its own for `PMA_PROFILE=1`.
        crate::compute::profile::start(&opts.device);
        let chunk = chunks[i];
        let c = chunk.len();
        let mut o = Vec::with_capacity(3 * c);
        let mut d = Vec::with_capacity(3 * c);
        let mut bg = Vec::with_capacity(3 * c);
        for &p in chunk {
            o.extend_from_slice(&origin);
            d.extend_from_slice(&cam.ray_dir(p % w, p / w, false));
            bg.extend_from_slice(&rgb[3 * p..3 * p + 3]);
        }
        let dev = &opts.device;
        let out = renderer.render_chunk(
            &Tensor::from_vec(o, (c, 3), dev)?,
            &Tensor::from_vec(d, (c, 3), dev)?,
            &Tensor::from_vec(bg, (c, 3), dev)?,
        )?;
        Ok::<_, ModelError>((
            host_f32_shaped("chunk rgb", &out.rgb, &[c, 3])?,
            host_f32_shaped("chunk acc", &out.acc, &[c])?,
            host_f32_shaped("chunk disp", &out.disp, &[c])?,
            out.stats,
        ))
    })?;
    let mut stats = PassStats::default();
    for (chunk, (chunk_rgb, chunk_acc, chunk_disp, chunk_stats)) in chunks.iter().zip(outs) {
        stats.add(&chunk_stats);
        for (i, &p) in chunk.iter().enumerate() {
            rgb[3 * p..3 * p + 3].copy_from_slice(&chunk_rgb[3 * i..3 * i + 3]);
            acc[p] = chunk_acc[i];
            disp[p] = chunk_disp[i];
        }
    }
    Ok(RenderedImage {
        height: h,
        width: w,
        rgb,
        acc,
        disp,
        stats,
    })
}

impl Avatar {
    // ---- whole renders ------------------------------------------------------------------

    /// Inference: render rays (eval mode, no noise, no gradient, bounded memory), leaving
    /// out what `opts` says.
    pub fn render_rays(&self, rays: &Rays, poses: &Poses, opts: &PassOptions) -> Result<Outputs> {
        self.forward(rays, poses, &mut Mode::Infer, opts, None)
    }

    /// Render a whole image of one pose (eval mode, mean frame code, black or given
    /// background), in chunks of rays inside the body's 2-D box: memory stays bounded at any
    /// resolution. `kp3d` are the pose's joint positions (for the box); `opts.pass` says what
    /// the passes may leave out.
    pub fn render_image(
        &self,
        poses: &Poses,
        kp3d: &Joints,
        cam: &pma_data::camera::Camera,
        background: Option<&[f32]>,
        opts: &ImageOptions,
    ) -> Result<RenderedImage> {
        if poses.bones.len() != 1 {
            return Err(ModelError::Input(format!(
                "render_image takes one pose, found {}",
                poses.bones.len()
            )));
        }
        // The GNN and every other per-pose term once per image, not once per chunk.
        let pose = self.pose_features(poses, None)?;
        let renderer = |o: &Tensor, d: &Tensor, bg: &Tensor| -> Result<ChunkRender> {
            let rays = Rays {
                origins: o.clone(),
                dirs: d.clone(),
                bgs: Some(bg.clone()),
                framecodes: vec![-1; o.dim(0)?],
            };
            self.render_chunk(&rays, poses, &pose, &opts.pass)
        };
        render_image(&renderer, cam, kp3d, background, opts)
    }

    /// One chunk of rays of one pose (inference, `pose` from [`Self::pose_features`]): the
    /// fine render's rgb, acc and disp, as [`Self::forward_with_pose`] gives them.
    ///
    /// With ray culling, the rays that cross no bone box skip everything after casting: all
    /// their samples are culled (raw outputs 0), so they render as exactly the background
    /// with acc and disp 0. Only the other rays are composited and resampled; their samples,
    /// network calls and results are those of the whole chunk (culled rays add no sample to
    /// a call, and compositing and resampling are per ray).
    pub fn render_chunk(
        &self,
        rays: &Rays,
        poses: &Poses,
        pose: &PoseFeatures,
        opts: &PassOptions,
    ) -> Result<ChunkRender> {
        let of = |out: Outputs| ChunkRender {
            rgb: out.fine.rgb,
            acc: out.fine.acc,
            disp: out.fine.disp,
            stats: out.stats,
        };
        // Rays of several poses come in equal blocks per pose, which dropping rays would break.
        if !opts.culling.rays || poses.bones.len() != 1 {
            return Ok(of(self.forward_with_pose(
                rays,
                poses,
                pose,
                &mut Mode::Infer,
                opts,
            )?));
        }
        crate::render::batch::check_batch(rays, poses)?;
        let cast = crate::render::batch::cast_batch(rays, poses, self.dtype())?;
        let (rays, poses) = cast.as_ref().map_or((rays, poses), |(r, p)| (r, p));
        let coarse = self.cast(rays, poses, pose, opts)?;
        crate::compute::profile::mark("cast", self.device());
        let n = rays.origins.dim(0)?;
        let alive: Vec<usize> = match &coarse.bounds {
            Some(b) => (0..n).filter(|&r| b.ray_hits_body[r]).collect(),
            None => (0..n).collect(),
        };
        if alive.len() == n {
            return Ok(of(self.forward_cast(
                rays,
                poses,
                pose,
                coarse,
                &mut Mode::Infer,
                opts,
            )?));
        }
        let dev = rays.origins.device();
        let mut rgb = match &rays.bgs {
            Some(bg) => host_f32_shaped("bgs", bg, &[n, 3])?,
            None => vec![0f32; 3 * n],
        };
        let (mut acc, mut disp) = (vec![0f32; n], vec![0f32; n]);
        let per_ray = (coarse.z.dim(1)? + self.ray_caster().n_importance()) as u64;
        let dead = (n - alive.len()) as u64;
        let mut stats = PassStats {
            samples: per_ray * dead,
            rays_culled: dead,
            ..PassStats::default()
        };
        if let (false, Some(bounds)) = (alive.is_empty(), &coarse.bounds) {
            let rows: Vec<u32> = alive.iter().map(|&r| r as u32).collect();
            let idx = Tensor::from_vec(rows, alive.len(), dev)?;
            let pick = |t: &Tensor| t.index_select(&idx, 0);
            let sub = Rays {
                origins: pick(&rays.origins)?,
                dirs: pick(&rays.dirs)?,
                bgs: rays.bgs.as_ref().map(pick).transpose()?,
                framecodes: alive.iter().map(|&r| rays.framecodes[r]).collect(),
            };
            let samples = CoarseSamples {
                bounds: Some(bounds.select(&alive)),
                z: pick(&coarse.z)?,
                pts: pick(&coarse.pts)?,
                fine_u: coarse.fine_u_of(&alive),
            };
            let out = self.forward_cast(&sub, poses, pose, samples, &mut Mode::Infer, opts)?;
            let m = alive.len();
            let sub_rgb = host_f32_shaped("chunk rgb", &out.fine.rgb, &[m, 3])?;
            let sub_acc = host_f32_shaped("chunk acc", &out.fine.acc, &[m])?;
            let sub_disp = host_f32_shaped("chunk disp", &out.fine.disp, &[m])?;
            for (k, &r) in alive.iter().enumerate() {
                rgb[3 * r..3 * r + 3].copy_from_slice(&sub_rgb[3 * k..3 * k + 3]);
                acc[r] = sub_acc[k];
                disp[r] = sub_disp[k];
            }
            stats.add(&out.stats);
        }
        Ok(ChunkRender {
            rgb: Tensor::from_vec(rgb, (n, 3), dev)?,
            acc: Tensor::from_vec(acc, n, dev)?,
            disp: Tensor::from_vec(disp, n, dev)?,
            stats,
        })
    }
}
