use std::path::Path;
use std::time::Duration;

use reqwest::StatusCode;
use serde_json::{Value, json};

use super::LONG;
use super::common::{self, *};

on_both_databases!(job_lifecycle_through_ingest);
async fn job_lifecycle_through_ingest(db: Db) {
    let fx = fixture();
    let srv = db.serve(&fx.data, &["--part-size", "4096"]);
    let (c, base, mut inputs) = client_with_inputs(&srv, &fx).await;
    inputs["control_points"] = json!(upload(&c, &base, "control_points", &fx.control_points).await);
    inputs["field_dbh"] = json!(upload(&c, &base, "field_dbh", &fx.field_dbh).await);
    let job = create_job(&c, &base, &job_until(&inputs, "ingest")).await;
    let id = id_of(&job);
    // Queued, unless a polling worker claimed it before the answer was read.
    assert!(
        job["state"] == "queued" || job["state"] == "running",
        "{job}"
    );
    assert_eq!(
        job["params"]["anchors"]["outlier_k"], 16,
        "defaults are filled in"
    );

    let (job, progress) = wait_job(&c, &base, &id, LONG, is_terminal).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    assert_eq!(job["attempt"], 1);
    assert_eq!(job["progress"], 1.0);
    assert!(
        progress.windows(2).all(|w| w[1] >= w[0]),
        "progress decreased: {progress:?}"
    );
    let ingest = stage(&job, "ingest");
    assert_eq!(ingest["state"], "done");
    assert_eq!(ingest["metrics"]["lidar"]["points"], fx.lidar_points);
    assert_eq!(ingest["metrics"]["lidar"]["offset"][0], 500_000.0);
    assert_eq!(ingest["metrics"]["colmap"]["images_registered"], 4);
    assert_eq!(ingest["metrics"]["control_points"], 4);
    assert_eq!(ingest["metrics"]["field_trees"], 1);
    assert_eq!(
        job["stages"].as_array().map(Vec::len),
        Some(1),
        "only the stages up to `until`"
    );

    // Results gather the finished stages' reports.
    let job_url = format!("{base}/v1/jobs/{id}");
    let results = send_json(c.get(format!("{job_url}/results"))).await;
    assert_eq!(
        results["stages"]["ingest"]["lidar"]["points"],
        fx.lidar_points
    );

    // Artifacts: listed with hashes, downloadable with ETag and Range.
    let arts = job["artifacts"].as_array().expect("artifacts");
    let names: Vec<&str> = arts.iter().filter_map(|a| a["name"].as_str()).collect();
    for want in [
        "ingest/report.json",
        "ingest/cloud.ply",
        "ingest/sparse/cameras.txt",
    ] {
        assert!(names.contains(&want), "{want} missing from {names:?}");
    }
    let ply = arts
        .iter()
        .find(|a| a["name"] == "ingest/cloud.ply")
        .expect("ply");
    let href = format!("{base}{}", ply["href"].as_str().expect("href"));
    let full = send(c.get(&href)).await;
    assert_eq!(full.status(), StatusCode::OK);
    let etag = full.headers()["etag"].to_str().expect("etag").to_string();
    assert_eq!(
        etag,
        format!("\"{}\"", ply["sha256"].as_str().expect("sha"))
    );
    let body = full.bytes().await.expect("bytes");
    assert_eq!(body.len() as u64, ply["size"].as_u64().expect("size"));
    assert_eq!(sha256_hex(&body), ply["sha256"].as_str().expect("sha"));
    assert!(body.starts_with(b"ply\n"));
    let cached = send(c.get(&href).header("if-none-match", &etag)).await;
    assert_eq!(cached.status(), StatusCode::NOT_MODIFIED);
    let range = |bytes: String| send(c.get(&href).header("range", format!("bytes={bytes}")));
    let part = range("0-9".into()).await;
    assert_eq!(part.status(), StatusCode::PARTIAL_CONTENT);
    assert_eq!(
        part.headers()["content-range"],
        format!("bytes 0-9/{}", body.len()).as_str()
    );
    assert_eq!(part.bytes().await.expect("bytes").as_ref(), &body[..10]);
    let tail = range("-4".into()).await;
    assert_eq!(
        tail.bytes().await.expect("bytes").as_ref(),
        &body[body.len() - 4..]
    );
    let bad = range(format!("{}-", body.len() + 10)).await;
    assert_eq!(
        bad.headers()["content-range"],
        format!("bytes */{}", body.len()).as_str()
    );
    expect_problem(bad, StatusCode::RANGE_NOT_SATISFIABLE).await;
    let encoded = send(c.get(format!("{job_url}/artifacts/ingest%2Freport.json"))).await;
    assert_eq!(encoded.status(), StatusCode::OK);
    let escape = c.get(format!("{job_url}/artifacts/ingest/../../sylva.db"));
    send_problem(escape, StatusCode::NOT_FOUND).await;
    object_store_holds_the_blobs(&db, &fx.data, &id, ply).await;
    // No inventory before stage dbh.
    send_problem(c.get(format!("{job_url}/trees.csv")), StatusCode::NOT_FOUND).await;

    // Log and events.
    let log = log_text(&c, &base, &id).await;
    assert!(log.contains("stage ingest finished"), "{log}");
    let events = send(c.get(format!("{job_url}/events"))).await;
    assert_eq!(events.headers()["content-type"], "text/event-stream");
    let text = tokio::time::timeout(Duration::from_secs(20), events.text())
        .await
        .expect("stream ends")
        .expect("text");
    assert!(text.contains("event: job"), "{text}");
    assert!(text.contains("event: log"), "{text}");
    assert!(text.contains("event: end"), "{text}");
    assert!(text.contains("\"state\":\"succeeded\""), "{text}");

    // Listing with a cursor.
    let list = send_json(c.get(format!("{base}/v1/jobs?state=succeeded&limit=1"))).await;
    assert_eq!(list["jobs"][0]["id"], id.as_str());

    // Metrics count it.
    let metrics = send(c.get(format!("{base}/metrics"))).await;
    let metrics = metrics.text().await.expect("text");
    for counted in [
        "sylva_jobs{state=\"succeeded\"} 1",
        "sylva_stage_duration_seconds_count{stage=\"ingest\"} 1",
    ] {
        assert!(metrics.contains(counted), "{metrics}");
    }
    assert!(
        !metrics.contains("sylva_upload_bytes_total 0\n"),
        "{metrics}"
    );

    // Delete: gone from the API and from disk.
    let del = send(c.delete(&job_url)).await;
    assert_eq!(del.status(), StatusCode::NO_CONTENT);
    send_problem(c.get(&job_url), StatusCode::NOT_FOUND).await;
    assert!(!fx.data.join("jobs").join(&id).exists());
    if let Some(bucket) = db.bucket() {
        let keys = bucket.keys();
        assert!(
            !keys
                .iter()
                .any(|k| k.starts_with(&format!("sylva/jobs/{id}/"))),
            "the job's objects outlive it: {keys:?}"
        );
    }
}

