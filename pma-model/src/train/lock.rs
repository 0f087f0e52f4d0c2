//! One writer per run directory: an advisory lock on `RUN/.lock`, held for the whole run.
//!
//! The lock is `flock(LOCK_EX | LOCK_NB)` (through `fs4`, which also covers Windows'
//! `LockFileEx`): the kernel releases it when the holder's file is closed, so a process that
//! was killed (even with `kill -9`) never leaves a stale lock behind, and a second writer
//! learns at once that the directory is taken. The holder writes its PID into the file
//! after taking the lock, so the refusal can name it. Readers (`pma eval`, a viewer) do not
//! lock: they read complete checkpoints only (see [`crate::network::run_dir`]).
//!
//! `fs4` rather than `fd-lock`: `fd-lock`'s guard borrows the file, which a lock held by a
//! long-lived value cannot easily keep; `fs4` locks the `File` itself. (`std`'s `File::lock`
//! needs Rust 1.89, newer than this workspace's minimum.) Advisory locks bind only those
//! that take them, and `flock` on some network filesystems is local to one machine.

use std::fs::File;
use std::io::{Read as _, Seek as _, SeekFrom, Write as _};
use std::path::{Path, PathBuf};

use fs4::{FileExt, TryLockError};

use super::error::TrainError;
use crate::network::run_dir::LOCK_FILE;

/// The run directory's lock; released when dropped (or when the process ends).
#[derive(Debug)]
pub struct RunLock {
    file: File,
    path: PathBuf,
    /// This lock created the file (it was not there before).
    created: bool,
}

impl RunLock {
    /// Take the lock of `dir` (which must exist), or fail with [`TrainError::Locked`]
    /// naming the holder's PID.
    pub fn acquire(dir: &Path) -> Result<Self, TrainError> {
        let path = dir.join(LOCK_FILE);
        let write_err = |source| TrainError::from(pma_data::FileError::write(&path, source));
        loop {
            // Not truncated on open: the holder's PID stays readable until we own the lock.
            let mut open = std::fs::OpenOptions::new();
            open.read(true).write(true);
            let (mut file, created) = match open.clone().create_new(true).open(&path) {
                Ok(f) => (f, true),
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => match open.open(&path) {
                    Ok(f) => (f, false),
                    // Removed since (a refused run that had created it): try again.
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
                    Err(e) => return Err(write_err(e)),
                },
                Err(e) => return Err(write_err(e)),
            };
            // Called through the trait: `std`'s newer inherent `File::try_lock` would shadow it.
            match FileExt::try_lock(&file) {
                Ok(()) => {}
                Err(TryLockError::WouldBlock) => {
                    let mut text = String::new();
                    let _ = file.read_to_string(&mut text);
                    return Err(TrainError::Locked {
                        dir: dir.to_path_buf(),
                        pid: text.trim().parse().ok(),
                    });
                }
                Err(TryLockError::Error(e)) => return Err(write_err(e)),
            }
            // The file locked must still be the one at the path: a holder that removes the
            // file it created ([`Self::remove`]) may have done so between our open and our
            // lock, and a lock on a removed file guards nothing.
            if !is_at(&file, &path) {
                continue;
            }
            file.set_len(0).map_err(write_err)?;
            file.seek(SeekFrom::Start(0)).map_err(write_err)?;
            writeln!(file, "{}", std::process::id()).map_err(write_err)?;
            file.flush().map_err(write_err)?;
            return Ok(Self {
                file,
                path,
                created,
            });
        }
    }

    /// The lock file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Release the lock, removing its file if this lock created it: for a session refused
    /// before it wrote anything, which leaves the directory as it found it. The file goes
    /// while still locked; a process that opened it meanwhile sees it gone once it holds
    /// the lock and takes the new one ([`Self::acquire`]).
    pub fn remove(self) {
        if self.created {
            let _ = std::fs::remove_file(&self.path);
        }
    }
}

/// Whether `file` is the file now at `path` (same device and inode).
fn is_at(file: &File, path: &Path) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        match (file.metadata(), std::fs::metadata(path)) {
            (Ok(a), Ok(b)) => a.dev() == b.dev() && a.ino() == b.ino(),
            _ => false,
        }
    }
    #[cfg(not(unix))]
    {
        let _ = file;
        path.exists()
    }
}

impl Drop for RunLock {
    fn drop(&mut self) {
        // The PID goes with the lock; the file stays (removing it would race a new holder).
        let _ = self.file.set_len(0);
        let _ = FileExt::unlock(&self.file);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn second_writer_is_refused_with_the_holders_pid_and_released_on_drop() {
        let dir = tempfile::tempdir().unwrap();
        let held = RunLock::acquire(dir.path()).unwrap();
        // flock locks belong to the open file description: a second open in the same
        // process conflicts like another process would.
        match RunLock::acquire(dir.path()) {
            Err(TrainError::Locked { pid, .. }) => assert_eq!(pid, Some(std::process::id())),
            other => panic!("expected Locked, got {other:?}"),
        }
        drop(held);
        RunLock::acquire(dir.path()).unwrap();
    }

    #[test]
    fn a_file_opened_before_its_removal_is_not_the_run_lock() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(LOCK_FILE);
        let held = RunLock::acquire(dir.path()).unwrap();
        // A second trainer opened the file just before the first one removed it.
        let stale = File::open(&path).unwrap();
        assert!(is_at(&stale, &path));
        held.remove();
        assert!(!is_at(&stale, &path));
        let next = RunLock::acquire(dir.path()).unwrap();
        assert!(is_at(&next.file, &path) && !is_at(&stale, &path));
    }

    #[test]
    fn a_lock_that_created_its_file_removes_it_and_one_that_found_it_does_not() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join(LOCK_FILE);
        RunLock::acquire(dir.path()).unwrap().remove();
        assert!(!file.exists(), "created by the lock: removed");
        drop(RunLock::acquire(dir.path()).unwrap());
        assert!(file.exists(), "dropped: kept");
        RunLock::acquire(dir.path()).unwrap().remove();
        assert!(file.exists(), "found by the lock: kept");
    }
}
