use reqwest::StatusCode;
use serde_json::{Value, json};

use super::common::*;

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
