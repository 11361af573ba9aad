//! The runner against a stand-in for COLMAP: a shell script that prints COLMAP's progress
//! lines, fails, or hangs with a child of its own, so cancellation, the time limit and the
//! errors are tested without COLMAP installed.

use std::os::unix::fs::PermissionsExt;
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, Ordering};

use super::*;

fn script(dir: &Path, body: &str) -> PathBuf {
    let path = dir.join("fake-colmap");
    std::fs::write(&path, format!("#!/bin/sh\n{body}\n")).expect("write script");
    std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o755)).expect("chmod");
    path
}

fn options(program: PathBuf, photos_dir: &Path) -> SfmOptions {
    SfmOptions {
        program,
        photos_dir: photos_dir.to_path_buf(),
        photos: 4,
        camera_model: "SIMPLE_RADIAL".into(),
        single_camera: true,
        max_image_size: 2000,
        matching: Matching::Exhaustive,
        spatial_neighbours: 20,
        sequential_overlap: 10,
        min_model_size: 3,
        threads: 0,
        use_gpu: false,
        time_limit: None,
    }
}

/// Records fractions and log lines; cancelled once `cancel_after` fractions arrived... or
/// when told.
#[derive(Default)]
struct Recorder {
    fractions: Mutex<Vec<f64>>,
    lines: Mutex<Vec<String>>,
    cancelled: AtomicBool,
}

impl Progress for Recorder {
    fn set(&self, f: f64) {
        self.fractions.lock().expect("lock").push(f);
    }
    fn log(&self, m: &str) {
        self.lines.lock().expect("lock").push(m.to_string());
    }
    fn is_cancelled(&self) -> bool {
        self.cancelled.load(Ordering::SeqCst)
    }
}

/// Whether a process with this id still runs (a zombie counts as gone).
fn alive(pid: i32) -> bool {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
    // The state is the field after the command name in parentheses.
    let state = stat.rsplit_once(") ").map(|(_, r)| r.chars().next());
    matches!(state, Some(Some(c)) if c != 'Z' && c != 'X')
}

#[test]
fn progress_runs_through_the_three_steps_and_each_is_timed() {
    let dir = tempfile::tempdir().expect("tmp");
    let program = script(
        dir.path(),
        r#"case "$1" in
  feature_extractor) echo "Processed file [1/2]"; echo "  Name:  a.jpg"; echo "  Features: 12"; echo "Processed file [2/2]" >&2 ;;
  exhaustive_matcher) echo "Matching block [1/2, 1/2] in 1.0s"; echo "Matching block [2/2, 2/2] in 1.0s" ;;
  mapper) echo "Registering image #3 (2)"; echo "Registering image #1 (4)" ;;
esac"#,
    );
    let rec = Recorder::default();
    let log = dir.path().join("colmap.log");
    let run = reconstruct(&options(program, dir.path()), dir.path(), &log, &rec).expect("runs");
    assert_eq!(
        run.steps.iter().map(|s| s.step).collect::<Vec<_>>(),
        ["features", "matching", "mapper"]
    );
    assert_eq!(run.features.get("a.jpg"), Some(&12));
    let f = rec.fractions.lock().expect("lock").clone();
    assert!(f.windows(2).all(|w| w[1] >= w[0] - 1e-12), "{f:?}");
    assert!(
        (f.last().copied().unwrap_or(0.0) - 1.0).abs() < 1e-9,
        "{f:?}"
    );
    // The extractor's second line came on stderr and still counted.
    assert!(f.iter().any(|x| (x - 0.2).abs() < 1e-9), "{f:?}");
    let text = std::fs::read_to_string(&log).expect("log");
    assert!(text.contains("Registering image #1 (4)"));
}

#[test]
fn a_failing_step_quotes_the_end_of_its_output() {
    let dir = tempfile::tempdir().expect("tmp");
    let program = script(
        dir.path(),
        r#"echo "ERROR: failed to create sparse model" >&2; exit 1"#,
    );
    let e = reconstruct(
        &options(program, dir.path()),
        dir.path(),
        &dir.path().join("log"),
        &Recorder::default(),
    )
    .expect_err("fails");
    let text = e.to_string();
    assert!(
        matches!(
            e,
            SfmError::Failed {
                step: "features",
                ..
            }
        ),
        "{text}"
    );
    assert!(text.contains("failed to create sparse model"), "{text}");
}

#[test]
fn a_missing_program_names_the_package() {
    let dir = tempfile::tempdir().expect("tmp");
    let program = dir.path().join("no-such-colmap");
    let e = check_program(&program).expect_err("missing");
    assert!(matches!(e, SfmError::NotInstalled { .. }));
    assert!(e.to_string().contains("apt-get install colmap"), "{e}");
    let e = reconstruct(
        &options(program, dir.path()),
        dir.path(),
        &dir.path().join("log"),
        &Recorder::default(),
    )
    .expect_err("missing");
    assert!(matches!(e, SfmError::NotInstalled { .. }), "{e}");
}

/// A step that hangs with a child of its own: cancellation ends both, promptly.
#[test]
fn cancellation_leaves_no_process_of_the_step_behind() {
    let dir = tempfile::tempdir().expect("tmp");
    let pids = dir.path().join("pids");
    let program = script(
        dir.path(),
        &format!(
            "sleep 300 &\necho $$ $! > {}\necho 'Processed file [1/4]'\nwait",
            pids.display()
        ),
    );
    let rec = std::sync::Arc::new(Recorder::default());
    let stopper = {
        let rec = rec.clone();
        let pids = pids.clone();
        std::thread::spawn(move || {
            for _ in 0..200 {
                if pids.is_file() {
                    break;
                }
                std::thread::sleep(Duration::from_millis(25));
            }
            std::thread::sleep(Duration::from_millis(200));
            rec.cancelled.store(true, Ordering::SeqCst);
        })
    };
    let started = Instant::now();
    let e = reconstruct(
        &options(program, dir.path()),
        dir.path(),
        &dir.path().join("log"),
        rec.as_ref(),
    )
    .expect_err("cancelled");
    let _ = stopper.join();
    assert!(matches!(e, SfmError::Cancelled), "{e}");
    assert!(started.elapsed() < Duration::from_secs(20));
    let text = std::fs::read_to_string(&pids).expect("pids");
    let ids: Vec<i32> = text
        .split_whitespace()
        .filter_map(|t| t.parse().ok())
        .collect();
    assert_eq!(ids.len(), 2, "{text}");
    // The orphaned `sleep` is reaped by init a moment later.
    let until = Instant::now() + Duration::from_secs(5);
    while ids.iter().any(|&p| alive(p)) && Instant::now() < until {
        std::thread::sleep(Duration::from_millis(50));
    }
    for p in ids {
        assert!(!alive(p), "process {p} of the cancelled step still runs");
    }
}

#[test]
fn the_time_limit_stops_a_step() {
    let dir = tempfile::tempdir().expect("tmp");
    let program = script(dir.path(), "exec sleep 300");
    let mut opts = options(program, dir.path());
    opts.time_limit = Some(Duration::from_millis(300));
    let e = reconstruct(
        &opts,
        dir.path(),
        &dir.path().join("log"),
        &Recorder::default(),
    )
    .expect_err("timed out");
    assert!(
        matches!(
            e,
            SfmError::TimedOut {
                step: "features",
                ..
            }
        ),
        "{e}"
    );
}
