//! The command line's progress bars: one look for every command.

use indicatif::{ProgressBar, ProgressStyle};

/// `prefix [elapsed] bar pos/len (eta) message`; hidden when `quiet`.
pub fn bar(quiet: bool, len: u64, prefix: &str) -> ProgressBar {
    styled(
        quiet,
        len,
        prefix,
        "{prefix} [{elapsed_precise}] {bar:30} {human_pos}/{human_len} ({eta}) {msg}",
    )
}

/// As [`bar`] without the estimated time: for work whose message carries its own estimate.
#[cfg(feature = "train")]
pub fn bar_without_eta(quiet: bool, len: u64, prefix: &str) -> ProgressBar {
    styled(
        quiet,
        len,
        prefix,
        "{prefix} [{elapsed_precise}] {bar:30} {human_pos}/{human_len} {msg}",
    )
}

fn styled(quiet: bool, len: u64, prefix: &str, template: &str) -> ProgressBar {
    if quiet {
        return ProgressBar::hidden();
    }
    let style = ProgressStyle::with_template(template)
        .expect("static template")
        .progress_chars("=> ");
    ProgressBar::new(len)
        .with_style(style)
        .with_prefix(prefix.to_string())
}

/// A bench's phases as progress bars (none with `--quiet`), its notes on stdout and
/// warnings on stderr.
#[cfg(feature = "train")]
pub struct Phases {
    quiet: bool,
    bar: indicatif::ProgressBar,
}

#[cfg(feature = "train")]
impl Phases {
    pub fn new(quiet: bool) -> Self {
        Self {
            quiet,
            bar: indicatif::ProgressBar::hidden(),
        }
    }
}

#[cfg(feature = "train")]
impl pma_model::bench::BenchObserver for Phases {
    fn phase(&mut self, name: &str, total: u64) {
        self.bar = bar(self.quiet, total, name);
        self.bar
            .enable_steady_tick(std::time::Duration::from_millis(500));
    }

    fn progress(&mut self, done: u64, message: &str) {
        self.bar.set_position(done);
        self.bar.set_message(message.to_string());
    }

    fn phase_end(&mut self) {
        self.bar.finish_and_clear();
    }

    fn note(&mut self, line: &str) {
        self.bar.suspend(|| println!("{line}"));
    }

    fn warning(&mut self, line: &str) {
        self.bar.suspend(|| eprintln!("warning: {line}"));
    }
}
