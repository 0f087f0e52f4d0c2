//! `pma-infer MODEL OUT.png [SIZE] [--device D] [--occupancy] [--early-stop EPS]
//! [--cull-joints]`: the smallest program that uses a trained avatar.
//!
//! Loads a pma checkpoint and renders the avatar's rest pose, standing upright (head −y),
//! from the front at SIZE×SIZE pixels (default 256) on a black background, with normalised
//! view directions (as `pma render`). `--occupancy` skips the samples in the empty cells of
//! the model's occupancy grid (the model must have one); `--early-stop EPS` leaves out the
//! samples behind the depth where a ray's transmittance falls below EPS; `--cull-joints`
//! carries each network call's samples through the per-joint work of the joints whose
//! window is non-zero at them only (exact up to float summation order). It links
//! `pma-model` without its `train` feature and parses its arguments by hand, so it pulls in
//! no optimiser, loss, CLI or progress-bar code.
//!
//! Exit status, as `pma`'s: 0 success, 2 refused input (usage, a bad flag or size, a model
//! that cannot be read, an output path that cannot be written), 1 any other failure.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use candle_core::Device;
use pma_data::cylinder::HeadDir;
use pma_data::fsio::{parent_dir, AtomicFile};
use pma_model::render::camera_path::{facing, framing_camera, load_avatar, ViewDirs};
use pma_model::render::image::ImageOptions;
use pma_model::render::PassOptions;

const USAGE: &str = "usage: pma-infer MODEL.safetensors OUT.png [SIZE] \
                     [--device cpu|cuda|cuda:N|metal] [--occupancy] [--early-stop EPS] \
                     [--cull-joints]";

/// An error with the exit status it gets.
#[derive(Debug)]
enum Failed {
    /// The input or the command line is wrong: exit 2.
    Refused(String),
    /// Anything else: exit 1.
    Failure(String),
}

impl Failed {
    fn code(&self) -> u8 {
        match self {
            Failed::Refused(_) => 2,
            Failed::Failure(_) => 1,
        }
    }
}

impl std::fmt::Display for Failed {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Failed::Refused(m) | Failed::Failure(m) => f.write_str(m),
        }
    }
}

impl From<String> for Failed {
    fn from(m: String) -> Self {
        Failed::Refused(m)
    }
}

impl From<&str> for Failed {
    fn from(m: &str) -> Self {
        Failed::Refused(m.to_string())
    }
}

impl Failed {
    /// A library error, by the kind it says it is.
    fn of<E: pma_data::ExitKind + std::fmt::Display>(e: E) -> Self {
        match e.kind() {
            pma_data::ErrorKind::Refused => Failed::Refused(e.to_string()),
            _ => Failed::Failure(e.to_string()),
        }
    }
}

impl From<pma_model::error::ModelError> for Failed {
    fn from(e: pma_model::error::ModelError) -> Self {
        Failed::of(e)
    }
}

impl From<pma_model::compute::device::DeviceError> for Failed {
    fn from(e: pma_model::compute::device::DeviceError) -> Self {
        Failed::of(e)
    }
}

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> ExitCode {
    // Data-parallel CPU workers, one per core, set up before any candle op.
    pma_model::compute::parallel::configure_cpu(0);
    match parse(std::env::args().skip(1).collect()).and_then(|a| run(&a)) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("pma-infer: {e}");
            ExitCode::from(e.code())
        }
    }
}

struct Args {
    model: PathBuf,
    out: PathBuf,
    size: usize,
    /// `--device` as given (default cpu); opened in `run` so parsing stays side-effect free.
    device: String,
    /// `--occupancy`: skip the samples in empty cells of the model's grid.
    occupancy: bool,
    /// `--early-stop EPS`: the transmittance below which a ray's later samples are skipped.
    early_stop: Option<f64>,
    /// `--cull-joints`: network calls carry only the joints their samples need.
    cull_joints: bool,
}

fn parse(mut args: Vec<String>) -> Result<Args, Failed> {
    // Flags may stand anywhere; take them out before the positionals.
    let device = take_value(&mut args, "--device")?.unwrap_or_else(|| "cpu".to_string());
    let early_stop =
        match take_value(&mut args, "--early-stop")? {
            Some(v) => Some(v.parse::<f64>().map_err(|_| {
                format!("--early-stop needs a transmittance in (0, 1), found {v:?}")
            })?),
            None => None,
        };
    let occupancy = take_switch(&mut args, "--occupancy");
    let cull_joints = take_switch(&mut args, "--cull-joints");
    let mut a = parse_positional(&args)?;
    a.device = device;
    a.occupancy = occupancy;
    a.early_stop = early_stop;
    a.cull_joints = cull_joints;
    Ok(a)
}

