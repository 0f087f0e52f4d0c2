//! One module per subcommand: clap `Args` plus `run`. The pipelines live in the libraries;
//! these modules parse, call and print.

pub mod ablate;
pub mod bench;
pub mod check_stability;
pub mod convert;
pub mod demo;
pub mod eval;
pub mod forward;
pub mod inspect;
pub mod mesh;
pub mod metrics;
#[cfg(feature = "train")]
pub mod plot;
pub mod progress;
pub mod render;
pub mod synth;
pub mod train;
pub mod view;

use std::path::Path;

use anyhow::Context as _;
use pma_data::dataset::{Dataset, Profile};
use pma_data::motion::MotionError;
use pma_data::synth::SynthError;
use pma_data::DataError;
use pma_model::error::ModelError;
use pma_model::interrupt::Interrupted;

/// Exit status of a command refused because of its input (a split the file does not hold,
/// a corrupt file, an out-of-range flag), as for clap's usage errors: the user has to change
/// the command or its input.
pub const EXIT_REFUSED: u8 = 2;
/// Exit status of a command stopped by Ctrl-C (128 + SIGINT, as a shell reports it).
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

/// Return a [`Refused`] error with a formatted message (a flag out of range, a file that
/// lacks what the command needs).
macro_rules! refuse {
    ($($arg:tt)*) => {
        return Err($crate::cli::Refused::new(format!($($arg)*)).into())
    };
}
pub(crate) use refuse;

/// The exit status for `e`, the one rule of every command: [`EXIT_INTERRUPTED`] once Ctrl-C
/// was pressed (whatever the error it caused), [`EXIT_REFUSED`] for input errors (see
/// [`is_input_error`]), [`EXIT_FAILURE`] otherwise.
pub fn exit_code(e: &anyhow::Error) -> u8 {
    if pma_model::interrupt::requested() || e.chain().any(|c| c.is::<Interrupted>()) {
        return EXIT_INTERRUPTED;
    }
    // The outermost error that says what it is decides; contexts added on the way up are
    // plain messages and say nothing.
    for cause in e.chain() {
        if cause.is::<Refused>() {
            return EXIT_REFUSED;
        }
        if let Some(input) = is_input_error(cause) {
            return if input { EXIT_REFUSED } else { EXIT_FAILURE };
        }
    }
    EXIT_FAILURE
}

