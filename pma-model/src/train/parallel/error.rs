//! Why a data-parallel group cannot go on ([`GroupError`]).

/// Why a group cannot go on. Every rank that meets one stops with it; the run directory keeps
/// its last complete checkpoint.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum GroupError {
    /// A rank ended (an error, a panic, a killed process) while the others needed it.
    #[error("rank {rank} of {size} left the group ({why}); the other ranks stopped too")]
    Left {
        rank: usize,
        size: usize,
        why: String,
    },
    /// A collective did not complete in time: a rank hangs or died without a word.
    #[error(
        "rank {rank} of {size} waited {secs} s for the group at a collective (--group-timeout); \
         a rank hangs or died"
    )]
    Timeout { rank: usize, size: usize, secs: u64 },
    /// The ranks computed different things where they must agree.
    #[error("the ranks disagree: {0}")]
    Disagree(String),
    /// The communication library failed.
    #[error("{0}")]
    Engine(String),
}

impl pma_data::ExitKind for GroupError {
    fn kind(&self) -> pma_data::ErrorKind {
        pma_data::ErrorKind::Failure
    }
}
