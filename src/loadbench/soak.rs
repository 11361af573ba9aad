//! `sylva bench soak`: many small jobs through real `sylva` processes, with random cancels
//! and one SIGKILL, counting anything lost.
//!
//! The promise docs/operations.md makes ("a killed process loses no accepted upload, no job, no
//! finished stage"; "duplicate jobs from client retries" never happen) only means something
//! under load, so this runs the embedded default as a user would: `sylva serve` (the API,
//! SQLite and local files, with the larger half of `--workers` worker slots) and one
//! `sylva worker` process on the same data folder with the rest, both this same binary. A
//! generated plot (`sylva synth --preset tiny`, seeded) is uploaded once through the resumable
//! upload API, then `--jobs` jobs stopping after `ingest` are submitted, each with its own
//! Idempotency-Key and retried until accepted, keeping at most four jobs per worker slot
//! unfinished. A seeded share of them is cancelled at a random moment; `--pollers` clients
//! read job status every 100 ms; once half the jobs have finished, the `--restart` process is
//! killed with SIGKILL and started again on the same port and folder.
//!
//! At the end every accepted job must exist and be finished, every succeeded job must still
//! list its stage's outputs, every upload must still be complete, no job may exist twice and
//! the database must pass `PRAGMA integrity_check`; anything else counts as lost and the
//! command exits non-zero. Latency is measured from send to the last byte of the body for every
//! request that got an answer; requests with no answer (while the API was down) are counted
//! apart. Jobs per hour count finished jobs over the time from the first submission to the
//! last job finishing.

use std::collections::{HashMap, HashSet};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::Args;
use rand_chacha::ChaCha8Rng;
use rand_core::{RngCore, SeedableRng};
use reqwest::StatusCode;
use serde_json::{Value, json};
use sha2::{Digest, Sha256};

use super::{ScratchDir, quantile_ms};
use sylva::jobs::JobStore;

/// Unfinished jobs kept per worker slot: enough that no worker ever waits for work, few enough
/// that submissions go on for most of the run (and so across the restart).
const BACKLOG_PER_WORKER: usize = 4;
/// Pause between two status reads of one poller, milliseconds (a script polling 10 times a
/// second; the web page polls less often).
const POLL_EVERY_MS: u64 = 100;
/// Cancels land at a uniformly random moment this long after the job's submission, ms: about
/// the time a small job spends queued and running with the default backlog, so some land while
/// it is queued, some while it runs, some too late.
const CANCEL_WITHIN_MS: u64 = 1000;
/// A job not finished after this many seconds without any job finishing counts as lost.
const STALL_SECS: u64 = 180;
/// Longest a request may take before it counts as unanswered, seconds.
const REQUEST_TIMEOUT_SECS: u64 = 30;
/// Longest a process may take to start (API answering /livez, worker announcing itself).
const START_TIMEOUT_SECS: u64 = 60;

/// Flags of `sylva bench soak` (its job count is `--jobs`).
#[derive(Debug, Clone, Args)]
pub struct SoakArgs {
    /// soak: worker slots in all, split between `sylva serve` (the larger half) and one
    /// `sylva worker` process (the rest). Default 2: one each.
    #[arg(long, env = "SYLVA_BENCH_WORKERS", default_value_t = 2)]
    pub workers: u32,
    /// soak: seed of the generated plot, of which jobs are cancelled and when, and of the
    /// pollers' picks; the same seed makes the same choices.
    #[arg(long, env = "SYLVA_BENCH_SEED", default_value_t = 1)]
    pub seed: u64,
    /// soak: share of jobs cancelled at a random moment within 1 s of their submission, in
    /// [0, 1] (default 0.1).
    #[arg(long, env = "SYLVA_BENCH_CANCEL_SHARE", default_value_t = 0.1)]
    pub cancel_share: f64,
    /// soak: clients reading job status every 100 ms (default 4).
    #[arg(long, env = "SYLVA_BENCH_POLLERS", default_value_t = 4)]
    pub pollers: u32,
    /// soak: the process killed with SIGKILL and restarted once half the jobs have finished:
    /// `serve` (the API with its workers; default), `worker` (the worker-only process) or
    /// `none`.
    #[arg(long, env = "SYLVA_BENCH_RESTART", default_value = "serve")]
    pub restart: String,
}

