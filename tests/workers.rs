//! Workers as separate processes sharing one job database (an SQLite file, or PostgreSQL):
//! crash take-over and concurrency. Each test runs on both databases.

mod common;

use std::time::Duration;

use common::*;
use serde_json::json;

on_both_databases!(killed_worker_job_is_reclaimed_after_the_lease_with_attempt_2);
async fn killed_worker_job_is_reclaimed_after_the_lease_with_attempt_2(db: Db) {
    let fx = fixture();
    let data = fx.dir.path().join("data");
    let api = db.serve(&data, &["--workers", "0"]);
    let (c, base) = (client(), api.base.clone());
    let inputs = upload_inputs(&c, &base, &fx).await;
    let mut a = db.worker(
        &data,
        &["--lease-secs", "2", "--debug-stage-pause-ms", "60000"],
    );
    let job = create_job(
        &c,
        &base,
        &json!({ "inputs": inputs, "params": { "until": "ingest" } }),
    )
    .await;
    let id = job["id"].as_str().expect("id").to_string();
    let (running, _) = wait_job(&c, &base, &id, Duration::from_secs(60), |j| {
        j["state"] == "running" && stage(j, "ingest")["state"] == "running"
    })
    .await;
    assert_eq!(running["attempt"], 1);

    // A second worker is already running; the first dies mid-stage without a word.
    let _b = db.worker(&data, &["--lease-secs", "2", "--poll-ms", "50"]);
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
    let data = fx.dir.path().join("data");
    let api = db.serve(&data, &["--workers", "0"]);
    let (c, base) = (client(), api.base.clone());
    let inputs = upload_inputs(&c, &base, &fx).await;
    let mut a = db.worker(
        &data,
        &["--lease-secs", "60", "--debug-stage-pause-ms", "60000"],
    );
    let job = create_job(
        &c,
        &base,
        &json!({ "inputs": inputs, "params": { "until": "ingest" } }),
    )
    .await;
    let id = job["id"].as_str().expect("id").to_string();
    wait_job(&c, &base, &id, Duration::from_secs(60), |j| {
        stage(j, "ingest")["state"] == "running"
    })
    .await;
    a.kill();
    // The restarted worker sees that the process holding the job is gone (same host) and
    // does not wait for the 60 s lease.
    let _b = db.worker(&data, &["--lease-secs", "60"]);
    let (job, _) = wait_job(&c, &base, &id, Duration::from_secs(30), is_terminal).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    assert_eq!(job["attempt"], 2);
}

on_both_databases!(eight_clients_create_jobs_while_two_workers_claim_without_lock_errors);
async fn eight_clients_create_jobs_while_two_workers_claim_without_lock_errors(db: Db) {
    let fx = fixture();
    let data = fx.dir.path().join("data");
    let api = db.serve(&data, &["--workers", "0"]);
    let base = api.base.clone();
    let c = client();
    let inputs = upload_inputs(&c, &base, &fx).await;
    let w1 = db.worker(&data, &["--poll-ms", "50"]);
    let w2 = db.worker(&data, &["--poll-ms", "50"]);
    let mut tasks = Vec::new();
    for client_no in 0..8 {
        let (base, inputs) = (base.clone(), inputs.clone());
        tasks.push(tokio::spawn(async move {
            let c = client();
            let mut ids = Vec::new();
            for k in 0..3 {
                let body = json!({ "inputs": inputs, "params": { "until": "ingest", "ingest": { "decode_images": k % 2 == 0 } } });
                let r = c
                    .post(format!("{base}/v1/jobs"))
                    .header("idempotency-key", format!("client-{client_no}-job-{k}"))
                    .json(&body)
                    .send()
                    .await
                    .expect("create");
                assert_eq!(r.status(), reqwest::StatusCode::ACCEPTED, "{:?}", r.text().await);
                let v: serde_json::Value = r.json().await.expect("json");
                ids.push(v["id"].as_str().expect("id").to_string());
                // Poll in between, as clients do.
                let r = c.get(format!("{base}/v1/jobs?limit=5")).send().await.expect("list");
                assert_eq!(r.status(), reqwest::StatusCode::OK);
            }
            ids
        }));
    }
    let mut ids = Vec::new();
    for t in tasks {
        ids.extend(t.await.expect("client task"));
    }
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
    let data = fx.dir.path().join("data");
    let api = db.serve(&data, &["--workers", "0"]);
    let (c, base) = (client(), api.base.clone());
    let inputs = upload_inputs(&c, &base, &fx).await;
    let body = move |k: usize| json!({ "inputs": inputs, "params": { "until": "ingest", "ingest": { "decode_images": k.is_multiple_of(2) } } });

    // Worker A takes the first job and stalls in its stage until it is killed.
    let mut a = db.worker(
        &data,
        &["--lease-secs", "3", "--debug-stage-pause-ms", "60000"],
    );
    let a_pid = a.child.id();
    let first = create_job(&c, &base, &body(0)).await;
    let first = first["id"].as_str().expect("id").to_string();
    wait_job(&c, &base, &first, Duration::from_secs(60), |j| {
        stage(j, "ingest")["state"] == "running"
    })
    .await;

    // B and C join, and 29 more jobs arrive from three clients at once.
    let b = db.worker(&data, &["--poll-ms", "200"]);
    let w_c = db.worker(&data, &["--poll-ms", "200"]);
    let mut tasks = Vec::new();
    for client_no in 0..3 {
        let (base, body) = (base.clone(), body.clone());
        tasks.push(tokio::spawn(async move {
            let c = client();
            let mut ids = Vec::new();
            for k in (1..30).filter(|k| k % 3 == client_no) {
                let job = create_job(&c, &base, &body(k)).await;
                ids.push(job["id"].as_str().expect("id").to_string());
            }
            ids
        }));
    }
    let mut ids = vec![first.clone()];
    for t in tasks {
        ids.extend(t.await.expect("client task"));
    }
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
    let data = fx.dir.path().join("data");
    let srv = serve(
        &data,
        &[
            "--debug-stage-pause-ms",
            "600000",
            "--max-stage-secs",
            "3600,ingest=1",
        ],
    );
    let (c, base) = (client(), srv.base.clone());
    let inputs = upload_inputs(&c, &base, &fx).await;
    let body = json!({ "inputs": inputs, "params": { "until": "ingest" } });
    let started = std::time::Instant::now();
    let job = create_job(&c, &base, &body).await;
    let id = job["id"].as_str().expect("id").to_string();
    let (job, _) = wait_job(&c, &base, &id, Duration::from_secs(60), is_terminal).await;
    assert_eq!(job["state"], "failed", "{job}");
    assert_eq!(
        job["error"]["type"], "urn:sylva:problem:stage-timeout",
        "{job}"
    );
    let detail = job["error"]["detail"].as_str().expect("detail");
    assert!(detail.contains("limit of 1 s"), "{detail}");
    assert_eq!(stage(&job, "ingest")["state"], "failed");
    assert!(
        started.elapsed() < Duration::from_secs(30),
        "stopped long after its limit"
    );
    // The worker is free again: the next job is claimed (and stopped the same way).
    let next = create_job(&c, &base, &body).await;
    let nid = next["id"].as_str().expect("id").to_string();
    let (next, _) = wait_job(&c, &base, &nid, Duration::from_secs(60), is_terminal).await;
    assert_eq!(next["error"]["type"], "urn:sylva:problem:stage-timeout");
}

