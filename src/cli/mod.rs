//! One module per subcommand: clap `Args` plus `run`. The pipelines live in the libraries;
//! these modules parse, call and print. The commands that train (`train`, `demo`, `ablate`,
//! `bench`) exist only in a build with the `train` feature (on by default).

#[cfg(feature = "train")]
pub mod ablate;
#[cfg(feature = "train")]
pub mod bench;
pub mod check_stability;
pub mod convert;
#[cfg(feature = "train")]
pub mod demo;
#[cfg(feature = "train")]
pub mod doctor;
pub mod eval;
pub mod forward;
pub mod inspect;
pub mod mesh;
pub mod metrics;
pub mod occupancy;
pub mod plot;
pub mod progress;
pub mod render;
pub mod synth;
#[cfg(feature = "train")]
pub mod train;
pub mod view;

use std::path::Path;

use anyhow::Context as _;
use pma_data::dataset::{Dataset, Profile};
use pma_data::{ErrorKind, ExitKind};
use pma_model::compute::numerics::Numerics;
use pma_model::render::camera_path::ViewDirs;

/// Exit status of a command refused because of its input (a split the file does not hold,
/// a corrupt file, an out-of-range flag, an output that would replace an input), as for
/// clap's usage errors: the user has to change the command or its input.
pub const EXIT_REFUSED: u8 = 2;
/// Exit status of a command stopped by Ctrl-C (128 + SIGINT, as a shell reports it);
/// SIGTERM and SIGHUP give 143 and 129.
pub const EXIT_INTERRUPTED: u8 = 130;
/// Exit status of every other failure.
pub const EXIT_FAILURE: u8 = 1;

/// An error the user has to fix in the command or its input (see [`EXIT_REFUSED`]).
#[derive(Debug)]
pub struct Refused(Box<dyn std::error::Error + Send + Sync>);

impl Refused {
    pub fn new(e: impl Into<Box<dyn std::error::Error + Send + Sync>>) -> Self {
        Self(e.into())
    }
}

impl std::fmt::Display for Refused {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        self.0.fmt(f)
    }
}

impl std::error::Error for Refused {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        self.0.source()
    }
}

impl ExitKind for Refused {
    fn kind(&self) -> ErrorKind {
        ErrorKind::Refused
    }
}

/// Return a [`Refused`] error with a formatted message (a flag out of range, a file that
/// lacks what the command needs).
macro_rules! refuse {
    ($($arg:tt)*) => {
        return Err($crate::cli::Refused::new(format!($($arg)*)).into())
    };
}
pub(crate) use refuse;

/// What `e` is: [`ErrorKind::Interrupted`] once a stop was requested (whatever error it
/// caused), otherwise the kind of the outermost library error in its chain (each says
/// itself what it is, see [`pma_data::ExitKind`]; contexts added on the way up say
/// nothing), [`ErrorKind::Failure`] when none does.
pub fn error_kind(e: &anyhow::Error) -> ErrorKind {
    if pma_model::interrupt::requested() {
        return ErrorKind::Interrupted;
    }
    e.chain()
        .find_map(library_kind)
        .unwrap_or(ErrorKind::Failure)
}

/// The kind of `e` if it is one of the libraries' errors.
fn library_kind(e: &(dyn std::error::Error + 'static)) -> Option<ErrorKind> {
    macro_rules! kinds {
        ($($t:ty),* $(,)?) => {
            $(if let Some(x) = e.downcast_ref::<$t>() {
                return Some(x.kind());
            })*
        };
    }
    kinds!(
        Refused,
        pma_data::fsio::PathError,
        pma_data::DataError,
        pma_data::motion::MotionError,
        pma_data::synth::SynthError,
        pma_data::interrupt::Interrupted,
        pma_model::error::ModelError,
        pma_model::eval::EvalError,
        pma_model::render::batch_file::BatchFileError,
        pma_model::tools::video::VideoError,
        pma_model::compute::device::DeviceError,
        pma_model::compute::device::Tf32Error,
        pma_convert::ConvertError,
    );
    #[cfg(feature = "train")]
    kinds!(pma_model::train::TrainError, pma_model::bench::BenchError);
    None
}

/// The exit status for `e`, the one rule of every command: [`EXIT_REFUSED`] for refused
/// input, 128 + the signal for an interruption ([`EXIT_INTERRUPTED`] for Ctrl-C),
/// [`EXIT_FAILURE`] otherwise.
pub fn exit_code(e: &anyhow::Error) -> u8 {
    match error_kind(e) {
        ErrorKind::Refused => EXIT_REFUSED,
        ErrorKind::Failure => EXIT_FAILURE,
        ErrorKind::Interrupted => match pma_model::interrupt::signal() {
            s @ 1..=127 => 128 + s as u8,
            _ => EXIT_INTERRUPTED,
        },
    }
}

/// `e` and its causes on one line, each cause left out when the message already holds it
/// (many errors print their source themselves); any line break inside a message is joined.
pub fn report(e: &anyhow::Error) -> String {
    let mut out = String::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if out.contains(&text) {
            continue;
        }
        if !out.is_empty() {
            out.push_str(": ");
        }
        out.push_str(&text);
    }
    pma_data::error::one_line(&out)
}

