use std::time::Duration;

use reqwest::StatusCode;
use serde_json::{Value, json};

use super::common::{self, *};

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
