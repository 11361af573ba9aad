//! Quotas and retention through the API: per-token quotas on unfinished jobs and stored
//! bytes (429 + Retry-After), abandoned uploads expiring, finished jobs losing their files
//! after the retention time (410 Gone) while their record stays, and `sylva gc`.

mod common;

use std::time::Duration;

use common::*;
use reqwest::header::{AUTHORIZATION, HeaderMap, HeaderValue};
use reqwest::{Client, StatusCode};
use serde_json::{Value, json};

fn client_for(token: &str) -> Client {
    let mut h = HeaderMap::new();
    h.insert(
        AUTHORIZATION,
        HeaderValue::from_str(&format!("Bearer {token}")).expect("header"),
    );
    Client::builder()
        .default_headers(h)
        .timeout(Duration::from_secs(60))
        .build()
        .expect("client")
}

fn retry_after(r: &reqwest::Response) -> u64 {
    r.headers()
        .get("retry-after")
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse().ok())
        .expect("a Retry-After in seconds")
}

async fn open_upload(c: &Client, base: &str, size: u64) -> reqwest::Response {
    c.post(format!("{base}/v1/uploads"))
        .json(&json!({ "kind": "lidar", "filename": "more.las", "size": size }))
        .send()
        .await
        .expect("create upload")
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
    let (alice, bob) = (client_for("alice-token"), client_for("bob-token"));
    let a_inputs = upload_inputs(&alice, &base, &fx).await;
    let body = json!({ "inputs": a_inputs, "params": { "until": "ingest" } });
    let first = create_job(&alice, &base, &body).await;
    let first = first["id"].as_str().expect("id").to_string();

    // A second unfinished job for the same token: 429 with Retry-After.
    let r = alice
        .post(format!("{base}/v1/jobs"))
        .json(&body)
        .send()
        .await
        .expect("second job");
    assert!(retry_after(&r) >= 1);
    let p = expect_problem(r, StatusCode::TOO_MANY_REQUESTS).await;
    assert_eq!(p["type"], "urn:sylva:problem:quota-exceeded", "{p}");
    // Bob has his own quota, and cannot use Alice's uploads.
    let r = bob
        .post(format!("{base}/v1/jobs"))
        .json(&body)
        .send()
        .await
        .expect("bob with alice's inputs");
    expect_problem(r, StatusCode::UNPROCESSABLE_ENTITY).await;
    let b_inputs = upload_inputs(&bob, &base, &fx).await;
    let bobs = create_job(
        &bob,
        &base,
        &json!({ "inputs": b_inputs, "params": { "until": "ingest" } }),
    )
    .await;
    let bobs = bobs["id"].as_str().expect("id").to_string();

    // Stored bytes: Alice's inputs leave less than 2000 bytes of her quota.
    let r = open_upload(&alice, &base, 2000).await;
    assert!(retry_after(&r) >= 1);
    let p = expect_problem(r, StatusCode::TOO_MANY_REQUESTS).await;
    assert!(
        p["detail"].as_str().expect("detail").contains("quota"),
        "{p}"
    );
    // A small one fits; left open, it expires after --upload-ttl-secs and the sweep
    // removes its bytes (and gives the quota back).
    let r = open_upload(&alice, &base, 500).await;
    assert_eq!(r.status(), StatusCode::CREATED);
    let open: Value = r.json().await.expect("json");
    let open = open["id"].as_str().expect("id").to_string();
    let r = alice
        .put(format!("{base}/v1/uploads/{open}/parts/0"))
        .body(vec![1u8; 500])
        .send()
        .await
        .expect("part");
    assert_eq!(r.status(), StatusCode::OK);
    assert!(data.join("uploads").join(&open).exists());
    let deadline = std::time::Instant::now() + Duration::from_secs(30);
    loop {
        let u: Value = alice
            .get(format!("{base}/v1/uploads/{open}"))
            .send()
            .await
            .expect("status")
            .json()
            .await
            .expect("json");
        if u["state"] == "expired" && !data.join("uploads").join(&open).exists() {
            break;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "never swept: {u}; {}",
            srv.stderr_text()
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let r = alice
        .put(format!("{base}/v1/uploads/{open}/parts/0"))
        .body(vec![1u8; 500])
        .send()
        .await
        .expect("part");
    expect_problem(r, StatusCode::GONE).await;

    // Once the first job has finished, Alice may submit again.
    let (job, _) = wait_job(&alice, &base, &first, Duration::from_secs(60), is_terminal).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    assert!(job["expires_at"].is_null(), "retention is off: {job}");
    let second = create_job(&alice, &base, &body).await;
    let second = second["id"].as_str().expect("id").to_string();
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
    let out = std::process::Command::new(BIN)
        .args(["gc", "--job-retention-secs", "1", "--data"])
        .arg(&data)
        .output()
        .expect("sylva gc");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{text}");
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
        let r = alice
            .get(format!("{base}{path}"))
            .send()
            .await
            .expect("get");
        expect_problem(r, StatusCode::GONE).await;
    }
    let r = alice
        .post(format!("{base}/v1/jobs/{first}/retry"))
        .send()
        .await
        .expect("retry");
    expect_problem(r, StatusCode::GONE).await;
    // The record, its stage metrics and its log stay.
    let r = alice
        .get(format!("{base}/v1/jobs/{first}/results"))
        .send()
        .await
        .expect("results");
    assert_eq!(r.status(), StatusCode::OK);
    assert!(log_text(&alice, &base, &first).await.contains("ingest"));
    // A job on expired inputs: 410 naming the upload.
    let r = alice
        .post(format!("{base}/v1/jobs"))
        .json(&body)
        .send()
        .await
        .expect("job on expired inputs");
    let p = expect_problem(r, StatusCode::GONE).await;
    assert!(
        p["detail"].as_str().expect("detail").contains("expired"),
        "{p}"
    );
}
