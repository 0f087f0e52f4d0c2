//! `pma mesh`: extract a coloured triangle mesh of a trained avatar in one pose.
//!
//! The density `relu(σ)` (no noise) is sampled on a cubic-cell grid covering
//! the posed body's part boxes (`--res` samples along the longest side) and turned into a
//! surface by marching cubes at `--threshold` (PM's default 5.0). Points outside every part
//! box count as empty (`--no-box-mask` evaluates them too). Vertices are written in world
//! coordinates (the reference's exporter uses axis-swapped index space; pma does not), with
//! normals toward lower density and colours = the radiance seen along the inward normal with
//! the mean frame code. `--preview PNG` rasterises the mesh from a framing camera.
//!
//! The pose: frame `--frame` of `--poses` (any pma-npz; retargeted onto the avatar like
//! `pma render --poses`), or by default the avatar's rest pose standing upright (head −y).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context as _;
use image::RgbImage;
use pma_data::cylinder::HeadDir;
use pma_data::skeleton::Joints;
use pma_model::render::avatar::Avatar;
use pma_model::render::camera_path::{facing, framing_camera};
use pma_model::tools::mesh::{
    colour_vertices, marching_cubes, render_preview, sample_grid, write_ply, AvatarField, Grid,
    Mesh, DEFAULT_THRESHOLD,
};
use pma_model::tools::retarget::{retarget, MotionClip, RootScale};

use super::{progress, read_motion, refuse, write_png};

#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Trained model (`RUN/model.safetensors`, or the run directory: its newest complete model).
    #[arg(long)]
    pub model: PathBuf,
    /// Pose source: a motion or dataset npz (default: the rest pose, upright).
    #[arg(long)]
    pub poses: Option<PathBuf>,
    /// Pose row of `--poses`.
    #[arg(long, default_value_t = 0)]
    pub frame: usize,
    /// Root trajectory scale for `--poses` (`legs`, `none` or a factor); moves the mesh only.
    #[arg(long, default_value = "legs")]
    pub root_scale: String,
    /// Grid samples along the longest side of the body's bounds.
    #[arg(long, default_value_t = 256)]
    pub res: usize,
    /// Density threshold of the surface.
    #[arg(long, default_value_t = DEFAULT_THRESHOLD)]
    pub threshold: f32,
    /// Grid points per density call.
    #[arg(long, default_value_t = 65536)]
    pub chunk: usize,
    /// Skip vertex colours.
    #[arg(long)]
    pub no_colour: bool,
    /// Evaluate the network outside the part boxes too.
    #[arg(long)]
    pub no_box_mask: bool,
    /// Points in cells the model's occupancy grid marks empty get density 0 without the
    /// network (the model needs a grid: `pma train --occupancy` or `pma occupancy build`).
    #[arg(long)]
    pub occupancy: bool,
    /// Colour with the reference's raw view directions (see `pma render --reference-dirs`).
    #[arg(long)]
    pub reference_dirs: bool,
    /// Also write a rasterised preview of the mesh (PNG).
    #[arg(long)]
    pub preview: Option<PathBuf>,
    /// Preview size in pixels (square).
    #[arg(long, default_value_t = 256)]
    pub preview_res: usize,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
    /// Compute device of the density and colour queries: cpu, cuda, cuda:N, metal (cuda/metal
    /// need a binary built with that feature). Marching cubes runs on the CPU.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Output PLY.
    #[arg(short = 'o', long)]
    pub out: PathBuf,
}

