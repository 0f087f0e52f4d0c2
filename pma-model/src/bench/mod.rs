//! What `pma bench` measures (feature `train`): parity against each speed option side by
//! side in one process ([`measure`]), and step accounting ([`account()`]).
//!
//! | module | what |
//! | --- | --- |
//! | [`options`] | the configurations compared ([`BenchOption`]): culling, the vectorised sine |
//! | [`measure`] | render and training speed, memory and quality per option ([`BenchReport`]) |
//! | [`account`] | one training step and one inference pass as a GPU would run them |
//! | [`shares`] | the share of samples that run the network per pass, per option (counts) |
//! | [`quality`] | time to quality: held-out PSNR against training time, per option |
//!
//! Everything runs for real on this machine; timings are wall times of this process, and
//! held-out quality is scored by [`crate::eval`]'s protocol.

pub mod account;
pub mod measure;
pub mod options;
pub mod quality;
pub mod scaling;
pub mod shares;

pub use account::{account, AccountReport, AccountRequest};
pub use measure::{measure, BenchReport, BenchRequest, ForwardResult, OptionResult};
pub use options::{options, BenchOption};
pub use quality::{
    quality_options, select_options, time_to_quality, QualityReport, QualityRequest,
};
pub use shares::{shares, PassShare, SharesReport, SharesRequest};

use crate::error::ModelError;
use crate::eval::EvalError;
use crate::train::TrainError;

#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// A setting the bench cannot run with (the message names it).
    #[error("{0}")]
    Setting(String),

    /// The synthetic scene could not be made.
    #[error("synthesising the {what} scene: {source}")]
    Scene {
        what: &'static str,
        #[source]
        source: Box<pma_data::synth::SynthError>,
    },

    /// The model to render could not be loaded.
    #[error("loading {}: {source}", path.display())]
    Load {
        path: std::path::PathBuf,
        #[source]
        source: Box<ModelError>,
    },

    // Boxed: the wrapped errors are large and these results are passed around a lot.
    #[error(transparent)]
    Train(Box<TrainError>),

    #[error(transparent)]
    Eval(Box<EvalError>),

    #[error(transparent)]
    Model(Box<ModelError>),

    #[error(transparent)]
    Data(Box<pma_data::DataError>),

    #[error(transparent)]
    Candle(Box<candle_core::Error>),
}

impl pma_data::ExitKind for BenchError {
    fn kind(&self) -> pma_data::ErrorKind {
        match self {
            Self::Setting(_) => pma_data::ErrorKind::Refused,
            Self::Scene { source, .. } => source.kind(),
            Self::Load { source, .. } => source.kind(),
            Self::Train(e) => e.kind(),
            Self::Eval(e) => e.kind(),
            Self::Model(e) => e.kind(),
            Self::Data(e) => e.kind(),
            Self::Candle(_) => pma_data::ErrorKind::Failure,
        }
    }
}

crate::error::boxed_from!(
    BenchError:
    Train(TrainError),
    Eval(EvalError),
    Model(ModelError),
    Data(pma_data::DataError),
    Candle(candle_core::Error),
);

crate::error::interrupted_as_model!(BenchError);

pub type Result<T> = std::result::Result<T, BenchError>;

/// How a bench run reports what it is doing; every method does nothing by default.
pub trait BenchObserver {
    /// A phase of `total` steps begins.
    fn phase(&mut self, _name: &str, _total: u64) {}
    /// `done` steps of the phase are complete; `message` says what runs now.
    fn progress(&mut self, _done: u64, _message: &str) {}
    /// The phase is over.
    fn phase_end(&mut self) {}
    /// A line worth showing (a scene being made, a model trained).
    fn note(&mut self, _line: &str) {}
    /// Something the user should know about the figures.
    fn warning(&mut self, _line: &str) {}
}

/// Reports nothing.
pub struct Silent;

impl BenchObserver for Silent {}

/// Peak resident set size of this process so far (Linux `VmHWM`), MiB; `None` where the
/// system does not say.
pub fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// Reset the peak RSS to the current RSS (Linux `clear_refs` 5); false where unsupported.
pub fn reset_peak_rss() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}
