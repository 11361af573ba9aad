//! Structure from motion by COLMAP's command line: feature extraction, matching and the
//! incremental mapper, each a child process, as the paper ran COLMAP before its own method
//! (docs/method.md, Stage 0).
//!
//! Why a child process and not a library: COLMAP is C++ with no maintained Rust binding, and
//! its command line is the interface it documents and keeps stable; Debian ships it (3.8).
//! The runner
//! - starts each step in its own process group, with `QT_QPA_PLATFORM=offscreen` (COLMAP links
//!   Qt and asks for a display otherwise) and, on Linux, a parent-death signal, so that no
//!   COLMAP process outlives the worker that started it;
//! - reads the step's output line by line into the job's log file (`colmap.log`) and its
//!   progress ([`progress`]);
//! - ends the whole process group (SIGTERM, then SIGKILL after [`KILL_GRACE`]) when the job is
//!   cancelled or loses its lease (both arrive as [`Progress::is_cancelled`]), or when the
//!   time limit passes.

pub mod progress;

use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use serde::Serialize;

use crate::progress::{Progress, SubProgress};
pub use progress::Step;

/// How long a step has after SIGTERM before SIGKILL.
pub const KILL_GRACE: Duration = Duration::from_secs(3);

/// The environment variable naming the COLMAP program (default `colmap`, found on `PATH`).
/// A worker setting, never a job parameter: a job must not choose what the worker executes.
pub const COLMAP_ENV: &str = "SYLVA_COLMAP_BIN";

/// The COLMAP program this process runs: `$SYLVA_COLMAP`, else `colmap` on `PATH`.
pub fn colmap_program() -> PathBuf {
    std::env::var_os(COLMAP_ENV)
        .filter(|v| !v.is_empty())
        .map_or_else(|| PathBuf::from("colmap"), PathBuf::from)
}

/// How photos are paired for matching.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Matching {
    /// Every pair: n(n−1)/2 pairs, the most thorough.
    Exhaustive,
    /// Each photo with its nearest neighbours by EXIF GPS position.
    Spatial,
    /// Each photo with the next ones in name order (capture order).
    Sequential,
}

impl Matching {
    pub fn name(self) -> &'static str {
        match self {
            Matching::Exhaustive => "exhaustive",
            Matching::Spatial => "spatial",
            Matching::Sequential => "sequential",
        }
    }
}

/// One reconstruction's settings, as stage `sfm` resolved them.
#[derive(Debug, Clone)]
pub struct SfmOptions {
    /// The COLMAP program ([`colmap_program`]).
    pub program: PathBuf,
    /// The folder of photos (COLMAP's `--image_path`).
    pub photos_dir: PathBuf,
    /// How many photos there are (for the mapper's progress).
    pub photos: usize,
    /// A COLMAP camera model name (e.g. `SIMPLE_RADIAL`).
    pub camera_model: String,
    /// One camera shared by every photo.
    pub single_camera: bool,
    /// Longest photo side for feature extraction, pixels.
    pub max_image_size: u32,
    pub matching: Matching,
    /// Neighbours per photo for spatial matching.
    pub spatial_neighbours: u32,
    /// Neighbours in name order for sequential matching.
    pub sequential_overlap: u32,
    /// Smallest model the mapper keeps, photos.
    pub min_model_size: u32,
    /// CPU threads per step (0: all).
    pub threads: usize,
    /// Run on CUDA where COLMAP was built with it.
    pub use_gpu: bool,
    /// The whole reconstruction ends with [`SfmError::TimedOut`] past this.
    pub time_limit: Option<Duration>,
}

/// Why a reconstruction did not finish.
#[derive(Debug, thiserror::Error)]
pub enum SfmError {
    /// The COLMAP program cannot be started (a worker fault, not the job's).
    #[error(
        "COLMAP is not available on this worker: cannot run `{program}` ({detail}); install \
         Debian's package `colmap` (apt-get install colmap), or set {COLMAP_ENV} to the program"
    )]
    NotInstalled { program: String, detail: String },
    /// A step exited with an error; `tail` is the end of its output.
    #[error("COLMAP's {step} step failed ({status}): {tail}")]
    Failed {
        step: &'static str,
        status: String,
        tail: String,
    },
    /// The time limit passed during `step`.
    #[error("COLMAP's {step} step was stopped at the time limit of {limit_s} s")]
    TimedOut { step: &'static str, limit_s: u64 },
    #[error("cancelled")]
    Cancelled,
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
}

/// The time one step took, seconds.
#[derive(Debug, Clone, Serialize)]
pub struct StepTime {
    pub step: &'static str,
    pub seconds: f64,
}

