//! The file-system layer: every file pma writes goes through [`write_atomic`] or
//! [`AtomicFile`], every input is opened with [`open_input`], and every command checks its
//! paths with [`PathCheck`] before it starts.
//!
//! **Writes.** The data lands in a temporary file in the target's directory and is renamed
//! over the target once complete and synced, so a reader (or a crash, or Ctrl-C) sees the old
//! file or the new one, never half of one. Temporary files are created owner-only (0600);
//! the finished file gets the mode an ordinary `File::create` would give it (0666 less the
//! umask, so 0644 under the usual umask), checkpoints included: they are meant to be shipped
//! and read by other accounts. [`commit_all`] commits several files only once all of them
//! are complete.
//!
//! **Inputs** must be regular files: a FIFO, a device or a directory is refused at once,
//! without blocking in `open` (a FIFO without a writer would) and without reading an
//! endless device. [`read_input`] reads at most the file's real size, and no more than a
//! cap the caller gives.
//!
//! **Fault injection.** With `PMA_FSIO_FAIL_AFTER=N` in the environment, the writes of this
//! process through this module fail once N bytes have been written, as on a full disk (the
//! fault-injection tests use it where they cannot mount a small filesystem). With
//! `PMA_FSIO_DELAY_US=N` each write first sleeps N µs, as on a slow disk, so that a test can
//! interrupt a write in progress on any machine rather than racing a fast one.

use std::fs::File;
use std::io::{self, BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// Write `path` atomically: `fill` writes the whole content into a buffered temporary file.
/// The file is flushed and synced before the rename, and the directory after it.
pub fn write_atomic_with<F>(path: &Path, fill: F) -> io::Result<()>
where
    F: FnOnce(&mut BufWriter<Writer<&File>>) -> io::Result<()>,
{
    let tmp = AtomicFile::create(path)?;
    {
        let mut w = BufWriter::new(tmp.writer());
        fill(&mut w)?;
        w.flush()?;
    }
    tmp.commit()
}

/// [`write_atomic_with`] for content already in memory.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> io::Result<()> {
    write_atomic_with(path, |w| w.write_all(bytes))
}

/// A temporary file beside `path` that becomes `path` on [`AtomicFile::commit`]; dropped
/// without a commit, it is removed. For writers that need a `File`-like sink (zip, image
/// encoders) or that write in several steps: write through [`AtomicFile::writer`].
pub struct AtomicFile {
    tmp: tempfile::NamedTempFile,
    path: PathBuf,
}

impl AtomicFile {
    pub fn create(path: &Path) -> io::Result<Self> {
        Ok(Self {
            tmp: scratch_beside(path)?,
            path: path.to_path_buf(),
        })
    }

    /// A writer into the temporary file (counted by the fault injection).
    pub fn writer(&self) -> Writer<&File> {
        Writer(self.tmp.as_file())
    }

    /// [`Self::writer`] owning a second handle of the file, for encoders that keep their sink.
    pub fn owned_writer(&self) -> io::Result<Writer<File>> {
        Ok(Writer(self.tmp.as_file().try_clone()?))
    }

    /// The temporary file itself (reading back what was written).
    pub fn file(&self) -> &File {
        self.tmp.as_file()
    }

    /// Where the data goes until the commit (for writers that take a path).
    pub fn temp_path(&self) -> &Path {
        self.tmp.path()
    }

    /// The final path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Sync, give the usual mode, rename over the final path, sync the directory.
    pub fn commit(self) -> io::Result<()> {
        commit_all(vec![self])
    }

    fn prepare(&self) -> io::Result<()> {
        fault_check()?;
        self.tmp.as_file().sync_all()?;
        set_default_mode(self.tmp.as_file())
    }
}

/// A scratch file beside `path` (`.pma-*.tmp` in its directory, removed when dropped), for
/// a writer that builds an output from an intermediate file. An error creating it names no
/// temporary: the caller names `path`.
pub fn scratch_beside(path: &Path) -> io::Result<tempfile::NamedTempFile> {
    tempfile::Builder::new()
        .prefix(".pma-")
        .suffix(".tmp")
        .tempfile_in(parent_dir(path))
        .map_err(without_temp_path)
}

