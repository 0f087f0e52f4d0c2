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
