//! `pma-infer MODEL OUT.png [SIZE]`: the smallest program that uses a trained avatar.
//!
//! Loads a pma checkpoint and renders the avatar's rest pose, standing upright (head −y),
//! from the front at SIZE×SIZE pixels (default 256) on a black background, with normalised
//! view directions (as `pma render`). It links `pma-model` without its `train` feature and
//! parses its arguments by hand, so it pulls in no optimiser, loss, CLI or progress-bar code.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use candle_core::Device;
use pma_data::cylinder::HeadDir;
use pma_model::camera_path::{facing, framing_camera, load_avatar, ViewDirs};
use pma_model::image::ImageOptions;

const USAGE: &str = "usage: pma-infer MODEL.safetensors OUT.png [SIZE]";

type BoxError = Box<dyn std::error::Error>;

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> ExitCode {
    match parse(std::env::args().skip(1).collect()).and_then(|a| run(&a)) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("pma-infer: {e}");
            ExitCode::FAILURE
        }
    }
}

struct Args {
    model: PathBuf,
    out: PathBuf,
    size: usize,
}

fn parse(args: Vec<String>) -> Result<Args, BoxError> {
    match args.as_slice() {
        [h] if h == "-h" || h == "--help" => {
            println!("{USAGE}");
            std::process::exit(0);
        }
        [model, out] => Ok(Args {
            model: model.into(),
            out: out.into(),
            size: 256,
        }),
        [model, out, size] => {
            let size: usize = size
                .parse()
                .ok()
                .filter(|s| (8..=4096).contains(s))
                .ok_or_else(|| format!("SIZE must be an integer in 8..=4096, found {size:?}"))?;
            Ok(Args {
                model: model.into(),
                out: out.into(),
                size,
            })
        }
        _ => Err(USAGE.into()),
    }
}

fn run(args: &Args) -> Result<(), BoxError> {
    let t0 = Instant::now();
    let device = Device::Cpu;
    let avatar = load_avatar(&args.model, &device, ViewDirs::Normalized)
        .map_err(|e| format!("loading {}: {e}", args.model.display()))?;
    let t_load = t0.elapsed();
    // SMPL's rest pose is y-up; a half turn about x stands it up in the training convention.
    let mut bones = [[0f32; 3]; 24];
    bones[0] = [std::f32::consts::PI, 0.0, 0.0];
    let (poses, kp3d) = avatar.pose_from_bones(&bones, [0.0; 3])?;
    let cam = framing_camera(&kp3d, HeadDir::NegY, facing(&bones), args.size, args.size)?;
    let t1 = Instant::now();
    let img = avatar.render_image(&poses, &kp3d, &cam, None, &ImageOptions::default())?;
    let t_render = t1.elapsed();
    let px: Vec<u8> = img
        .rgb
        .iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    let rgb = image::RgbImage::from_raw(img.width as u32, img.height as u32, px)
        .ok_or("rendered image has the wrong size")?;
    write_png(&rgb, &args.out)?;
    println!(
        "wrote {} ({}x{}): load {:.3} s, render {:.3} s",
        args.out.display(),
        img.width,
        img.height,
        t_load.as_secs_f64(),
        t_render.as_secs_f64()
    );
    Ok(())
}

/// Encode, then replace `path` atomically (temporary file + rename).
fn write_png(img: &image::RgbImage, path: &Path) -> Result<(), BoxError> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let mut tmp =
        tempfile::NamedTempFile::new_in(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    img.write_to(
        &mut std::io::BufWriter::new(tmp.as_file_mut()),
        image::ImageFormat::Png,
    )
    .map_err(|e| format!("{}: {e}", path.display()))?;
    tmp.as_file()
        .sync_all()
        .map_err(|e| format!("{}: {e}", path.display()))?;
    tmp.persist(path)
        .map_err(|e| format!("{}: {}", path.display(), e.error))?;
    Ok(())
}