/// `tempfile`'s error without the temporary's name it appends (`... at path
/// ".pma-XXXX.tmp"`; its error type keeps the cause private): callers name the output,
/// which is what the user asked for.
fn without_temp_path(e: io::Error) -> io::Error {
    let text = e.to_string();
    match text.rsplit_once(" at path ") {
        Some((cause, _)) if e.get_ref().is_some() => io::Error::new(e.kind(), cause.to_string()),
        _ => e,
    }
}

/// Commit several files as one step as far as a failure can tell: every file is synced
/// before the first rename, so a full disk or a write error leaves none of them (the
/// temporaries are removed). The renames follow in order, then the directories are synced;
/// only a crash between two renames can leave some renamed and not the others, so put the
/// file whose presence says "complete" last.
pub fn commit_all(files: Vec<AtomicFile>) -> io::Result<()> {
    for f in &files {
        f.prepare()?;
    }
    let mut dirs: Vec<PathBuf> = Vec::new();
    for f in files {
        let dir = parent_dir(&f.path).to_path_buf();
        f.tmp.persist(&f.path).map_err(|e| e.error)?;
        if !dirs.contains(&dir) {
            dirs.push(dir);
        }
    }
    for d in dirs {
        sync_dir(&d)?;
    }
    Ok(())
}

/// Directories created for outputs, outermost first, to remove again those left empty.
#[derive(Debug, Default)]
pub struct CreatedDirs(std::sync::Mutex<Vec<PathBuf>>);

impl CreatedDirs {
    pub const fn new() -> Self {
        Self(std::sync::Mutex::new(Vec::new()))
    }

    fn list(&self) -> std::sync::MutexGuard<'_, Vec<PathBuf>> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// `std::fs::create_dir_all`, remembering each directory it creates.
    pub fn create_all(&self, dir: &Path) -> io::Result<()> {
        let mut missing = Vec::new();
        let mut d = Some(dir);
        while let Some(p) = d.filter(|p| !p.as_os_str().is_empty()) {
            if std::fs::symlink_metadata(p).is_ok() {
                break;
            }
            missing.push(p.to_path_buf());
            d = p.parent();
        }
        std::fs::create_dir_all(dir)?;
        self.list().extend(missing.into_iter().rev());
        Ok(())
    }

    /// Remove the directories created here that are still empty, innermost first, and
    /// return them. A directory holding anything stays, and so does every directory that
    /// was there before.
    pub fn remove_empty(&self) -> Vec<PathBuf> {
        let dirs = std::mem::take(&mut *self.list());
        dirs.into_iter()
            .rev()
            .filter(|d| std::fs::remove_dir(d).is_ok())
            .collect()
    }
}

/// The output directories this process created.
static CREATED_DIRS: CreatedDirs = CreatedDirs::new();

/// `std::fs::create_dir_all` for an output directory, remembering each directory it
/// creates: a command that then fails removes the ones still empty
/// ([`remove_empty_created_dirs`]) instead of leaving them behind.
pub fn create_dir_all(dir: &Path) -> io::Result<()> {
    CREATED_DIRS.create_all(dir)
}

/// Remove the directories [`create_dir_all`] created in this process that are still empty
/// (see [`CreatedDirs::remove_empty`]); for a command that failed.
pub fn remove_empty_created_dirs() -> Vec<PathBuf> {
    CREATED_DIRS.remove_empty()
}

/// Make the entries of `dir` (files created, renamed or removed in it) durable.
pub fn sync_dir(dir: &Path) -> io::Result<()> {
    #[cfg(unix)]
    {
        File::open(dir)?.sync_all()
    }
    #[cfg(not(unix))]
    {
        let _ = dir;
        Ok(())
    }
}

/// The directory a file is created in (`.` for a bare file name).
pub fn parent_dir(path: &Path) -> &Path {
    match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    }
}

/// A sink of this module: writes are counted against the injected fault budget
/// (`PMA_FSIO_FAIL_AFTER`), and otherwise passed through.
pub struct Writer<F>(F);

impl<F: Write> Write for Writer<F> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        fault_charge(buf.len())?;
        self.0.write(buf)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.0.flush()
    }
}

impl<F: Seek> Seek for Writer<F> {
    fn seek(&mut self, pos: SeekFrom) -> io::Result<u64> {
        self.0.seek(pos)
    }
}

/// Bytes written so far through [`Writer`]s, and the injected budget (`u64::MAX`: none).
static WRITTEN: AtomicU64 = AtomicU64::new(0);

