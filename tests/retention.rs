//! Quotas and retention through the API: per-token quotas on unfinished jobs and stored
//! bytes (429 + Retry-After), abandoned uploads expiring, finished jobs losing their files
//! after the retention time (410 Gone) while their record stays, and `sylva gc`.

mod common;

use std::time::Duration;

use common::*;
use reqwest::{Client, StatusCode};
use serde_json::json;

fn retry_after(r: &reqwest::Response) -> u64 {
    r.headers()
        .get("retry-after")
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse().ok())
        .expect("a Retry-After in seconds")
}

/// Opens an upload of `size` bytes; the answer.
async fn open_more(c: &Client, base: &str, size: u64) -> reqwest::Response {
    let body = json!({ "kind": "lidar", "filename": "more.las", "size": size });
    send(c.post(format!("{base}/v1/uploads")).json(&body)).await
}

#[tokio::test(flavor = "multi_thread")]
async fn quotas_are_per_token_and_retention_removes_files_but_keeps_records() {
    let fx = fixture();
    let data = fx.dir.path().join("data");
    let inputs_bytes = std::fs::metadata(&fx.lidar).expect("lidar").len()
        + std::fs::metadata(&fx.colmap_zip).expect("zip").len();
    let quota = inputs_bytes + 1000;
    let quota_arg = quota.to_string();
    // Phase 1: quotas, with files kept for ever and every stage held for a moment.
    let srv = serve(
        &data,
        &[
            "--token",
            "alice-token,bob-token",
            "--quota-jobs",
            "1",
            "--quota-bytes",
            &quota_arg,
            "--job-retention-secs",
            "0",
            "--upload-ttl-secs",
            "1",
            "--gc-interval-secs",
            "1",
            "--debug-stage-pause-ms",
            "2000",
        ],
    );
    let base = srv.base.clone();
    let (alice, bob) = (keyed_client("alice-token"), keyed_client("bob-token"));
    let a_inputs = upload_inputs(&alice, &base, &fx).await;
    let body = job_until(&a_inputs, "ingest");
    let first = submit(&alice, &base, &body).await;
    let new_job = |c: &Client| c.post(format!("{base}/v1/jobs")).json(&body);

    // A second unfinished job for the same token: 429 with Retry-After.
    let r = send(new_job(&alice)).await;
    assert!(retry_after(&r) >= 1);
    let p = expect_problem(r, StatusCode::TOO_MANY_REQUESTS).await;
    assert_eq!(p["type"], "urn:sylva:problem:quota-exceeded", "{p}");
    // Bob has his own quota, and cannot use Alice's uploads.
    send_problem(new_job(&bob), StatusCode::UNPROCESSABLE_ENTITY).await;
    let b_inputs = upload_inputs(&bob, &base, &fx).await;
    let bobs = submit(&bob, &base, &job_until(&b_inputs, "ingest")).await;

    // Stored bytes: Alice's inputs leave less than 2000 bytes of her quota.
    let r = open_more(&alice, &base, 2000).await;
    assert!(retry_after(&r) >= 1);
    let p = expect_problem(r, StatusCode::TOO_MANY_REQUESTS).await;
    assert!(detail(&p).contains("quota"), "{p}");
    // A small one fits; left open, it expires after --upload-ttl-secs and the sweep
    // removes its bytes (and gives the quota back).
    let r = open_more(&alice, &base, 500).await;
    assert_eq!(r.status(), StatusCode::CREATED);
    let open = id_of(&r.json().await.expect("json"));
    let part = || put_part(&alice, &base, &open, 0, vec![1u8; 500]);
    assert_eq!(part().await.status(), StatusCode::OK);
    assert!(data.join("uploads").join(&open).exists());
    poll_until(Duration::from_secs(30), 200, async || {
        let u = send_json(alice.get(format!("{base}/v1/uploads/{open}"))).await;
        if u["state"] == "expired" && !data.join("uploads").join(&open).exists() {
            return Ok(());
        }
        Err(format!("never swept: {u}; {}", srv.stderr_text()))
    })
    .await;
    expect_problem(part().await, StatusCode::GONE).await;

    // Once the first job has finished, Alice may submit again.
    let (job, _) = wait_job(&alice, &base, &first, Duration::from_secs(60), is_terminal).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    assert!(job["expires_at"].is_null(), "retention is off: {job}");
    let second = submit(&alice, &base, &body).await;
    wait_job(&alice, &base, &second, Duration::from_secs(60), is_terminal).await;
    wait_job(&bob, &base, &bobs, Duration::from_secs(60), is_terminal).await;
    drop(srv);

    // Phase 2: the same data with a retention of one second, swept by `sylva gc` while the
    // server runs.
    let srv = serve(
        &data,
        &[
            "--token",
            "alice-token,bob-token",
            "--job-retention-secs",
            "1",
            "--gc-interval-secs",
            "0",
        ],
    );
    let base = srv.base.clone();
    let job = get_job(&alice, &base, &first).await;
    assert!(job["expires_at"].is_string(), "{job}");
    let artifact = job["artifacts"][0]["href"]
        .as_str()
        .expect("an artifact")
        .to_string();
    tokio::time::sleep(Duration::from_millis(1200)).await;
    let out = succeeds(&mut sylva_command(
        &["gc", "--job-retention-secs", "1"],
        &data,
    ));
    let text = String::from_utf8_lossy(&out.stdout);
    let count = |label: &str| -> u64 {
        text.lines()
            .find_map(|l| l.strip_prefix(label))
            .and_then(|v| v.trim().parse().ok())
            .unwrap_or_else(|| panic!("no {label:?} in {text}"))
    };
    assert_eq!(count("jobs purged:"), 3, "{text}");
    // The inputs, read by no job with files any more, expire in the same sweep.
    assert_eq!(count("uploads expired:"), 4, "{text}");
    assert!(count("bytes freed:") >= 2 * inputs_bytes, "{text}");
    let left: Vec<_> = std::fs::read_dir(data.join("uploads"))
        .map(|d| d.flatten().map(|e| e.file_name()).collect())
        .unwrap_or_default();
    assert!(left.is_empty(), "upload folders left: {left:?}");

    let job = get_job(&alice, &base, &first).await;
    assert_eq!(job["state"], "succeeded");
    assert!(job["purged_at"].is_string(), "{job}");
    assert_eq!(job["artifacts"], json!([]), "{job}");
    assert!(!data.join("jobs").join(&first).exists(), "files left");
    for path in [artifact, format!("/v1/jobs/{first}/trees.csv")] {
        send_problem(alice.get(format!("{base}{path}")), StatusCode::GONE).await;
    }
    let retry = alice.post(format!("{base}/v1/jobs/{first}/retry"));
    send_problem(retry, StatusCode::GONE).await;
    // The record, its stage metrics and its log stay.
    let r = send(alice.get(format!("{base}/v1/jobs/{first}/results"))).await;
    assert_eq!(r.status(), StatusCode::OK);
    assert!(log_text(&alice, &base, &first).await.contains("ingest"));
    // A job on expired inputs: 410 naming the upload.
    let new_job = alice.post(format!("{base}/v1/jobs")).json(&body);
    let p = send_problem(new_job, StatusCode::GONE).await;
    assert!(detail(&p).contains("expired"), "{p}");
}
