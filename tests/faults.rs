//! Faults from outside: a full disk during an upload and during a stage. The data directory
//! (blobs and the SQLite database) lives on a small tmpfs mounted for the test, so the disk
//! really fills; without the right to mount (not root, or no tmpfs) the test says why and
//! passes.

mod common;

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Duration;

use common::*;
use reqwest::StatusCode;
use serde_json::{Value, json};

/// A tmpfs mounted at a fresh folder, unmounted when dropped.
struct Tmpfs {
    dir: PathBuf,
}

impl Tmpfs {
    fn mount(size: &str) -> Option<Tmpfs> {
        let dir =
            std::env::temp_dir().join(format!("sylva-full-{}", uuid::Uuid::new_v4().simple()));
        std::fs::create_dir_all(&dir).ok()?;
        let out = std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(&dir)
            .output();
        match out {
            Ok(o) if o.status.success() => Some(Tmpfs { dir }),
            Ok(o) => {
                eprintln!(
                    "disk-full test skipped: cannot mount a tmpfs ({})",
                    String::from_utf8_lossy(&o.stderr).trim()
                );
                let _ = std::fs::remove_dir(&dir);
                None
            }
            Err(e) => {
                sylva::testing::skip("mount", &format!("disk-full test: no mount command ({e})"));
                let _ = std::fs::remove_dir(&dir);
                None
            }
        }
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount")
            .arg("-l")
            .arg(&self.dir)
            .status();
        let _ = std::fs::remove_dir(&self.dir);
    }
}

/// Fills the filesystem holding `dir` with one file, to the last byte.
fn fill(dir: &Path) -> PathBuf {
    let path = dir.join("filler");
    let mut f = std::fs::File::create(&path).expect("filler");
    let block = vec![0u8; 64 << 10];
    loop {
        if f.write_all(&block).is_err() {
            break;
        }
    }
    // Whatever the last partial block could still take.
    for _ in 0..(64 << 10) {
        if f.write_all(&[0]).is_err() {
            break;
        }
    }
    let _ = f.flush();
    path
}

/// `PRAGMA integrity_check` of the SQLite file at `path` says "ok".
async fn assert_intact(path: &Path) {
    let url = format!("sqlite://{}", path.display());
    let mut conn = <sqlx::SqliteConnection as sqlx::Connection>::connect(&url)
        .await
        .expect("open the database");
    let check: (String,) = sqlx::query_as("PRAGMA integrity_check")
        .fetch_one(&mut conn)
        .await
        .expect("integrity_check");
    assert_eq!(check.0, "ok");
}