/// How a stop request is named to the user.
fn signal_name(signal: i32) -> &'static str {
    match signal {
        1 => "SIGHUP",
        15 => "SIGTERM",
        _ => "Ctrl-C",
    }
}

/// The line for a command stopped by a signal: what the command says about where it
/// stopped, if anything, and that no file was left half-written.
pub fn interrupted_report(e: &anyhow::Error) -> String {
    let text = report(e);
    let said = text.trim_end_matches("interrupted").trim_end_matches(": ");
    let by = signal_name(pma_model::interrupt::signal());
    if said.is_empty()
        || !e
            .chain()
            .any(|c| c.is::<pma_data::interrupt::Interrupted>())
    {
        format!(
            "interrupted: stopped by {by}; files already complete are kept, none is half-written"
        )
    } else if said.contains("interrupted") {
        said.to_string()
    } else {
        format!("interrupted: {said}")
    }
}

/// Check every path of a command before any work (see [`pma_data::fsio::PathCheck`]).
pub fn check_paths(check: pma_data::fsio::PathCheck) -> anyhow::Result<()> {
    Ok(check.check()?)
}

/// The model a `--model` flag names: a model file, or a run directory's newest complete
/// model (`pma_model::network::run_dir::newest_model`).
pub fn model_path(path: &Path) -> anyhow::Result<std::path::PathBuf> {
    Ok(pma_model::network::run_dir::resolve_model(path)?)
}

/// The most CPU workers `--workers` accepts: 4 per core.
/// The view directions a `--reference-dirs` flag asks for: the reference's raw render-time
/// ones, or unit ones.
pub fn view_dirs(reference_dirs: bool) -> ViewDirs {
    if reference_dirs {
        ViewDirs::Reference
    } else {
        ViewDirs::Normalized
    }
}

/// The avatar at `path` on `device`, rendering with `dirs`, with the process's numerics.
pub fn load_model(
    path: &Path,
    device: &candle_core::Device,
    dirs: ViewDirs,
) -> anyhow::Result<pma_model::render::avatar::Avatar> {
    Ok(
        pma_model::render::camera_path::load_avatar(path, device, dirs)
            .with_context(|| format!("loading model {}", path.display()))?
            .with_numerics(numerics()),
    )
}

pub fn max_workers() -> usize {
    4 * std::thread::available_parallelism().map_or(1, |n| n.get())
}

/// Refuse `--workers` beyond [`max_workers`] (each worker is a thread with its own buffers).
pub fn check_workers(workers: usize) -> anyhow::Result<()> {
    let max = max_workers();
    if workers > max {
        refuse!(
            "--workers {workers}: at most {max} (4 per core of this machine; 0 = one per core)"
        );
    }
    Ok(())
}

#[cfg(feature = "train")]
/// Refuse a `--minutes` budget that is not finite and in (0, `MAX_MINUTES`].
pub fn check_minutes(flag: &str, minutes: Option<f64>) -> anyhow::Result<()> {
    const MAX: f64 = 1e6;
    if let Some(m) = minutes {
        if !(m.is_finite() && m > 0.0 && m <= MAX) {
            refuse!(
                "{flag} {}: expected a finite number of minutes in (0, {MAX}]",
                pma_data::error::short_number(m)
            );
        }
    }
    Ok(())
}

/// Open the compute device named by a `--device` flag: cpu, cuda, cuda:N, metal or metal:N.
/// A backend missing from this build is reported with the cargo feature that brings it.
pub fn device(spec: &str) -> anyhow::Result<candle_core::Device> {
    Ok(pma_model::compute::device::parse_device(spec)?)
}

/// [`device`], checking `--tf32` (CUDA only: refused elsewhere), which [`numerics`] then
/// carries to every avatar the command builds.
pub fn device_tf32(spec: &str, tf32: bool) -> anyhow::Result<candle_core::Device> {
    let dev = device(spec)?;
    pma_model::compute::device::check_tf32(tf32, &dev)?;
    NUMERICS.lock().unwrap_or_else(|e| e.into_inner()).tf32 = tf32;
    Ok(dev)
}

/// `--device` and `--tf32`, for the commands that compute on a device of the user's choice.
#[derive(clap::Args, Debug, Clone)]
pub struct DeviceArgs {
    /// Compute device: cpu, cuda, cuda:N, metal (cuda/metal need a binary built with that
    /// feature).
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// TF32 matrix products on CUDA: faster, changes results (see docs/numerics.md, "Low
    /// precision"); refused on other devices.
    #[arg(long)]
    pub tf32: bool,
}

impl DeviceArgs {
    /// The device, opened by [`device_tf32`].
    pub fn open(&self) -> anyhow::Result<candle_core::Device> {
        device_tf32(&self.device, self.tf32)
    }
}

/// The numeric choices of this command line (`--fast-sine`, `--tf32`): one command runs per
/// process, and every avatar and trainer it builds gets them.
static NUMERICS: std::sync::Mutex<Numerics> = std::sync::Mutex::new(Numerics::PARITY);