fn fault_budget() -> u64 {
    use std::sync::OnceLock;
    static BUDGET: OnceLock<u64> = OnceLock::new();
    *BUDGET.get_or_init(|| {
        std::env::var("PMA_FSIO_FAIL_AFTER")
            .ok()
            .and_then(|v| v.trim().parse().ok())
            .unwrap_or(u64::MAX)
    })
}

fn injected_full() -> io::Error {
    io::Error::new(
        io::ErrorKind::StorageFull,
        "No space left on device (injected: PMA_FSIO_FAIL_AFTER)",
    )
}

fn write_delay() -> Option<std::time::Duration> {
    use std::sync::OnceLock;
    static DELAY: OnceLock<Option<std::time::Duration>> = OnceLock::new();
    *DELAY.get_or_init(|| {
        std::env::var("PMA_FSIO_DELAY_US")
            .ok()
            .and_then(|v| v.trim().parse::<u64>().ok())
            .filter(|&us| us > 0)
            .map(|us| std::time::Duration::from_micros(us.min(1_000_000)))
    })
}

fn fault_charge(n: usize) -> io::Result<()> {
    if let Some(d) = write_delay() {
        std::thread::sleep(d);
    }
    let budget = fault_budget();
    if budget == u64::MAX {
        return Ok(());
    }
    let before = WRITTEN.fetch_add(n as u64, Ordering::SeqCst);
    if before.saturating_add(n as u64) > budget {
        return Err(injected_full());
    }
    Ok(())
}

/// A commit on a "full disk" fails too (renaming needs no space, but a real full disk
/// usually failed the writes before it; this keeps the injected disk consistent).
fn fault_check() -> io::Result<()> {
    let budget = fault_budget();
    if budget != u64::MAX && WRITTEN.load(Ordering::SeqCst) > budget {
        return Err(injected_full());
    }
    Ok(())
}

/// A writer for formats whose writer finalises itself on drop (zip): after the first failed
/// write or seek, the rest goes nowhere and succeeds, so the drop has nothing to complain
/// about; the first error has already been returned and the file is abandoned (see
/// [`AtomicFile`]). [`Latch::watch`] tells afterwards whether that happened, also once the
/// latch is buried inside an encoder.
pub struct Latch<W> {
    inner: W,
    failed: LatchWatch,
    pos: u64,
    end: u64,
}

/// The failure record of a [`Latch`], shared with whoever created it.
#[derive(Clone, Default)]
pub struct LatchWatch(std::sync::Arc<std::sync::OnceLock<(io::ErrorKind, String)>>);

impl LatchWatch {
    /// The first I/O error the latch met, if any (as a new error of the same kind and
    /// message).
    pub fn failure(&self) -> Option<io::Error> {
        self.0.get().map(|(k, m)| io::Error::new(*k, m.clone()))
    }
}

impl<W> Latch<W> {
    pub fn new(inner: W) -> Self {
        Self {
            inner,
            failed: LatchWatch::default(),
            pos: 0,
            end: 0,
        }
    }

    /// A handle on the failure record.
    pub fn watch(&self) -> LatchWatch {
        self.failed.clone()
    }

    /// The first I/O error met, if any.
    pub fn failure(&self) -> Option<io::Error> {
        self.failed.failure()
    }

    pub fn into_inner(self) -> W {
        self.inner
    }

    fn has_failed(&self) -> bool {
        self.failed.0.get().is_some()
    }

    fn fail(&mut self, e: io::Error) -> io::Error {
        let _ = self.failed.0.set((e.kind(), e.to_string()));
        e
    }
}

impl<W: Write> Write for Latch<W> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        if self.has_failed() {
            self.pos += buf.len() as u64;
            self.end = self.end.max(self.pos);
            return Ok(buf.len());
        }
        match self.inner.write(buf) {
            Ok(n) => {
                self.pos += n as u64;
                self.end = self.end.max(self.pos);
                Ok(n)
            }
            Err(e) => Err(self.fail(e)),
        }
    }

    fn flush(&mut self) -> io::Result<()> {
        if self.has_failed() {
            return Ok(());
        }
        self.inner.flush().map_err(|e| self.fail(e))
    }
}

impl<W: Seek> Seek for Latch<W> {
    fn seek(&mut self, pos: SeekFrom) -> io::Result<u64> {
        if !self.has_failed() {
            match self.inner.seek(pos) {
                Ok(p) => {
                    self.pos = p;
                    self.end = self.end.max(p);
                    return Ok(p);
                }
                Err(e) => return Err(self.fail(e)),
            }
        }
        self.pos = match pos {
            SeekFrom::Start(p) => p,
            SeekFrom::Current(d) => self.pos.saturating_add_signed(d),
            SeekFrom::End(d) => self.end.saturating_add_signed(d),
        };
        Ok(self.pos)
    }
}

