//! The API against a real server process, a real HTTP client and a real job database: the
//! tests that exercise the queue and the upload records run on SQLite and on PostgreSQL.

mod common;

use std::path::Path;
use std::time::Duration;

use common::*;
use reqwest::StatusCode;
use serde_json::{Value, json};

const LONG: Duration = Duration::from_secs(120);

on_both_databases!(job_lifecycle_through_ingest);
async fn job_lifecycle_through_ingest(db: Db) {
    let fx = fixture();
    let data = fx.dir.path().join("data");
    let srv = db.serve(&data, &["--part-size", "4096"]);
    let (c, base) = (client(), srv.base.clone());
    let mut inputs = upload_inputs(&c, &base, &fx).await;
    inputs["control_points"] = json!(upload(&c, &base, "control_points", &fx.control_points).await);
    inputs["field_dbh"] = json!(upload(&c, &base, "field_dbh", &fx.field_dbh).await);
    let job = create_job(
        &c,
        &base,
        &json!({ "inputs": inputs, "params": { "until": "ingest" } }),
    )
    .await;
    let id = job["id"].as_str().expect("id").to_string();
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
    let results: Value = c
        .get(format!("{base}/v1/jobs/{id}/results"))
        .send()
        .await
        .expect("results")
        .json()
        .await
        .expect("json");
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
    let full = c.get(&href).send().await.expect("get");
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
    let cached = c
        .get(&href)
        .header("if-none-match", &etag)
        .send()
        .await
        .expect("get");
    assert_eq!(cached.status(), StatusCode::NOT_MODIFIED);
    let part = c
        .get(&href)
        .header("range", "bytes=0-9")
        .send()
        .await
        .expect("range");
    assert_eq!(part.status(), StatusCode::PARTIAL_CONTENT);
    assert_eq!(
        part.headers()["content-range"],
        format!("bytes 0-9/{}", body.len()).as_str()
    );
    assert_eq!(part.bytes().await.expect("bytes").as_ref(), &body[..10]);
    let tail = c
        .get(&href)
        .header("range", "bytes=-4")
        .send()
        .await
        .expect("range");
    assert_eq!(
        tail.bytes().await.expect("bytes").as_ref(),
        &body[body.len() - 4..]
    );
    let bad = c
        .get(&href)
        .header("range", format!("bytes={}-", body.len() + 10))
        .send()
        .await
        .expect("range");
    assert_eq!(
        bad.headers()["content-range"],
        format!("bytes */{}", body.len()).as_str()
    );
    expect_problem(bad, StatusCode::RANGE_NOT_SATISFIABLE).await;
    let encoded = c
        .get(format!(
            "{base}/v1/jobs/{id}/artifacts/ingest%2Freport.json"
        ))
        .send()
        .await
        .expect("get");
    assert_eq!(encoded.status(), StatusCode::OK);
    expect_problem(
        c.get(format!(
            "{base}/v1/jobs/{id}/artifacts/ingest/../../sylva.db"
        ))
        .send()
        .await
        .expect("get"),
        StatusCode::NOT_FOUND,
    )
    .await;
    object_store_holds_the_blobs(&db, &data, &id, ply).await;
    // No inventory before stage dbh.
    expect_problem(
        c.get(format!("{base}/v1/jobs/{id}/trees.csv"))
            .send()
            .await
            .expect("get"),
        StatusCode::NOT_FOUND,
    )
    .await;

    // Log and events.
    let log = log_text(&c, &base, &id).await;
    assert!(log.contains("stage ingest finished"), "{log}");
    let events = c
        .get(format!("{base}/v1/jobs/{id}/events"))
        .send()
        .await
        .expect("events");
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
    let list: Value = c
        .get(format!("{base}/v1/jobs?state=succeeded&limit=1"))
        .send()
        .await
        .expect("list")
        .json()
        .await
        .expect("json");
    assert_eq!(list["jobs"][0]["id"], id.as_str());

    // Metrics count it.
    let metrics = c
        .get(format!("{base}/metrics"))
        .send()
        .await
        .expect("metrics")
        .text()
        .await
        .expect("text");
    assert!(
        metrics.contains("sylva_jobs{state=\"succeeded\"} 1"),
        "{metrics}"
    );
    assert!(
        metrics.contains("sylva_stage_duration_seconds_count{stage=\"ingest\"} 1"),
        "{metrics}"
    );
    assert!(
        !metrics.contains("sylva_upload_bytes_total 0\n"),
        "{metrics}"
    );

    // Delete: gone from the API and from disk.
    let del = c
        .delete(format!("{base}/v1/jobs/{id}"))
        .send()
        .await
        .expect("delete");
    assert_eq!(del.status(), StatusCode::NO_CONTENT);
    expect_problem(
        c.get(format!("{base}/v1/jobs/{id}"))
            .send()
            .await
            .expect("get"),
        StatusCode::NOT_FOUND,
    )
    .await;
    assert!(!data.join("jobs").join(&id).exists());
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
    let r = no_follow.get(&href).send().await.expect("get");
    assert_eq!(r.status(), StatusCode::TEMPORARY_REDIRECT);
    let location = r.headers()["location"]
        .to_str()
        .expect("location")
        .to_string();
    assert!(location.contains("X-Amz-Signature="), "{location}");
    let body = client()
        .get(&href)
        .send()
        .await
        .expect("get")
        .bytes()
        .await
        .expect("bytes");
    assert_eq!(sha256_hex(&body), ply["sha256"].as_str().expect("sha"));
    let replica = db.serve(data, &["--workers", "0"]);
    let href = format!("{}{}", replica.base, ply["href"].as_str().expect("href"));
    let part = no_follow
        .get(&href)
        .header("range", "bytes=4-11")
        .send()
        .await
        .expect("range");
    assert_eq!(part.status(), StatusCode::PARTIAL_CONTENT);
    let full = client().get(&href).send().await.expect("get");
    let full = full.bytes().await.expect("bytes");
    assert_eq!(part.bytes().await.expect("bytes").as_ref(), &full[4..12]);
}

