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
//!
//! Work that others wait for must not stop halfway: a rank of a data-parallel group that left
//! a step would leave its peers waiting for its gradients. While a [`Hold`] lives, [`check`]
//! passes; the holder polls [`requested`] at points where the whole group can agree to stop.

use std::sync::atomic::{AtomicBool, AtomicI32, AtomicUsize, Ordering};

static REQUESTED: AtomicBool = AtomicBool::new(false);
static SIGNAL: AtomicI32 = AtomicI32::new(0);
static HOLDS: AtomicUsize = AtomicUsize::new(0);

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

/// `Err(Interrupted)` once an interruption is requested, unless a [`Hold`] lives.
pub fn check() -> Result<(), Interrupted> {
    if requested() && HOLDS.load(Ordering::SeqCst) == 0 {
        Err(Interrupted)
    } else {
        Ok(())
    }
}

/// While it lives, [`check`] passes in every thread of the process (a request is kept, and
/// [`requested`] still reports it): see the module's docs.
#[must_use = "checks pass only while the hold lives"]
pub struct Hold(());

/// Hold [`check`] until the returned guard drops.
pub fn hold() -> Hold {
    HOLDS.fetch_add(1, Ordering::SeqCst);
    Hold(())
}

impl Drop for Hold {
    fn drop(&mut self) {
        HOLDS.fetch_sub(1, Ordering::SeqCst);
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