/// A path a command cannot use: a missing or non-regular input, an output that would replace
/// an input, an output path that is not UTF-8 (refused, [`ErrorKind::Refused`]); or an
/// output that cannot be created where asked: its directory is missing, a directory or a
/// device is in its place ([`ErrorKind::Failure`], like any output that cannot be written).
/// The message names the flag and the path.
///
/// [`ErrorKind::Refused`]: crate::error::ErrorKind::Refused
/// [`ErrorKind::Failure`]: crate::error::ErrorKind::Failure
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{message}")]
pub struct PathError {
    pub message: String,
    pub kind: crate::error::ErrorKind,
}

impl PathError {
    fn refused(message: String) -> Self {
        Self {
            message,
            kind: crate::error::ErrorKind::Refused,
        }
    }

    fn unwritable(message: String) -> Self {
        Self {
            message,
            kind: crate::error::ErrorKind::Failure,
        }
    }
}

impl crate::error::ExitKind for PathError {
    fn kind(&self) -> crate::error::ErrorKind {
        self.kind
    }
}

/// What a file is, for messages ("a FIFO", "a character device", "a directory").
pub fn file_type_name(ft: &std::fs::FileType) -> &'static str {
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if ft.is_fifo() {
            return "a FIFO";
        }
        if ft.is_char_device() {
            return "a character device";
        }
        if ft.is_block_device() {
            return "a block device";
        }
        if ft.is_socket() {
            return "a socket";
        }
    }
    if ft.is_dir() {
        "a directory"
    } else if ft.is_symlink() {
        "a symbolic link"
    } else {
        "not a regular file"
    }
}

fn not_regular(ft: &std::fs::FileType) -> io::Error {
    io::Error::new(
        io::ErrorKind::InvalidInput,
        format!("{}, not a regular file", file_type_name(ft)),
    )
}

/// Open an input for reading; anything but a regular file is refused (`InvalidInput`)
/// without blocking: the file is opened non-blocking, checked, and only then read.
pub fn open_input(path: &Path) -> io::Result<File> {
    let mut opts = std::fs::OpenOptions::new();
    opts.read(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        opts.custom_flags(libc::O_NONBLOCK);
    }
    let f = opts.open(path)?;
    let ft = f.metadata()?.file_type();
    if !ft.is_file() {
        return Err(not_regular(&ft));
    }
    #[cfg(unix)]
    {
        // Back to blocking reads (a regular file ignores the flag, but stay plain).
        use std::os::fd::AsRawFd;
        let fd = f.as_raw_fd();
        // SAFETY: fcntl on a descriptor this function owns; no memory is passed.
        unsafe {
            let flags = libc::fcntl(fd, libc::F_GETFL);
            if flags >= 0 {
                libc::fcntl(fd, libc::F_SETFL, flags & !libc::O_NONBLOCK);
            }
        }
    }
    Ok(f)
}

/// The whole of an input file ([`open_input`]), refused (`InvalidData`) when it is larger
/// than `max` bytes. Reads the size the file has when opened and no more, so a file that
/// grows cannot make this read without end.
pub fn read_input(path: &Path, max: u64) -> io::Result<Vec<u8>> {
    use std::io::Read;
    let f = open_input(path)?;
    let len = f.metadata()?.len();
    if len > max {
        return Err(io::Error::new(
            io::ErrorKind::InvalidData,
            format!("{len} bytes, more than the {max} bytes accepted for this file"),
        ));
    }
    let mut buf = Vec::with_capacity(len as usize);
    f.take(len).read_to_end(&mut buf)?;
    Ok(buf)
}

/// [`read_input`] as UTF-8 text.
pub fn read_input_to_string(path: &Path, max: u64) -> io::Result<String> {
    String::from_utf8(read_input(path, max)?)
        .map_err(|_| io::Error::new(io::ErrorKind::InvalidData, "not UTF-8 text"))
}

