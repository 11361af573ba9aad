//! Workers as separate processes sharing one SQLite file: crash take-over and concurrency.

mod common;

use std::time::Duration;

use common::*;
use serde_json::json;

#[tokio::test(flavor = "multi_thread")]
async fn killed_worker_job_is_reclaimed_after_the_lease_with_attempt_2() {
    let fx = fixture();
    let data = fx.dir.path().join("data");
    let api = serve(&data, &["--workers", "0"]);
    let (c, base) = (client(), api.base.clone());
    let inputs = upload_inputs(&c, &base, &fx).await;
    let mut a = worker(
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
    let _b = worker(&data, &["--lease-secs", "2", "--poll-ms", "50"]);
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

#[tokio::test(flavor = "multi_thread")]
async fn a_restarted_worker_recovers_the_jobs_of_a_dead_process_at_once() {
    let fx = fixture();
    let data = fx.dir.path().join("data");
    let api = serve(&data, &["--workers", "0"]);
    let (c, base) = (client(), api.base.clone());
    let inputs = upload_inputs(&c, &base, &fx).await;
    let mut a = worker(
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
    let restarted = std::time::Instant::now();
    let _b = worker(&data, &["--lease-secs", "60"]);
    let (job, _) = wait_job(&c, &base, &id, Duration::from_secs(30), is_terminal).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    assert_eq!(job["attempt"], 2);
    assert!(restarted.elapsed() < Duration::from_secs(30));
}

#[tokio::test(flavor = "multi_thread")]
async fn eight_clients_create_jobs_while_two_workers_claim_without_lock_errors() {
    let fx = fixture();
    let data = fx.dir.path().join("data");
    let api = serve(&data, &["--workers", "0"]);
    let base = api.base.clone();
    let c = client();
    let inputs = upload_inputs(&c, &base, &fx).await;
    let w1 = worker(&data, &["--poll-ms", "50"]);
    let w2 = worker(&data, &["--poll-ms", "50"]);
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