/// `--fast-sine`, `--deterministic` and `--bf16-trunk` (set once, before the command runs).
pub fn set_numerics(fast_sine: bool, deterministic: bool, bf16_trunk: bool) {
    let mut k = NUMERICS.lock().unwrap_or_else(|e| e.into_inner());
    k.fast_sine = fast_sine;
    k.deterministic = deterministic;
    k.bf16_trunk = bf16_trunk;
}

/// How this command's avatars compute.
pub fn numerics() -> Numerics {
    *NUMERICS.lock().unwrap_or_else(|e| e.into_inner())
}

/// Read a dataset for `profile`, printing its warnings.
pub fn read_dataset(path: &Path, profile: Profile) -> anyhow::Result<Dataset> {
    let data = pma_model::eval::read_dataset(path, profile)?;
    for w in &data.warnings {
        eprintln!("warning: {}: {w}", path.display());
    }
    Ok(data)
}

/// A motion (or any pma-npz) file's pose rows for `avatar`
/// (`pma_model::tools::retarget::read_motion`), printing the file's warnings.
pub fn read_motion(
    avatar: &pma_model::Avatar,
    path: &Path,
) -> anyhow::Result<pma_model::tools::retarget::MotionClip> {
    let (clip, ds) = pma_model::tools::retarget::read_motion(avatar, path)?;
    for w in &ds.warnings {
        eprintln!("warning: {}: {w}", path.display());
    }
    if clip.rest.is_none() {
        eprintln!(
            "note: {} has no rest_pose of its own: its root trajectory is kept as is",
            path.display()
        );
    }
    Ok(clip)
}

/// Serialise `value` as pretty JSON and replace `path` atomically.
pub fn write_json<T: serde::Serialize>(value: &T, path: &Path) -> anyhow::Result<()> {
    let mut text = serde_json::to_string_pretty(value)?;
    text.push('\n');
    pma_data::fsio::write_atomic(path, text.as_bytes())
        .with_context(|| format!("writing {}", path.display()))
}

/// Encode `img` as PNG and replace `path` atomically.
pub fn write_png(img: &image::RgbImage, path: &Path) -> anyhow::Result<()> {
    Ok(pma_model::eval::write_png(img, path)?)
}

/// Route SIGINT (Ctrl-C), SIGTERM and SIGHUP to the process-wide interrupt flag, recording
/// which signal came: long work stops at its next check and the command exits with 128 +
/// the signal (130, 143, 129), leaving only complete files (a training run first saves its
/// last complete step). A second signal exits at once, as a plain signal would; a run
/// directory stays resumable (its last complete checkpoint is kept).
///
/// `signal-hook` rather than `ctrlc`: the handler must know which signal arrived for the
/// exit status, and `ctrlc` (even with its `termination` feature) calls one handler for all
/// of them without saying which. The signals are read on a thread of their own, so the
/// reaction may print and exit safely.
#[cfg(unix)]
pub fn install_interrupt_handler() {
    use signal_hook::consts::{SIGHUP, SIGINT, SIGTERM};
    use std::io::Write as _;
    let mut signals = match signal_hook::iterator::Signals::new([SIGINT, SIGTERM, SIGHUP]) {
        Ok(s) => s,
        Err(e) => {
            let _ = writeln!(
                std::io::stderr(),
                "warning: cannot install the signal handler ({e}); Ctrl-C stops at once"
            );
            return;
        }
    };
    let spawned = std::thread::Builder::new()
        .name("signals".into())
        .spawn(move || {
            for (n, sig) in signals.forever().enumerate() {
                // stderr may be gone (SIGHUP): messages are best effort.
                let mut err = std::io::stderr();
                if n > 0 {
                    let _ = writeln!(err, "\n{}: exiting at once", signal_name(sig));
                    std::process::exit(128 + sig);
                }
                let _ = writeln!(
                    err,
                    "\n{}: stopping (press Ctrl-C again to exit at once)",
                    signal_name(sig)
                );
                pma_model::interrupt::request_by(sig);
            }
        });
    if let Err(e) = spawned {
        let _ = writeln!(
            std::io::stderr(),
            "warning: cannot start the signal thread ({e}); Ctrl-C stops at once"
        );
    }
}

/// Ctrl-C only where there are no Unix signals.
#[cfg(not(unix))]
pub fn install_interrupt_handler() {
    use std::sync::atomic::{AtomicUsize, Ordering};
    static PRESSES: AtomicUsize = AtomicUsize::new(0);
    let handler = ctrlc::set_handler(|| {
        if PRESSES.fetch_add(1, Ordering::SeqCst) > 0 {
            eprintln!("\nsecond Ctrl-C: exiting at once");
            std::process::exit(EXIT_INTERRUPTED.into());
        }
        eprintln!("\nCtrl-C: stopping (press again to exit at once)");
        pma_model::interrupt::request();
    });
    if let Err(e) = handler {
        eprintln!("warning: cannot install the Ctrl-C handler ({e}); Ctrl-C stops at once");
    }
}