/// Which process the forced restart hits.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Victim {
    Serve,
    Worker,
    Nobody,
}

/// The HTTP API as the clients see it, recording the latency of every answered request.
struct Api {
    http: reqwest::Client,
    base: String,
    latencies_us: Mutex<Vec<u64>>,
    unanswered: AtomicU64,
}

/// An answered request: status and body.
struct Answer {
    status: StatusCode,
    retry_after: Option<u64>,
    body: bytes::Bytes,
}

impl Answer {
    fn json(&self) -> Value {
        serde_json::from_slice(&self.body).unwrap_or(Value::Null)
    }
}

impl Api {
    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    /// Sends `req`; `None` when no answer came (connection refused or reset, timeout).
    async fn send(&self, req: reqwest::RequestBuilder) -> Option<Answer> {
        let t0 = Instant::now();
        let answer = match req.send().await {
            Ok(resp) => {
                let status = resp.status();
                let retry_after = resp
                    .headers()
                    .get("retry-after")
                    .and_then(|v| v.to_str().ok())
                    .and_then(|v| v.parse().ok());
                resp.bytes().await.ok().map(|body| Answer {
                    status,
                    retry_after,
                    body,
                })
            }
            Err(_) => None,
        };
        match &answer {
            Some(_) => {
                let us = u64::try_from(t0.elapsed().as_micros()).unwrap_or(u64::MAX);
                if let Ok(mut l) = self.latencies_us.lock() {
                    l.push(us);
                }
            }
            None => {
                self.unanswered.fetch_add(1, Ordering::Relaxed);
            }
        }
        answer
    }

    async fn get(&self, path: &str) -> Option<Answer> {
        self.send(self.http.get(self.url(path))).await
    }
}

/// A `sylva` child process and how to start it again.
struct Proc {
    label: &'static str,
    args: Vec<String>,
    data: PathBuf,
    child: Child,
    starts: u32,
}

impl Proc {
    fn start(label: &'static str, args: Vec<String>, data: &Path) -> anyhow::Result<Self> {
        let child = spawn(label, &args, data, 0)?;
        Ok(Self {
            label,
            args,
            data: data.to_path_buf(),
            child,
            starts: 1,
        })
    }

    /// The log file of the `n`-th start (0-based).
    fn log(data: &Path, label: &str, n: u32) -> PathBuf {
        data.join(format!("{label}-{n}.log"))
    }

    /// SIGKILL, as the OOM killer or a power cut would stop it, then reap it (a zombie would
    /// still look alive to the start-up recovery of its successor).
    fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    fn restart(&mut self) -> anyhow::Result<()> {
        self.child = spawn(self.label, &self.args, &self.data, self.starts)?;
        self.starts += 1;
        Ok(())
    }

    /// SIGTERM (a clean stop), then SIGKILL after 10 s.
    fn stop(&mut self) {
        if let Ok(pid) = i32::try_from(self.child.id()) {
            // SAFETY: kill(2) on our own child's pid with a valid signal has no memory effects.
            unsafe {
                libc::kill(pid, libc::SIGTERM);
            }
        }
        let deadline = Instant::now() + Duration::from_secs(10);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        self.kill();
    }

    /// The end of the current log, for error messages.
    fn log_tail(&self) -> String {
        let text = std::fs::read_to_string(Self::log(&self.data, self.label, self.starts - 1))
            .unwrap_or_default();
        let start = text.len().saturating_sub(2000);
        text.get(start..).unwrap_or("").to_string()
    }

    /// Fails if the process has exited.
    fn check_alive(&mut self) -> anyhow::Result<()> {
        if let Ok(Some(status)) = self.child.try_wait() {
            anyhow::bail!(
                "sylva {} exited ({status}):\n{}",
                self.label,
                self.log_tail()
            );
        }
        Ok(())
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            self.kill();
        }
    }
}