on_both_databases!(a_failed_stage_fails_the_job_clearly_and_retry_resumes_there);
async fn a_failed_stage_fails_the_job_clearly_and_retry_resumes_there(db: Db) {
    let fx = fixture();
    let srv = db.serve(&fx.dir.path().join("data"), &[]);
    let (c, base) = (client(), srv.base.clone());
    let inputs = upload_inputs(&c, &base, &fx).await;
    let job = create_job(&c, &base, &json!({ "inputs": inputs })).await;
    let id = job["id"].as_str().expect("id").to_string();
    let (job, _) = wait_job(&c, &base, &id, LONG, is_terminal).await;
    assert_eq!(job["state"], "failed");
    assert_eq!(job["stage"], "register");
    // The fixture's photos do not show its LiDAR scene: registration refuses clearly.
    let detail = job["error"]["detail"].as_str().expect("detail");
    assert!(detail.contains("control points are required"), "{detail}");
    assert_eq!(job["error"]["status"], 422);
    assert_eq!(stage(&job, "ingest")["state"], "done");
    assert_eq!(stage(&job, "register")["state"], "failed");
    let ingest_done_at = stage(&job, "ingest")["finished_at"].clone();

    // A stage after the first unfinished one cannot be the restart point.
    let r = c
        .post(format!("{base}/v1/jobs/{id}/retry"))
        .json(&json!({ "from_stage": "train" }))
        .send()
        .await
        .expect("retry");
    expect_problem(r, StatusCode::UNPROCESSABLE_ENTITY).await;
    let r = c
        .post(format!("{base}/v1/jobs/{id}/retry"))
        .json(&json!({ "from_stage": "nope" }))
        .send()
        .await
        .expect("retry");
    expect_problem(r, StatusCode::UNPROCESSABLE_ENTITY).await;

    // With an object store the retry runs on another machine (a fresh data directory), which
    // fetches ingest's outputs from the store instead of running it again.
    let srv = if db.bucket().is_some() {
        drop(srv);
        db.serve(&fx.dir.path().join("data"), &[])
    } else {
        srv
    };
    let base = srv.base.clone();

    // Retry without a stage resumes at register: ingest is not run again.
    let r = c
        .post(format!("{base}/v1/jobs/{id}/retry"))
        .send()
        .await
        .expect("retry");
    assert_eq!(r.status(), StatusCode::ACCEPTED);
    let (job, _) = wait_job(&c, &base, &id, LONG, is_terminal).await;
    assert_eq!(job["state"], "failed");
    assert_eq!(
        stage(&job, "ingest")["finished_at"],
        ingest_done_at,
        "ingest was not redone"
    );
    let detail = job["error"]["detail"].as_str().expect("detail");
    assert!(detail.contains("control points are required"), "{detail}");
    if db.bucket().is_some() {
        let log = log_text(&c, &base, &id).await;
        assert!(log.contains("from the object store"), "{log}");
    }

    // Retry from ingest runs it again.
    let r = c
        .post(format!("{base}/v1/jobs/{id}/retry"))
        .json(&json!({ "from_stage": "ingest" }))
        .send()
        .await
        .expect("retry");
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
    let queued = create_job(
        &c,
        &base,
        &json!({ "inputs": inputs, "params": { "until": "ingest" } }),
    )
    .await;
    let qid = queued["id"].as_str().expect("id");
    let (done, _) = wait_job(&c, &base, qid, LONG, is_terminal).await;
    assert_eq!(done["state"], "succeeded");
    let r = c
        .post(format!("{base}/v1/jobs/{qid}/retry"))
        .send()
        .await
        .expect("retry");
    expect_problem(r, StatusCode::CONFLICT).await;
}

