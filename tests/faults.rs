//! Faults from outside: a full disk during an upload and during a stage. The data directory
//! (blobs and the SQLite database) lives on a small tmpfs mounted for the test, so the disk
//! really fills; without the right to mount (not root, or no tmpfs) the test says why and
//! passes.

mod common;

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Duration;

use common::*;
use reqwest::{Client, StatusCode};
use serde_json::Value;

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

impl Tmpfs {
    /// The data folder of the test's `sylva serve` on this disk.
    fn data(&self) -> PathBuf {
        self.dir.join("data")
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

/// Waits for job `id` to end (60 s at most), asserting that it failed with a disk-full (507)
/// problem; the job.
async fn fails_with_507(c: &Client, base: &str, id: &str) -> Value {
    let (job, _) = wait_job(c, base, id, Duration::from_secs(60), is_terminal).await;
    assert_eq!(job["state"], "failed", "{job}");
    assert_eq!(job["error"]["status"], 507, "{job}");
    job
}

/// Retries job `id`, asserting 202; its id.
async fn retried(c: &Client, base: &str, id: String) -> String {
    let r = send(c.post(format!("{base}/v1/jobs/{id}/retry"))).await;
    assert_eq!(r.status(), StatusCode::ACCEPTED);
    id
}

#[tokio::test(flavor = "multi_thread")]
async fn a_full_disk_gives_507_and_a_failed_stage_and_the_database_survives() {
    let Some(fs) = Tmpfs::mount("24m") else {
        return;
    };
    let fx = fixture();
    let srv = serve(&fs.data(), &["--min-free-bytes", "0"]);
    let (c, base, inputs) = client_with_inputs(&srv, &fx).await;
    // An upload opened before the disk fills.
    let pending = id_of(&open_upload(&c, &base, "lidar", "late.las", 200_000).await);
    let late_part = || put_part(&c, &base, &pending, 0, vec![7u8; 200_000]);

    let filler = fill(&fs.dir);

    // A part that cannot be stored: 507, as a problem.
    let r = late_part().await;
    // The body may be left unread: the answer says the connection will not be reused.
    assert_eq!(
        r.headers().get("connection").map(|v| v.as_bytes()),
        Some(&b"close"[..]),
        "{:?}",
        r.headers()
    );
    let p = expect_problem(r, StatusCode::INSUFFICIENT_STORAGE).await;
    assert!(detail(&p).contains("disk"), "{p}");

    // A job on the full disk: refused with 507 at creation, or accepted and its stage
    // fails with a disk-full problem. Never a 500, never stuck.
    let body = job_until(&inputs, "ingest");
    let r = send(c.post(format!("{base}/v1/jobs")).json(&body)).await;
    let failed_job = if r.status() == StatusCode::ACCEPTED {
        let job: Value = r.json().await.expect("json");
        let id = id_of(&job);
        fails_with_507(&c, &base, &id).await;
        Some(id)
    } else {
        expect_problem(r, StatusCode::INSUFFICIENT_STORAGE).await;
        None
    };

    // The service is still up while the disk is full.
    for path in ["/livez", "/v1/jobs"] {
        let r = send(c.get(format!("{base}{path}"))).await;
        assert_eq!(r.status(), StatusCode::OK, "{path}");
    }

    // Space comes back: the same work goes through, and the database is intact.
    std::fs::remove_file(&filler).expect("free the disk");
    let id = match failed_job {
        Some(id) => retried(&c, &base, id).await,
        None => submit(&c, &base, &body).await,
    };
    let (job, _) = wait_job(&c, &base, &id, Duration::from_secs(60), is_terminal).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    assert_eq!(late_part().await.status(), StatusCode::OK);

    drop(srv);
    assert_intact(&fs.data().join("sylva.db")).await;
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
    let db = fx.dir.path().join("sylva.db");
    let db_arg = db.display().to_string();
    let srv = serve(
        &fs.data(),
        &[
            "--min-free-bytes",
            "0",
            "--database",
            &db_arg,
            "--debug-stage-pause-ms",
            "1500",
        ],
    );
    let (c, base, inputs) = client_with_inputs(&srv, &fx).await;
    let id = submit(&c, &base, &job_until(&inputs, "ingest")).await;
    // The stage has started (it waits 1.5 s before its work): now the disk fills.
    wait_job(&c, &base, &id, Duration::from_secs(30), |j| {
        j["state"] == "running"
    })
    .await;
    let filler = fill(&fs.dir);
    let job = fails_with_507(&c, &base, &id).await;
    assert_eq!(job["error"]["stage"], "ingest", "{job}");
    assert_eq!(stage(&job, "ingest")["state"], "failed", "{job}");
    let live = send(c.get(format!("{base}/livez"))).await;
    assert_eq!(live.status(), StatusCode::OK);

    std::fs::remove_file(&filler).expect("free the disk");
    let id = retried(&c, &base, id).await;
    let (job, _) = wait_job(&c, &base, &id, Duration::from_secs(60), is_terminal).await;
    assert_eq!(job["state"], "succeeded", "{job}");

    drop(srv);
    assert_intact(&db).await;
}