/// What a finished reconstruction left.
#[derive(Debug, Clone)]
pub struct SfmRun {
    /// COLMAP's output folder: one model per sub-folder (`0`, `1`, …).
    pub sparse_root: PathBuf,
    /// The SQLite database of features and matches.
    pub database: PathBuf,
    pub steps: Vec<StepTime>,
    /// Features per photo, from the extractor's output.
    pub features: std::collections::BTreeMap<String, u64>,
}

/// Checks that the COLMAP program starts (`colmap help`), returning the first line it
/// prints (its version).
pub fn check_program(program: &Path) -> Result<String, SfmError> {
    let out = Command::new(program)
        .arg("help")
        .env("QT_QPA_PLATFORM", "offscreen")
        .stdin(Stdio::null())
        .output()
        .map_err(|e| SfmError::NotInstalled {
            program: program.display().to_string(),
            detail: e.to_string(),
        })?;
    let text = String::from_utf8_lossy(&out.stdout);
    Ok(text
        .lines()
        .find(|l| !l.trim().is_empty())
        .unwrap_or("")
        .trim()
        .to_string())
}

/// Runs extraction, matching and the mapper in `work` (which must exist), logging every
/// line COLMAP prints to `log`.
pub fn reconstruct(
    opts: &SfmOptions,
    work: &Path,
    log: &Path,
    progress: &dyn Progress,
) -> Result<SfmRun, SfmError> {
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| SfmError::Io { path, source }
    };
    let database = work.join("database.db");
    let sparse_root = work.join("sparse");
    std::fs::create_dir_all(&sparse_root).map_err(io(&sparse_root))?;
    let mut log_file = std::fs::File::create(log).map_err(io(log))?;
    let deadline = opts.time_limit.map(|t| (Instant::now() + t, t));
    let threads = if opts.threads == 0 {
        "-1".to_string()
    } else {
        opts.threads.to_string()
    };
    let gpu = if opts.use_gpu { "1" } else { "0" };
    let db = database.display().to_string();
    let photos = opts.photos_dir.display().to_string();
    let mut steps = Vec::new();
    let mut features = progress::FeatureCounts::default();
    for step in Step::ALL {
        let args: Vec<String> = match step {
            Step::Extract => vec![
                "feature_extractor".into(),
                "--database_path".into(),
                db.clone(),
                "--image_path".into(),
                photos.clone(),
                "--ImageReader.camera_model".into(),
                opts.camera_model.clone(),
                "--ImageReader.single_camera".into(),
                u8::from(opts.single_camera).to_string(),
                "--SiftExtraction.use_gpu".into(),
                gpu.into(),
                "--SiftExtraction.max_image_size".into(),
                opts.max_image_size.to_string(),
                "--SiftExtraction.num_threads".into(),
                threads.clone(),
            ],
            Step::Match => {
                let mut a = vec![
                    format!("{}_matcher", opts.matching.name()),
                    "--database_path".into(),
                    db.clone(),
                    "--SiftMatching.use_gpu".into(),
                    gpu.into(),
                    "--SiftMatching.num_threads".into(),
                    threads.clone(),
                ];
                match opts.matching {
                    Matching::Exhaustive => {}
                    Matching::Spatial => a.extend([
                        "--SpatialMatching.is_gps".into(),
                        "1".into(),
                        "--SpatialMatching.max_num_neighbors".into(),
                        opts.spatial_neighbours.to_string(),
                    ]),
                    Matching::Sequential => a.extend([
                        "--SequentialMatching.overlap".into(),
                        opts.sequential_overlap.to_string(),
                        "--SequentialMatching.quadratic_overlap".into(),
                        "1".into(),
                    ]),
                }
                a
            }
            Step::Map => vec![
                "mapper".into(),
                "--database_path".into(),
                db.clone(),
                "--image_path".into(),
                photos.clone(),
                "--output_path".into(),
                sparse_root.display().to_string(),
                "--Mapper.num_threads".into(),
                threads.clone(),
                "--Mapper.min_model_size".into(),
                opts.min_model_size.to_string(),
            ],
        };
        progress.log(&format!(
            "COLMAP {} ({})",
            step.name(),
            if step == Step::Match {
                opts.matching.name()
            } else {
                args[0].as_str()
            }
        ));
        let sub = SubProgress::new(progress, step.start(), step.weight());
        let started = Instant::now();
        run_step(
            &opts.program,
            &args,
            step,
            opts.photos,
            deadline,
            &mut log_file,
            &sub,
            &mut |line| {
                if step == Step::Extract {
                    features.feed(line);
                }
            },
        )?;
        let seconds = started.elapsed().as_secs_f64();
        progress.log(&format!("COLMAP {} took {seconds:.0} s", step.name()));
        steps.push(StepTime {
            step: step.name(),
            seconds,
        });
    }
    let _ = log_file.flush();
    Ok(SfmRun {
        sparse_root,
        database,
        steps,
        features: features.counts,
    })
}

