//! Workers: claim jobs from the queue and run their stages with progress, heartbeats,
//! cancellation and checkpoints.
//!
//! One worker slot runs one job at a time. While a stage runs on a blocking thread, a
//! heartbeat task renews the lease every [`tick`], publishes progress (never lower than
//! before), flushes the stage's log lines and learns whether the user cancelled or another
//! worker took the job over. Either stops the stage through its cancellation flag. Stages
//! that use the GPU also hold a slot of the process-wide GPU semaphore.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use serde_json::json;
use tokio::sync::{Notify, Semaphore, watch};

use crate::config::WorkerArgs;
use crate::io::archive::ExtractLimits;
use crate::jobs::{Claim, DbError, Heartbeat, JobStore, RunEnd, UploadKind};
use crate::pipeline::{self, PipelineParams, Stage, StageError, StageInputs};
use crate::progress::{CancelFlag, Progress};
use crate::store::BlobStore;

/// What runs the worker loops; cheap to clone.
#[derive(Clone)]
pub struct WorkerPool {
    db: JobStore,
    blobs: BlobStore,
    args: WorkerArgs,
    gpu: Arc<Semaphore>,
    wake: Arc<Notify>,
    host: String,
}

/// The heartbeat period: a third of the lease, at most half a second so progress and
/// cancellation are seen promptly.
pub fn tick(lease: Duration) -> Duration {
    (lease / 3).min(Duration::from_millis(500))
}

/// Progress of the running stage, shared between the stage thread and the heartbeat task.
struct StageProgress {
    fraction_bits: AtomicU64,
    lines: Mutex<Vec<String>>,
    cancel: CancelFlag,
    /// `--debug-crash-at` for this stage: the process kills itself once the stage reports
    /// this fraction (tests only; `None` in production).
    crash_at: Option<(Stage, f64)>,
}

impl StageProgress {
    fn fraction(&self) -> f64 {
        f64::from_bits(self.fraction_bits.load(Ordering::Relaxed))
    }
}

impl Progress for StageProgress {
    fn set(&self, fraction: f64) {
        let f = fraction.clamp(0.0, 1.0);
        if let Some((stage, at)) = self.crash_at
            && f >= at
        {
            crash_now(stage, f);
        }
        let _ = self
            .fraction_bits
            .fetch_update(Ordering::Relaxed, Ordering::Relaxed, |old| {
                (f > f64::from_bits(old)).then_some(f.to_bits())
            });
    }
    fn log(&self, message: &str) {
        if let Ok(mut lines) = self.lines.lock() {
            lines.push(message.to_string());
        }
    }
    fn is_cancelled(&self) -> bool {
        self.cancel.is_cancelled()
    }
}

/// Where `--debug-crash-at` kills this process inside `stage` (builds with the
/// `fault-injection` feature only; `None` otherwise).
fn crash_point(args: &WorkerArgs, stage: Stage) -> Option<(Stage, f64)> {
    #[cfg(feature = "fault-injection")]
    {
        args.debug_crash_at
            .filter(|c| c.stage == stage)
            .map(|c| (c.stage, c.fraction))
    }
    #[cfg(not(feature = "fault-injection"))]
    {
        let _ = (args, stage);
        None
    }
}

/// `--debug-crash-at`: kills this process with SIGKILL, as the kernel's OOM killer or a
/// power cut would stop it (no unwinding, no destructors, no flush), from inside a stage.
fn crash_now(stage: Stage, fraction: f64) -> ! {
    eprintln!("sylva: --debug-crash-at: SIGKILL inside stage {stage} at progress {fraction:.3}");
    // SAFETY: kill(2) with our own pid and a valid signal number has no memory effects.
    unsafe {
        libc::kill(libc::getpid(), libc::SIGKILL);
    }
    // SIGKILL cannot be caught; should it somehow not land, never carry on as if nothing
    // happened.
    std::process::abort()
}

/// Job progress once `stage` is `fraction` done, given the stages the job runs.
fn job_progress(stages: &[Stage], stage: Stage, fraction: f64) -> f64 {
    let total: f64 = stages.iter().map(|s| s.weight()).sum();
    let before: f64 = stages
        .iter()
        .filter(|s| **s < stage)
        .map(|s| s.weight())
        .sum();
    ((before + stage.weight() * fraction) / total.max(1e-9)).clamp(0.0, 1.0)
}