on_both_databases!(upload_interrupted_and_resumed_with_repeated_part);
async fn upload_interrupted_and_resumed_with_repeated_part(db: Db) {
    let fx = fixture();
    let srv = db.serve(&fx.dir.path().join("data"), &["--part-size", "1024"]);
    let (c, base) = (client(), srv.base.clone());
    let bytes = std::fs::read(&fx.lidar).expect("read");
    assert!(bytes.len() > 5 * 1024);
    let created = c
        .post(format!("{base}/v1/uploads"))
        .json(&json!({ "kind": "lidar", "filename": "plot.las", "size": bytes.len(), "sha256": sha256_hex(&bytes) }))
        .send()
        .await
        .expect("create");
    assert_eq!(created.status(), StatusCode::CREATED);
    assert!(created.headers().contains_key("location"));
    let created: Value = created.json().await.expect("json");
    let id = created["id"].as_str().expect("id").to_string();
    let parts: Vec<&[u8]> = bytes.chunks(1024).collect();
    assert_eq!(created["parts_total"], parts.len());

    // The connection "dies" after two parts.
    for (n, p) in parts.iter().enumerate().take(2) {
        let r = c
            .put(format!("{base}/v1/uploads/{id}/parts/{n}"))
            .body(p.to_vec())
            .send()
            .await
            .expect("part");
        assert_eq!(r.status(), StatusCode::OK);
    }
    // The client asks what arrived, by GET and by HEAD.
    let st = c
        .get(format!("{base}/v1/uploads/{id}"))
        .send()
        .await
        .expect("status");
    assert_eq!(st.headers()["upload-state"], "open");
    let st: Value = st.json().await.expect("json");
    assert_eq!(st["parts_received"], json!([0, 1]));
    assert_eq!(st["bytes_received"], 2048);
    let head = c
        .head(format!("{base}/v1/uploads/{id}"))
        .send()
        .await
        .expect("head");
    assert_eq!(head.status(), StatusCode::OK);
    assert_eq!(head.headers()["upload-bytes-received"], "2048");
    assert_eq!(
        head.headers()["upload-length"],
        bytes.len().to_string().as_str()
    );

    // Completing too early names the missing parts.
    let early = c
        .post(format!("{base}/v1/uploads/{id}/complete"))
        .send()
        .await
        .expect("complete");
    let p = expect_problem(early, StatusCode::CONFLICT).await;
    assert!(
        p["detail"].as_str().expect("detail").contains("missing"),
        "{p}"
    );

    // A repeated part gives the same result.
    let again: Value = c
        .put(format!("{base}/v1/uploads/{id}/parts/1"))
        .body(parts[1].to_vec())
        .send()
        .await
        .expect("part")
        .json()
        .await
        .expect("json");
    assert_eq!(again["sha256"], sha256_hex(parts[1]));
    assert_eq!(again["size"], 1024);

    // Wrong part length, a part out of range, a part over the part size.
    let r = c
        .put(format!("{base}/v1/uploads/{id}/parts/2"))
        .body(vec![0u8; 10])
        .send()
        .await
        .expect("part");
    expect_problem(r, StatusCode::UNPROCESSABLE_ENTITY).await;
    let r = c
        .put(format!("{base}/v1/uploads/{id}/parts/999"))
        .body(vec![0u8; 10])
        .send()
        .await
        .expect("part");
    expect_problem(r, StatusCode::UNPROCESSABLE_ENTITY).await;
    let r = c
        .put(format!("{base}/v1/uploads/{id}/parts/2"))
        .body(vec![0u8; 4096])
        .send()
        .await
        .expect("part");
    expect_problem(r, StatusCode::PAYLOAD_TOO_LARGE).await;

    // Resume: the rest, then complete.
    for (n, p) in parts.iter().enumerate().skip(2) {
        let r = c
            .put(format!("{base}/v1/uploads/{id}/parts/{n}"))
            .body(p.to_vec())
            .send()
            .await
            .expect("part");
        assert_eq!(r.status(), StatusCode::OK);
    }
    let done = c
        .post(format!("{base}/v1/uploads/{id}/complete"))
        .send()
        .await
        .expect("complete");
    assert_eq!(done.status(), StatusCode::OK);
    let done: Value = done.json().await.expect("json");
    assert_eq!(done["state"], "complete");
    assert_eq!(done["sha256"], sha256_hex(&bytes));
    assert_eq!(
        done["inspection"]["point_cloud"]["declared_points"],
        fx.lidar_points
    );
    // Completing twice is harmless; parts can no longer change.
    let twice = c
        .post(format!("{base}/v1/uploads/{id}/complete"))
        .send()
        .await
        .expect("complete");
    assert_eq!(twice.status(), StatusCode::OK);
    let r = c
        .put(format!("{base}/v1/uploads/{id}/parts/0"))
        .body(parts[0].to_vec())
        .send()
        .await
        .expect("part");
    expect_problem(r, StatusCode::CONFLICT).await;
}

