//! `pma convert motion`: real motion (AIST++/SMPL npz or CMU BVH) → a motion-profile npz.

use std::path::PathBuf;

use clap::ValueEnum;
use pma_convert::dataset::Layout;
use pma_convert::motion::{convert_motion, read_rest_pose, MotionOptions, DEFAULT_NPZ_FPS};
use pma_data::fsio::PathCheck;

#[derive(clap::Args)]
pub struct Args {
    /// SMPL npz (`poses (T,72)` + `trans (T,3)`) or CMU `.bvh`.
    input: PathBuf,
    /// Output `.npz` (`bones`, `root_locs`, `kp3d`, `skts`, `cyls`, `rest_pose`).
    #[arg(short, long)]
    output: PathBuf,
    /// Resample to this frame rate.
    #[arg(long)]
    fps: Option<f64>,
    /// Keep source frames a..b (end exclusive), before resampling: `a:b`, `a:` or `:b`.
    #[arg(long, value_parser = parse_range)]
    frames: Option<RangeArg>,
    /// Up-axis convention of the dataset the motion will drive.
    #[arg(long, value_enum, default_value_t = TargetArg::H36mZju)]
    target: TargetArg,
    /// Rest pose for kinematics: a pma checkpoint (.safetensors) or dataset (.npz).
    /// Default: the synthetic scene's SMPL rest pose.
    #[arg(long)]
    rest_pose: Option<PathBuf>,
    /// Frame rate of an SMPL npz that stores none.
    #[arg(long, default_value_t = DEFAULT_NPZ_FPS)]
    npz_fps: f64,
}

#[derive(Clone, Copy, ValueEnum)]
enum TargetArg {
    H36mZju,
    Aist,
}

#[derive(Clone, Debug)]
struct RangeArg {
    start: usize,
    end: Option<usize>,
}

fn parse_range(s: &str) -> Result<RangeArg, String> {
    let (a, b) = s
        .split_once(':')
        .ok_or_else(|| format!("expected a:b, found {s:?}"))?;
    let num = |x: &str, what: &str| -> Result<Option<usize>, String> {
        if x.is_empty() {
            Ok(None)
        } else {
            x.parse()
                .map(Some)
                .map_err(|_| format!("{what} of {s:?} is not a frame number"))
        }
    };
    let start = num(a, "start")?.unwrap_or(0);
    let end = num(b, "end")?;
    if end.is_some_and(|e| e <= start) {
        return Err(format!("empty frame range {s:?}"));
    }
    Ok(RangeArg { start, end })
}

/// The highest `--fps`/`--npz-fps` accepted: motion capture runs at 30-120 fps.
const MAX_FPS: f64 = 1000.0;

pub fn run(args: Args) -> anyhow::Result<()> {
    for (flag, v) in [("--fps", args.fps), ("--npz-fps", Some(args.npz_fps))] {
        if let Some(v) = v {
            if !(v.is_finite() && v > 0.0 && v <= MAX_FPS) {
                crate::cli::refuse!("{flag} {v}: expected a frame rate in (0, {MAX_FPS}]");
            }
        }
    }
    crate::cli::check_paths(
        PathCheck::new()
            .input("motion", &args.input)
            .input_opt("--rest-pose", args.rest_pose.as_deref())
            .output("--output", &args.output),
    )?;
    let opts = MotionOptions {
        frames: args.frames.map(|r| r.start..r.end.unwrap_or(usize::MAX)),
        fps: args.fps,
        target: match args.target {
            TargetArg::H36mZju => Layout::H36mZju,
            TargetArg::Aist => Layout::Aist,
        },
        rest_pose: args.rest_pose.as_deref().map(read_rest_pose).transpose()?,
        npz_fps: args.npz_fps,
        ..Default::default()
    };
    let rep = convert_motion(&args.input, &args.output, &opts)?;
    println!(
        "{}: {} frames at {} fps (from {} at {} fps), head {:?} (source {:?})",
        args.output.display(),
        rep.frames,
        rep.fps,
        rep.source_frames,
        rep.source_fps,
        rep.up,
        rep.source_up
    );
    Ok(())
}