/// With an object store, another API replica on another machine (its own empty data
/// directory) serves what a worker stored, and large artifacts go out as presigned redirects.
async fn object_store_holds_the_blobs(db: &Db, data: &Path, id: &str, ply: &Value) {
    let Some(bucket) = db.bucket() else {
        return;
    };
    let keys = bucket.keys();
    for want in [
        format!("sylva/jobs/{id}/ingest/cloud.ply"),
        format!("sylva/jobs/{id}/ingest/report.json"),
    ] {
        assert!(keys.contains(&want), "{want} not in the bucket: {keys:?}");
    }
    assert!(
        keys.iter()
            .any(|k| k.starts_with("sylva/uploads/") && k.contains("/blob.")),
        "no upload blob in the bucket: {keys:?}"
    );
    assert!(
        !keys.iter().any(|k| k.contains("/parts/")),
        "parts of completed uploads remain: {keys:?}"
    );
    let replica = db.serve(data, &["--workers", "0", "--presign-min-bytes", "0"]);
    let href = format!("{}{}", replica.base, ply["href"].as_str().expect("href"));
    let no_follow = reqwest::Client::builder()
        .redirect(reqwest::redirect::Policy::none())
        .build()
        .expect("client");
    let r = send(no_follow.get(&href)).await;
    assert_eq!(r.status(), StatusCode::TEMPORARY_REDIRECT);
    let location = r.headers()["location"]
        .to_str()
        .expect("location")
        .to_string();
    assert!(location.contains("X-Amz-Signature="), "{location}");
    let body = send(client().get(&href))
        .await
        .bytes()
        .await
        .expect("bytes");
    assert_eq!(sha256_hex(&body), ply["sha256"].as_str().expect("sha"));
    let replica = db.serve(data, &["--workers", "0"]);
    let href = format!("{}{}", replica.base, ply["href"].as_str().expect("href"));
    let part = send(no_follow.get(&href).header("range", "bytes=4-11")).await;
    assert_eq!(part.status(), StatusCode::PARTIAL_CONTENT);
    let full = send(client().get(&href))
        .await
        .bytes()
        .await
        .expect("bytes");
    assert_eq!(part.bytes().await.expect("bytes").as_ref(), &full[4..12]);
}