/// Each input's local path (a file, or an archive's unpacked folder) and the name its owner
/// gave the upload.
type InputNames = Vec<(std::path::PathBuf, String)>;

/// `text` (a stage's error) with the server's paths of the inputs replaced by the names their
/// owners gave them: a problem names the caller's file, never a path on the server.
fn name_inputs(text: &str, names: &InputNames) -> String {
    let mut out = text.to_string();
    for (path, name) in names {
        let p = path.display().to_string();
        if p.is_empty() {
            continue;
        }
        // Inside an unpacked archive: `<dir>/sparse/0/x` becomes `<name>: sparse/0/x`.
        out = out.replace(&format!("{p}/"), &format!("{name}: "));
        out = out.replace(&p, name);
    }
    out
}

/// A problem+json object for a failed stage.
fn stage_problem(stage: Stage, e: &StageError, names: &InputNames) -> serde_json::Value {
    let (slug, title, status) = match e {
        StageError::Device(_) => ("device-unavailable", "GPU unavailable", 503),
        StageError::Unavailable(_) => ("tool-unavailable", "Tool unavailable", 503),
        _ if e.is_storage_full() => ("insufficient-storage", "Disk full", 507),
        _ if e.is_input_fault() => ("input-unusable", "Input unusable", 422),
        _ => ("stage-failed", "Stage failed", 500),
    };
    let mut problem = json!({
        "type": format!("urn:sylva:problem:{slug}"),
        "title": title,
        "status": status,
        "detail": name_inputs(&e.to_string(), names),
        "stage": stage.name(),
    });
    if let StageError::Refused { candidates, .. } = e {
        problem["candidates"] = json!(candidates);
    }
    problem
}

enum Outcome {
    Done,
    /// The run ended (failed, canceled or lost its lease); stop working on the job.
    Stop,
}

impl WorkerPool {
    pub fn new(db: JobStore, blobs: BlobStore, args: WorkerArgs, wake: Arc<Notify>) -> Self {
        let host = std::fs::read_to_string("/etc/hostname")
            .map(|h| h.trim().to_string())
            .unwrap_or_else(|_| "localhost".into());
        Self {
            db,
            blobs,
            gpu: Arc::new(Semaphore::new(args.gpu_slots.max(1) as usize)),
            args,
            wake,
            host,
        }
    }

    pub fn host(&self) -> &str {
        &self.host
    }

    /// Start-up recovery: jobs held by dead worker processes of this host become claimable
    /// at once. Call before [`WorkerPool::run`].
    pub async fn recover(&self) {
        match self.db.recover(&self.host, self.args.lease() * 4).await {
            Ok(n) if n > 0 => tracing::warn!(jobs = n, "recovered jobs of a crashed process"),
            Ok(_) => {}
            Err(e) => tracing::error!(error = %e, "start-up recovery failed"),
        }
    }

    /// Runs `args.workers` worker loops until `shutdown` turns true. Where the database
    /// announces new jobs (PostgreSQL), idle loops wake on the announcement; they poll every
    /// `poll_ms` regardless.
    pub async fn run(self, shutdown: watch::Receiver<bool>) {
        let listener = self.db.listen_for_work(self.wake.clone());
        let mut handles = Vec::new();
        for slot in 0..self.args.workers {
            let me = self.clone();
            let rx = shutdown.clone();
            let id = format!(
                "{}-{}-{slot}-{}",
                self.host,
                std::process::id(),
                &uuid::Uuid::new_v4().simple().to_string()[..8]
            );
            handles.push(tokio::spawn(async move { me.slot_loop(id, rx).await }));
        }
        for h in handles {
            let _ = h.await;
        }
        if let Some(l) = listener {
            l.abort();
        }
    }