#[tokio::test(flavor = "multi_thread")]
async fn a_full_disk_gives_507_and_a_failed_stage_and_the_database_survives() {
    let Some(fs) = Tmpfs::mount("24m") else {
        return;
    };
    let fx = fixture();
    let data = fs.dir.join("data");
    let srv = serve(&data, &["--min-free-bytes", "0"]);
    let (c, base) = (client(), srv.base.clone());
    let inputs = upload_inputs(&c, &base, &fx).await;
    // An upload opened before the disk fills.
    let pending: Value = c
        .post(format!("{base}/v1/uploads"))
        .json(&json!({ "kind": "lidar", "filename": "late.las", "size": 200_000 }))
        .send()
        .await
        .expect("create")
        .json()
        .await
        .expect("json");
    let pending = pending["id"].as_str().expect("id").to_string();

    let filler = fill(&fs.dir);

    // A part that cannot be stored: 507, as a problem.
    let r = c
        .put(format!("{base}/v1/uploads/{pending}/parts/0"))
        .body(vec![7u8; 200_000])
        .send()
        .await
        .expect("part");
    // The body may be left unread: the answer says the connection will not be reused.
    assert_eq!(
        r.headers().get("connection").map(|v| v.as_bytes()),
        Some(&b"close"[..]),
        "{:?}",
        r.headers()
    );
    let p = expect_problem(r, StatusCode::INSUFFICIENT_STORAGE).await;
    assert!(
        p["detail"].as_str().expect("detail").contains("disk"),
        "{p}"
    );

    // A job on the full disk: refused with 507 at creation, or accepted and its stage
    // fails with a disk-full problem. Never a 500, never stuck.
    let r = c
        .post(format!("{base}/v1/jobs"))
        .json(&json!({ "inputs": inputs, "params": { "until": "ingest" } }))
        .send()
        .await
        .expect("create job");
    let failed_job = if r.status() == StatusCode::ACCEPTED {
        let job: Value = r.json().await.expect("json");
        let id = job["id"].as_str().expect("id").to_string();
        let (job, _) = wait_job(&c, &base, &id, Duration::from_secs(60), is_terminal).await;
        assert_eq!(job["state"], "failed", "{job}");
        assert_eq!(job["error"]["status"], 507, "{job}");
        Some(id)
    } else {
        expect_problem(r, StatusCode::INSUFFICIENT_STORAGE).await;
        None
    };

    // The service is still up while the disk is full.
    let live = c.get(format!("{base}/livez")).send().await.expect("livez");
    assert_eq!(live.status(), StatusCode::OK);
    let list = c.get(format!("{base}/v1/jobs")).send().await.expect("list");
    assert_eq!(list.status(), StatusCode::OK);

    // Space comes back: the same work goes through, and the database is intact.
    std::fs::remove_file(&filler).expect("free the disk");
    let id = match failed_job {
        Some(id) => {
            let r = c
                .post(format!("{base}/v1/jobs/{id}/retry"))
                .send()
                .await
                .expect("retry");
            assert_eq!(r.status(), StatusCode::ACCEPTED);
            id
        }
        None => {
            let job = create_job(
                &c,
                &base,
                &json!({ "inputs": inputs, "params": { "until": "ingest" } }),
            )
            .await;
            job["id"].as_str().expect("id").to_string()
        }
    };
    let (job, _) = wait_job(&c, &base, &id, Duration::from_secs(60), is_terminal).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    let r = c
        .put(format!("{base}/v1/uploads/{pending}/parts/0"))
        .body(vec![7u8; 200_000])
        .send()
        .await
        .expect("part");
    assert_eq!(r.status(), StatusCode::OK);

    drop(srv);
    assert_intact(&data.join("sylva.db")).await;
}

/// The disk fills while a stage runs: the stage fails with a disk-full (507) problem, the
/// worker goes on, the database (kept on another disk here, as a PostgreSQL deployment or a
/// separate volume would) records it all, and a retry succeeds once space is back.
#[tokio::test(flavor = "multi_thread")]
async fn a_disk_that_fills_during_a_stage_fails_it_with_507_and_a_retry_succeeds() {
    let Some(fs) = Tmpfs::mount("24m") else {
        return;
    };
    let fx = fixture();
    let data = fs.dir.join("data");
    let db = fx.dir.path().join("sylva.db");
    let db_arg = db.display().to_string();
    let srv = serve(
        &data,
        &[
            "--min-free-bytes",
            "0",
            "--database",
            &db_arg,
            "--debug-stage-pause-ms",
            "1500",
        ],
    );
    let (c, base) = (client(), srv.base.clone());
    let inputs = upload_inputs(&c, &base, &fx).await;
    let job = create_job(
        &c,
        &base,
        &json!({ "inputs": inputs, "params": { "until": "ingest" } }),
    )
    .await;
    let id = job["id"].as_str().expect("id").to_string();
    // The stage has started (it waits 1.5 s before its work): now the disk fills.
    wait_job(&c, &base, &id, Duration::from_secs(30), |j| {
        j["state"] == "running"
    })
    .await;
    let filler = fill(&fs.dir);
    let (job, _) = wait_job(&c, &base, &id, Duration::from_secs(60), is_terminal).await;
    assert_eq!(job["state"], "failed", "{job}");
    assert_eq!(job["error"]["status"], 507, "{job}");
    assert_eq!(job["error"]["stage"], "ingest", "{job}");
    assert_eq!(stage(&job, "ingest")["state"], "failed", "{job}");
    let live = c.get(format!("{base}/livez")).send().await.expect("livez");
    assert_eq!(live.status(), StatusCode::OK);

    std::fs::remove_file(&filler).expect("free the disk");
    let r = c
        .post(format!("{base}/v1/jobs/{id}/retry"))
        .send()
        .await
        .expect("retry");
    assert_eq!(r.status(), StatusCode::ACCEPTED);
    let (job, _) = wait_job(&c, &base, &id, Duration::from_secs(60), is_terminal).await;
    assert_eq!(job["state"], "succeeded", "{job}");

    drop(srv);
    assert_intact(&db).await;
}