on_both_databases!(wrong_checksum_and_unusable_content_are_422);
async fn wrong_checksum_and_unusable_content_are_422(db: Db) {
    let fx = fixture();
    let srv = db.serve(&fx.dir.path().join("data"), &[]);
    let (c, base) = (client(), srv.base.clone());
    let bytes = std::fs::read(&fx.lidar).expect("read");
    let put_all = |id: String, body: Vec<u8>| {
        let c = c.clone();
        let base = base.clone();
        async move {
            c.put(format!("{base}/v1/uploads/{id}/parts/0"))
                .body(body)
                .send()
                .await
                .expect("part");
            c.post(format!("{base}/v1/uploads/{id}/complete"))
                .send()
                .await
                .expect("complete")
        }
    };
    let create = |kind: &str, name: &str, size: usize, sha: Option<String>| {
        let c = c.clone();
        let base = base.clone();
        // `sha256` is left out when there is none (null is refused as not a hex digest).
        let mut body = json!({ "kind": kind, "filename": name, "size": size });
        if let Some(sha) = sha {
            body["sha256"] = json!(sha);
        }
        async move {
            let v: Value = c
                .post(format!("{base}/v1/uploads"))
                .json(&body)
                .send()
                .await
                .expect("create")
                .json()
                .await
                .expect("json");
            v["id"].as_str().expect("id").to_string()
        }
    };
    let id = create("lidar", "plot.las", bytes.len(), Some("0".repeat(64))).await;
    let p = expect_problem(
        put_all(id, bytes.clone()).await,
        StatusCode::UNPROCESSABLE_ENTITY,
    )
    .await;
    assert!(
        p["detail"].as_str().expect("detail").contains("SHA-256"),
        "{p}"
    );

    // A truncated LAS: size and checksum match what was sent, the content does not.
    let cut = bytes[..bytes.len() / 2].to_vec();
    let id = create("lidar", "cut.las", cut.len(), None).await;
    let p = expect_problem(put_all(id, cut).await, StatusCode::UNPROCESSABLE_ENTITY).await;
    assert!(
        p["detail"].as_str().expect("detail").starts_with("cut.las"),
        "names the file: {p}"
    );

    // A control point table with too few pairs.
    let csv = b"sfm_x,sfm_y,sfm_z,lidar_x,lidar_y,lidar_z\n1,2,3,4,5,6\n".to_vec();
    let id = create("control_points", "cp.csv", csv.len(), None).await;
    expect_problem(put_all(id, csv).await, StatusCode::UNPROCESSABLE_ENTITY).await;

    // A COLMAP archive whose model names a photo that is not there.
    let broken = fx.dir.path().join("broken");
    std::fs::create_dir_all(broken.join("images")).expect("mkdir");
    std::fs::create_dir_all(broken.join("sparse")).expect("mkdir");
    for f in ["cameras.txt", "images.txt", "points3D.txt"] {
        std::fs::copy(
            fx.colmap_dir.join("sparse/0").join(f),
            broken.join("sparse").join(f),
        )
        .expect("copy");
    }
    std::fs::copy(
        fx.colmap_dir.join("images/img_000.png"),
        broken.join("images/img_000.png"),
    )
    .expect("copy");
    let zip = fx.dir.path().join("broken.zip");
    zip_dir(&broken, &zip);
    let z = std::fs::read(&zip).expect("read");
    let id = create("colmap", "broken.zip", z.len(), None).await;
    let p = expect_problem(put_all(id, z).await, StatusCode::UNPROCESSABLE_ENTITY).await;
    assert!(
        p["detail"].as_str().expect("detail").contains("missing"),
        "{p}"
    );
}

on_both_databases!(same_idempotency_key_gives_one_job);
async fn same_idempotency_key_gives_one_job(db: Db) {
    let fx = fixture();
    let srv = db.serve(&fx.dir.path().join("data"), &["--workers", "0"]);
    let (c, base) = (client(), srv.base.clone());
    let inputs = upload_inputs(&c, &base, &fx).await;
    let body = json!({ "inputs": inputs, "params": { "until": "ingest" } });
    let mut ids = Vec::new();
    for _ in 0..3 {
        let r = c
            .post(format!("{base}/v1/jobs"))
            .header("idempotency-key", "plot-7-upload-1")
            .json(&body)
            .send()
            .await
            .expect("create");
        assert_eq!(r.status(), StatusCode::ACCEPTED);
        assert!(r.headers().contains_key("location"));
        let v: Value = r.json().await.expect("json");
        ids.push(v["id"].as_str().expect("id").to_string());
    }
    assert!(ids.iter().all(|i| *i == ids[0]), "{ids:?}");
    let list: Value = c
        .get(format!("{base}/v1/jobs"))
        .send()
        .await
        .expect("list")
        .json()
        .await
        .expect("json");
    assert_eq!(list["jobs"].as_array().map(Vec::len), Some(1));
    // The same key with another request is refused.
    let other = json!({ "inputs": inputs, "params": { "until": "register" } });
    let r = c
        .post(format!("{base}/v1/jobs"))
        .header("idempotency-key", "plot-7-upload-1")
        .json(&other)
        .send()
        .await
        .expect("create");
    expect_problem(r, StatusCode::UNPROCESSABLE_ENTITY).await;
    // A different key makes a second job; list pages through both with the cursor.
    let r = c
        .post(format!("{base}/v1/jobs"))
        .header("idempotency-key", "plot-7-upload-2")
        .json(&body)
        .send()
        .await
        .expect("create");
    assert_eq!(r.status(), StatusCode::ACCEPTED);
    let page1: Value = c
        .get(format!("{base}/v1/jobs?limit=1"))
        .send()
        .await
        .expect("list")
        .json()
        .await
        .expect("json");
    let cursor = page1["next_cursor"].as_str().expect("cursor");
    let page2: Value = c
        .get(format!("{base}/v1/jobs?limit=1&cursor={cursor}"))
        .send()
        .await
        .expect("list")
        .json()
        .await
        .expect("json");
    assert_eq!(page2["jobs"][0]["id"], ids[0].as_str());
    assert_ne!(page1["jobs"][0]["id"], ids[0].as_str());
}

