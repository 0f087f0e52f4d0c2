//! `pma convert capture`: a raw ZJU-MoCap capture folder → pma-npz v1.

use std::path::PathBuf;

use clap::ValueEnum;
use pma_convert::capture::{convert_capture, CaptureOptions, Split};
use pma_data::dataset::Compression;
use pma_data::fsio::PathCheck;

#[derive(clap::Args)]
pub struct Args {
    /// The capture folder (holds annots.npy; H36M-ZJU: `S9/Posing`).
    dir: PathBuf,
    /// The SMPL model (`SMPL_NEUTRAL.pkl` as distributed, or an .npz conversion).
    #[arg(long)]
    smpl: PathBuf,
    /// Output `.npz`.
    #[arg(short, long)]
    output: PathBuf,
    /// Which images: training views and frames; the other views (novel_view);
    /// the other views on the frames after the training ones (novel_pose).
    #[arg(long, value_enum, default_value_t = SplitArg::Train)]
    split: SplitArg,
    /// Training camera indices.
    #[arg(long, value_delimiter = ',', default_value = "0,1,2")]
    train_views: Vec<usize>,
    /// Training frames START:COUNT:INTERVAL (COUNT empty: to the end). novel_pose needs COUNT.
    #[arg(long, default_value = "0::5")]
    frames: pma_convert::capture::Frames,
    /// Number of novel-pose frames (default: all after the training ones).
    #[arg(long)]
    eval_frames: Option<usize>,
    /// Resize factor in (0, 1]: images area-averaged, masks nearest, intrinsics scaled.
    #[arg(long)]
    res: Option<f64>,
    /// Parameter folder inside DIR (default: new_params if present, else params).
    #[arg(long)]
    params: Option<String>,
    /// Do not mark the mask boundary band (value 100) in the sampling masks.
    #[arg(long)]
    no_border: bool,
    /// Deflate the members.
    #[arg(long)]
    compress: bool,
}

#[derive(Clone, Copy, ValueEnum)]
enum SplitArg {
    Train,
    #[value(name = "novel_view")]
    NovelView,
    #[value(name = "novel_pose")]
    NovelPose,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    crate::cli::check_paths(
        PathCheck::new()
            .input_dir("capture", &args.dir)
            .input("--smpl", &args.smpl)
            .output("--output", &args.output),
    )?;
    let mut opts = CaptureOptions::new(args.smpl);
    opts.split = match args.split {
        SplitArg::Train => Split::Train,
        SplitArg::NovelView => Split::NovelView,
        SplitArg::NovelPose => Split::NovelPose,
    };
    opts.train_views = args.train_views;
    opts.frames = args.frames;
    opts.eval_frames = args.eval_frames;
    opts.res = args.res;
    opts.params_dir = args.params;
    opts.erode_border = !args.no_border;
    if args.compress {
        opts.compression = Compression::Deflated;
    }
    let rep = super::with_bar("capture images", |progress| {
        convert_capture(&args.dir, &args.output, &opts, progress)
    })?;
    println!(
        "{}: {} split, views {:?}, {} poses ({}/), {} cameras, {} images of {}x{}",
        args.output.display(),
        opts.split.name(),
        rep.views,
        rep.n_poses,
        rep.params_dir,
        rep.n_cameras,
        rep.n_images,
        rep.width,
        rep.height
    );
    Ok(())
}
