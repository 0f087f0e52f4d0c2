//! `pma convert`: reference checkpoints, A-NeRF/DANBO datasets and real motion
//! into pma formats. Parsing and reporting only; the work is in `pma-convert`.
//!
//! Exit status: 0 on success; 2 when an input is refused (one line on stderr
//! naming the file, the key or byte offset, and what was expected vs found),
//! and no output file is created; 1 when the output cannot be written.

use std::{ops::Range, path::PathBuf};

use clap::{Subcommand, ValueEnum};
use pma_convert::{
    capture::{convert_capture, CaptureOptions, Split},
    checkpoint::{convert_checkpoint, CheckpointOptions},
    dataset::{convert_dataset, DatasetOptions, Layout},
    motion::{convert_motion, read_rest_pose, MotionOptions, DEFAULT_NPZ_FPS},
    ConvertError,
};
use pma_data::dataset::{Compression, Profile};

#[derive(clap::Args)]
#[command(
    after_help = "Exit status: 0 on success; 2 when an input is refused (one line on stderr names the file, the key or byte offset, and what was expected vs found; no output is written); 1 when the output cannot be written."
)]
pub struct Args {
    #[command(subcommand)]
    what: What,
}

#[derive(Subcommand)]
enum What {
    /// A reference `torch.save` checkpoint (.th) → pma checkpoint (.safetensors).
    ///
    /// Tensors are copied byte for byte; the config is inferred from their
    /// shapes and checked. The pickle is interpreted without running code:
    /// anything but tensors and plain containers is refused.
    Checkpoint {
        /// The reference checkpoint (`{'model', 'optimizer', 'global_iter'}`).
        input: PathBuf,
        /// Output pma checkpoint.
        #[arg(short, long)]
        output: PathBuf,
        /// Also write the Adam state as a training state (`<OUT stem>.optim.safetensors`),
        /// so training can resume from the reference checkpoint.
        #[arg(long)]
        with_optimizer: bool,
    },
    /// A processed .h5 (h36m_zju, perfcap, surreal, mixamo, aist) or a pma-npz → validated pma-npz v1.
    Dataset {
        /// Input `.h5`/`.hdf5` or `.npz`.
        input: PathBuf,
        /// Output `.npz`.
        #[arg(short, long)]
        output: PathBuf,
        /// What the output must support; also what it keeps (motion: poses;
        /// render: + cameras and backgrounds; eval/train: + images and masks).
        #[arg(long, value_enum, default_value_t = ProfileArg::Train)]
        profile: ProfileArg,
        /// The .h5 layout (detected from the keys when omitted).
        #[arg(long, value_enum)]
        layout: Option<LayoutArg>,
        /// Deflate the members (smaller, but no memory-mapped pixel access).
        #[arg(long)]
        compress: bool,
        /// Accept a rest pose whose root is not at the origin.
        #[arg(long)]
        allow_offset_root: bool,
        /// Accept 0/255 masks and store them as {0,1}.
        #[arg(long)]
        binarize_masks: bool,
        /// Accept RGBA images and drop alpha.
        #[arg(long)]
        drop_alpha: bool,
    },
    /// A raw ZJU-MoCap capture folder (annots.npy, images, masks, params) → pma-npz v1.
    ///
    /// Follows the reference H36M-ZJU preprocessing: SMPL joints from the
    /// user's model, ground plane to x-z, images and masks undistorted,
    /// per-camera median backgrounds. Pickled `.npy`/`.pkl` files are read
    /// without running code.
    Capture {
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
    },
    /// Real motion (AIST++/SMPL npz or CMU BVH) → a motion-profile npz for retargeting.
    Motion {
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
    },
}

#[derive(Clone, Copy, ValueEnum)]
enum ProfileArg {
    Train,
    Eval,
    Render,
    Motion,
}

#[derive(Clone, Copy, ValueEnum)]
enum LayoutArg {
    H36mZju,
    Perfcap,
    Surreal,
    Mixamo,
    Aist,
}