/// Bad --max-stage-secs values stop the process at start with a clear message.
#[test]
fn a_bad_stage_limit_is_refused_at_start() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = std::process::Command::new(BIN)
        .args(["worker", "--max-stage-secs", "train=soon", "--data"])
        .arg(dir.path())
        .output()
        .expect("run");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
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
    let data = fx.dir.path().join("data");
    let api = db.serve(&data, &["--workers", "0"]);
    let (c, base) = (client(), api.base.clone());
    let inputs = upload_inputs(&c, &base, &fx).await;
    let a = db.worker(
        &data,
        &["--lease-secs", "2", "--debug-stage-pause-ms", "3000"],
    );
    let job = create_job(
        &c,
        &base,
        &json!({ "inputs": inputs, "params": { "until": "ingest" } }),
    )
    .await;
    let id = job["id"].as_str().expect("id").to_string();
    wait_job(&c, &base, &id, Duration::from_secs(60), |j| {
        stage(j, "ingest")["state"] == "running"
    })
    .await;
    let pid = a.child.id() as libc::pid_t;
    // SAFETY: signals to our own child process.
    assert_eq!(unsafe { libc::kill(pid, libc::SIGSTOP) }, 0);
    let _b = db.worker(&data, &["--lease-secs", "2", "--poll-ms", "50"]);
    let (job, _) = wait_job(&c, &base, &id, Duration::from_secs(60), is_terminal).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    assert_eq!(job["attempt"], 2, "{job}");
    let finished = job["finished_at"].clone();

    // SAFETY: as above.
    assert_eq!(unsafe { libc::kill(pid, libc::SIGCONT) }, 0);
    // The thawed worker wakes inside its stage pause, finishes the stage and tries to record
    // it: refused, since the job is no longer its own.
    let deadline = std::time::Instant::now() + Duration::from_secs(30);
    while !a.stderr_text().contains("lease lost") {
        assert!(
            std::time::Instant::now() < deadline,
            "the thawed worker never noticed: {}",
            a.stderr_text()
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
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
    let a = create_job(&c, &base, &body).await;
    let a = a["id"].as_str().expect("id").to_string();
    let (job, _) = wait_job(&c, &base, &a, Duration::from_secs(300), |j| {
        is_terminal(j) || stage(j, "train")["state"] == "running"
    })
    .await;
    assert_eq!(job["state"], "running", "{job}");
    let b = create_job(&c, &base, &body).await;
    let b = b["id"].as_str().expect("id").to_string();
    let deadline = std::time::Instant::now() + Duration::from_secs(300);
    while !log_text(&c, &base, &b)
        .await
        .contains("waiting for a GPU slot")
    {
        let job = get_job(&c, &base, &b).await;
        assert!(
            std::time::Instant::now() < deadline && !is_terminal(&job),
            "the second job never waited for the GPU: {job}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }

    let asked = time::OffsetDateTime::now_utc();
    let r = c
        .post(format!("{base}/v1/jobs/{a}/cancel"))
        .send()
        .await
        .expect("cancel");
    assert_eq!(r.status(), reqwest::StatusCode::ACCEPTED);
    // The second job's log says when it got the slot (server clock, the same machine's).
    let deadline = std::time::Instant::now() + Duration::from_secs(30);
    let acquired = loop {
        let r: serde_json::Value = c
            .get(format!("{base}/v1/jobs/{b}/log"))
            .send()
            .await
            .expect("log")
            .json()
            .await
            .expect("json");
        let line = r["lines"].as_array().and_then(|lines| {
            lines
                .iter()
                .find(|l| l["message"] == "GPU slot acquired")
                .cloned()
        });
        if let Some(line) = line {
            break line;
        }
        assert!(std::time::Instant::now() < deadline, "slot never handed on");
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
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
    c.post(format!("{base}/v1/jobs/{b}/cancel"))
        .send()
        .await
        .expect("cancel b");
}
