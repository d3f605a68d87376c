//! Progress bars and log lines shared by every training loop.
//!
//! A bar shows `{pos}/{len}`, elapsed and remaining time, the rate and a message; it is hidden
//! when progress is switched off. Messages go above a visible bar, or to stderr when the bar is
//! hidden (not a terminal, or switched off), so logs of unattended runs keep every line.

use indicatif::{ProgressBar, ProgressStyle};

/// The template of the training loops' bars.
pub const TEMPLATE: &str = "{bar:30} {pos}/{len} [{elapsed_precise}<{eta_precise}] {per_sec} {msg}";

/// A bar over `total` steps starting at `position`, drawn with `template` (hidden unless `show`).
pub fn progress_bar(show: bool, total: u64, position: u64, template: &str) -> ProgressBar {
    if !show {
        return ProgressBar::hidden();
    }
    let b = ProgressBar::new(total);
    b.set_style(ProgressStyle::with_template(template).expect("valid template"));
    b.set_position(position);
    b
}

/// Prints a line above the progress bar, or to stderr when the bar is hidden.
pub fn say(bar: &ProgressBar, message: String) {
    if bar.is_hidden() {
        eprintln!("{message}");
    } else {
        bar.println(message);
    }
}