#[tokio::test(flavor = "multi_thread")]
async fn auth_on_requires_a_bearer_token_and_never_logs_it() {
    let fx = fixture();
    let srv = serve(
        &fx.dir.path().join("data"),
        &["--token", "s3cret-token-value,second-token"],
    );
    let (c, base) = (client(), srv.base.clone());
    let r = c.get(format!("{base}/v1/jobs")).send().await.expect("get");
    assert_eq!(r.headers()["www-authenticate"], "Bearer");
    expect_problem(r, StatusCode::UNAUTHORIZED).await;
    let r = c
        .get(format!("{base}/v1/jobs"))
        .bearer_auth("wrong")
        .send()
        .await
        .expect("get");
    expect_problem(r, StatusCode::UNAUTHORIZED).await;
    let r = c
        .post(format!("{base}/v1/uploads"))
        .json(&json!({}))
        .send()
        .await
        .expect("post");
    expect_problem(r, StatusCode::UNAUTHORIZED).await;
    for token in ["s3cret-token-value", "second-token"] {
        let r = c
            .get(format!("{base}/v1/jobs"))
            .bearer_auth(token)
            .send()
            .await
            .expect("get");
        assert_eq!(r.status(), StatusCode::OK);
    }
    for open in ["/livez", "/readyz", "/metrics", "/openapi.yaml", "/"] {
        let r = c.get(format!("{base}{open}")).send().await.expect("get");
        assert_eq!(r.status(), StatusCode::OK, "{open} is public");
    }
    let info: Value = c
        .get(format!("{base}/v1/info"))
        .bearer_auth("second-token")
        .send()
        .await
        .expect("get")
        .json()
        .await
        .expect("json");
    assert_eq!(info["auth"], true);
    drop(c);
    assert!(
        !srv.stderr_text().contains("s3cret"),
        "the token reached the log"
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn errors_are_problem_json_with_real_status_codes() {
    let fx = fixture();
    let srv = serve(
        &fx.dir.path().join("data"),
        &["--max-json-bytes", "2000", "--workers", "0"],
    );
    let (c, base) = (client(), srv.base.clone());
    let p = expect_problem(
        c.get(format!("{base}/v1/nothing-here"))
            .send()
            .await
            .expect("get"),
        StatusCode::NOT_FOUND,
    )
    .await;
    assert_eq!(p["type"], "urn:sylva:problem:no-such-route");
    let p = expect_problem(
        c.get(format!("{base}/v1/jobs/0123456789abcdef0123456789abcdef"))
            .send()
            .await
            .expect("get"),
        StatusCode::NOT_FOUND,
    )
    .await;
    assert_eq!(p["type"], "urn:sylva:problem:not-found");
    let r = c
        .patch(format!("{base}/v1/jobs"))
        .send()
        .await
        .expect("patch");
    let allow = r.headers()["allow"].to_str().expect("allow").to_string();
    assert!(allow.contains("GET") && allow.contains("POST"), "{allow}");
    expect_problem(r, StatusCode::METHOD_NOT_ALLOWED).await;
    let big = json!({ "kind": "lidar", "filename": "x".repeat(5000), "size": 1 });
    expect_problem(
        c.post(format!("{base}/v1/uploads"))
            .json(&big)
            .send()
            .await
            .expect("post"),
        StatusCode::PAYLOAD_TOO_LARGE,
    )
    .await;
    let big_job = json!({ "inputs": { "lidar": "a".repeat(3000), "colmap": "b" } });
    expect_problem(
        c.post(format!("{base}/v1/jobs"))
            .json(&big_job)
            .send()
            .await
            .expect("post"),
        StatusCode::PAYLOAD_TOO_LARGE,
    )
    .await;
    let r = c
        .post(format!("{base}/v1/jobs"))
        .header("content-type", "text/plain")
        .body("hello")
        .send()
        .await
        .expect("post");
    expect_problem(r, StatusCode::UNSUPPORTED_MEDIA_TYPE).await;
    let r = c
        .post(format!("{base}/v1/jobs"))
        .header("content-type", "application/json")
        .body("{not json")
        .send()
        .await
        .expect("post");
    expect_problem(r, StatusCode::BAD_REQUEST).await;
    let r = c
        .post(format!("{base}/v1/uploads"))
        .header("content-type", "application/json")
        .body("{\"kind\": \"lidar\"")
        .send()
        .await
        .expect("post");
    expect_problem(r, StatusCode::BAD_REQUEST).await;
    let r = c
        .post(format!("{base}/v1/uploads"))
        .json(&json!({ "kind": "photo", "filename": "a", "size": 1 }))
        .send()
        .await
        .expect("post");
    expect_problem(r, StatusCode::UNPROCESSABLE_ENTITY).await;
    let r = c
        .post(format!("{base}/v1/uploads"))
        .json(&json!({ "kind": "lidar", "filename": "a", "size": 0 }))
        .send()
        .await
        .expect("post");
    expect_problem(r, StatusCode::UNPROCESSABLE_ENTITY).await;
    let r = c
        .post(format!("{base}/v1/uploads"))
        .json(&json!({ "kind": "lidar", "filename": "a", "size": 20_000_000_000_000u64 }))
        .send()
        .await
        .expect("post");
    expect_problem(r, StatusCode::PAYLOAD_TOO_LARGE).await;
    let inputs = upload_inputs(&c, &base, &fx).await;
    let r = c
        .post(format!("{base}/v1/jobs"))
        .json(&json!({ "inputs": inputs, "params": { "anchors": { "voxel": 1 } } }))
        .send()
        .await
        .expect("post");
    let p = expect_problem(r, StatusCode::UNPROCESSABLE_ENTITY).await;
    assert!(
        p["detail"].as_str().expect("detail").contains("voxel"),
        "{p}"
    );
    let r = c
        .post(format!("{base}/v1/jobs"))
        .json(&json!({ "inputs": { "lidar": inputs["colmap"], "colmap": inputs["colmap"] } }))
        .send()
        .await
        .expect("post");
    let p = expect_problem(r, StatusCode::UNPROCESSABLE_ENTITY).await;
    assert!(
        p["detail"]
            .as_str()
            .expect("detail")
            .contains("inputs.lidar"),
        "{p}"
    );
    let r = c
        .post(format!("{base}/v1/jobs"))
        .json(&json!({ "inputs": inputs, "webhook": { "url": "http://10.0.0.1/hook" } }))
        .send()
        .await
        .expect("post");
    expect_problem(r, StatusCode::UNPROCESSABLE_ENTITY).await;
    let r = c
        .get(format!("{base}/v1/jobs?limit=0"))
        .send()
        .await
        .expect("get");
    expect_problem(r, StatusCode::BAD_REQUEST).await;
    let r = c
        .get(format!("{base}/v1/jobs?state=done"))
        .send()
        .await
        .expect("get");
    expect_problem(r, StatusCode::BAD_REQUEST).await;
    let r = c
        .get(format!("{base}/v1/jobs?cursor=xyz"))
        .send()
        .await
        .expect("get");
    expect_problem(r, StatusCode::BAD_REQUEST).await;
}

fn write_zip(path: &std::path::Path, f: impl FnOnce(&mut zip::ZipWriter<std::fs::File>)) {
    let mut z = zip::ZipWriter::new(std::fs::File::create(path).expect("create"));
    f(&mut z);
    z.finish().expect("finish");
}

#[tokio::test(flavor = "multi_thread")]
async fn hostile_archives_are_refused() {
    use std::io::Write;
    let fx = fixture();
    let data = fx.dir.path().join("data");
    let srv = serve(&data, &["--workers", "0"]);
    let (c, base) = (client(), srv.base.clone());
    let opts = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated);
    let slip = fx.dir.path().join("slip.zip");
    write_zip(&slip, |z| {
        z.start_file("sparse/cameras.txt", opts).expect("start");
        z.write_all(b"# nothing").expect("write");
        z.start_file("../../evil.txt", opts).expect("start");
        z.write_all(b"pwned").expect("write");
    });
    let link = fx.dir.path().join("link.zip");
    write_zip(&link, |z| {
        z.add_symlink("images/passwd", "/etc/passwd", opts)
            .expect("symlink");
    });
    let bomb = fx.dir.path().join("bomb.zip");
    write_zip(&bomb, |z| {
        z.start_file("images/zeros.png", opts).expect("start");
        let block = vec![0u8; 1 << 20];
        for _ in 0..64 {
            z.write_all(&block).expect("write");
        }
    });
    let empty = fx.dir.path().join("empty.zip");
    write_zip(&empty, |_| {});
    for (path, words) in [
        (&slip, "unsafe"),
        (&link, "link"),
        (&bomb, "ratio"),
        (&empty, "no regular file"),
    ] {
        let bytes = std::fs::read(path).expect("read");
        let created: Value = c
            .post(format!("{base}/v1/uploads"))
            .json(&json!({ "kind": "colmap", "filename": "project.zip", "size": bytes.len() }))
            .send()
            .await
            .expect("create")
            .json()
            .await
            .expect("json");
        let id = created["id"].as_str().expect("id");
        c.put(format!("{base}/v1/uploads/{id}/parts/0"))
            .body(bytes)
            .send()
            .await
            .expect("part");
        let r = c
            .post(format!("{base}/v1/uploads/{id}/complete"))
            .send()
            .await
            .expect("complete");
        let p = expect_problem(r, StatusCode::UNPROCESSABLE_ENTITY).await;
        let detail = p["detail"].as_str().expect("detail").to_lowercase();
        assert!(detail.contains(words), "{} → {detail}", path.display());
        assert!(
            detail.starts_with("project.zip"),
            "names the file: {detail}"
        );
    }
    for escaped in [
        fx.dir.path().join("evil.txt"),
        data.join("evil.txt"),
        data.join("uploads").join("evil.txt"),
    ] {
        assert!(!escaped.exists(), "{} was written", escaped.display());
    }
}

on_both_databases!(cancel_stops_running_and_queued_jobs);
async fn cancel_stops_running_and_queued_jobs(db: Db) {
    let fx = fixture();
    let data = fx.dir.path().join("data");
    let srv = db.serve(&data, &["--debug-stage-pause-ms", "60000"]);
    let (c, base) = (client(), srv.base.clone());
    let inputs = upload_inputs(&c, &base, &fx).await;
    let body = json!({ "inputs": inputs, "params": { "until": "ingest" } });
    let running = create_job(&c, &base, &body).await;
    let rid = running["id"].as_str().expect("id").to_string();
    let queued = create_job(&c, &base, &body).await;
    let qid = queued["id"].as_str().expect("id").to_string();
    wait_job(&c, &base, &rid, LONG, |j| {
        j["state"] == "running" && j["stage"] == "ingest"
    })
    .await;

    // The queued one is canceled at once.
    let r = c
        .post(format!("{base}/v1/jobs/{qid}/cancel"))
        .send()
        .await
        .expect("cancel");
    assert_eq!(r.status(), StatusCode::ACCEPTED);
    let v: Value = r.json().await.expect("json");
    assert_eq!(v["state"], "canceled");

    // The running one is asked to stop and stops promptly.
    let asked = std::time::Instant::now();
    let r = c
        .post(format!("{base}/v1/jobs/{rid}/cancel"))
        .send()
        .await
        .expect("cancel");
    assert_eq!(r.status(), StatusCode::ACCEPTED);
    let v: Value = r.json().await.expect("json");
    assert!(
        matches!(v["state"].as_str(), Some("canceling" | "canceled")),
        "{v}"
    );
    let (job, _) = wait_job(&c, &base, &rid, Duration::from_secs(10), is_terminal).await;
    assert_eq!(job["state"], "canceled");
    assert_eq!(stage(&job, "ingest")["state"], "canceled");
    assert!(
        asked.elapsed() < Duration::from_secs(5),
        "cancel took {:?}",
        asked.elapsed()
    );

    // A finished job cannot be canceled again.
    let r = c
        .post(format!("{base}/v1/jobs/{rid}/cancel"))
        .send()
        .await
        .expect("cancel");
    expect_problem(r, StatusCode::CONFLICT).await;
}

on_both_databases!(one_request_multipart_submission_runs);
async fn one_request_multipart_submission_runs(db: Db) {
    let fx = fixture();
    let srv = db.serve(&fx.dir.path().join("data"), &[]);
    let (c, base) = (client(), srv.base.clone());
    let part = |path: &std::path::Path| {
        reqwest::multipart::Part::bytes(std::fs::read(path).expect("read")).file_name(
            path.file_name()
                .and_then(|n| n.to_str())
                .unwrap_or("f")
                .to_string(),
        )
    };
    let form = reqwest::multipart::Form::new()
        .part("lidar", part(&fx.lidar))
        .part("colmap", part(&fx.colmap_zip))
        .part("field_dbh", part(&fx.field_dbh))
        .text("params", r#"{"until": "ingest"}"#);
    let r = c
        .post(format!("{base}/v1/jobs"))
        .multipart(form)
        .send()
        .await
        .expect("post");
    assert_eq!(r.status(), StatusCode::ACCEPTED, "{:?}", r.text().await);
    let v: Value = r.json().await.expect("json");
    let id = v["id"].as_str().expect("id");
    let (job, _) = wait_job(&c, &base, id, LONG, is_terminal).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    assert_eq!(stage(&job, "ingest")["metrics"]["field_trees"], 1);
    // Missing colmap part.
    let form = reqwest::multipart::Form::new().part("lidar", part(&fx.lidar));
    let r = c
        .post(format!("{base}/v1/jobs"))
        .multipart(form)
        .send()
        .await
        .expect("post");
    expect_problem(r, StatusCode::UNPROCESSABLE_ENTITY).await;
}

on_both_databases!(an_expired_upload_is_gone);
async fn an_expired_upload_is_gone(db: Db) {
    let dir = tempfile::tempdir().expect("tempdir");
    let srv = db.serve(
        &dir.path().join("data"),
        &["--upload-ttl-secs", "1", "--workers", "0"],
    );
    let (c, base) = (client(), srv.base.clone());
    let v: Value = c
        .post(format!("{base}/v1/uploads"))
        .json(&json!({ "kind": "lidar", "filename": "a.xyz", "size": 6 }))
        .send()
        .await
        .expect("create")
        .json()
        .await
        .expect("json");
    let id = v["id"].as_str().expect("id");
    tokio::time::sleep(Duration::from_millis(1100)).await;
    let r = c
        .put(format!("{base}/v1/uploads/{id}/parts/0"))
        .body("1 2 3\n")
        .send()
        .await
        .expect("part");
    expect_problem(r, StatusCode::GONE).await;
    let r = c
        .post(format!("{base}/v1/uploads/{id}/complete"))
        .send()
        .await
        .expect("complete");
    expect_problem(r, StatusCode::GONE).await;
}

/// Uploads `bytes` as one upload of `kind` named `name`; the answer to `complete`.
async fn upload_whole(
    c: &reqwest::Client,
    base: &str,
    kind: &str,
    name: &str,
    bytes: Vec<u8>,
) -> reqwest::Response {
    let created: Value = c
        .post(format!("{base}/v1/uploads"))
        .json(&json!({ "kind": kind, "filename": name, "size": bytes.len() }))
        .send()
        .await
        .expect("create")
        .json()
        .await
        .expect("json");
    let id = created["id"].as_str().expect("id").to_string();
    let part = created["part_size"].as_u64().expect("part_size") as usize;
    for (n, chunk) in bytes.chunks(part).enumerate() {
        let r = c
            .put(format!("{base}/v1/uploads/{id}/parts/{n}"))
            .body(chunk.to_vec())
            .send()
            .await
            .expect("part");
        assert_eq!(r.status(), StatusCode::OK, "part {n} of {name}");
    }
    c.post(format!("{base}/v1/uploads/{id}/complete"))
        .send()
        .await
        .expect("complete")
}

/// Each bad input of issue 10 is a clear problem that names the file and the fault, and the
/// service carries on.
#[tokio::test(flavor = "multi_thread")]
async fn bad_inputs_are_clear_problems_naming_the_file_and_the_fault() {
    let fx = fixture();
    let data = fx.dir.path().join("data");
    let srv = serve(&data, &["--max-upload-bytes", "1073741824"]);
    let (c, base) = (client(), srv.base.clone());
    let detail_of = |p: &Value| p["detail"].as_str().expect("detail").to_string();
    let refused = |r: reqwest::Response| expect_problem(r, StatusCode::UNPROCESSABLE_ENTITY);

    // A LAS whose header declares more points than the file holds.
    let mut las = std::fs::read(&fx.lidar).expect("las");
    let n = u32::from_le_bytes(las[107..111].try_into().expect("4 bytes"));
    las[107..111].copy_from_slice(&(n + 5000).to_le_bytes());
    if las.len() > 255 && u16::from_le_bytes([las[94], las[95]]) >= 375 {
        let n64 = u64::from_le_bytes(las[247..255].try_into().expect("8 bytes"));
        las[247..255].copy_from_slice(&(n64 + 5000).to_le_bytes());
    }
    let d = detail_of(&refused(upload_whole(&c, &base, "lidar", "count.las", las).await).await);
    assert!(d.starts_with("count.las") && d.contains("points"), "{d}");

    // PLY headers that promise more vertices than the body has (ASCII and binary).
    let header = |enc: &str| {
        format!(
            "ply\nformat {enc} 1.0\nelement vertex 100\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
        )
    };
    let ascii = format!("{}1 2 3\n4 5 6\n", header("ascii")).into_bytes();
    let d = detail_of(&refused(upload_whole(&c, &base, "lidar", "rows.ply", ascii).await).await);
    assert!(
        d.starts_with("rows.ply") && d.contains("100 vertices"),
        "{d}"
    );
    let mut binary = header("binary_little_endian").into_bytes();
    binary.extend_from_slice(&[0u8; 120]);
    let d = detail_of(&refused(upload_whole(&c, &base, "lidar", "bytes.ply", binary).await).await);
    assert!(
        d.starts_with("bytes.ply") && d.contains("100 vertices"),
        "{d}"
    );

    // Non-finite coordinates.
    let xyz = b"1 2 3\n4 nan 6\n7 8 9\n".to_vec();
    let d = detail_of(&refused(upload_whole(&c, &base, "lidar", "nan.xyz", xyz).await).await);
    assert!(
        d.starts_with("nan.xyz") && d.contains("line 2") && d.contains("non-finite"),
        "{d}"
    );

    // A COLMAP project with an unsupported camera model; no server path in the answer.
    let project = fx.dir.path().join("fisheye");
    for sub in ["images", "sparse/0"] {
        std::fs::create_dir_all(project.join(sub)).expect("mkdir");
        for e in std::fs::read_dir(fx.colmap_dir.join(sub)).expect("read_dir") {
            let e = e.expect("entry");
            std::fs::copy(e.path(), project.join(sub).join(e.file_name())).expect("copy");
        }
    }
    let cams = project.join("sparse/0/cameras.txt");
    let text = std::fs::read_to_string(&cams).expect("cameras");
    std::fs::write(&cams, text.replace("PINHOLE", "FISHEYE_X")).expect("write");
    let zip = fx.dir.path().join("fisheye.zip");
    zip_dir(&project, &zip);
    let bytes = std::fs::read(&zip).expect("zip");
    let d =
        detail_of(&refused(upload_whole(&c, &base, "colmap", "fisheye.zip", bytes).await).await);
    assert!(
        d.starts_with("fisheye.zip") && d.contains("FISHEYE_X"),
        "{d}"
    );
    assert!(
        d.contains("sparse/0/cameras.txt"),
        "names the file inside: {d}"
    );
    assert!(
        !d.contains(&data.display().to_string()),
        "leaks a server path: {d}"
    );

    // An empty archive.
    let empty = fx.dir.path().join("empty");
    std::fs::create_dir_all(&empty).expect("mkdir");
    let zip = fx.dir.path().join("empty.zip");
    zip_dir(&empty, &zip);
    let bytes = std::fs::read(&zip).expect("zip");
    let d = detail_of(&refused(upload_whole(&c, &base, "colmap", "empty.zip", bytes).await).await);
    assert!(
        d.starts_with("empty.zip") && d.contains("no regular file"),
        "{d}"
    );

    // 10 GB declared against a 1 GiB limit: 413 before a byte is sent.
    let r = c
        .post(format!("{base}/v1/uploads"))
        .json(&json!({ "kind": "lidar", "filename": "big.laz", "size": 10_000_000_000u64 }))
        .send()
        .await
        .expect("create");
    let p = expect_problem(r, StatusCode::PAYLOAD_TOO_LARGE).await;
    assert!(detail_of(&p).contains("1073741824"), "{p}");

    // A cloud in millimetres is accepted with a warning (it may be a huge plot after all).
    let mut cloud =
        sylva::io::pointcloud::read_point_cloud(&fx.lidar, &sylva::progress::NoProgress)
            .expect("read las");
    for p in &mut cloud.positions {
        *p *= 1000.0;
    }
    let mm = fx.dir.path().join("mm.las");
    sylva::io::las::write_las(&mm, &cloud, false).expect("write las");
    let r = upload_whole(
        &c,
        &base,
        "lidar",
        "mm.las",
        std::fs::read(&mm).expect("mm"),
    )
    .await;
    assert_eq!(r.status(), StatusCode::OK);
    let up: Value = r.json().await.expect("json");
    let warnings = up["inspection"]["warnings"].to_string();
    assert!(
        warnings.contains("mm.las") && warnings.contains("millimetres"),
        "{up}"
    );

    // Nothing else was harmed: the service is ready and a good upload still goes through.
    let ready = c
        .get(format!("{base}/readyz"))
        .send()
        .await
        .expect("readyz");
    assert_eq!(ready.status(), StatusCode::OK);
    let good = std::fs::read(&fx.lidar).expect("las");
    let r = upload_whole(&c, &base, "lidar", "good.las", good).await;
    assert_eq!(r.status(), StatusCode::OK);
}