    async fn slot_loop(self, id: String, mut shutdown: watch::Receiver<bool>) {
        tracing::info!(worker = %id, "worker started");
        let poll = Duration::from_millis(self.args.poll_ms.max(10));
        while !*shutdown.borrow() {
            if let Err(e) = self
                .db
                .register_worker(&id, &self.host, std::process::id())
                .await
            {
                tracing::warn!(error = %e, "worker registration failed");
            }
            match self
                .db
                .claim(&id, self.args.lease(), self.args.max_attempts.max(1) as i64)
                .await
            {
                Ok(Some(claim)) => {
                    let span =
                        tracing::info_span!("job", id = %claim.job_id, attempt = claim.attempt);
                    let _ = tracing::Instrument::instrument(self.run_job(&id, claim), span).await;
                    continue;
                }
                Ok(None) => {}
                Err(e) => tracing::warn!(error = %e, "claim failed"),
            }
            tokio::select! {
                _ = tokio::time::sleep(poll) => {}
                _ = self.wake.notified() => {}
                _ = shutdown.changed() => {}
            }
        }
        let _ = self.db.unregister_worker(&id).await;
        tracing::info!(worker = %id, "worker stopped");
    }

    async fn log(&self, job: &str, level: &str, stage: Option<Stage>, message: &str) {
        if let Err(e) = self
            .db
            .append_log(job, level, stage.map(|s| s.name()), message)
            .await
        {
            tracing::warn!(error = %e, "job log write failed");
        }
    }

    async fn inputs(&self, claim: &Claim) -> Result<(StageInputs, InputNames), String> {
        let mut paths = Vec::new();
        let mut names = InputNames::new();
        for (kind, id) in claim.inputs.all() {
            let up = self
                .db
                .get_upload(id)
                .await
                .map_err(|e| e.to_string())?
                .ok_or_else(|| format!("input upload {id} no longer exists"))?;
            // The API already checked archives against its limits; these only guard the
            // re-extraction on a machine that has not seen the upload yet.
            let limits = ExtractLimits {
                max_entries: u64::MAX,
                max_unpacked_bytes: u64::MAX,
                max_ratio: f64::INFINITY,
            };
            let unpack = kind.is_archive().then_some(&limits);
            let path = self
                .blobs
                .local_input(id, &up.filename, unpack)
                .await
                .map_err(|e| format!("input upload {id} ({}): {e}", up.filename))?;
            names.push((path.clone(), up.filename.clone()));
            paths.push((kind, path));
        }
        let get = |k: UploadKind| {
            paths
                .iter()
                .find(|(kk, _)| *kk == k)
                .map(|(_, p)| p.clone())
        };
        Ok((
            StageInputs {
                lidar: get(UploadKind::Lidar).ok_or("no lidar input")?,
                colmap: get(UploadKind::Colmap),
                photos: get(UploadKind::Photos),
                control_points: get(UploadKind::ControlPoints),
                field_dbh: get(UploadKind::FieldDbh),
            },
            names,
        ))
    }

    async fn run_job(&self, worker: &str, claim: Claim) {
        let job = claim.job_id.clone();
        let fail = |detail: String| RunEnd::Failed {
            stage: None,
            problem: json!({
                "type": "urn:sylva:problem:job-invalid",
                "title": "Job cannot run",
                "status": 422,
                "detail": detail,
            }),
        };
        let params: PipelineParams = match serde_json::from_value(claim.params.clone()) {
            Ok(p) => p,
            Err(e) => {
                let _ = self
                    .db
                    .finish_job(&job, &claim.token, &fail(format!("params: {e}")))
                    .await;
                return;
            }
        };
        let (inputs, names) = match self.inputs(&claim).await {
            Ok(i) => i,
            Err(e) => {
                let _ = self.db.finish_job(&job, &claim.token, &fail(e)).await;
                return;
            }
        };
        let stages = params.stages();
        let first = stages
            .iter()
            .find(|s| !claim.done.iter().any(|d| d == s.name()));
        let msg = match (claim.attempt, first) {
            (1, _) => format!("claimed by worker {worker}"),
            (n, Some(s)) => format!("resumed at stage {s} by worker {worker} (attempt {n})"),
            (n, None) => format!("resumed by worker {worker} (attempt {n})"),
        };
        tracing::info!("{msg}");
        self.log(&job, "info", None, &msg).await;
        let work_dir = self.blobs.job_dir(&job);
        if let Err(e) = std::fs::create_dir_all(&work_dir) {
            let _ = self
                .db
                .finish_job(
                    &job,
                    &claim.token,
                    &fail(format!("cannot create the job folder: {e}")),
                )
                .await;
            return;
        }
        match self.blobs.pull_stages(&job, &claim.done).await {
            Ok(0) => {}
            Ok(n) => {
                let msg = format!("fetched {n} finished-stage file(s) from the object store");
                self.log(&job, "info", None, &msg).await;
            }
            Err(e) => {
                // The store may be briefly away: give the job back for another try rather
                // than failing work that is already done.
                tracing::warn!(error = %e, "cannot fetch finished stages; the job will be re-claimed");
                return;
            }
        }
        for &stage in &stages {
            if claim.done.iter().any(|d| d == stage.name()) {
                continue;
            }
            match self
                .run_stage(
                    &claim,
                    stage,
                    &stages,
                    (&inputs, &names),
                    &params,
                    &work_dir,
                )
                .await
            {
                Outcome::Done => {}
                Outcome::Stop => return,
            }
        }
        match self
            .db
            .finish_job(&job, &claim.token, &RunEnd::Succeeded)
            .await
        {
            Ok(()) => self.log(&job, "info", None, "job succeeded").await,
            Err(e) => tracing::warn!(error = %e, "could not mark the job succeeded"),
        }
    }

