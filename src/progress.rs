//! Progress reporting and cancellation for long loops.
//!
//! Every long-running loop in Sylva (reading a 60-million-point cloud, extracting an archive,
//! training) takes a `&dyn Progress`. It reports the fraction done of the current task and
//! asks whether the work has been cancelled, so the worker can stop a stage promptly and the
//! API can show a progress bar. The trait lives in the lowest room so every other room may use
//! it without knowing about jobs or HTTP.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

/// Receives progress of one task and answers whether it should stop.
pub trait Progress: Send + Sync {
    /// Fraction of the current task done, in [0, 1]. Values outside are clamped by receivers;
    /// a receiver never shows a smaller value than one it already showed.
    fn set(&self, fraction: f64);

    /// A human-readable line for the job log (e.g. "read 1.2 M points").
    fn log(&self, _message: &str) {}

    /// True once the work has been cancelled; loops check it and return early.
    fn is_cancelled(&self) -> bool {
        false
    }
}

/// A progress sink that ignores everything and is never cancelled (tests, one-off tools).
#[derive(Debug, Default, Clone, Copy)]
pub struct NoProgress;

impl Progress for NoProgress {
    fn set(&self, _fraction: f64) {}
}

/// A progress sink that is cancelled from the start: for checking that a loop stops promptly.
#[derive(Debug, Default, Clone, Copy)]
pub struct Cancelled;

impl Progress for Cancelled {
    fn set(&self, _fraction: f64) {}
    fn is_cancelled(&self) -> bool {
        true
    }
}

/// A progress sink that ignores fractions and prints each log line to stderr, indented and
/// named by its label (the stage's name, or nothing): for benchmarks and examples, whose own
/// output is a table that a bar would garble. Never cancelled.
#[derive(Debug, Default, Clone, Copy)]
pub struct LogLines(pub &'static str);

impl Progress for LogLines {
    fn set(&self, _fraction: f64) {}
    fn log(&self, message: &str) {
        match self.0 {
            "" => eprintln!("    {message}"),
            label => eprintln!("    {label}: {message}"),
        }
    }
}

/// A shared cancellation flag: cheap to clone, set once, read from any thread.
#[derive(Debug, Default, Clone)]
pub struct CancelFlag(Arc<AtomicBool>);

impl CancelFlag {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn cancel(&self) {
        self.0.store(true, Ordering::SeqCst);
    }

    pub fn is_cancelled(&self) -> bool {
        self.0.load(Ordering::SeqCst)
    }
}

/// Maps progress of a sub-task onto a slice [start, start + span] of a parent task.
pub struct SubProgress<'a> {
    parent: &'a dyn Progress,
    start: f64,
    span: f64,
}

impl<'a> SubProgress<'a> {
    pub fn new(parent: &'a dyn Progress, start: f64, span: f64) -> Self {
        Self {
            parent,
            start,
            span,
        }
    }
}

impl Progress for SubProgress<'_> {
    fn set(&self, fraction: f64) {
        self.parent
            .set(self.start + self.span * fraction.clamp(0.0, 1.0));
    }
    fn log(&self, message: &str) {
        self.parent.log(message);
    }
    fn is_cancelled(&self) -> bool {
        self.parent.is_cancelled()
    }
}