/// How many of COLMAP's last lines an error quotes.
const TAIL_LINES: usize = 8;

/// The child's process group, ended on drop unless it has been reaped.
struct Group {
    child: Child,
    reaped: bool,
}

impl Group {
    /// SIGTERM to the whole group, SIGKILL after the grace period, then reap the child.
    fn end(&mut self) {
        if self.reaped {
            return;
        }
        let pgid = self.child.id() as libc::pid_t;
        // SAFETY: killpg only sends a signal; the group is the one this child leads
        // (process_group(0) at spawn), so nothing outside it is signalled.
        unsafe { libc::killpg(pgid, libc::SIGTERM) };
        let until = Instant::now() + KILL_GRACE;
        while Instant::now() < until {
            if matches!(self.child.try_wait(), Ok(Some(_))) {
                break;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        // SAFETY: as above; the group may hold grandchildren even once the leader exited.
        unsafe { libc::killpg(pgid, libc::SIGKILL) };
        let _ = self.child.wait();
        self.reaped = true;
    }
}

impl Drop for Group {
    fn drop(&mut self) {
        self.end();
    }
}

/// Runs one COLMAP step to its end, or ends its process group on cancellation or at the
/// deadline.
#[allow(clippy::too_many_arguments)]
fn run_step(
    program: &Path,
    args: &[String],
    step: Step,
    photos: usize,
    deadline: Option<(Instant, Duration)>,
    log: &mut std::fs::File,
    progress: &dyn Progress,
    on_line: &mut dyn FnMut(&str),
) -> Result<(), SfmError> {
    use std::os::unix::process::CommandExt;
    let mut cmd = Command::new(program);
    cmd.args(args)
        .env("QT_QPA_PLATFORM", "offscreen")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .process_group(0);
    #[cfg(target_os = "linux")]
    // SAFETY: prctl is async-signal-safe; it only asks the kernel to SIGKILL this child when
    // the thread that spawned it dies (a worker killed mid-stage), and touches no memory.
    unsafe {
        cmd.pre_exec(|| {
            libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
            Ok(())
        });
    }
    let child = cmd.spawn().map_err(|e| SfmError::NotInstalled {
        program: program.display().to_string(),
        detail: e.to_string(),
    })?;
    let mut group = Group {
        child,
        reaped: false,
    };
    let (tx, rx) = mpsc::channel::<String>();
    let mut readers = Vec::new();
    let stdout = group
        .child
        .stdout
        .take()
        .map(|s| Box::new(s) as Box<dyn std::io::Read + Send>);
    let stderr = group
        .child
        .stderr
        .take()
        .map(|s| Box::new(s) as Box<dyn std::io::Read + Send>);
    for pipe in [stdout, stderr].into_iter().flatten() {
        let tx = tx.clone();
        readers.push(std::thread::spawn(move || {
            for line in BufReader::new(pipe).lines() {
                let Ok(line) = line else { break };
                if tx.send(line).is_err() {
                    break;
                }
            }
        }));
    }
    drop(tx);
    let mut tail: std::collections::VecDeque<String> = std::collections::VecDeque::new();
    let mut last_logged = Instant::now();
    let mut done = 0.0f64;
    loop {
        match rx.recv_timeout(Duration::from_millis(200)) {
            Ok(line) => {
                let _ = writeln!(log, "{line}");
                on_line(&line);
                if let Some(f) = progress::fraction(step, &line, photos) {
                    done = done.max(f);
                    progress.set(done);
                    if last_logged.elapsed() > Duration::from_secs(30) {
                        progress.log(&format!("COLMAP {}: {:.0}%", step.name(), done * 100.0));
                        last_logged = Instant::now();
                    }
                }
                if !line.trim().is_empty() {
                    tail.push_back(line);
                    if tail.len() > TAIL_LINES {
                        tail.pop_front();
                    }
                }
            }
            Err(mpsc::RecvTimeoutError::Timeout) => {}
            // Both pipes closed: the step is ending.
            Err(mpsc::RecvTimeoutError::Disconnected) => break,
        }
        if progress.is_cancelled() {
            group.end();
            return Err(SfmError::Cancelled);
        }
        if let Some((at, limit)) = deadline
            && Instant::now() >= at
        {
            group.end();
            return Err(SfmError::TimedOut {
                step: step.name(),
                limit_s: limit.as_secs(),
            });
        }
    }
    for r in readers {
        let _ = r.join();
    }
    let status = group.child.wait().map_err(|source| SfmError::Io {
        path: program.to_path_buf(),
        source,
    })?;
    group.reaped = true;
    if status.success() {
        Ok(())
    } else {
        Err(SfmError::Failed {
            step: step.name(),
            status: status.to_string(),
            tail: tail.into_iter().collect::<Vec<_>>().join(" | "),
        })
    }
}

#[cfg(test)]
mod tests;