/// Take the switch `name` out of `args`; whether it was there.
fn take_switch(args: &mut Vec<String>, name: &str) -> bool {
    match args.iter().position(|a| a == name) {
        Some(i) => {
            args.remove(i);
            true
        }
        None => false,
    }
}

/// Take `NAME VALUE` or `NAME=VALUE` out of `args`.
fn take_value(args: &mut Vec<String>, name: &str) -> Result<Option<String>, Failed> {
    let with_eq = format!("{name}=");
    let Some(i) = args
        .iter()
        .position(|a| a == name || a.starts_with(&with_eq))
    else {
        return Ok(None);
    };
    let flag = args.remove(i);
    match flag.strip_prefix(&with_eq) {
        Some(v) => Ok(Some(v.to_string())),
        None if i < args.len() => Ok(Some(args.remove(i))),
        None => Err(format!("{name} needs a value; {USAGE}").into()),
    }
}

fn parse_positional(args: &[String]) -> Result<Args, Failed> {
    let help = matches!(args, [h] if h == "-h" || h == "--help");
    if let Some(flag) = args.iter().find(|a| a.starts_with("--") && !help) {
        return Err(format!("unknown flag {flag:?}; {USAGE}").into());
    }
    match args {
        [h] if h == "-h" || h == "--help" => {
            println!("{USAGE}");
            std::process::exit(0);
        }
        [model, out] => Ok(Args {
            model: model.into(),
            out: out.into(),
            size: 256,
            device: String::new(),
            occupancy: false,
            early_stop: None,
            cull_joints: false,
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
                device: String::new(),
                occupancy: false,
                early_stop: None,
                cull_joints: false,
            })
        }
        _ => Err(USAGE.into()),
    }
}

fn run(args: &Args) -> Result<(), Failed> {
    let t0 = Instant::now();
    let device: Device = pma_model::compute::device::parse_device(&args.device)?;
    let avatar =
        load_avatar(&args.model, &device, ViewDirs::Normalized).map_err(
            |e| match Failed::from(e) {
                Failed::Refused(m) => {
                    Failed::Refused(format!("loading {}: {m}", args.model.display()))
                }
                Failed::Failure(m) => {
                    Failed::Failure(format!("loading {}: {m}", args.model.display()))
                }
            },
        )?;
    let t_load = t0.elapsed();
    // SMPL's rest pose is y-up; a half turn about x stands it up in the training convention.
    let mut bones = [[0f32; 3]; 24];
    bones[0] = [std::f32::consts::PI, 0.0, 0.0];
    let (poses, kp3d) = avatar.pose_from_bones(&bones, [0.0; 3])?;
    let cam = framing_camera(&kp3d, HeadDir::NegY, facing(&bones), args.size, args.size)?;
    let t1 = Instant::now();
    // Ray tensors must live on the model's device.
    let opts = ImageOptions {
        device: device.clone(),
        pass: PassOptions {
            occupancy: args.occupancy,
            early_stop: args.early_stop,
            cull_joints: args.cull_joints,
            ..PassOptions::default()
        },
        ..ImageOptions::default()
    };
    let img = avatar.render_image(&poses, &kp3d, &cam, None, &opts)?;
    let t_render = t1.elapsed();
    let px: Vec<u8> = img
        .rgb
        .iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    let rgb = image::RgbImage::from_raw(img.width as u32, img.height as u32, px)
        .ok_or_else(|| Failed::Failure("rendered image has the wrong size".into()))?;
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

/// Encode, then replace `path` atomically.
/// A directory that cannot take the file is refused input; failing to write it is a failure.
fn write_png(img: &image::RgbImage, path: &Path) -> Result<(), Failed> {
    let named = |e: &dyn std::fmt::Display| Failed::Failure(format!("{}: {e}", path.display()));
    let tmp = AtomicFile::create(path)
        .map_err(|e| Failed::Refused(format!("{}: {e}", parent_dir(path).display())))?;
    img.write_to(
        &mut std::io::BufWriter::new(tmp.writer()),
        image::ImageFormat::Png,
    )
    .map_err(|e| named(&e))?;
    tmp.commit().map_err(|e| named(&e))?;
    Ok(())
}
