//! Workers as separate processes sharing one job database (an SQLite file, or PostgreSQL):
//! crash take-over and concurrency. Each test runs on both databases.

mod common;

use std::time::Duration;

use common::*;
use reqwest::Client;
use serde_json::json;

/// A server without workers on `db` over the fixture's data, the fixture's inputs uploaded,
/// worker A started with `a_flags` and a job up to ingest submitted: the server, A, the
/// client with the base URL, and the job's id.
async fn job_for_a(
    db: &Db,
    fx: &Fixture,
    a_flags: &[&str],
) -> (Proc, Proc, (Client, String), String) {
    let api = db.serve(&fx.data, &["--workers", "0"]);
    let (c, base, inputs) = client_with_inputs(&api, fx).await;
    let a = db.worker(&fx.data, a_flags);
    let id = submit(&c, &base, &job_until(&inputs, "ingest")).await;
    (api, a, (c, base), id)
}

on_both_databases!(killed_worker_job_is_reclaimed_after_the_lease_with_attempt_2);
async fn killed_worker_job_is_reclaimed_after_the_lease_with_attempt_2(db: Db) {
    let fx = fixture();
    let a_flags = ["--lease-secs", "2", "--debug-stage-pause-ms", "60000"];
    let (_api, mut a, (c, base), id) = job_for_a(&db, &fx, &a_flags).await;
    let (running, _) = wait_job(&c, &base, &id, Duration::from_secs(60), |j| {
        j["state"] == "running" && stage(j, "ingest")["state"] == "running"
    })
    .await;
    assert_eq!(running["attempt"], 1);

    // A second worker is already running; the first dies mid-stage without a word.
    let _b = db.worker(&fx.data, &["--lease-secs", "2", "--poll-ms", "50"]);
    a.kill();
    let killed_at = std::time::Instant::now();
    let (job, progress) = wait_job(&c, &base, &id, Duration::from_secs(60), is_terminal).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    assert_eq!(job["attempt"], 2, "re-claimed once");
    assert!(
        killed_at.elapsed() >= Duration::from_millis(1000),
        "taken over before the lease ran out"
    );
    assert!(
        progress.windows(2).all(|w| w[1] >= w[0]),
        "progress decreased: {progress:?}"
    );
    let log = log_text(&c, &base, &id).await;
    assert!(log.contains("resumed at stage ingest"), "{log}");
    assert!(log.contains("(attempt 2)"), "{log}");
    assert_eq!(stage(&job, "ingest")["state"], "done");
}

on_both_databases!(a_restarted_worker_recovers_the_jobs_of_a_dead_process_at_once);
async fn a_restarted_worker_recovers_the_jobs_of_a_dead_process_at_once(db: Db) {
    let fx = fixture();
    let a_flags = ["--lease-secs", "60", "--debug-stage-pause-ms", "60000"];
    let (_api, mut a, (c, base), id) = job_for_a(&db, &fx, &a_flags).await;
    wait_job(&c, &base, &id, Duration::from_secs(60), |j| {
        stage(j, "ingest")["state"] == "running"
    })
    .await;
    a.kill();
    // The restarted worker sees that the process holding the job is gone (same host) and
    // does not wait for the 60 s lease.
    let _b = db.worker(&fx.data, &["--lease-secs", "60"]);
    let (job, _) = wait_job(&c, &base, &id, Duration::from_secs(30), is_terminal).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    assert_eq!(job["attempt"], 2);
}