    #[allow(clippy::too_many_arguments)]
    async fn run_stage(
        &self,
        claim: &Claim,
        stage: Stage,
        stages: &[Stage],
        (inputs, names): (&StageInputs, &InputNames),
        params: &PipelineParams,
        work_dir: &std::path::Path,
    ) -> Outcome {
        let job = &claim.job_id;
        match self
            .db
            .start_stage(job, &claim.token, stage, claim.attempt)
            .await
        {
            Ok(()) => {}
            Err(DbError::Fenced) => return Outcome::Stop,
            Err(e) => {
                tracing::error!(error = %e, "cannot start stage");
                return Outcome::Stop;
            }
        }
        self.log(job, "info", Some(stage), &format!("stage {stage} started"))
            .await;
        let progress = Arc::new(StageProgress {
            fraction_bits: AtomicU64::new(0f64.to_bits()),
            lines: Mutex::new(Vec::new()),
            cancel: CancelFlag::new(),
            crash_at: crash_point(&self.args, stage),
        });

        let heartbeat = StageHeartbeat::start(
            &self.db,
            claim,
            self.args.lease(),
            stage,
            stages,
            progress.clone(),
        );
        let gpu_slot = self.gpu_slot(job, stage, &progress.cancel).await;

        // The runtime limit: a watchdog cancels the stage once it has run too long.
        let limit = self
            .args
            .max_stage_runtime(stage.name())
            .unwrap_or(Duration::from_secs(172_800));
        let timed_out = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let watchdog = {
            let (timed_out, progress) = (timed_out.clone(), progress.clone());
            tokio::spawn(async move {
                tokio::time::sleep(limit).await;
                timed_out.store(true, Ordering::SeqCst);
                progress.cancel.cancel();
            })
        };
        let pause = self
            .args
            .debug_stage_pause(stage.name())
            .unwrap_or(Duration::ZERO);
        if !pause.is_zero() {
            tokio::select! {
                _ = tokio::time::sleep(pause) => {}
                _ = wait_cancel(&progress.cancel) => {}
            }
        }
        let result = if progress.cancel.is_cancelled() {
            Err(StageError::Cancelled)
        } else {
            let (inputs, params, work_dir) =
                (inputs.clone(), params.clone(), work_dir.to_path_buf());
            let p = progress.clone();
            tokio::task::spawn_blocking(move || {
                pipeline::execute_stage(stage, &inputs, &work_dir, &params, p.as_ref())
            })
            .await
            .unwrap_or_else(|join| {
                Err(StageError::Input(format!(
                    "internal error: stage {stage} crashed: {join}"
                )))
            })
        };
        watchdog.abort();
        let lost = heartbeat.stop().await;
        drop(gpu_slot);

        if lost {
            tracing::warn!("lease lost during stage {stage}; another worker owns the job");
            return Outcome::Stop;
        }
        let timed_out = timed_out.load(Ordering::SeqCst).then_some(limit);
        self.settle(
            claim,
            stage,
            (stages, names),
            work_dir,
            result,
            timed_out,
            &progress.cancel,
        )
        .await
    }