on_both_databases!(a_failed_stage_fails_the_job_clearly_and_retry_resumes_there);
async fn a_failed_stage_fails_the_job_clearly_and_retry_resumes_there(db: Db) {
    let fx = fixture();
    let srv = db.serve(&fx.data, &[]);
    let (c, base, inputs) = client_with_inputs(&srv, &fx).await;
    let id = submit(&c, &base, &json!({ "inputs": inputs })).await;
    let (job, _) = wait_job(&c, &base, &id, LONG, is_terminal).await;
    assert_eq!(job["state"], "failed");
    assert_eq!(job["stage"], "register");
    // The fixture's photos do not show its LiDAR scene: the automatic alignment (what a job
    // without control points does) refuses, saying what to supply.
    assert!(
        detail(&job["error"]).contains("automatic registration")
            && detail(&job["error"]).contains("supply control points"),
        "{job}"
    );
    assert_eq!(job["error"]["status"], 422);
    assert_eq!(stage(&job, "ingest")["state"], "done");
    assert_eq!(stage(&job, "register")["state"], "failed");
    let ingest_done_at = stage(&job, "ingest")["finished_at"].clone();

    // A stage after the first unfinished one cannot be the restart point.
    let retry = |base: &str, id: &str| c.post(format!("{base}/v1/jobs/{id}/retry"));
    for from in ["train", "nope"] {
        let from_stage = retry(&base, &id).json(&json!({ "from_stage": from }));
        send_problem(from_stage, StatusCode::UNPROCESSABLE_ENTITY).await;
    }

    // With an object store the retry runs on another machine (a fresh data directory), which
    // fetches ingest's outputs from the store instead of running it again.
    let srv = if db.bucket().is_some() {
        drop(srv);
        db.serve(&fx.data, &[])
    } else {
        srv
    };
    let base = srv.base.clone();

    // Retry without a stage resumes at register: ingest is not run again.
    let r = send(retry(&base, &id)).await;
    assert_eq!(r.status(), StatusCode::ACCEPTED);
    let (job, _) = wait_job(&c, &base, &id, LONG, is_terminal).await;
    assert_eq!(job["state"], "failed");
    assert_eq!(
        stage(&job, "ingest")["finished_at"],
        ingest_done_at,
        "ingest was not redone"
    );
    assert!(
        detail(&job["error"]).contains("supply control points"),
        "{job}"
    );
    if db.bucket().is_some() {
        let log = log_text(&c, &base, &id).await;
        assert!(log.contains("from the object store"), "{log}");
    }

    // Retry from ingest runs it again.
    let r = send(retry(&base, &id).json(&json!({ "from_stage": "ingest" }))).await;
    assert_eq!(r.status(), StatusCode::ACCEPTED);
    let (job, _) = wait_job(&c, &base, &id, LONG, |j| {
        is_terminal(j) && stage(j, "ingest")["state"] == "done"
    })
    .await;
    assert_eq!(job["state"], "failed");
    assert_ne!(
        stage(&job, "ingest")["finished_at"],
        ingest_done_at,
        "ingest ran again"
    );
    let log = log_text(&c, &base, &id).await;
    assert!(log.contains("retry requested from stage ingest"), "{log}");

    // A running or queued job cannot be retried or deleted.
    let qid = submit(&c, &base, &job_until(&inputs, "ingest")).await;
    let (done, _) = wait_job(&c, &base, &qid, LONG, is_terminal).await;
    assert_eq!(done["state"], "succeeded");
    send_problem(retry(&base, &qid), StatusCode::CONFLICT).await;
}