on_both_databases!(eight_clients_create_jobs_while_two_workers_claim_without_lock_errors);
async fn eight_clients_create_jobs_while_two_workers_claim_without_lock_errors(db: Db) {
    let fx = fixture();
    let api = db.serve(&fx.data, &["--workers", "0"]);
    let (c, base, inputs) = client_with_inputs(&api, &fx).await;
    let w1 = db.worker(&fx.data, &["--poll-ms", "50"]);
    let w2 = db.worker(&fx.data, &["--poll-ms", "50"]);
    let ids = jobs_from_clients(8, |client_no, c| {
        let (base, inputs) = (base.clone(), inputs.clone());
        async move {
            let mut ids = Vec::new();
            for k in 0..3 {
                let body = json!({ "inputs": inputs, "params": { "until": "ingest", "ingest": { "decode_images": k % 2 == 0 } } });
                let key = format!("client-{client_no}-job-{k}");
                let r = send(c.post(format!("{base}/v1/jobs")).header("idempotency-key", key).json(&body)).await;
                assert_eq!(r.status(), reqwest::StatusCode::ACCEPTED, "{:?}", r.text().await);
                let v: serde_json::Value = r.json().await.expect("json");
                ids.push(id_of(&v));
                // Poll in between, as clients do.
                let r = send(c.get(format!("{base}/v1/jobs?limit=5"))).await;
                assert_eq!(r.status(), reqwest::StatusCode::OK);
            }
            ids
        }
    })
    .await;
    assert_eq!(ids.len(), 24);
    for id in &ids {
        let (job, _) = wait_job(&c, &base, id, Duration::from_secs(240), is_terminal).await;
        assert_eq!(job["state"], "succeeded", "{job}");
        assert_eq!(job["attempt"], 1, "each job processed exactly once: {job}");
    }
    for p in [&api, &w1, &w2] {
        let text = p.stderr_text();
        assert!(!text.contains("database is locked"), "{text}");
        assert!(!text.contains("ERROR"), "{text}");
    }
    // Both workers took part.
    let mut claimed_by = std::collections::HashSet::new();
    for id in &ids {
        let log = log_text(&c, &base, id).await;
        let w = log
            .lines()
            .find_map(|l| l.strip_prefix("claimed by worker "))
            .map(str::to_string);
        claimed_by.insert(w.expect("claim line"));
    }
    assert!(claimed_by.len() >= 2, "{claimed_by:?}");
}

/// The ids of the jobs that `clients` concurrent clients create, each as `jobs(client_no, c)`
/// does with a client `c` of its own, in the clients' order.
async fn jobs_from_clients<F>(clients: usize, jobs: impl Fn(usize, Client) -> F) -> Vec<String>
where
    F: Future<Output = Vec<String>> + Send + 'static,
{
    let tasks: Vec<_> = (0..clients)
        .map(|n| tokio::spawn(jobs(n, client())))
        .collect();
    let mut ids = Vec::new();
    for t in tasks {
        ids.extend(t.await.expect("client task"));
    }
    ids
}

/// The workers that claimed a job, in order, from its log (`claimed by worker W`, then
/// `resumed at stage S by worker W (attempt N)`).
async fn claimants(c: &reqwest::Client, base: &str, id: &str) -> Vec<String> {
    log_text(c, base, id)
        .await
        .lines()
        .filter(|l| l.starts_with("claimed ") || l.starts_with("resumed "))
        .filter_map(|l| l.split_once("by worker "))
        .map(|(_, w)| w.split_whitespace().next().unwrap_or("").to_string())
        .collect()
}

/// Whether a worker id (`host-pid-slot-tag`) belongs to process `pid`.
fn of_process(worker: &str, pid: u32) -> bool {
    worker.contains(&format!("-{pid}-"))
}

