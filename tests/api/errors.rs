use reqwest::StatusCode;
use serde_json::{Value, json};

use super::common::*;

#[tokio::test(flavor = "multi_thread")]
async fn auth_on_requires_a_bearer_token_and_never_logs_it() {
    let fx = fixture();
    let srv = serve(&fx.data, &["--token", "s3cret-token-value,second-token"]);
    let (c, base) = (client(), srv.base.clone());
    let jobs = format!("{base}/v1/jobs");
    let r = send(c.get(&jobs)).await;
    assert_eq!(r.headers()["www-authenticate"], "Bearer");
    expect_problem(r, StatusCode::UNAUTHORIZED).await;
    send_problem(c.get(&jobs).bearer_auth("wrong"), StatusCode::UNAUTHORIZED).await;
    let new_upload = c.post(format!("{base}/v1/uploads")).json(&json!({}));
    send_problem(new_upload, StatusCode::UNAUTHORIZED).await;
    for token in ["s3cret-token-value", "second-token"] {
        let r = send(c.get(&jobs).bearer_auth(token)).await;
        assert_eq!(r.status(), StatusCode::OK);
    }
    for open in ["/livez", "/readyz", "/metrics", "/openapi.yaml", "/"] {
        let r = send(c.get(format!("{base}{open}"))).await;
        assert_eq!(r.status(), StatusCode::OK, "{open} is public");
    }
    let info = send_json(c.get(format!("{base}/v1/info")).bearer_auth("second-token")).await;
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
    let srv = serve(&fx.data, &["--max-json-bytes", "2000", "--workers", "0"]);
    let (c, base) = (client(), srv.base.clone());
    let get = |path: &str| c.get(format!("{base}{path}"));
    let post = |path: &str| c.post(format!("{base}{path}"));
    let json_text = |path: &str, text: &'static str| {
        post(path)
            .header("content-type", "application/json")
            .body(text)
    };
    for (path, kind) in [
        ("/v1/nothing-here", "urn:sylva:problem:no-such-route"),
        (
            "/v1/jobs/0123456789abcdef0123456789abcdef",
            "urn:sylva:problem:not-found",
        ),
    ] {
        let p = send_problem(get(path), StatusCode::NOT_FOUND).await;
        assert_eq!(p["type"], kind);
    }
    let r = send(c.patch(format!("{base}/v1/jobs"))).await;
    let allow = r.headers()["allow"].to_str().expect("allow").to_string();
    assert!(allow.contains("GET") && allow.contains("POST"), "{allow}");
    expect_problem(r, StatusCode::METHOD_NOT_ALLOWED).await;
    let big = json!({ "kind": "lidar", "filename": "x".repeat(5000), "size": 1 });
    let big_job = json!({ "inputs": { "lidar": "a".repeat(3000), "colmap": "b" } });
    let plain = post("/v1/jobs")
        .header("content-type", "text/plain")
        .body("hello");
    let upload = |kind: &str, size: u64| {
        post("/v1/uploads").json(&json!({ "kind": kind, "filename": "a", "size": size }))
    };
    for (req, status) in [
        (
            post("/v1/uploads").json(&big),
            StatusCode::PAYLOAD_TOO_LARGE,
        ),
        (
            post("/v1/jobs").json(&big_job),
            StatusCode::PAYLOAD_TOO_LARGE,
        ),
        (plain, StatusCode::UNSUPPORTED_MEDIA_TYPE),
        (json_text("/v1/jobs", "{not json"), StatusCode::BAD_REQUEST),
        (
            json_text("/v1/uploads", "{\"kind\": \"lidar\""),
            StatusCode::BAD_REQUEST,
        ),
        (upload("photo", 1), StatusCode::UNPROCESSABLE_ENTITY),
        (upload("lidar", 0), StatusCode::UNPROCESSABLE_ENTITY),
        (
            upload("lidar", 20_000_000_000_000),
            StatusCode::PAYLOAD_TOO_LARGE,
        ),
    ] {
        send_problem(req, status).await;
    }
    let inputs = upload_inputs(&c, &base, &fx).await;
    let job = |body: Value| post("/v1/jobs").json(&body);
    let bad_params = json!({ "inputs": inputs, "params": { "anchors": { "voxel": 1 } } });
    let p = send_problem(job(bad_params), StatusCode::UNPROCESSABLE_ENTITY).await;
    assert!(detail(&p).contains("voxel"), "{p}");
    // A CRS that does not parse, or one in degrees, is refused at submission, named.
    for crs in ["the plot grid", "EPSG:4326"] {
        let bad_crs = json!({ "inputs": inputs, "params": { "crs": crs } });
        let p = send_problem(job(bad_crs), StatusCode::UNPROCESSABLE_ENTITY).await;
        assert!(detail(&p).contains("params.crs"), "{p}");
    }
    // So is a wood density no wood has.
    let dense = json!({ "inputs": inputs, "params": { "segment": { "allometry": { "wood_density_g_cm3": 5.0 } } } });
    let p = send_problem(job(dense), StatusCode::UNPROCESSABLE_ENTITY).await;
    assert!(detail(&p).contains("wood_density_g_cm3"), "{p}");
    let swapped = json!({ "inputs": { "lidar": inputs["colmap"], "colmap": inputs["colmap"] } });
    let p = send_problem(job(swapped), StatusCode::UNPROCESSABLE_ENTITY).await;
    assert!(detail(&p).contains("inputs.lidar"), "{p}");
    let private = json!({ "inputs": inputs, "webhook": { "url": "http://10.0.0.1/hook" } });
    send_problem(job(private), StatusCode::UNPROCESSABLE_ENTITY).await;
    for query in ["limit=0", "state=done", "cursor=xyz"] {
        send_problem(get(&format!("/v1/jobs?{query}")), StatusCode::BAD_REQUEST).await;
    }
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
    let srv = serve(&fx.data, &["--workers", "0"]);
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
        let size = bytes.len() as u64;
        let id = id_of(&open_upload(&c, &base, "colmap", "project.zip", size).await);
        put_part(&c, &base, &id, 0, bytes).await;
        let r = complete_upload(&c, &base, &id).await;
        let p = expect_problem(r, StatusCode::UNPROCESSABLE_ENTITY).await;
        let detail = detail(&p).to_lowercase();
        assert!(detail.contains(words), "{} → {detail}", path.display());
        assert!(
            detail.starts_with("project.zip"),
            "names the file: {detail}"
        );
    }
    for escaped in [
        fx.dir.path().join("evil.txt"),
        fx.data.join("evil.txt"),
        fx.data.join("uploads").join("evil.txt"),
    ] {
        assert!(!escaped.exists(), "{} was written", escaped.display());
    }
}
