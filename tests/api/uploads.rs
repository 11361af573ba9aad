use std::time::Duration;

use reqwest::StatusCode;
use serde_json::{Value, json};

use super::common::{self, *};

on_both_databases!(upload_interrupted_and_resumed_with_repeated_part);
async fn upload_interrupted_and_resumed_with_repeated_part(db: Db) {
    let fx = fixture();
    let srv = db.serve(&fx.data, &["--part-size", "1024"]);
    let (c, base) = (client(), srv.base.clone());
    let bytes = std::fs::read(&fx.lidar).expect("read");
    assert!(bytes.len() > 5 * 1024);
    let body = json!({ "kind": "lidar", "filename": "plot.las", "size": bytes.len(), "sha256": sha256_hex(&bytes) });
    let created = send(c.post(format!("{base}/v1/uploads")).json(&body)).await;
    assert_eq!(created.status(), StatusCode::CREATED);
    assert!(created.headers().contains_key("location"));
    let created: Value = created.json().await.expect("json");
    let id = id_of(&created);
    let parts: Vec<&[u8]> = bytes.chunks(1024).collect();
    assert_eq!(created["parts_total"], parts.len());
    let put = |n: usize, body: Vec<u8>| put_part(&c, &base, &id, n, body);
    let complete = || complete_upload(&c, &base, &id);

    // The connection "dies" after two parts.
    for (n, p) in parts.iter().enumerate().take(2) {
        assert_eq!(put(n, p.to_vec()).await.status(), StatusCode::OK);
    }
    // The client asks what arrived, by GET and by HEAD.
    let st = send(c.get(format!("{base}/v1/uploads/{id}"))).await;
    assert_eq!(st.headers()["upload-state"], "open");
    let st: Value = st.json().await.expect("json");
    assert_eq!(st["parts_received"], json!([0, 1]));
    assert_eq!(st["bytes_received"], 2048);
    let head = send(c.head(format!("{base}/v1/uploads/{id}"))).await;
    assert_eq!(head.status(), StatusCode::OK);
    assert_eq!(head.headers()["upload-bytes-received"], "2048");
    assert_eq!(
        head.headers()["upload-length"],
        bytes.len().to_string().as_str()
    );

    // Completing too early names the missing parts.
    let p = expect_problem(complete().await, StatusCode::CONFLICT).await;
    assert!(detail(&p).contains("missing"), "{p}");

    // A repeated part gives the same result.
    let again: Value = put(1, parts[1].to_vec()).await.json().await.expect("json");
    assert_eq!(again["sha256"], sha256_hex(parts[1]));
    assert_eq!(again["size"], 1024);

    // Wrong part length, a part out of range, a part over the part size.
    for (n, len, status) in [
        (2, 10, StatusCode::UNPROCESSABLE_ENTITY),
        (999, 10, StatusCode::UNPROCESSABLE_ENTITY),
        (2, 4096, StatusCode::PAYLOAD_TOO_LARGE),
    ] {
        expect_problem(put(n, vec![0u8; len]).await, status).await;
    }

    // Resume: the rest, then complete.
    for (n, p) in parts.iter().enumerate().skip(2) {
        assert_eq!(put(n, p.to_vec()).await.status(), StatusCode::OK);
    }
    let done = complete().await;
    assert_eq!(done.status(), StatusCode::OK);
    let done: Value = done.json().await.expect("json");
    assert_eq!(done["state"], "complete");
    assert_eq!(done["sha256"], sha256_hex(&bytes));
    assert_eq!(
        done["inspection"]["point_cloud"]["declared_points"],
        fx.lidar_points
    );
    // Completing twice is harmless; parts can no longer change.
    assert_eq!(complete().await.status(), StatusCode::OK);
    expect_problem(put(0, parts[0].to_vec()).await, StatusCode::CONFLICT).await;
}