/// Decode an image file opened with [`open_input`] (format from the extension, or from the
/// content when the extension names none).
pub fn open_image(path: &Path) -> image::ImageResult<image::DynamicImage> {
    let f = open_input(path).map_err(image::ImageError::IoError)?;
    let mut r = image::ImageReader::new(io::BufReader::new(f));
    match image::ImageFormat::from_path(path) {
        Ok(fmt) => r.set_format(fmt),
        Err(_) => {
            r = r
                .with_guessed_format()
                .map_err(image::ImageError::IoError)?
        }
    }
    r.decode()
}

/// Identity of an existing file: (device, inode) on Unix.
fn identity(meta: &std::fs::Metadata) -> Option<(u64, u64)> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        Some((meta.dev(), meta.ino()))
    }
    #[cfg(not(unix))]
    {
        let _ = meta;
        None
    }
}

/// A path as the check resolved it: its canonical form and, if it exists, its identity.
struct Resolved {
    flag: String,
    shown: PathBuf,
    canonical: PathBuf,
    id: Option<(u64, u64)>,
}

impl Resolved {
    fn same(&self, other: &Resolved) -> bool {
        self.canonical == other.canonical || (self.id.is_some() && self.id == other.id)
    }

    fn describe(&self) -> String {
        format!("{} {}", self.flag, self.shown.display())
    }
}

/// The paths of one command, checked together before any work starts ([`PathCheck::check`]):
///
/// * inputs exist and are regular files (or directories where asked);
/// * an output file's directory exists, the output is not a directory, a FIFO or a device,
///   and its path is valid UTF-8 (it is written into reports);
/// * an output directory is a directory or can be created;
/// * no output is an input, by canonical path or by identity (device and inode: a hard
///   link), and no two outputs are the same file.
#[derive(Default)]
pub struct PathCheck {
    inputs: Vec<(String, PathBuf, bool)>,
    outputs: Vec<(String, PathBuf)>,
    out_dirs: Vec<(String, PathBuf, Vec<String>)>,
}

impl PathCheck {
    pub fn new() -> Self {
        Self::default()
    }

    /// An input file named by `flag`.
    pub fn input(mut self, flag: &str, path: &Path) -> Self {
        self.inputs.push((flag.into(), path.into(), false));
        self
    }

    /// [`Self::input`] for an optional flag.
    pub fn input_opt(self, flag: &str, path: Option<&Path>) -> Self {
        match path {
            Some(p) => self.input(flag, p),
            None => self,
        }
    }

    /// An input directory.
    pub fn input_dir(mut self, flag: &str, path: &Path) -> Self {
        self.inputs.push((flag.into(), path.into(), true));
        self
    }

    /// An output file (created or replaced).
    pub fn output(mut self, flag: &str, path: &Path) -> Self {
        self.outputs.push((flag.into(), path.into()));
        self
    }

    /// [`Self::output`] for an optional flag.
    pub fn output_opt(self, flag: &str, path: Option<&Path>) -> Self {
        match path {
            Some(p) => self.output(flag, p),
            None => self,
        }
    }

    /// An output directory (created if missing) and the names of the files written in it.
    pub fn output_dir<I, S>(mut self, flag: &str, dir: &Path, files: I) -> Self
    where
        I: IntoIterator<Item = S>,
        S: Into<String>,
    {
        self.out_dirs.push((
            flag.into(),
            dir.into(),
            files.into_iter().map(Into::into).collect(),
        ));
        self
    }