// The field closures return `pma_model`'s error, which carries candle's (large) one.
#[allow(clippy::result_large_err)]
pub fn run(mut args: Args) -> anyhow::Result<()> {
    check_args(&args)?;
    let device = super::device(&args.device)?;
    args.model = super::model_path(&args.model)?;
    super::check_paths(
        pma_data::fsio::PathCheck::new()
            .input("--model", &args.model)
            .input_opt("--poses", args.poses.as_deref())
            .output("--out", &args.out)
            .output_opt("--preview", args.preview.as_deref()),
    )?;
    let dirs = super::view_dirs(args.reference_dirs);
    let avatar = super::load_model(&args.model, &device, dirs)?;
    if args.occupancy && avatar.occupancy().is_none() {
        refuse!(
            "--occupancy: {} has no occupancy grid (train with `--occupancy` or build one with \
             `pma occupancy build`)",
            args.model.display()
        );
    }
    let (bones, root) = mesh_pose(&args, &avatar)?;
    let (poses, kp3d) = avatar.pose_from_bones(&bones, root)?;
    let mut field = AvatarField::new(&avatar, &poses)?;
    field.mask_outside_boxes = !args.no_box_mask;
    if args.occupancy {
        field = field.skip_empty_cells(&poses)?;
    }
    let (lo, hi) = field.bounds();
    let grid = Grid::covering(lo, hi, args.res, 2)?;

    let bar = progress::bar(args.quiet, grid.len() as u64, "density points");
    let t0 = Instant::now();
    let values = sample_grid(
        &grid,
        args.chunk,
        |pts| field.density(pts),
        &mut |done, _| bar.set_position(done as u64),
    )?;
    bar.finish_and_clear();
    let t_density = t0.elapsed().as_secs_f64();
    if args.occupancy {
        let (evaluated, skipped) = field.density_counts();
        println!(
            "occupancy grid: {skipped} of {} density points skipped as empty",
            evaluated + skipped
        );
    }
    let t1 = Instant::now();
    let mut mesh = marching_cubes(&values, &grid, args.threshold)?;
    let t_mc = t1.elapsed().as_secs_f64();
    if mesh.triangles.is_empty() {
        let max = values.iter().copied().fold(0f32, f32::max);
        refuse!(
            "no surface at density threshold {}: the largest density on the {:?} grid is {max:.3} \
             (pass a lower --threshold)",
            args.threshold,
            grid.dims
        );
    }
    let t2 = Instant::now();
    if !args.no_colour {
        colour_vertices(&mut mesh, 16_384, |p, d| field.radiance(p, d))?;
    }
    let t_colour = t2.elapsed().as_secs_f64();
    write_ply(&mesh, &args.out).with_context(|| format!("writing {}", args.out.display()))?;
    print_mesh(&args, &mesh);
    println!(
        "grid {:?} ({} points, spacing {:.4}): density {t_density:.2} s, marching cubes {t_mc:.2} s, colours {t_colour:.2} s",
        grid.dims,
        grid.len(),
        grid.spacing
    );
    if let Some(png) = &args.preview {
        write_preview(&mesh, &kp3d, &bones, args.preview_res, png)?;
        println!("wrote preview {}", png.display());
    }
    Ok(())
}

fn check_args(args: &Args) -> anyhow::Result<()> {
    if !(2..=1024).contains(&args.res) {
        refuse!("--res must be in 2..=1024, found {}", args.res);
    }
    if !args.threshold.is_finite() {
        refuse!("--threshold must be finite");
    }
    if !(1..=1 << 24).contains(&args.chunk) {
        refuse!("--chunk {} must be in 1..={}", args.chunk, 1 << 24);
    }
    if !(8..=4096).contains(&args.preview_res) {
        refuse!("--preview-res must be in 8..=4096");
    }
    Ok(())
}

/// Bone rotations and root of the pose to mesh: frame `--frame` of `--poses` retargeted onto
/// the avatar, or the rest pose upright.
fn mesh_pose(args: &Args, avatar: &Avatar) -> anyhow::Result<(Joints, [f32; 3])> {
    let Some(p) = &args.poses else {
        // The rest pose, turned from SMPL's y-up to the training convention's head −y.
        let mut b = [[0f32; 3]; 24];
        b[0] = [std::f32::consts::PI, 0.0, 0.0];
        return Ok((b, [0.0; 3]));
    };
    let clip = read_motion(avatar, p)?;
    if args.frame >= clip.len() {
        refuse!(
            "--frame {} is past the {} pose(s) of {}",
            args.frame,
            clip.len(),
            p.display()
        );
    }
    let one = MotionClip {
        bones: vec![clip.bones[args.frame]],
        roots: vec![clip.roots[args.frame]],
        ..clip
    };
    let scale: RootScale = args.root_scale.parse()?;
    let f = retarget(&one, avatar.rest_pose(), scale)?.frames.remove(0);
    Ok((f.bones, f.root))
}

fn print_mesh(args: &Args, mesh: &Mesh) {
    let stats = mesh.edge_stats();
    let (mlo, mhi) = mesh.bounds().expect("non-empty mesh");
    println!(
        "wrote {}: {} vertices, {} triangles, {}; bounds {:.3?}..{:.3?}",
        args.out.display(),
        mesh.vertices.len(),
        mesh.triangles.len(),
        if stats.is_watertight() {
            "watertight".to_string()
        } else {
            format!(
                "{} boundary / {} non-manifold edges",
                stats.boundary, stats.non_manifold
            )
        },
        mlo,
        mhi
    );
}

/// The mesh rasterised from a framing camera, as a PNG.
fn write_preview(
    mesh: &Mesh,
    kp3d: &Joints,
    bones: &Joints,
    res: usize,
    png: &std::path::Path,
) -> anyhow::Result<()> {
    let cam = framing_camera(kp3d, HeadDir::NegY, facing(bones), res, res)?;
    let rgb = render_preview(mesh, &cam, [1.0; 3])?;
    let px: Vec<u8> = rgb.iter().map(|v| (v * 255.0).round() as u8).collect();
    let img = RgbImage::from_raw(cam.width as u32, cam.height as u32, px).expect("H·W·3 values");
    write_png(&img, png)
}