on_both_databases!(three_worker_processes_run_thirty_jobs_once_each_across_a_sigkill);
async fn three_worker_processes_run_thirty_jobs_once_each_across_a_sigkill(db: Db) {
    let fx = fixture();
    let api = db.serve(&fx.data, &["--workers", "0"]);
    let (c, base, inputs) = client_with_inputs(&api, &fx).await;
    let body = move |k: usize| json!({ "inputs": inputs, "params": { "until": "ingest", "ingest": { "decode_images": k.is_multiple_of(2) } } });

    // Worker A takes the first job and stalls in its stage until it is killed.
    let mut a = db.worker(
        &fx.data,
        &["--lease-secs", "3", "--debug-stage-pause-ms", "60000"],
    );
    let a_pid = a.child.id();
    let first = submit(&c, &base, &body(0)).await;
    wait_job(&c, &base, &first, Duration::from_secs(60), |j| {
        stage(j, "ingest")["state"] == "running"
    })
    .await;

    // B and C join, and 29 more jobs arrive from three clients at once.
    let b = db.worker(&fx.data, &["--poll-ms", "200"]);
    let w_c = db.worker(&fx.data, &["--poll-ms", "200"]);
    let mut ids = vec![first.clone()];
    let more = jobs_from_clients(3, |client_no, c| {
        let (base, body) = (base.clone(), body.clone());
        async move {
            let mut ids = Vec::new();
            for k in (1..30).filter(|k| k % 3 == client_no) {
                ids.push(submit(&c, &base, &body(k)).await);
            }
            ids
        }
    });
    ids.extend(more.await);
    assert_eq!(ids.len(), 30);

    // A dies mid-job without a word (SIGKILL).
    assert!(
        get_job(&c, &base, &first).await["state"] == "running",
        "A still holds the first job"
    );
    a.kill();

    for id in &ids {
        let (job, progress) = wait_job(&c, &base, id, Duration::from_secs(300), is_terminal).await;
        assert_eq!(job["state"], "succeeded", "{job}");
        assert_eq!(stage(&job, "ingest")["state"], "done", "{job}");
        assert!(
            progress.windows(2).all(|w| w[1] >= w[0]),
            "progress decreased: {progress:?}"
        );
        let who = claimants(&c, &base, id).await;
        if *id == first {
            assert_eq!(job["attempt"], 2, "re-claimed once after the kill: {job}");
            assert_eq!(who.len(), 2, "{who:?}");
            assert!(of_process(&who[0], a_pid), "A claimed it first: {who:?}");
            assert!(
                !of_process(&who[1], a_pid),
                "another worker finished it: {who:?}"
            );
        } else {
            assert_eq!(job["attempt"], 1, "processed exactly once: {job}");
            assert_eq!(who.len(), 1, "claimed once: {who:?}");
            assert!(
                !of_process(&who[0], a_pid),
                "A was stalled in its first job: {who:?}"
            );
        }
    }
    // Both survivors took part, and nothing went wrong in any process.
    let (b_pid, c_pid) = (b.child.id(), w_c.child.id());
    let mut by = std::collections::HashSet::new();
    for id in &ids {
        for w in claimants(&c, &base, id).await {
            by.insert(if of_process(&w, b_pid) {
                "B"
            } else if of_process(&w, c_pid) {
                "C"
            } else {
                "A"
            });
        }
    }
    assert_eq!(by.len(), 3, "{by:?}");
    for p in [&api, &b, &w_c] {
        let text = p.stderr_text();
        assert!(!text.contains("ERROR"), "{text}");
        assert!(!text.contains("claim failed"), "{text}");
    }
}

/// A stage that hangs is stopped at its runtime limit and the job fails clearly; the worker
/// goes on to the next job.
#[tokio::test(flavor = "multi_thread")]
async fn a_hung_stage_fails_at_its_runtime_limit() {
    let fx = fixture();
    let srv = serve(
        &fx.data,
        &[
            "--debug-stage-pause-ms",
            "600000",
            "--max-stage-secs",
            "3600,ingest=1",
        ],
    );
    let (c, base, inputs) = client_with_inputs(&srv, &fx).await;
    let body = job_until(&inputs, "ingest");
    let started = std::time::Instant::now();
    let id = submit(&c, &base, &body).await;
    let (job, _) = wait_job(&c, &base, &id, Duration::from_secs(60), is_terminal).await;
    assert_eq!(job["state"], "failed", "{job}");
    assert_eq!(
        job["error"]["type"], "urn:sylva:problem:stage-timeout",
        "{job}"
    );
    assert!(detail(&job["error"]).contains("limit of 1 s"), "{job}");
    assert_eq!(stage(&job, "ingest")["state"], "failed");
    assert!(
        started.elapsed() < Duration::from_secs(30),
        "stopped long after its limit"
    );
    // The worker is free again: the next job is claimed (and stopped the same way).
    let nid = submit(&c, &base, &body).await;
    let (next, _) = wait_job(&c, &base, &nid, Duration::from_secs(60), is_terminal).await;
    assert_eq!(next["error"]["type"], "urn:sylva:problem:stage-timeout");
}

/// Bad --max-stage-secs values stop the process at start with a clear message.
#[test]
fn a_bad_stage_limit_is_refused_at_start() {
    let dir = tempfile::tempdir().expect("tempdir");
    let err = fails(&mut sylva_command(
        &["worker", "--max-stage-secs", "train=soon"],
        dir.path(),
    ));
    assert!(
        err.contains("--max-stage-secs") && err.contains("train=soon"),
        "{err}"
    );
}

