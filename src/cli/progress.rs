//! The one progress printer of the command line: a bar on stderr (indicatif) for each stage of
//! `sylva run` and for one-off commands, with the stage's messages printed above it. Where
//! stderr is not a terminal the bar is hidden and only the messages are printed, so logs and
//! test output stay readable.

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

use sylva::progress::{CancelFlag, Progress};

/// Steps of the bar: a fraction in [0, 1] is shown to 0.1 %.
const STEPS: u64 = 1000;

pub(super) struct ConsoleProgress {
    label: String,
    bar: ProgressBar,
    cancel: Option<CancelFlag>,
}

impl ConsoleProgress {
    /// A bar named `label` (a stage's or a command's name); `cancel`, when given, is what
    /// [`Progress::is_cancelled`] reports (Ctrl-C in `sylva run`).
    pub(super) fn new(label: &str, cancel: Option<CancelFlag>) -> Self {
        let bar = ProgressBar::with_draw_target(Some(STEPS), ProgressDrawTarget::stderr());
        if let Ok(style) =
            ProgressStyle::with_template("{prefix:>9} [{bar:30}] {percent:>3}% {elapsed}")
        {
            bar.set_style(style.progress_chars("#>."));
        }
        bar.set_prefix(label.to_string());
        Self {
            label: label.to_string(),
            bar,
            cancel,
        }
    }
}

impl Drop for ConsoleProgress {
    fn drop(&mut self) {
        self.bar.finish();
    }
}

impl Progress for ConsoleProgress {
    fn set(&self, fraction: f64) {
        let pos = (fraction.clamp(0.0, 1.0) * STEPS as f64).round() as u64;
        // Never backwards: a stage's sub-steps may report out of order.
        if pos > self.bar.position() {
            self.bar.set_position(pos);
        }
    }

    fn log(&self, message: &str) {
        let line = format!("{:>9}: {message}", self.label);
        if self.bar.is_hidden() {
            eprintln!("{line}");
        } else {
            self.bar.println(line);
        }
    }

    fn is_cancelled(&self) -> bool {
        self.cancel.as_ref().is_some_and(CancelFlag::is_cancelled)
    }
}