    /// A GPU slot for `stage` when it uses the GPU, waiting (and saying so in the job's log)
    /// while every slot of this worker is busy; `None` for a CPU stage or on cancel.
    async fn gpu_slot(
        &self,
        job: &str,
        stage: Stage,
        cancel: &CancelFlag,
    ) -> Option<tokio::sync::OwnedSemaphorePermit> {
        if !stage.uses_gpu() {
            return None;
        }
        if let Ok(p) = self.gpu.clone().try_acquire_owned() {
            return Some(p);
        }
        self.log(
            job,
            "info",
            Some(stage),
            "waiting for a GPU slot (every slot of this worker is busy)",
        )
        .await;
        let p = tokio::select! {
            p = self.gpu.clone().acquire_owned() => p.ok(),
            _ = wait_cancel(cancel) => None,
        };
        if p.is_some() {
            self.log(job, "info", Some(stage), "GPU slot acquired")
                .await;
        }
        p
    }

    /// Records how `stage` ended: its checkpoint once its outputs are in the object store, or
    /// the job's end: timed out (`timed_out` holds the limit it passed), canceled or failed.
    #[allow(clippy::too_many_arguments)]
    async fn settle(
        &self,
        claim: &Claim,
        stage: Stage,
        (stages, names): (&[Stage], &InputNames),
        work_dir: &std::path::Path,
        result: Result<pipeline::StageOutcome, StageError>,
        timed_out: Option<Duration>,
        cancel: &CancelFlag,
    ) -> Outcome {
        let job = &claim.job_id;
        let token = &claim.token;
        // With an object store the outputs go there before the stage counts as done.
        let result = match result {
            Ok(outcome) => match self.blobs.push_stage(job, stage.name()).await {
                Ok(()) => Ok(outcome),
                Err(e) => Err(StageError::Io(crate::io::IoError::Io {
                    path: work_dir.join(stage.name()),
                    source: std::io::Error::other(format!(
                        "the stage's outputs could not be copied to the object store: {e}"
                    )),
                })),
            },
            Err(e) => Err(e),
        };
        match result {
            Ok(outcome) => {
                let jp = job_progress(stages, stage, 1.0);
                match self
                    .db
                    .finish_stage(job, token, stage, &outcome.report, &outcome.files, jp)
                    .await
                {
                    Ok(()) => {
                        self.log(job, "info", Some(stage), &format!("stage {stage} finished"))
                            .await;
                        Outcome::Done
                    }
                    Err(e) => {
                        tracing::warn!(error = %e, "checkpoint refused");
                        Outcome::Stop
                    }
                }
            }
            Err(_) if let Some(limit) = timed_out => {
                let detail = format!(
                    "stage {stage} ran longer than its limit of {} s and was stopped \
                     (--max-stage-secs)",
                    limit.as_secs()
                );
                tracing::warn!("{detail}");
                let end = RunEnd::Failed {
                    stage: Some(stage.name().into()),
                    problem: json!({
                        "type": "urn:sylva:problem:stage-timeout",
                        "title": "Stage timed out",
                        "status": 500,
                        "detail": detail,
                        "stage": stage.name(),
                    }),
                };
                self.end_in_stage(job, token, stage, "error", &detail, &end)
                    .await
            }
            Err(StageError::Cancelled) | Err(_) if cancel.is_cancelled() => {
                let end = RunEnd::Canceled {
                    stage: Some(stage.name().into()),
                };
                let line = format!("canceled during stage {stage}");
                self.end_in_stage(job, token, stage, "info", &line, &end)
                    .await
            }
            Err(e) => {
                tracing::warn!(error = %e, "stage {stage} failed");
                let end = RunEnd::Failed {
                    stage: Some(stage.name().into()),
                    problem: stage_problem(stage, &e, names),
                };
                let line = format!(
                    "stage {stage} failed: {}",
                    name_inputs(&e.to_string(), names)
                );
                self.end_in_stage(job, token, stage, "error", &line, &end)
                    .await
            }
        }
    }

    /// Ends the run of `job` in `stage` as `end`, after logging `line` at `level`.
    async fn end_in_stage(
        &self,
        job: &str,
        token: &str,
        stage: Stage,
        level: &str,
        line: &str,
        end: &RunEnd,
    ) -> Outcome {
        self.log(job, level, Some(stage), line).await;
        let _ = self.db.finish_job(job, token, end).await;
        Outcome::Stop
    }
}