// A worker that stops answering without dying (a frozen process, a stalled VM: its
// heartbeat stops) loses the job after the lease; another worker finishes it, and the frozen
// one, once thawed, is fenced out: it writes nothing over the finished job and carries on.
on_both_databases!(a_frozen_worker_loses_its_job_after_the_lease_and_is_fenced_when_it_thaws);
async fn a_frozen_worker_loses_its_job_after_the_lease_and_is_fenced_when_it_thaws(db: Db) {
    let fx = fixture();
    let a_flags = ["--lease-secs", "2", "--debug-stage-pause-ms", "3000"];
    let (_api, a, (c, base), id) = job_for_a(&db, &fx, &a_flags).await;
    wait_job(&c, &base, &id, Duration::from_secs(60), |j| {
        stage(j, "ingest")["state"] == "running"
    })
    .await;
    let pid = a.child.id() as libc::pid_t;
    // SAFETY: signals to our own child process.
    assert_eq!(unsafe { libc::kill(pid, libc::SIGSTOP) }, 0);
    let _b = db.worker(&fx.data, &["--lease-secs", "2", "--poll-ms", "50"]);
    let (job, _) = wait_job(&c, &base, &id, Duration::from_secs(60), is_terminal).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    assert_eq!(job["attempt"], 2, "{job}");
    let finished = job["finished_at"].clone();

    // SAFETY: as above.
    assert_eq!(unsafe { libc::kill(pid, libc::SIGCONT) }, 0);
    // The thawed worker wakes inside its stage pause, finishes the stage and tries to record
    // it: refused, since the job is no longer its own.
    poll_until(Duration::from_secs(30), 200, async || {
        let text = a.stderr_text();
        if text.contains("lease lost") {
            return Ok(());
        }
        Err(format!("the thawed worker never noticed: {text}"))
    })
    .await;
    let after = get_job(&c, &base, &id).await;
    assert_eq!(after["state"], "succeeded", "{after}");
    assert_eq!(after["attempt"], 2);
    assert_eq!(
        after["finished_at"], finished,
        "overwritten by the fenced worker"
    );
}

/// Cancelling a job that holds the GPU slot hands the slot to the next job within a second.
#[tokio::test(flavor = "multi_thread")]
async fn cancel_frees_the_gpu_slot_within_a_second() {
    // A generated plot (the small fixture has too little to register): its stages up to
    // training run for real.
    let dir = tempfile::tempdir().expect("tempdir");
    let plot = synthetic_plot(dir.path(), 1);
    let data = dir.path().join("data");
    // Two job slots, one GPU slot; the train stage holds its GPU slot for two minutes.
    let srv = serve(
        &data,
        &[
            "--workers",
            "2",
            "--gpu-slots",
            "1",
            "--debug-stage-pause-ms",
            "train=120000",
        ],
    );
    let (c, base) = (client(), srv.base.clone());
    let inputs = json!({
        "lidar": upload(&c, &base, "lidar", &plot.join("lidar.laz")).await,
        "colmap": upload(&c, &base, "colmap", &plot.join("colmap.zip")).await,
        "control_points": upload(&c, &base, "control_points", &plot.join("control_points.csv")).await,
    });
    let body =
        json!({ "inputs": inputs, "params": { "until": "train", "train": { "backend": "cpu" } } });
    let a = submit(&c, &base, &body).await;
    let (job, _) = wait_job(&c, &base, &a, Duration::from_secs(300), |j| {
        is_terminal(j) || stage(j, "train")["state"] == "running"
    })
    .await;
    assert_eq!(job["state"], "running", "{job}");
    let b = submit(&c, &base, &body).await;
    poll_until(Duration::from_secs(300), 100, async || {
        if log_text(&c, &base, &b)
            .await
            .contains("waiting for a GPU slot")
        {
            return Ok(());
        }
        let job = get_job(&c, &base, &b).await;
        let why = format!("the second job never waited for the GPU: {job}");
        assert!(!is_terminal(&job), "{why}");
        Err(why)
    })
    .await;

    let asked = time::OffsetDateTime::now_utc();
    let cancel = |id: &str| send(c.post(format!("{base}/v1/jobs/{id}/cancel")));
    assert_eq!(cancel(&a).await.status(), reqwest::StatusCode::ACCEPTED);
    // The second job's log says when it got the slot (server clock, the same machine's).
    let acquired = poll_until(Duration::from_secs(30), 50, async || {
        let lines = log_lines(&c, &base, &b).await;
        let line = lines
            .into_iter()
            .find(|l| l["message"] == "GPU slot acquired");
        line.ok_or_else(|| "slot never handed on".to_string())
    })
    .await;
    let at = time::OffsetDateTime::parse(
        acquired["ts"].as_str().expect("ts"),
        &time::format_description::well_known::Rfc3339,
    )
    .expect("rfc3339");
    let waited = at - asked;
    assert!(
        waited < time::Duration::seconds(1),
        "the GPU slot came free {waited} after the cancel"
    );
    let (job, _) = wait_job(&c, &base, &a, Duration::from_secs(10), is_terminal).await;
    assert_eq!(job["state"], "canceled");
    cancel(&b).await;
}
