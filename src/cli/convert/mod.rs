//! `pma convert`: reference checkpoints, A-NeRF/DANBO datasets and real motion
//! into pma formats. Parsing and reporting only; the work is in `pma-convert`.
//! One file per subcommand: its flags, their checks, the call and its report.
//!
//! Exit status: 0 on success; 2 when an input is refused (one line on stderr
//! naming the file, the key or byte offset, and what was expected vs found),
//! and no output file is created; 1 when the output cannot be written.

use clap::Subcommand;

mod capture;
mod checkpoint;
mod dataset;
mod motion;

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
    Checkpoint(checkpoint::Args),
    /// A processed .h5 (h36m_zju, perfcap, surreal, mixamo, aist) or a pma-npz → validated pma-npz v1.
    Dataset(dataset::Args),
    /// A raw ZJU-MoCap capture folder (annots.npy, images, masks, params) → pma-npz v1.
    ///
    /// Follows the reference H36M-ZJU preprocessing: SMPL joints from the
    /// user's model, ground plane to x-z, images and masks undistorted,
    /// per-camera median backgrounds. Pickled `.npy`/`.pkl` files are read
    /// without running code.
    Capture(capture::Args),
    /// Real motion (AIST++/SMPL npz or CMU BVH) → a motion-profile npz for retargeting.
    Motion(motion::Args),
}

/// Each subcommand checks its paths (inputs exist and are regular files, the output is not
/// an input and can be created) and flags, then converts. Every error says itself what it
/// is (see `pma_convert::ConvertError`'s `ExitKind`): refused input exits 2, a failure to
/// write the output 1, an interruption 130; the message is one line naming the file.
pub fn run(args: Args) -> anyhow::Result<()> {
    match args.what {
        What::Checkpoint(a) => checkpoint::run(a),
        What::Dataset(a) => dataset::run(a),
        What::Capture(a) => capture::run(a),
        What::Motion(a) => motion::run(a),
    }
}

/// `convert` with a progress bar labelled `label` that its progress callback
/// (`done, total`) moves; the bar is gone when it returns.
fn with_bar<T>(label: &str, convert: impl FnOnce(&mut dyn FnMut(u64, u64)) -> T) -> T {
    let bar = super::progress::bar(false, 0, label);
    let out = convert(&mut |done, total| {
        bar.set_length(total);
        bar.set_position(done);
    });
    bar.finish_and_clear();
    out
}