/// Resolves once `flag` is set (checked every 20 ms).
/// The heartbeat of one running stage: every tick it renews the lease, reports progress,
/// copies the stage's log lines to the job's log and picks up a cancel request; it cancels
/// the stage when the lease is lost.
struct StageHeartbeat {
    stop: watch::Sender<bool>,
    task: tokio::task::JoinHandle<()>,
    lost: Arc<std::sync::atomic::AtomicBool>,
}

impl StageHeartbeat {
    fn start(
        db: &JobStore,
        claim: &Claim,
        lease: Duration,
        stage: Stage,
        stages: &[Stage],
        progress: Arc<StageProgress>,
    ) -> Self {
        let (stop, mut stop_rx) = watch::channel(false);
        let lost = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let db = db.clone();
        let lost_flag = lost.clone();
        let (job, token) = (claim.job_id.clone(), claim.token.clone());
        let stages = stages.to_vec();
        let task = tokio::spawn(async move {
            loop {
                let stop = tokio::select! {
                    _ = tokio::time::sleep(tick(lease)) => false,
                    _ = stop_rx.changed() => true,
                };
                let lines: Vec<String> = progress
                    .lines
                    .lock()
                    .map(|mut l| std::mem::take(&mut *l))
                    .unwrap_or_default();
                for line in lines {
                    let level = if line.starts_with("warning") {
                        "warn"
                    } else {
                        "info"
                    };
                    let _ = db.append_log(&job, level, Some(stage.name()), &line).await;
                }
                let f = progress.fraction();
                let jp = job_progress(&stages, stage, f);
                match db
                    .heartbeat(&job, &token, lease, jp, Some((stage.name(), f)))
                    .await
                {
                    Ok(Heartbeat::Ok) => {}
                    Ok(Heartbeat::CancelRequested) => progress.cancel.cancel(),
                    Ok(Heartbeat::Lost) => {
                        lost_flag.store(true, Ordering::SeqCst);
                        progress.cancel.cancel();
                    }
                    Err(e) => tracing::warn!(error = %e, "heartbeat failed"),
                }
                if stop {
                    break;
                }
            }
        });
        StageHeartbeat { stop, task, lost }
    }

    /// Stops it after one last beat (the stage's last log lines and progress); true when the
    /// lease was lost meanwhile.
    async fn stop(self) -> bool {
        let _ = self.stop.send(true);
        let _ = self.task.await;
        self.lost.load(Ordering::SeqCst)
    }
}

async fn wait_cancel(flag: &CancelFlag) {
    while !flag.is_cancelled() {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn job_progress_is_monotonic_across_stages() {
        let stages = PipelineParams::default().stages();
        let mut last = 0.0;
        for &s in &stages {
            for k in 0..=10 {
                let p = job_progress(&stages, s, k as f64 / 10.0);
                assert!(p >= last - 1e-12, "{s} {k}: {p} < {last}");
                last = p;
            }
        }
        assert!((last - 1.0).abs() < 1e-9);
        let only_ingest = [Stage::Ingest];
        assert!((job_progress(&only_ingest, Stage::Ingest, 1.0) - 1.0).abs() < 1e-9);
    }

    #[test]
    fn stage_progress_never_decreases() {
        let p = StageProgress {
            fraction_bits: AtomicU64::new(0f64.to_bits()),
            lines: Mutex::new(Vec::new()),
            cancel: CancelFlag::new(),
            crash_at: None,
        };
        p.set(0.5);
        p.set(0.2);
        assert_eq!(p.fraction(), 0.5);
        p.set(2.0);
        assert_eq!(p.fraction(), 1.0);
    }
}

#[cfg(test)]
mod input_name_tests {
    use super::{InputNames, name_inputs};
    use std::path::PathBuf;

    #[test]
    fn a_stage_error_names_the_callers_files_not_the_servers_paths() {
        let names: InputNames = vec![
            (
                PathBuf::from("/srv/data/uploads/0193/blob.laz"),
                "plot 7.laz".into(),
            ),
            (
                PathBuf::from("/srv/data/uploads/0194/unpacked"),
                "project.zip".into(),
            ),
        ];
        let e = "/srv/data/uploads/0193/blob.laz: bad point data; \
                 /srv/data/uploads/0194/unpacked/sparse/0/images.bin: truncated";
        assert_eq!(
            name_inputs(e, &names),
            "plot 7.laz: bad point data; project.zip: sparse/0/images.bin: truncated"
        );
        assert_eq!(name_inputs("no paths here", &names), "no paths here");
    }
}