    /// Inputs first, then outputs that would replace an input, then outputs that cannot be
    /// created where asked: the first problem found, in that order.
    pub fn check(&self) -> Result<(), PathError> {
        fn refuse<T>(flag: &str, p: &Path, what: String) -> Result<T, PathError> {
            Err(PathError::refused(format!(
                "{flag} {}: {what}",
                p.display()
            )))
        }
        let mut inputs = Vec::new();
        for (flag, p, dir) in &self.inputs {
            let meta = match std::fs::metadata(p) {
                Ok(m) => m,
                Err(e) if e.kind() == io::ErrorKind::NotFound => {
                    return refuse(flag, p, "no such file or directory".into())
                }
                Err(e) => return refuse(flag, p, e.to_string()),
            };
            let ft = meta.file_type();
            match (dir, ft.is_dir(), ft.is_file()) {
                (true, true, _) | (false, _, true) => {}
                (true, false, _) => return refuse(flag, p, "not a directory".into()),
                (false, _, false) => {
                    return refuse(
                        flag,
                        p,
                        format!("{}, not a regular file", file_type_name(&ft)),
                    )
                }
            }
            let canonical = std::fs::canonicalize(p).or_else(|e| refuse(flag, p, e.to_string()))?;
            inputs.push(Resolved {
                flag: flag.clone(),
                shown: p.clone(),
                canonical,
                id: identity(&meta),
            });
        }
        // Outputs whose place is unusable cannot replace anything: kept for last.
        let mut unusable: Option<PathError> = None;
        let mut outputs: Vec<Resolved> = Vec::new();
        let mut add = |r: Result<Resolved, PathError>| -> Result<(), PathError> {
            match r {
                Ok(o) => outputs.push(o),
                Err(e) if e.kind == crate::error::ErrorKind::Refused => return Err(e),
                Err(e) => {
                    unusable.get_or_insert(e);
                }
            }
            Ok(())
        };
        for (flag, p) in &self.outputs {
            add(resolve_output(flag, p))?;
        }
        for (flag, dir, files) in &self.out_dirs {
            if dir.to_str().is_none() {
                return refuse(flag, dir, "the path is not valid UTF-8".into());
            }
            let place = |what: String| {
                Err(PathError::unwritable(format!(
                    "{flag} {}: {what}",
                    dir.display()
                )))
            };
            match std::fs::metadata(dir) {
                Ok(m) if m.is_dir() => {
                    for f in files {
                        add(resolve_output(flag, &dir.join(f)))?;
                    }
                }
                Ok(m) => add(place(format!(
                    "{}, expected a directory",
                    file_type_name(&m.file_type())
                )))?,
                Err(e) if e.kind() == io::ErrorKind::NotFound => {
                    // Created later: its nearest existing ancestor must be a directory.
                    let mut up = dir.parent();
                    while let Some(a) = up.filter(|a| !a.as_os_str().is_empty()) {
                        match std::fs::metadata(a) {
                            Ok(m) if m.is_dir() => break,
                            Ok(_) => {
                                add(place(format!("{} is not a directory", a.display())))?;
                                break;
                            }
                            Err(e) if e.kind() == io::ErrorKind::NotFound => up = a.parent(),
                            Err(e) => {
                                add(place(e.to_string()))?;
                                break;
                            }
                        }
                    }
                }
                Err(e) => add(place(e.to_string()))?,
            }
        }
        for (k, o) in outputs.iter().enumerate() {
            if let Some(i) = inputs.iter().find(|i| i.same(o)) {
                return Err(PathError::refused(format!(
                    "{} would overwrite the input {}; choose another output",
                    o.describe(),
                    i.describe()
                )));
            }
            if let Some(o2) = outputs[..k].iter().find(|o2| o2.same(o)) {
                return Err(PathError::refused(format!(
                    "{} and {} are the same file; choose different outputs",
                    o2.describe(),
                    o.describe()
                )));
            }
        }
        match unusable {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }
}

/// An output file: its path must be UTF-8 (refused otherwise), its directory must exist
/// and an existing file there must be a regular one (unusable otherwise).
fn resolve_output(flag: &str, p: &Path) -> Result<Resolved, PathError> {
    let refuse = |what: String| PathError::refused(format!("{flag} {}: {what}", p.display()));
    let unusable = |what: String| PathError::unwritable(format!("{flag} {}: {what}", p.display()));
    if p.to_str().is_none() {
        return Err(refuse("the path is not valid UTF-8".into()));
    }
    let Some(name) = p.file_name() else {
        return Err(refuse("expected a file name".into()));
    };
    let dir = parent_dir(p);
    let dir_canon = match std::fs::canonicalize(dir) {
        Ok(d) => d,
        Err(e) if e.kind() == io::ErrorKind::NotFound => {
            return Err(unusable(format!(
                "directory {} does not exist",
                dir.display()
            )))
        }
        Err(e) => return Err(unusable(format!("directory {}: {e}", dir.display()))),
    };
    if !dir_canon.is_dir() {
        return Err(unusable(format!("{} is not a directory", dir.display())));
    }
    let (canonical, id) = match std::fs::metadata(p) {
        Ok(m) => {
            let ft = m.file_type();
            if ft.is_dir() {
                return Err(unusable("is a directory, expected a file".into()));
            }
            if !ft.is_file() {
                return Err(unusable(format!(
                    "{}; pma only replaces regular files",
                    file_type_name(&ft)
                )));
            }
            (
                std::fs::canonicalize(p).map_err(|e| unusable(e.to_string()))?,
                identity(&m),
            )
        }
        Err(e) if e.kind() == io::ErrorKind::NotFound => (dir_canon.join(name), None),
        Err(e) => return Err(unusable(e.to_string())),
    };
    Ok(Resolved {
        flag: flag.into(),
        shown: p.into(),
        canonical,
        id,
    })
}

/// 0666 less the process umask: what `File::create` gives a new file.
#[cfg(unix)]
fn set_default_mode(f: &File) -> io::Result<()> {
    use std::os::unix::fs::PermissionsExt;
    f.set_permissions(std::fs::Permissions::from_mode(0o666 & !umask()))
}

#[cfg(not(unix))]
fn set_default_mode(_f: &File) -> io::Result<()> {
    Ok(())
}

/// The process umask, read once. Reading it means setting it, so it is read from
/// `/proc/self/status` where possible and otherwise assumed to be the usual 022.
#[cfg(unix)]
fn umask() -> u32 {
    use std::sync::OnceLock;
    static UMASK: OnceLock<u32> = OnceLock::new();
    *UMASK.get_or_init(|| {
        std::fs::read_to_string("/proc/self/status")
            .ok()
            .and_then(|s| {
                s.lines()
                    .find_map(|l| l.strip_prefix("Umask:"))
                    .and_then(|v| u32::from_str_radix(v.trim(), 8).ok())
            })
            .unwrap_or(0o022)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_temporary_that_cannot_be_created_is_not_named() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("missing").join("out.npz");
        for e in [
            AtomicFile::create(&out).err().unwrap(),
            scratch_beside(&out).err().unwrap(),
        ] {
            assert_eq!(e.kind(), io::ErrorKind::NotFound);
            let text = e.to_string();
            assert!(!text.contains(".pma-") && !text.contains(".tmp"), "{text}");
            assert!(text.contains("No such file or directory"), "{text}");
        }
    }

    #[test]
    fn created_dirs_left_empty_go_and_nothing_else_does() {
        let tmp = tempfile::tempdir().unwrap();
        let before = tmp.path().join("before");
        std::fs::create_dir(&before).unwrap();
        let created = CreatedDirs::new();
        // Three levels below a directory that existed: all three are new.
        let deep = before.join("a").join("b").join("c");
        created.create_all(&deep).unwrap();
        // One that gets a file stays, with its parents.
        let kept = tmp.path().join("kept").join("x");
        created.create_all(&kept).unwrap();
        std::fs::write(kept.join("f"), b"1").unwrap();
        // Creating an existing directory again adds nothing.
        created.create_all(&before).unwrap();
        let removed = created.remove_empty();
        assert_eq!(
            removed,
            [deep.clone(), before.join("a").join("b"), before.join("a")]
        );
        assert!(before.is_dir() && !before.join("a").exists());
        assert!(kept.join("f").is_file());
        assert!(created.remove_empty().is_empty(), "the list is spent");
    }

    #[test]
    fn writes_whole_file_with_umask_mode() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.bin");
        write_atomic(&p, b"hello").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"hello");
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = std::fs::metadata(&p).unwrap().permissions().mode() & 0o777;
            assert_eq!(mode, 0o666 & !umask());
            assert_ne!(mode & 0o044, 0, "others/group must be able to read");
        }
        // Only the target is left in the directory.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn failed_fill_leaves_old_file_and_no_temp() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.txt");
        write_atomic(&p, b"old").unwrap();
        let err = write_atomic_with(&p, |w| {
            w.write_all(b"partial")?;
            Err(io::Error::other("cut short"))
        })
        .unwrap_err();
        assert_eq!(err.to_string(), "cut short");
        assert_eq!(std::fs::read(&p).unwrap(), b"old");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn atomic_file_commits_or_vanishes() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("b.bin");
        {
            let f = AtomicFile::create(&p).unwrap();
            f.writer().write_all(b"dropped").unwrap();
        }
        assert!(!p.exists());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        let f = AtomicFile::create(&p).unwrap();
        f.writer().write_all(b"kept").unwrap();
        f.commit().unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"kept");
    }

    #[cfg(unix)]
    #[test]
    fn inputs_must_be_regular_files_and_are_never_blocked_on() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("f.npz");
        let c = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
        // SAFETY: a plain libc call with a valid NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
        // Would block forever in a blocking open (no writer).
        let e = open_input(&fifo).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::InvalidInput);
        assert!(e.to_string().contains("a FIFO"), "{e}");
        let e = read_input(Path::new("/dev/zero"), 1 << 20).unwrap_err();
        assert!(e.to_string().contains("character device"), "{e}");
        let e = open_input(dir.path()).unwrap_err();
        assert!(e.to_string().contains("a directory"), "{e}");
        let p = dir.path().join("a.toml");
        std::fs::write(&p, b"0123456789").unwrap();
        assert_eq!(read_input(&p, 10).unwrap(), b"0123456789");
        let e = read_input(&p, 9).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::InvalidData);
        let e = PathCheck::new().input("--data", &fifo).check().unwrap_err();
        assert!(
            e.message.contains("--data") && e.message.contains("a FIFO"),
            "{e}"
        );
    }

    #[test]
    fn outputs_never_replace_inputs() {
        let dir = tempfile::tempdir().unwrap();
        let model = dir.path().join("model.safetensors");
        std::fs::write(&model, b"weights").unwrap();
        // The same file by another spelling, and by a hard link.
        let other = dir.path().join(".").join("model.safetensors");
        let e = PathCheck::new()
            .input("--model", &model)
            .output("--out", &other)
            .check()
            .unwrap_err();
        assert!(
            e.message.contains("would overwrite the input --model"),
            "{e}"
        );
        assert_eq!(e.kind, crate::error::ErrorKind::Refused);
        let link = dir.path().join("link.safetensors");
        std::fs::hard_link(&model, &link).unwrap();
        #[cfg(unix)]
        assert!(PathCheck::new()
            .input("--model", &model)
            .output("--out", &link)
            .check()
            .is_err());
        // A file written into an output directory.
        let e = PathCheck::new()
            .input("--model", &model)
            .output_dir("--out", dir.path(), ["model.safetensors"])
            .check()
            .unwrap_err();
        assert!(e.message.contains("would overwrite"), "{e}");
        // Outputs that cannot be created where asked.
        let e = PathCheck::new()
            .output("--out", &dir.path().join("missing/a.ply"))
            .check()
            .unwrap_err();
        assert!(e.message.contains("does not exist"), "{e}");
        // An output that cannot go where asked is a failure to write, not refused input.
        assert_eq!(e.kind, crate::error::ErrorKind::Failure);
        let e = PathCheck::new()
            .output("--out", dir.path())
            .check()
            .unwrap_err();
        assert!(e.message.contains("is a directory"), "{e}");
        let e = PathCheck::new()
            .output_dir("--out", &model, ["x.png"])
            .check()
            .unwrap_err();
        assert!(e.message.contains("expected a directory"), "{e}");
        // Distinct files pass.
        PathCheck::new()
            .input("--model", &model)
            .output("--out", &dir.path().join("mesh.ply"))
            .output_dir("--render", &dir.path().join("new/sub"), ["a.png"])
            .check()
            .unwrap();
    }

    #[cfg(unix)]
    #[test]
    fn non_utf8_outputs_are_refused_before_work() {
        use std::os::unix::ffi::OsStrExt;
        let dir = tempfile::tempdir().unwrap();
        let bad = dir.path().join(std::ffi::OsStr::from_bytes(b"m\xff.ply"));
        let e = PathCheck::new().output("--out", &bad).check().unwrap_err();
        assert!(e.message.contains("not valid UTF-8"), "{e}");
    }

    #[test]
    fn latch_swallows_writes_after_the_first_failure() {
        struct Failing(usize);
        impl Write for Failing {
            fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
                if self.0 < buf.len() {
                    return Err(io::Error::new(io::ErrorKind::StorageFull, "disk full"));
                }
                self.0 -= buf.len();
                Ok(buf.len())
            }
            fn flush(&mut self) -> io::Result<()> {
                Ok(())
            }
        }
        impl Seek for Failing {
            fn seek(&mut self, _: SeekFrom) -> io::Result<u64> {
                Ok(0)
            }
        }
        let mut l = Latch::new(Failing(4));
        l.write_all(b"abcd").unwrap();
        assert!(l.write_all(b"efgh").is_err());
        // Afterwards everything "succeeds" into nothing, and the failure is remembered.
        l.write_all(b"ijkl").unwrap();
        assert_eq!(l.stream_position().unwrap(), 8);
        assert_eq!(l.failure().unwrap().kind(), io::ErrorKind::StorageFull);
    }
}