#[derive(Clone, Copy, ValueEnum)]
enum SplitArg {
    Train,
    #[value(name = "novel_view")]
    NovelView,
    #[value(name = "novel_pose")]
    NovelPose,
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

fn profile(p: ProfileArg) -> Profile {
    match p {
        ProfileArg::Train => Profile::Train,
        ProfileArg::Eval => Profile::Eval,
        ProfileArg::Render => Profile::Render,
        ProfileArg::Motion => Profile::Motion,
    }
}

fn layout(l: LayoutArg) -> Layout {
    match l {
        LayoutArg::H36mZju => Layout::H36mZju,
        LayoutArg::Perfcap => Layout::PerfCap,
        LayoutArg::Surreal => Layout::Surreal,
        LayoutArg::Mixamo => Layout::Mixamo,
        LayoutArg::Aist => Layout::Aist,
    }
}

/// Checks the paths (inputs exist and are regular files, the output is not an input and
/// can be created) and the flags, then converts. Every error says itself what it is (see
/// `pma_convert::ConvertError`'s `ExitKind`): refused input exits 2, a failure to write the
/// output 1, an interruption 130; the message is one line naming the file.
pub fn run(args: Args) -> anyhow::Result<()> {
    args.what.check()?;
    Ok(convert(args)?)
}

/// The highest `--fps`/`--npz-fps` accepted: motion capture runs at 30-120 fps.
const MAX_FPS: f64 = 1000.0;

impl What {
    /// Paths and flags, before any work.
    fn check(&self) -> anyhow::Result<()> {
        use pma_data::fsio::PathCheck;
        let paths = match self {
            What::Checkpoint {
                input,
                output,
                with_optimizer,
            } => {
                let side = pma_convert::train_state::sidecar_path(output);
                PathCheck::new()
                    .input("checkpoint", input)
                    .output("--output", output)
                    .output_opt("--with-optimizer", with_optimizer.then_some(side.as_path()))
            }
            What::Dataset { input, output, .. } => PathCheck::new()
                .input("dataset", input)
                .output("--output", output),
            What::Capture {
                dir, smpl, output, ..
            } => PathCheck::new()
                .input_dir("capture", dir)
                .input("--smpl", smpl)
                .output("--output", output),
            What::Motion {
                input,
                output,
                rest_pose,
                fps,
                npz_fps,
                ..
            } => {
                for (flag, v) in [("--fps", *fps), ("--npz-fps", Some(*npz_fps))] {
                    if let Some(v) = v {
                        if !(v.is_finite() && v > 0.0 && v <= MAX_FPS) {
                            super::refuse!("{flag} {v}: expected a frame rate in (0, {MAX_FPS}]");
                        }
                    }
                }
                PathCheck::new()
                    .input("motion", input)
                    .input_opt("--rest-pose", rest_pose.as_deref())
                    .output("--output", output)
            }
        };
        super::check_paths(paths)
    }
}

fn convert(args: Args) -> Result<(), ConvertError> {
    match args.what {
        What::Checkpoint {
            input,
            output,
            with_optimizer,
        } => {
            let rep = convert_checkpoint(&input, &output, &CheckpointOptions { with_optimizer })?;
            println!(
                "{}: {} tensors, {} parameters, n_framecodes {}, global_iter {}",
                output.display(),
                rep.n_tensors,
                rep.n_parameters,
                rep.config.n_framecodes,
                rep.global_iter.map_or("-".into(), |g| g.to_string())
            );
            if let Some(side) = rep.train_state {
                println!(
                    "{}: Adam state ({} parameters had moments in the source; the others start from zero)",
                    side.display(),
                    rep.n_moments
                );
            }
        }
        What::Dataset {
            input,
            output,
            profile: p,
            layout: l,
            compress,
            allow_offset_root,
            binarize_masks,
            drop_alpha,
        } => {
            let mut opts = DatasetOptions::new(profile(p));
            opts.layout = l.map(layout);
            opts.compression = if compress {
                Compression::Deflated
            } else {
                Compression::Stored
            };
            opts.allow_offset_root = allow_offset_root;
            opts.binarize_masks = binarize_masks;
            opts.drop_alpha = drop_alpha;
            let bar = super::progress::bar(false, 0, "pixels of images");
            let rep = convert_dataset(&input, &output, &opts, &mut |done, total| {
                bar.set_length(total);
                bar.set_position(done);
            });
            bar.finish_and_clear();
            let rep = rep?;
            for w in &rep.warnings {
                eprintln!("warning: {w}");
            }
            println!(
                "{}: {}{} poses, {} cameras, {} images",
                output.display(),
                rep.layout
                    .map_or(String::new(), |l| format!("{l} layout, ")),
                rep.n_poses,
                rep.n_cameras,
                rep.n_images
            );
            for d in &rep.derived {
                println!("  derived: {d}");
            }
        }
        What::Capture {
            dir,
            smpl,
            output,
            split,
            train_views,
            frames,
            eval_frames,
            res,
            params,
            no_border,
            compress,
        } => {
            let mut opts = CaptureOptions::new(smpl);
            opts.split = match split {
                SplitArg::Train => Split::Train,
                SplitArg::NovelView => Split::NovelView,
                SplitArg::NovelPose => Split::NovelPose,
            };
            opts.train_views = train_views;
            opts.frames = frames;
            opts.eval_frames = eval_frames;
            opts.res = res;
            opts.params_dir = params;
            opts.erode_border = !no_border;
            if compress {
                opts.compression = Compression::Deflated;
            }
            let bar = super::progress::bar(false, 0, "capture images");
            let rep = convert_capture(&dir, &output, &opts, &mut |done, total| {
                bar.set_length(total);
                bar.set_position(done);
            });
            bar.finish_and_clear();
            let rep = rep?;
            println!(
                "{}: {} split, views {:?}, {} poses ({}/), {} cameras, {} images of {}x{}",
                output.display(),
                opts.split.name(),
                rep.views,
                rep.n_poses,
                rep.params_dir,
                rep.n_cameras,
                rep.n_images,
                rep.width,
                rep.height
            );
        }
        What::Motion {
            input,
            output,
            fps,
            frames,
            target,
            rest_pose,
            npz_fps,
        } => {
            let rest = rest_pose.as_deref().map(read_rest_pose).transpose()?;
            let frames: Option<Range<usize>> = frames.map(|r| r.start..r.end.unwrap_or(usize::MAX));
            let opts = MotionOptions {
                frames,
                fps,
                target: match target {
                    TargetArg::H36mZju => Layout::H36mZju,
                    TargetArg::Aist => Layout::Aist,
                },
                rest_pose: rest,
                npz_fps,
                ..Default::default()
            };
            let rep = convert_motion(&input, &output, &opts)?;
            println!(
                "{}: {} frames at {} fps (from {} at {} fps), head {:?} (source {:?})",
                output.display(),
                rep.frames,
                rep.fps,
                rep.source_frames,
                rep.source_fps,
                rep.up,
                rep.source_up
            );
        }
    }
    Ok(())
}
