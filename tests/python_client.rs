//! The Python client (`clients/python`, standard library only) against a live `sylva serve`:
//! a resumed upload, a job with an idempotency key, its events to the end, a verified download
//! and typed errors. Without `python3` the test prints why and passes (capability `python`).

#[path = "common/mod.rs"]
mod common;

use std::path::Path;
use std::process::Command;

use common::*;

#[test]
fn the_python_client_uploads_submits_follows_and_downloads() {
    if !Command::new("python3")
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success())
    {
        sylva::testing::skip("python", "no python3 to run the client");
        return;
    }
    let fx = fixture();
    let srv = serve(&fx.data, &["--part-size", "4096"]);
    let out = fx.dir.path().join("downloads");
    std::fs::create_dir_all(&out).expect("mkdir");
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("clients/python/tests/live.py");
    let run = Command::new("python3")
        .arg(&script)
        .arg(&srv.base)
        .arg(&fx.lidar)
        .arg(&fx.colmap_zip)
        .arg(&out)
        .output()
        .expect("python3 runs");
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(
        run.status.success(),
        "client failed: {stdout}\n{}\nserver: {}",
        String::from_utf8_lossy(&run.stderr),
        srv.stderr_text()
    );
    let r: serde_json::Value = serde_json::from_str(stdout.trim()).expect("one JSON object");
    eprintln!("{r}");
    assert_eq!(r["info"], true, "{r}");
    assert_eq!(r["resumed"], true, "{r}");
    assert_eq!(r["resumed_state"], "complete", "{r}");
    assert_eq!(r["idempotent"], true, "{r}");
    assert_eq!(r["state"], "succeeded", "{r}");
    for e in ["end", "job", "log"] {
        assert!(
            r["events"].as_array().expect("events").contains(&e.into()),
            "{r}"
        );
    }
    assert_eq!(
        r["downloaded_points"].as_u64(),
        Some(fx.lidar_points as u64),
        "{r}"
    );
    assert_eq!(r["results_stages"], serde_json::json!(["ingest"]), "{r}");
    assert_eq!(r["not_found"][0], 404, "{r}");
    assert_eq!(r["not_found"][1], "urn:sylva:problem:not-found", "{r}");
    assert_eq!(r["unprocessable"][0], 422, "{r}");
}
