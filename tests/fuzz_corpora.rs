//! The fuzz corpora replayed as ordinary tests: every input under `fuzz/corpus/<target>/` (the
//! seeds and what the fuzzer kept) and `fuzz/regressions/<target>/` (each crash, hang or
//! over-allocation it found, kept after the fix) through `sylva::pipeline::fuzz::run`. A reader
//! may refuse an input; it may not panic, and it must answer within a minute (a hang guard,
//! not a speed claim: the fuzzer's own limit is 10 s an input).

use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::Duration;

use sylva::pipeline::fuzz::{TARGETS, run};

/// Longest an input may take before it counts as a hang.
const HANG: Duration = Duration::from_secs(60);

fn fuzz_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz")
}

/// The files of `dir`, sorted; none when it does not exist.
fn inputs(dir: &Path) -> Vec<PathBuf> {
    let mut out: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|rd| {
            rd.filter_map(Result::ok)
                .map(|e| e.path())
                .filter(|p| p.is_file())
                .collect()
        })
        .unwrap_or_default();
    out.sort();
    out
}

/// Runs `target` on `input` in a thread of its own: `Err` with what went wrong on a panic or
/// past [`HANG`].
fn replay(target: &'static str, input: &Path) -> Result<(), String> {
    let bytes = std::fs::read(input).map_err(|e| format!("{}: {e}", input.display()))?;
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let scratch = tempfile::tempdir().expect("scratch");
        let outcome = std::panic::catch_unwind(|| {
            let _ = run(target, &bytes, scratch.path());
        });
        let _ = tx.send(outcome.map_err(|p| {
            p.downcast_ref::<String>()
                .cloned()
                .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_else(|| "a panic".into())
        }));
    });
    match rx.recv_timeout(HANG) {
        Ok(Ok(())) => Ok(()),
        Ok(Err(panic)) => Err(format!("{target} panicked on {}: {panic}", input.display())),
        Err(_) => Err(format!(
            "{target} took over {HANG:?} on {}",
            input.display()
        )),
    }
}

#[test]
fn every_target_has_a_seed_corpus() {
    let missing: Vec<&str> = TARGETS
        .iter()
        .copied()
        .filter(|t| inputs(&fuzz_dir().join("corpus").join(t)).is_empty())
        .collect();
    assert!(
        missing.is_empty(),
        "no seeds under fuzz/corpus/ for {missing:?} (fuzz/src/bin/seed.rs writes them)"
    );
}

/// Each target accepts at least one of its seeds, so the fuzzer starts inside the format
/// rather than at its first check.
#[test]
fn every_target_accepts_one_of_its_seeds() {
    let scratch = tempfile::tempdir().expect("scratch");
    let refused: Vec<String> = TARGETS
        .iter()
        .filter(|t| {
            !inputs(&fuzz_dir().join("corpus").join(t)).iter().any(|p| {
                let bytes = std::fs::read(p).expect("seed");
                run(t, &bytes, scratch.path()).is_ok()
            })
        })
        .map(|t| t.to_string())
        .collect();
    assert!(refused.is_empty(), "no seed accepted by {refused:?}");
}

#[test]
fn every_corpus_and_regression_input_is_refused_or_read_without_a_panic_or_a_hang() {
    let mut faults = Vec::new();
    let mut n = 0;
    for &target in TARGETS {
        for kind in ["corpus", "regressions"] {
            for input in inputs(&fuzz_dir().join(kind).join(target)) {
                n += 1;
                if let Err(e) = replay(target, &input) {
                    faults.push(e);
                }
            }
        }
    }
    assert!(n > 0, "no inputs under {}", fuzz_dir().display());
    assert!(
        faults.is_empty(),
        "{} of {n} inputs:\n{}",
        faults.len(),
        faults.join("\n")
    );
}