fn spawn(label: &str, args: &[String], data: &Path, n: u32) -> anyhow::Result<Child> {
    let exe = std::env::current_exe().context("cannot find the sylva binary")?;
    let log = std::fs::File::create(Proc::log(data, label, n))?;
    let out = std::fs::File::create(data.join(format!("{label}-{n}.out")))?;
    let mut cmd = Command::new(exe);
    // The children see only what is set here, not the bench's own SYLVA_* settings.
    for (k, _) in std::env::vars() {
        if k.starts_with("SYLVA_") {
            cmd.env_remove(k);
        }
    }
    cmd.args(args)
        .arg("--data")
        .arg(data)
        .env("SYLVA_LOG", "warn")
        .stdin(Stdio::null())
        .stdout(out)
        .stderr(log)
        .spawn()
        .with_context(|| format!("cannot start sylva {label}"))
}

/// Waits until the API answers /livez.
async fn wait_ready(api: &Api, p: &mut Proc) -> anyhow::Result<()> {
    let deadline = Instant::now() + Duration::from_secs(START_TIMEOUT_SECS);
    while Instant::now() < deadline {
        p.check_alive()?;
        if let Ok(r) = api.http.get(api.url("/livez")).send().await
            && r.status().is_success()
        {
            return Ok(());
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    anyhow::bail!(
        "sylva {} did not answer in time:\n{}",
        p.label,
        p.log_tail()
    )
}

/// Waits until the worker process says it started.
async fn wait_worker(p: &mut Proc) -> anyhow::Result<()> {
    let out = p.data.join(format!("{}-{}.out", p.label, p.starts - 1));
    let deadline = Instant::now() + Duration::from_secs(START_TIMEOUT_SECS);
    while Instant::now() < deadline {
        p.check_alive()?;
        if std::fs::read_to_string(&out).is_ok_and(|t| t.contains("sylva worker started")) {
            return Ok(());
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    anyhow::bail!("sylva {} did not start in time:\n{}", p.label, p.log_tail())
}

/// Uploads one file through the resumable API; returns the upload id.
async fn upload(api: &Api, kind: &str, path: &Path) -> anyhow::Result<String> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| kind.to_string());
    let body = json!({
        "kind": kind, "filename": name, "size": bytes.len(),
        "sha256": hex::encode(Sha256::digest(&bytes)),
    });
    let created = api
        .send(api.http.post(api.url("/v1/uploads")).json(&body))
        .await
        .filter(|a| a.status == StatusCode::CREATED)
        .ok_or_else(|| anyhow::anyhow!("cannot create the {kind} upload"))?
        .json();
    let id = created["id"].as_str().unwrap_or_default().to_string();
    let part = created["part_size"].as_u64().unwrap_or(0).max(1) as usize;
    for (n, chunk) in bytes.chunks(part).enumerate() {
        let req = api
            .http
            .put(api.url(&format!("/v1/uploads/{id}/parts/{n}")))
            .body(chunk.to_vec());
        api.send(req)
            .await
            .filter(|a| a.status.is_success())
            .ok_or_else(|| anyhow::anyhow!("part {n} of the {kind} upload refused"))?;
    }
    let done = api
        .send(
            api.http
                .post(api.url(&format!("/v1/uploads/{id}/complete"))),
        )
        .await;
    match done {
        Some(a) if a.status.is_success() => Ok(id),
        Some(a) => anyhow::bail!(
            "the {kind} upload was refused: {}",
            String::from_utf8_lossy(&a.body)
        ),
        None => anyhow::bail!("the {kind} upload got no answer"),
    }
}

/// What the clients saw of the jobs.
#[derive(Default)]
struct Shared {
    /// Ids of accepted jobs, in submission order.
    accepted: Mutex<Vec<String>>,
    /// Finished jobs among the accepted, as last counted by the monitor.
    finished: AtomicUsize,
    /// Submissions refused with a 4xx other than 429 (none expected).
    refused: AtomicUsize,
    cancels_accepted: AtomicUsize,
    cancels_too_late: AtomicUsize,
    submitting: AtomicBool,
    done: AtomicBool,
}

impl Shared {
    /// The ids of the jobs accepted so far.
    fn accepted_ids(&self) -> Vec<String> {
        self.accepted.lock().map(|l| l.clone()).unwrap_or_default()
    }
}

/// Submits job `k` until the API accepts it (the same Idempotency-Key on every try, so a try
/// whose answer was lost cannot make a second job). `None` if it was refused.
async fn submit(api: &Api, body: &Value, key: &str) -> Option<String> {
    loop {
        let req = api
            .http
            .post(api.url("/v1/jobs"))
            .header("idempotency-key", key)
            .json(body);
        match api.send(req).await {
            Some(a) if a.status.is_success() => {
                return a.json()["id"].as_str().map(str::to_string);
            }
            Some(a) if a.status == StatusCode::TOO_MANY_REQUESTS => {
                let secs = a.retry_after.unwrap_or(1).clamp(1, 10);
                tokio::time::sleep(Duration::from_secs(secs)).await;
            }
            Some(a) if a.status.is_client_error() => return None,
            // No answer or a server error (the API is restarting): try again shortly.
            _ => tokio::time::sleep(Duration::from_millis(200)).await,
        }
    }
}

/// Cancels `id` after `delay`, retrying while the API does not answer.
async fn cancel_later(api: Arc<Api>, shared: Arc<Shared>, id: String, delay: Duration) {
    tokio::time::sleep(delay).await;
    let deadline = Instant::now() + Duration::from_secs(120);
    while Instant::now() < deadline {
        let req = api.http.post(api.url(&format!("/v1/jobs/{id}/cancel")));
        match api.send(req).await {
            Some(a) if a.status.is_success() => {
                shared.cancels_accepted.fetch_add(1, Ordering::Relaxed);
                return;
            }
            Some(a) if a.status == StatusCode::CONFLICT => {
                shared.cancels_too_late.fetch_add(1, Ordering::Relaxed);
                return;
            }
            _ => tokio::time::sleep(Duration::from_millis(200)).await,
        }
    }
}

/// Submits `n` jobs, keeping at most `backlog` unfinished, and schedules the cancels.
async fn submitter(
    api: Arc<Api>,
    shared: Arc<Shared>,
    body: Value,
    n: u32,
    backlog: usize,
    a: SoakArgs,
) {
    let mut rng = ChaCha8Rng::seed_from_u64(a.seed ^ 0x5eed_ca9c);
    for k in 0..n {
        loop {
            let accepted = shared.accepted.lock().map(|l| l.len()).unwrap_or(0);
            if accepted.saturating_sub(shared.finished.load(Ordering::Relaxed)) < backlog {
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        let key = format!("sylva-bench-soak-{}-{k}", a.seed);
        let Some(id) = submit(&api, &body, &key).await else {
            shared.refused.fetch_add(1, Ordering::Relaxed);
            continue;
        };
        if let Ok(mut l) = shared.accepted.lock() {
            l.push(id.clone());
        }
        let draw = f64::from(rng.next_u32()) / f64::from(u32::MAX);
        let delay = Duration::from_millis(rng.next_u64() % CANCEL_WITHIN_MS);
        if draw < a.cancel_share {
            tokio::spawn(cancel_later(api.clone(), shared.clone(), id, delay));
        }
    }
    shared.submitting.store(false, Ordering::SeqCst);
}

/// Reads job status every [`POLL_EVERY_MS`]: mostly one seeded-random job, every fifth time
/// the first page of the list.
async fn poller(api: Arc<Api>, shared: Arc<Shared>, seed: u64) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut k = 0u64;
    while !shared.done.load(Ordering::Relaxed) {
        tokio::time::sleep(Duration::from_millis(POLL_EVERY_MS)).await;
        k += 1;
        let pick =
            shared.accepted.lock().ok().and_then(|l| {
                (!l.is_empty()).then(|| l[rng.next_u32() as usize % l.len()].clone())
            });
        let path = match pick {
            Some(id) if !k.is_multiple_of(5) => format!("/v1/jobs/{id}"),
            _ => "/v1/jobs?limit=50".to_string(),
        };
        let _ = api.get(&path).await;
    }
}

/// Every job's state, read page by page; `None` when the API did not answer.
async fn all_states(api: &Api) -> Option<HashMap<String, String>> {
    let mut out = HashMap::new();
    let mut cursor: Option<String> = None;
    loop {
        let path = match &cursor {
            Some(c) => format!("/v1/jobs?limit=200&cursor={c}"),
            None => "/v1/jobs?limit=200".to_string(),
        };
        let page = api.get(&path).await.filter(|a| a.status.is_success())?;
        let v = page.json();
        for j in v["jobs"].as_array().into_iter().flatten() {
            if let (Some(id), Some(state)) = (j["id"].as_str(), j["state"].as_str()) {
                out.insert(id.to_string(), state.to_string());
            }
        }
        match v["next_cursor"].as_str() {
            Some(c) => cursor = Some(c.to_string()),
            None => return Some(out),
        }
    }
}

/// Whether the last worker that claimed job `id` (from its log: `claimed by worker W` or
/// `resumed at stage S by worker W`, with W = `host-pid-slot-tag`) belongs to process `pid`.
async fn held_by(api: &Api, id: &str, pid: u32) -> bool {
    let Some(a) = api.get(&format!("/v1/jobs/{id}/log")).await else {
        return false;
    };
    let v = a.json();
    let last = v["lines"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|l| l["message"].as_str())
        .filter(|m| m.starts_with("claimed by worker ") || m.starts_with("resumed "))
        .filter_map(|m| m.split_once("by worker ").map(|(_, w)| w.to_string()))
        .next_back();
    last.is_some_and(|w| w.contains(&format!("-{pid}-")))
}

fn is_terminal(state: &str) -> bool {
    matches!(state, "succeeded" | "failed" | "canceled")
}

/// The forced restart as it happened.
struct Restart {
    victim: Victim,
    at_s: f64,
    /// Jobs the killed process was running, as far as the job logs tell.
    held: usize,
    down_s: f64,
}

/// Longest the restart waits, once due, for the process to be running a job, seconds.
const RESTART_WAIT_SECS: u64 = 30;

/// What the end-of-run checks found.
#[derive(Default)]
struct Tally {
    succeeded: usize,
    canceled: usize,
    failed: usize,
    lost: Vec<String>,
    resumed: usize,
    duplicates: usize,
}

/// Reads every accepted job and every upload back through the API.
async fn audit(api: &Api, ids: &[String], uploads: &[String]) -> Tally {
    let mut t = Tally::default();
    for id in ids {
        let Some(a) = api.get(&format!("/v1/jobs/{id}")).await else {
            t.lost.push(format!("job {id}: no answer"));
            continue;
        };
        if a.status == StatusCode::NOT_FOUND {
            t.lost.push(format!("job {id}: missing"));
            continue;
        }
        let j = a.json();
        match j["state"].as_str().unwrap_or("") {
            "succeeded" => {
                t.succeeded += 1;
                let has_report = j["artifacts"]
                    .as_array()
                    .into_iter()
                    .flatten()
                    .any(|x| x["name"] == "ingest/report.json");
                // Listed, and on disk: the report is the last file a stage writes.
                let readable = api
                    .get(&format!("/v1/jobs/{id}/artifacts/ingest/report.json"))
                    .await
                    .is_some_and(|a| a.status.is_success());
                if !(has_report && readable) {
                    t.lost
                        .push(format!("job {id}: succeeded without its ingest outputs"));
                }
            }
            "canceled" => t.canceled += 1,
            "failed" => {
                t.failed += 1;
                eprintln!("job {id} failed: {}", j["error"]);
            }
            other => t.lost.push(format!("job {id}: still {other}")),
        }
        if j["attempt"].as_i64().unwrap_or(0) > 1 {
            t.resumed += 1;
        }
    }
    for id in uploads {
        let state = api
            .get(&format!("/v1/uploads/{id}"))
            .await
            .map(|a| a.json()["state"].as_str().unwrap_or("").to_string());
        if state.as_deref() != Some("complete") {
            t.lost.push(format!("upload {id}: {state:?}"));
        }
    }
    t
}

/// Generates the tiny synthetic plot every job reads into `dir`, with its COLMAP folder packed
/// as `colmap.tar` for upload.
async fn make_plot(dir: &Path, seed: u64) -> anyhow::Result<()> {
    eprintln!("generating a tiny synthetic plot (seed {seed})…");
    let dir = dir.to_path_buf();
    tokio::task::spawn_blocking(move || -> anyhow::Result<()> {
        let mut p = sylva::synth::SynthParams::new(sylva::synth::Preset::Tiny);
        p.seed = seed;
        sylva::synth::generate(&p, &dir, &sylva::progress::NoProgress)?;
        let file = std::fs::File::create(dir.join("colmap.tar"))?;
        let mut tar = tar::Builder::new(file);
        tar.append_dir_all(".", dir.join("colmap"))?;
        tar.finish()?;
        Ok(())
    })
    .await?
}

/// The `sylva` processes of the run: serve, and a worker when it has slots.
struct Procs {
    serve: Proc,
    worker: Option<Proc>,
}

impl Procs {
    /// Starts serve on `api`'s port with `serve_slots` worker slots and, when `worker_slots`
    /// is not 0, a worker process with those; waits until both are up.
    async fn start(
        api: &Api,
        port: u16,
        (serve_slots, worker_slots): (u32, u32),
        data: &Path,
    ) -> anyhow::Result<Self> {
        let mut serve = Proc::start(
            "serve",
            vec![
                "serve".into(),
                "--listen".into(),
                format!("127.0.0.1:{port}"),
                "--workers".into(),
                serve_slots.to_string(),
                "--poll-ms".into(),
                "100".into(),
            ],
            data,
        )?;
        wait_ready(api, &mut serve).await?;
        let mut worker = None;
        if worker_slots > 0 {
            let mut w = Proc::start(
                "worker",
                vec![
                    "worker".into(),
                    "--workers".into(),
                    worker_slots.to_string(),
                    "--poll-ms".into(),
                    "100".into(),
                ],
                data,
            )?;
            wait_worker(&mut w).await?;
            worker = Some(w);
        }
        Ok(Self { serve, worker })
    }

    fn check_alive(&mut self) -> anyhow::Result<()> {
        self.serve.check_alive()?;
        self.worker.as_mut().map_or(Ok(()), Proc::check_alive)
    }

    /// The pid of the process `victim` names (serve when there is no worker).
    fn pid(&self, victim: Victim) -> u32 {
        match (victim, &self.worker) {
            (Victim::Worker, Some(w)) => w.child.id(),
            _ => self.serve.child.id(),
        }
    }

    /// SIGKILLs the process `victim` names, starts it again and waits until it is up.
    async fn kill_and_restart(
        &mut self,
        api: &Api,
        victim: Victim,
        held: usize,
    ) -> anyhow::Result<()> {
        match (victim, self.worker.as_mut()) {
            (Victim::Worker, Some(w)) => {
                eprintln!("SIGKILL of sylva worker ({held} job(s) running there)…");
                w.kill();
                w.restart()?;
                wait_worker(w).await
            }
            _ => {
                eprintln!("SIGKILL of sylva serve ({held} job(s) running there)…");
                self.serve.kill();
                self.serve.restart()?;
                wait_ready(api, &mut self.serve).await
            }
        }
    }

    fn stop(&mut self) {
        self.serve.stop();
        if let Some(w) = self.worker.as_mut() {
            w.stop();
        }
    }
}

/// Uploads the plot's three inputs; returns their upload ids and the body of every job.
async fn upload_inputs(api: &Api, plot: &Path) -> anyhow::Result<(Vec<String>, Value)> {
    let mut uploads = Vec::new();
    let mut inputs = serde_json::Map::new();
    for (kind, file) in [
        ("lidar", "lidar.laz"),
        ("colmap", "colmap.tar"),
        ("control_points", "control_points.csv"),
    ] {
        let id = upload(api, kind, &plot.join(file)).await?;
        inputs.insert(kind.to_string(), json!(id));
        uploads.push(id);
    }
    let body = json!({ "inputs": inputs, "params": { "until": "ingest" } });
    Ok((uploads, body))
}

/// Watches the run: counts finished jobs, kills and restarts the `victim` once half of the
/// `jobs` have finished (while it runs a job, when it can), and returns once every accepted
/// job is finished or none has finished for [`STALL_SECS`]. Returns the restart as it
/// happened and when the last job finished. `started`: when the first job was submitted.
async fn monitor(
    api: &Api,
    shared: &Shared,
    procs: &mut Procs,
    (victim, jobs): (Victim, u32),
    started: Instant,
) -> anyhow::Result<(Option<Restart>, Instant)> {
    let mut restart: Option<Restart> = None;
    let mut restart_due: Option<Instant> = None;
    let mut last_finished = (0usize, Instant::now());
    let mut last_job_done = started;
    loop {
        // Closer watch while waiting for the process to be killed to hold a job.
        let pause = if restart_due.is_some() && restart.is_none() {
            50
        } else {
            500
        };
        tokio::time::sleep(Duration::from_millis(pause)).await;
        procs.check_alive()?;
        let Some(states) = all_states(api).await else {
            continue;
        };
        let ids = shared.accepted_ids();
        let finished = ids
            .iter()
            .filter(|id| states.get(*id).is_some_and(|s| is_terminal(s)))
            .count();
        shared.finished.store(finished, Ordering::Relaxed);
        if finished > last_finished.0 {
            last_finished = (finished, Instant::now());
            last_job_done = Instant::now();
        }
        let all_done = !shared.submitting.load(Ordering::SeqCst) && finished >= ids.len();
        if restart.is_none() && victim != Victim::Nobody && finished * 2 >= jobs as usize {
            let due = *restart_due.get_or_insert_with(Instant::now);
            // Kill the process while it runs a job, so that a job is taken over.
            let pid = procs.pid(victim);
            let mut held = 0;
            for (id, state) in &states {
                if state == "running" && held_by(api, id, pid).await {
                    held += 1;
                }
            }
            if held == 0 && !all_done && due.elapsed() < Duration::from_secs(RESTART_WAIT_SECS) {
                continue;
            }
            let at_s = started.elapsed().as_secs_f64();
            let t0 = Instant::now();
            procs.kill_and_restart(api, victim, held).await?;
            restart = Some(Restart {
                victim,
                at_s,
                held,
                down_s: t0.elapsed().as_secs_f64(),
            });
        }
        if all_done {
            return Ok((restart, last_job_done));
        }
        if last_finished.1.elapsed() > Duration::from_secs(STALL_SECS) {
            eprintln!("no job finished for {STALL_SECS} s: stopping");
            return Ok((restart, last_job_done));
        }
    }
}

/// Runs the soak and prints its table on stdout (progress on stderr). Returns whether nothing
/// was lost.
pub async fn run(jobs: u32, a: &SoakArgs) -> anyhow::Result<bool> {
    let victim = match a.restart.as_str() {
        "serve" => Victim::Serve,
        "worker" => Victim::Worker,
        "none" => Victim::Nobody,
        other => anyhow::bail!("--restart must be serve, worker or none, not {other:?}"),
    };
    if !(0.0..=1.0).contains(&a.cancel_share) {
        anyhow::bail!("--cancel-share must lie in [0, 1]");
    }
    if jobs == 0 || a.workers == 0 {
        anyhow::bail!("--jobs and --workers must be at least 1");
    }
    let scratch = ScratchDir::new("soak")?;
    let data = scratch.0.join("data");
    std::fs::create_dir_all(&data)?;
    let plot = scratch.0.join("plot");
    make_plot(&plot, a.seed).await?;

    // The processes: serve with the larger half of the slots, a worker with the rest.
    let port = std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port();
    let worker_slots = a.workers / 2;
    let serve_slots = a.workers - worker_slots;
    let api = Arc::new(Api {
        http: reqwest::Client::builder()
            .timeout(Duration::from_secs(REQUEST_TIMEOUT_SECS))
            .build()?,
        base: format!("http://127.0.0.1:{port}"),
        latencies_us: Mutex::new(Vec::new()),
        unanswered: AtomicU64::new(0),
    });
    let mut procs = Procs::start(&api, port, (serve_slots, worker_slots), &data).await?;
    let victim = if victim == Victim::Worker && procs.worker.is_none() {
        eprintln!("--workers 1 runs no worker process: restarting serve instead");
        Victim::Serve
    } else {
        victim
    };
    let (uploads, body) = upload_inputs(&api, &plot).await?;

    eprintln!(
        "soaking: {jobs} jobs, {} worker slot(s) ({serve_slots} in serve, {worker_slots} in worker), \
         {} poller(s), cancel share {}, restart {:?}…",
        a.workers, a.pollers, a.cancel_share, victim
    );
    let shared = Arc::new(Shared::default());
    shared.submitting.store(true, Ordering::SeqCst);
    let started = Instant::now();
    let backlog = BACKLOG_PER_WORKER * a.workers as usize;
    let submit_task = tokio::spawn(submitter(
        api.clone(),
        shared.clone(),
        body,
        jobs,
        backlog,
        a.clone(),
    ));
    let pollers: Vec<_> = (0..a.pollers)
        .map(|i| {
            tokio::spawn(poller(
                api.clone(),
                shared.clone(),
                a.seed.wrapping_add(u64::from(i) + 1),
            ))
        })
        .collect();
    let (restart, last_job_done) =
        monitor(&api, &shared, &mut procs, (victim, jobs), started).await?;
    shared.done.store(true, Ordering::SeqCst);
    if !submit_task.is_finished() {
        submit_task.abort();
    }
    for p in pollers {
        let _ = p.await;
    }
    let wall_s = last_job_done.duration_since(started).as_secs_f64();

    // The audit, through the API, then through the database itself.
    let ids = shared.accepted_ids();
    let mut tally = audit(&api, &ids, &uploads).await;
    let all = all_states(&api).await.unwrap_or_default();
    let unique: HashSet<&String> = ids.iter().collect();
    tally.duplicates = all.len().saturating_sub(unique.len());
    if tally.duplicates > 0 {
        tally
            .lost
            .push(format!("{} job(s) more than accepted", tally.duplicates));
    }
    procs.stop();
    let db = JobStore::open_sqlite(&data.join("sylva.db"), 1)
        .await
        .context("cannot open the job database after the run")?;
    let integrity = db.integrity_check().await.unwrap_or_else(|e| e.to_string());
    if integrity != "ok" {
        tally
            .lost
            .push(format!("PRAGMA integrity_check: {integrity}"));
    }
    for l in &tally.lost {
        eprintln!("LOST: {l}");
    }
    let accepted = shared.cancels_accepted.load(Ordering::Relaxed);
    eprintln!(
        "cancels: {accepted} accepted ({} of those jobs finished their stage first), {} too \
         late (job already finished); {} submission(s) refused; database integrity: {integrity}",
        accepted.saturating_sub(tally.canceled),
        shared.cancels_too_late.load(Ordering::Relaxed),
        shared.refused.load(Ordering::Relaxed),
    );
    print_table(&api, ids.len(), a.workers, &tally, wall_s, restart.as_ref());
    Ok(tally.lost.is_empty())
}

/// Prints the soak's one-row table on stdout.
fn print_table(
    api: &Api,
    jobs: usize,
    workers: u32,
    tally: &Tally,
    wall_s: f64,
    restart: Option<&Restart>,
) {
    let mut lat = api
        .latencies_us
        .lock()
        .map(|l| l.clone())
        .unwrap_or_default();
    lat.sort_unstable();
    let finished = tally.succeeded + tally.canceled + tally.failed;
    let per_hour = finished as f64 / wall_s.max(1e-9) * 3600.0;
    let restart_text = match restart {
        None => "none".to_string(),
        Some(r) => format!(
            "{} SIGKILLed at {:.0} s running {} job(s), back in {:.1} s; {} job(s) resumed",
            match r.victim {
                Victim::Worker => "worker",
                _ => "serve",
            },
            r.at_s,
            r.held,
            r.down_s,
            tally.resumed
        ),
    };
    println!(
        "| jobs | workers | succeeded | canceled | failed | lost | jobs/hour | requests | p50 ms | p99 ms | unanswered | restart |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    println!(
        "| {} | {} | {} | {} | {} | {} | {:.0} | {} | {:.2} | {:.2} | {} | {} |",
        jobs,
        workers,
        tally.succeeded,
        tally.canceled,
        tally.failed,
        tally.lost.len(),
        per_hour,
        lat.len(),
        quantile_ms(&lat, 0.50),
        quantile_ms(&lat, 0.99),
        api.unanswered.load(Ordering::Relaxed),
        restart_text
    );
    let _ = std::io::stdout().flush();
}
