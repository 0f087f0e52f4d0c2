//! `pma convert dataset`: a processed .h5 or a pma-npz → validated pma-npz v1.

use std::path::PathBuf;

use clap::ValueEnum;
use pma_convert::dataset::{convert_dataset, DatasetOptions, Layout};
use pma_data::dataset::{Compression, Profile};
use pma_data::fsio::PathCheck;

#[derive(clap::Args)]
pub struct Args {
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

pub fn run(args: Args) -> anyhow::Result<()> {
    crate::cli::check_paths(
        PathCheck::new()
            .input("dataset", &args.input)
            .output("--output", &args.output),
    )?;
    let mut opts = DatasetOptions::new(match args.profile {
        ProfileArg::Train => Profile::Train,
        ProfileArg::Eval => Profile::Eval,
        ProfileArg::Render => Profile::Render,
        ProfileArg::Motion => Profile::Motion,
    });
    opts.layout = args.layout.map(|l| match l {
        LayoutArg::H36mZju => Layout::H36mZju,
        LayoutArg::Perfcap => Layout::PerfCap,
        LayoutArg::Surreal => Layout::Surreal,
        LayoutArg::Mixamo => Layout::Mixamo,
        LayoutArg::Aist => Layout::Aist,
    });
    opts.compression = if args.compress {
        Compression::Deflated
    } else {
        Compression::Stored
    };
    opts.allow_offset_root = args.allow_offset_root;
    opts.binarize_masks = args.binarize_masks;
    opts.drop_alpha = args.drop_alpha;
    let rep = super::with_bar("pixels of images", |progress| {
        convert_dataset(&args.input, &args.output, &opts, progress)
    })?;
    for w in &rep.warnings {
        eprintln!("warning: {w}");
    }
    println!(
        "{}: {}{} poses, {} cameras, {} images",
        args.output.display(),
        rep.layout
            .map_or(String::new(), |l| format!("{l} layout, ")),
        rep.n_poses,
        rep.n_cameras,
        rep.n_images
    );
    for d in &rep.derived {
        println!("  derived: {d}");
    }
    Ok(())
}