on_both_databases!(same_idempotency_key_gives_one_job);
async fn same_idempotency_key_gives_one_job(db: Db) {
    let fx = fixture();
    let srv = db.serve(&fx.data, &["--workers", "0"]);
    let (c, base, inputs) = client_with_inputs(&srv, &fx).await;
    let keyed = |key: &str, body: &Value| {
        c.post(format!("{base}/v1/jobs"))
            .header("idempotency-key", key)
            .json(body)
    };
    let body = job_until(&inputs, "ingest");
    let mut ids = Vec::new();
    for _ in 0..3 {
        let r = send(keyed("plot-7-upload-1", &body)).await;
        assert_eq!(r.status(), StatusCode::ACCEPTED);
        assert!(r.headers().contains_key("location"));
        let v: Value = r.json().await.expect("json");
        ids.push(id_of(&v));
    }
    assert!(ids.iter().all(|i| *i == ids[0]), "{ids:?}");
    let list = send_json(c.get(format!("{base}/v1/jobs"))).await;
    assert_eq!(list["jobs"].as_array().map(Vec::len), Some(1));
    // The same key with another request is refused.
    let other = job_until(&inputs, "register");
    let r = keyed("plot-7-upload-1", &other);
    send_problem(r, StatusCode::UNPROCESSABLE_ENTITY).await;
    // A different key makes a second job; list pages through both with the cursor.
    let r = send(keyed("plot-7-upload-2", &body)).await;
    assert_eq!(r.status(), StatusCode::ACCEPTED);
    let page1 = send_json(c.get(format!("{base}/v1/jobs?limit=1"))).await;
    let cursor = page1["next_cursor"].as_str().expect("cursor");
    let page2 = send_json(c.get(format!("{base}/v1/jobs?limit=1&cursor={cursor}"))).await;
    assert_eq!(page2["jobs"][0]["id"], ids[0].as_str());
    assert_ne!(page1["jobs"][0]["id"], ids[0].as_str());
}

on_both_databases!(cancel_stops_running_and_queued_jobs);
async fn cancel_stops_running_and_queued_jobs(db: Db) {
    let fx = fixture();
    let srv = db.serve(&fx.data, &["--debug-stage-pause-ms", "60000"]);
    let (c, base, inputs) = client_with_inputs(&srv, &fx).await;
    let body = job_until(&inputs, "ingest");
    let rid = submit(&c, &base, &body).await;
    let qid = submit(&c, &base, &body).await;
    wait_job(&c, &base, &rid, LONG, |j| {
        j["state"] == "running" && j["stage"] == "ingest"
    })
    .await;
    let cancel = |id: &str| c.post(format!("{base}/v1/jobs/{id}/cancel"));

    // The queued one is canceled at once.
    let r = send(cancel(&qid)).await;
    assert_eq!(r.status(), StatusCode::ACCEPTED);
    let v: Value = r.json().await.expect("json");
    assert_eq!(v["state"], "canceled");

    // The running one is asked to stop and stops promptly.
    let r = send(cancel(&rid)).await;
    assert_eq!(r.status(), StatusCode::ACCEPTED);
    let v: Value = r.json().await.expect("json");
    assert!(
        matches!(v["state"].as_str(), Some("canceling" | "canceled")),
        "{v}"
    );
    let (job, _) = wait_job(&c, &base, &rid, Duration::from_secs(10), is_terminal).await;
    assert_eq!(job["state"], "canceled");
    assert_eq!(stage(&job, "ingest")["state"], "canceled");

    // A finished job cannot be canceled again.
    send_problem(cancel(&rid), StatusCode::CONFLICT).await;
}

