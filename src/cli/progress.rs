//! Progress printers on stderr: a bar per stage for `sylva run`, a line for one-off commands.

use super::*;

/// A one-line progress bar on stderr for `sylva run`.
pub(super) struct ConsoleProgress {
    pub(super) stage: Stage,
    pub(super) cancel: CancelFlag,
    pub(super) last: Mutex<(Instant, f64)>,
}

impl Progress for ConsoleProgress {
    fn set(&self, fraction: f64) {
        let f = fraction.clamp(0.0, 1.0);
        if let Ok(mut last) = self.last.lock()
            && f > last.1
            && (last.0.elapsed() > Duration::from_millis(100) || f >= 1.0)
        {
            *last = (Instant::now(), f);
            let filled = (f * 30.0).round() as usize;
            eprint!(
                "\r{:>9} [{}{}] {:>3.0}%",
                self.stage.name(),
                "#".repeat(filled),
                ".".repeat(30 - filled),
                f * 100.0
            );
        }
    }
    fn log(&self, message: &str) {
        eprintln!("\r{:>9}: {message}", self.stage.name());
    }
    fn is_cancelled(&self) -> bool {
        self.cancel.is_cancelled()
    }
}

/// A progress line on stderr for one-off commands.
pub(super) struct LineProgress {
    label: &'static str,
    last: Mutex<(Instant, f64)>,
}

impl LineProgress {
    pub(super) fn new(label: &'static str) -> Self {
        Self {
            label,
            last: Mutex::new((Instant::now(), -1.0)),
        }
    }
}

impl Progress for LineProgress {
    fn set(&self, fraction: f64) {
        if let Ok(mut last) = self.last.lock()
            && fraction > last.1 + 0.01
            && last.0.elapsed() > Duration::from_millis(200)
        {
            *last = (Instant::now(), fraction);
            eprint!(
                "\r{}: {:>3.0}%",
                self.label,
                fraction.clamp(0.0, 1.0) * 100.0
            );
        }
    }
    fn log(&self, message: &str) {
        eprintln!("\r{}: {message}", self.label);
    }
}