on_both_databases!(wrong_checksum_and_unusable_content_are_422);
async fn wrong_checksum_and_unusable_content_are_422(db: Db) {
    let fx = fixture();
    let srv = db.serve(&fx.data, &[]);
    let (c, base) = (client(), srv.base.clone());
    let bytes = std::fs::read(&fx.lidar).expect("read");
    // Opens an upload of `body` (with `sha`, when there is one: null is refused as not a hex
    // digest), sends it as part 0 and completes it: the problem of that answer.
    let refused = async |kind: &str, name: &str, body: Vec<u8>, sha: Option<String>| {
        let mut open = json!({ "kind": kind, "filename": name, "size": body.len() });
        if let Some(sha) = sha {
            open["sha256"] = json!(sha);
        }
        let v = send_json(c.post(format!("{base}/v1/uploads")).json(&open)).await;
        let id = id_of(&v);
        put_part(&c, &base, &id, 0, body).await;
        let r = complete_upload(&c, &base, &id).await;
        expect_problem(r, StatusCode::UNPROCESSABLE_ENTITY).await
    };
    let p = refused("lidar", "plot.las", bytes.clone(), Some("0".repeat(64))).await;
    assert!(detail(&p).contains("SHA-256"), "{p}");

    // A truncated LAS: size and checksum match what was sent, the content does not.
    let cut = bytes[..bytes.len() / 2].to_vec();
    let p = refused("lidar", "cut.las", cut, None).await;
    assert!(detail(&p).starts_with("cut.las"), "names the file: {p}");

    // A control point table with too few pairs.
    let csv = b"sfm_x,sfm_y,sfm_z,lidar_x,lidar_y,lidar_z\n1,2,3,4,5,6\n".to_vec();
    refused("control_points", "cp.csv", csv, None).await;

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
    let p = refused("colmap", "broken.zip", z, None).await;
    assert!(detail(&p).contains("missing"), "{p}");
}

on_both_databases!(an_expired_upload_is_gone);
async fn an_expired_upload_is_gone(db: Db) {
    let dir = tempfile::tempdir().expect("tempdir");
    let srv = db.serve(
        &dir.path().join("data"),
        &["--upload-ttl-secs", "1", "--workers", "0"],
    );
    let (c, base) = (client(), srv.base.clone());
    let id = id_of(&open_upload(&c, &base, "lidar", "a.xyz", 6).await);
    tokio::time::sleep(Duration::from_millis(1100)).await;
    let r = put_part(&c, &base, &id, 0, "1 2 3\n").await;
    expect_problem(r, StatusCode::GONE).await;
    expect_problem(complete_upload(&c, &base, &id).await, StatusCode::GONE).await;
}

/// Uploads `bytes` as one upload of `kind` named `name`; the answer to `complete`.
async fn upload_whole(
    c: &reqwest::Client,
    base: &str,
    kind: &str,
    name: &str,
    bytes: Vec<u8>,
) -> reqwest::Response {
    upload_bytes(c, base, (kind, name), &bytes, false).await.1
}

/// Each bad input of issue 10 is a clear problem that names the file and the fault, and the
/// service carries on.
#[tokio::test(flavor = "multi_thread")]
async fn bad_inputs_are_clear_problems_naming_the_file_and_the_fault() {
    let fx = fixture();
    let srv = serve(&fx.data, &["--max-upload-bytes", "1073741824"]);
    let (c, base) = (client(), srv.base.clone());
    let detail_of = |p: &Value| detail(p).to_string();
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
        !d.contains(&fx.data.display().to_string()),
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
    let big = json!({ "kind": "lidar", "filename": "big.laz", "size": 10_000_000_000u64 });
    let r = c.post(format!("{base}/v1/uploads")).json(&big);
    let p = send_problem(r, StatusCode::PAYLOAD_TOO_LARGE).await;
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
    let ready = send(c.get(format!("{base}/readyz"))).await;
    assert_eq!(ready.status(), StatusCode::OK);
    let good = std::fs::read(&fx.lidar).expect("las");
    let r = upload_whole(&c, &base, "lidar", "good.las", good).await;
    assert_eq!(r.status(), StatusCode::OK);
}