on_both_databases!(one_request_multipart_submission_runs);
async fn one_request_multipart_submission_runs(db: Db) {
    let fx = fixture();
    let srv = db.serve(&fx.data, &[]);
    let (c, base) = (client(), srv.base.clone());
    let files = [
        ("lidar", &fx.lidar),
        ("colmap", &fx.colmap_zip),
        ("field_dbh", &fx.field_dbh),
    ];
    let form = multipart(&files).text("params", r#"{"until": "ingest"}"#);
    let r = send(c.post(format!("{base}/v1/jobs")).multipart(form)).await;
    assert_eq!(r.status(), StatusCode::ACCEPTED, "{:?}", r.text().await);
    let v: Value = r.json().await.expect("json");
    let id = id_of(&v);
    let (job, _) = wait_job(&c, &base, &id, LONG, is_terminal).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    assert_eq!(stage(&job, "ingest")["metrics"]["field_trees"], 1);
    // Missing colmap part.
    let form = multipart(&[("lidar", &fx.lidar)]);
    let r = c.post(format!("{base}/v1/jobs")).multipart(form);
    send_problem(r, StatusCode::UNPROCESSABLE_ENTITY).await;
}

on_both_databases!(a_fuzz_finding_fails_its_job_and_the_worker_runs_the_next);
/// Issue 43: each LAZ the fuzzer found (fuzz/regressions/laz/, kept after the fixes) sent as a
/// job's LiDAR is refused at submission (422 naming the file) or runs to an end: `failed` with
/// a problem naming the file where Sylva's reader refuses it, `succeeded` only where the reader
/// accepts it (one finding broke a debug assertion of the LAZ decoder's that release builds
/// leave out). The worker survives them all and the next job, on good inputs, succeeds.
async fn a_fuzz_finding_fails_its_job_and_the_worker_runs_the_next(db: Db) {
    let fx = fixture();
    let srv = db.serve(&fx.data, &[]);
    let (c, base) = (client(), srv.base.clone());
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/regressions/laz");
    let mut findings: Vec<std::path::PathBuf> = std::fs::read_dir(&dir)
        .expect("fuzz/regressions/laz")
        .filter_map(Result::ok)
        .map(|e| e.path())
        .collect();
    findings.sort();
    assert!(!findings.is_empty(), "no findings in {}", dir.display());
    let (mut refused, mut failed, mut read) = (0, 0, 0);
    let scratch = tempfile::tempdir().expect("scratch");
    for f in &findings {
        let accepted =
            sylva::pipeline::fuzz::run("laz", &std::fs::read(f).expect("finding"), scratch.path())
                .is_ok();
        // Named .laz, as a user's upload would be.
        let laz = fx.dir.path().join("finding.laz");
        std::fs::copy(f, &laz).expect("copy");
        let form = multipart(&[("lidar", &laz), ("colmap", &fx.colmap_zip)])
            .text("params", r#"{"until": "ingest"}"#);
        let r = send(c.post(format!("{base}/v1/jobs")).multipart(form)).await;
        if r.status() == StatusCode::UNPROCESSABLE_ENTITY {
            let p: Value = r.json().await.expect("problem");
            assert!(
                p.to_string().contains("finding.laz"),
                "{}: {p}",
                f.display()
            );
            refused += 1;
            continue;
        }
        assert_eq!(r.status(), StatusCode::ACCEPTED, "{}", f.display());
        let id = id_of(&r.json().await.expect("json"));
        let (job, _) = wait_job(&c, &base, &id, LONG, is_terminal).await;
        if accepted {
            assert_eq!(job["state"], "succeeded", "{}: {job}", f.display());
            read += 1;
            continue;
        }
        assert_eq!(job["state"], "failed", "{}: {job}", f.display());
        let why = detail(&job["error"]);
        assert!(
            why.contains("finding.laz") || why.contains("lidar"),
            "{}: {job}",
            f.display()
        );
        failed += 1;
    }
    eprintln!("{refused} refused at submission, {failed} failed, {read} read");
    assert_eq!(refused + failed + read, findings.len());
    assert!(refused + failed > 0, "every finding was read");
    let form = multipart(&[("lidar", &fx.lidar), ("colmap", &fx.colmap_zip)])
        .text("params", r#"{"until": "ingest"}"#);
    let r = send(c.post(format!("{base}/v1/jobs")).multipart(form)).await;
    assert_eq!(r.status(), StatusCode::ACCEPTED);
    let id = id_of(&r.json().await.expect("json"));
    let (job, _) = wait_job(&c, &base, &id, LONG, is_terminal).await;
    assert_eq!(
        job["state"], "succeeded",
        "after {refused} refused and {failed} failed: {job}"
    );
}
