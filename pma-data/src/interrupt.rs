//! Stopping long work early: one process-wide flag that a front end raises (the `pma` CLI
//! does so from its Ctrl-C handler) and that long loops poll between chunks of work.
//!
//! Library code calls [`check`] at the top of each chunk (a row of pixels, a chunk of rays or
//! grid points, an image) and returns [`Interrupted`] through its own error type; the work
//! already done is dropped, files being written are abandoned before their rename (see
//! [`crate::fsio`]), so nothing half-written appears. Polling reads one atomic and changes no
//! result: a run that is not interrupted is bit-identical with or without the checks.
//!
//! The flag is process-wide because a signal is: a library user that wants to cancel one job
//! of several runs each in its own process. Once raised it stays raised ([`reset`] is for
//! front ends that handle the interruption and carry on).

use std::sync::atomic::{AtomicBool, AtomicI32, Ordering};

static REQUESTED: AtomicBool = AtomicBool::new(false);
static SIGNAL: AtomicI32 = AtomicI32::new(0);

/// SIGINT's number, the signal [`request`] stands for.
pub const SIGINT: i32 = 2;

/// Ask every long loop of the process to stop at its next check (as Ctrl-C does).
pub fn request() {
    request_by(SIGINT);
}

/// [`request`], recording the signal that asked (the first one counts): a front end exits
/// with 128 + [`signal`] as a shell would report it.
pub fn request_by(signal: i32) {
    let _ = SIGNAL.compare_exchange(0, signal, Ordering::SeqCst, Ordering::SeqCst);
    REQUESTED.store(true, Ordering::SeqCst);
}

/// The signal of the first request (SIGINT = 2 for [`request`]); 0 when none was made.
pub fn signal() -> i32 {
    SIGNAL.load(Ordering::SeqCst)
}

/// Whether [`request`] was called (and not [`reset`] since).
pub fn requested() -> bool {
    REQUESTED.load(Ordering::Relaxed)
}

/// Lower the flag again.
pub fn reset() {
    REQUESTED.store(false, Ordering::SeqCst);
    SIGNAL.store(0, Ordering::SeqCst);
}

/// `Err(Interrupted)` once an interruption is requested.
pub fn check() -> Result<(), Interrupted> {
    if requested() {
        Err(Interrupted)
    } else {
        Ok(())
    }
}

/// Work stopped because an interruption was requested (Ctrl-C in the CLI).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("interrupted")]
pub struct Interrupted;

/// Whether `e` or one of its sources is [`Interrupted`].
pub fn caused(e: &(dyn std::error::Error + 'static)) -> bool {
    let mut cur = Some(e);
    while let Some(c) = cur {
        if c.is::<Interrupted>() {
            return true;
        }
        cur = c.source();
    }
    false
}