/// Whether a library error is about the input (a file, a key, a flag: exit 2) rather than a
/// failure of the work (exit 1); `None` for an error of a type not classified here. An I/O
/// error is input when the file is missing or unreadable as data, and a failure otherwise
/// (permissions, a full disk).
pub fn is_input_error(e: &(dyn std::error::Error + 'static)) -> Option<bool> {
    use pma_model::eval::EvalError;
    if let Some(e) = e.downcast_ref::<std::io::Error>() {
        return Some(io_input(e));
    }
    if let Some(e) = e.downcast_ref::<DataError>() {
        return Some(data_input(e));
    }
    if let Some(e) = e.downcast_ref::<MotionError>() {
        return Some(motion_input(e));
    }
    if let Some(e) = e.downcast_ref::<SynthError>() {
        return Some(match e {
            SynthError::Data(d) => data_input(d),
            SynthError::Motion(m) => motion_input(m),
            SynthError::Config { .. } => true,
            SynthError::Io { source, .. } => io_input(source),
            SynthError::Encode { .. } => false,
            SynthError::Interrupted(_) => false,
        });
    }
    if let Some(e) = e.downcast_ref::<ModelError>() {
        return Some(model_input(e));
    }
    if let Some(e) = e.downcast_ref::<EvalError>() {
        return Some(eval_input(e));
    }
    #[cfg(feature = "train")]
    if let Some(e) = e.downcast_ref::<pma_model::train::TrainError>() {
        return Some(train_input(e));
    }
    if e.is::<pma_model::compute::device::Tf32Error>() {
        return Some(true);
    }
    if let Some(e) = e.downcast_ref::<pma_model::compute::device::DeviceError>() {
        use pma_model::compute::device::DeviceError;
        return Some(matches!(
            e,
            DeviceError::Unknown(_) | DeviceError::NotCompiled { .. }
        ));
    }
    None
}

fn io_input(e: &std::io::Error) -> bool {
    use std::io::ErrorKind::*;
    matches!(
        e.kind(),
        NotFound | InvalidData | InvalidInput | UnexpectedEof | IsADirectory | NotADirectory
    )
}

fn data_input(e: &DataError) -> bool {
    match e {
        DataError::Io { source, .. } => io_input(source),
        _ => true,
    }
}

fn motion_input(e: &MotionError) -> bool {
    match e {
        MotionError::Io { source, .. } => io_input(source),
        _ => true,
    }
}

fn model_input(e: &ModelError) -> bool {
    match e {
        ModelError::Io { source, .. } => io_input(source),
        // Writes go through fsio (its failures are `Io`): this is a file that cannot be parsed.
        ModelError::Safetensors { .. }
        | ModelError::Checkpoint { .. }
        | ModelError::Config(_)
        | ModelError::Shape { .. }
        | ModelError::Input(_) => true,
        ModelError::Data(d) => data_input(d),
        ModelError::Candle(_) | ModelError::Interrupted(_) => false,
    }
}

fn eval_input(e: &pma_model::eval::EvalError) -> bool {
    use pma_model::eval::EvalError;
    match e {
        EvalError::Incomplete { .. } | EvalError::NothingScored { .. } => true,
        EvalError::Read { source, .. } => data_input(source),
        EvalError::Io { source, .. } => io_input(source),
        EvalError::Png { .. } | EvalError::Candle(_) => false,
        EvalError::Model(m) => model_input(m),
        EvalError::Data(d) => data_input(d),
        e => e.is_bad_input(),
    }
}

#[cfg(feature = "train")]
fn train_input(e: &pma_model::train::TrainError) -> bool {
    use pma_model::train::TrainError;
    match e {
        TrainError::Config(_)
        | TrainError::State(_)
        | TrainError::StateFile { .. }
        | TrainError::Resume { .. }
        | TrainError::RunExists(_) => true,
        TrainError::Io { source, .. } => io_input(source),
        TrainError::Diverged { .. }
        | TrainError::Stopped { .. }
        | TrainError::Observer(_)
        | TrainError::Candle(_) => false,
        TrainError::Model(m) => model_input(m),
        TrainError::Data(d) => data_input(d),
        TrainError::Eval(e) => eval_input(e),
    }
}

/// `e` and its causes on one line, each cause left out when the message already holds it
/// (many errors print their source themselves).
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
    out
}

/// The line for a command stopped by Ctrl-C: what the command says about where it stopped,
/// if anything, and that no file was left half-written.
pub fn interrupted_report(e: &anyhow::Error) -> String {
    let text = report(e);
    let said = text.trim_end_matches("interrupted").trim_end_matches(": ");
    if said.is_empty() || !e.chain().any(|c| c.is::<Interrupted>()) {
        "interrupted: stopped by Ctrl-C; files already complete are kept, none is half-written"
            .to_string()
    } else if said.contains("interrupted") {
        said.to_string()
    } else {
        format!("interrupted: {said}")
    }
}

/// Open the compute device named by a `--device` flag: cpu, cuda, cuda:N, metal or metal:N.
/// A backend missing from this build is reported with the cargo feature that brings it.
pub fn device(spec: &str) -> anyhow::Result<candle_core::Device> {
    Ok(pma_model::compute::device::parse_device(spec)?)
}

/// [`device`], then TF32 matrix products on (`--tf32`, CUDA only: refused elsewhere) or off.
pub fn device_tf32(spec: &str, tf32: bool) -> anyhow::Result<candle_core::Device> {
    let dev = device(spec)?;
    pma_model::compute::device::set_tf32(tf32, &dev)?;
    Ok(dev)
}

/// Read a dataset for `profile`, printing its warnings.
pub fn read_dataset(path: &Path, profile: Profile) -> anyhow::Result<Dataset> {
    let data = pma_model::eval::read_dataset(path, profile)?;
    for w in &data.warnings {
        eprintln!("warning: {}: {w}", path.display());
    }
    Ok(data)
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

/// Route Ctrl-C to the process-wide interrupt flag: long work stops at its next check and
/// the command exits with [`EXIT_INTERRUPTED`], leaving only complete files (a training run
/// first saves its last complete step). A second Ctrl-C exits at once, as a plain SIGINT
/// would.
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
