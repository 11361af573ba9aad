//! Queue semantics, checked the same way on both backends: each test body takes a
//! [`JobStore`] and runs once on an SQLite file and once on a fresh PostgreSQL database
//! (skipped, with the reason printed, where PostgreSQL is not installed).

use std::time::Duration;

use super::*;
use crate::pipeline::PipelineParams;
use crate::stage::Stage;

#[path = "../../tests/common/postgres.rs"]
mod test_postgres;

/// The database a test body runs on; held (never read) so the SQLite folder or the
/// PostgreSQL database lives until the test ends.
#[allow(dead_code)]
enum Scratch {
    Sqlite(tempfile::TempDir),
    Postgres(test_postgres::TestDatabase),
}

async fn open_sqlite() -> (Scratch, JobStore) {
    let dir = tempfile::tempdir().expect("tempdir");
    let db = JobStore::open_sqlite(&dir.path().join("t.db"), 4)
        .await
        .expect("open sqlite");
    (Scratch::Sqlite(dir), db)
}

async fn open_postgres() -> Option<(Scratch, JobStore)> {
    let pg = test_postgres::database()?;
    let db = JobStore::open(&Database::Postgres(pg.url.clone()), 8)
        .await
        .expect("open postgres");
    Some((Scratch::Postgres(pg), db))
}

/// Runs the async test body `$body(store)` once per backend, as `$name::sqlite` and
/// `$name::postgres`.
macro_rules! on_both_backends {
    ($name:ident) => {
        mod $name {
            #[tokio::test(flavor = "multi_thread")]
            async fn sqlite() {
                let (_keep, db) = super::open_sqlite().await;
                super::$name(db).await;
            }

            #[tokio::test(flavor = "multi_thread")]
            async fn postgres() {
                if let Some((_keep, db)) = super::open_postgres().await {
                    assert_eq!(db.backend_name(), "postgres");
                    super::$name(db).await;
                }
            }
        }
    };
}

fn upload(id: &str, kind: UploadKind) -> UploadRecord {
    let now = now_ms();
    UploadRecord {
        id: id.into(),
        kind,
        filename: "f".into(),
        size: 1,
        sha256: None,
        part_size: 1,
        complete: false,
        inspection: None,
        created_at: now,
        expires_at: now,
        completed_at: None,
        parts: vec![],
        owner: String::new(),
        expired: false,
    }
}

/// Queues job `id` for the anonymous owner over `inputs()`.
async fn create(
    db: &JobStore,
    id: &str,
    key: Option<&str>,
    hash: &str,
    max_queued: i64,
) -> Result<Created, DbError> {
    create_as(
        db,
        id,
        &inputs(),
        key,
        hash,
        "",
        Admission::queue(max_queued),
    )
    .await
}

async fn create_as(
    db: &JobStore,
    id: &str,
    inputs: &JobInputs,
    key: Option<&str>,
    hash: &str,
    owner: &str,
    limits: Admission,
) -> Result<Created, DbError> {
    let params = params();
    let job = NewJob {
        id,
        inputs,
        params: &params,
        stages: &Stage::ALL,
        idempotency_key: key,
        request_hash: hash,
        owner,
        webhook: None,
    };
    db.create_job(&job, limits).await
}

fn inputs() -> JobInputs {
    JobInputs {
        lidar: "l".into(),
        colmap: Some("c".into()),
        photos: None,
        control_points: None,
        field_dbh: None,
    }
}

fn params() -> serde_json::Value {
    serde_json::to_value(PipelineParams::default()).expect("params")
}

/// Two complete uploads (`l`, `c`) and `jobs` queued jobs `j0`, `j1`, ... over them.
async fn with_jobs(db: &JobStore, jobs: usize) -> Vec<String> {
    for (id, kind) in [("l", UploadKind::Lidar), ("c", UploadKind::Colmap)] {
        db.create_upload(&upload(id, kind)).await.expect("upload");
        db.put_part(id, 0, 1, "x").await.expect("part");
        db.complete_upload(id, "x", &serde_json::json!({"points": 1}))
            .await
            .expect("complete");
    }
    let mut ids = Vec::new();
    for k in 0..jobs {
        let id = format!("j{k}");
        create(db, &id, None, "h", 1000).await.expect("job");
        ids.push(id);
    }
    ids
}

/// `db.claim(...)`, which must give a job.
async fn claimed(db: &JobStore, worker: &str, lease: Duration, max_attempts: i64) -> Claim {
    let claim = db.claim(worker, lease, max_attempts).await.expect("claim");
    claim.expect("a job")
}

/// Stage ingest of `job` run to its end by the claim holding `token` (attempt `attempt`):
/// started, then finished with `metrics` and the job at `progress`.
async fn run_ingest(
    db: &JobStore,
    (job, token): (&str, &str),
    attempt: i64,
    metrics: serde_json::Value,
    progress: f64,
) {
    let stage = Stage::Ingest;
    db.start_stage(job, token, stage, attempt)
        .await
        .expect("start");
    let finished = db.finish_stage(job, token, stage, &metrics, &[], progress);
    finished.await.expect("checkpoint");
}

/// The deliveries due now, claimed for `lease` (10 at most).
async fn due_deliveries(db: &JobStore, lease: Duration) -> Vec<Delivery> {
    db.claim_deliveries(lease, 10).await.expect("claim")
}

/// Records `outcome` for delivery `id` as the claim holding `token`: whether it was recorded.
async fn finish_delivery(
    db: &JobStore,
    (id, token): (&str, &str),
    outcome: &DeliveryOutcome,
) -> bool {
    db.finish_delivery(id, token, outcome)
        .await
        .expect("finish")
}

async fn a_worker_that_lost_its_lease_cannot_write(db: JobStore) {
    let job = with_jobs(&db, 1).await.remove(0);
    let short = Duration::from_millis(50);
    let a = claimed(&db, "A", short, 5).await;
    assert_eq!(a.attempt, 1);
    assert!(
        db.claim("B", short, 5).await.expect("claim").is_none(),
        "leased"
    );
    tokio::time::sleep(Duration::from_millis(80)).await;
    let b = claimed(&db, "B", short, 5).await;
    assert_eq!(b.attempt, 2);
    // A is fenced out of every write.
    let r = db
        .finish_stage(
            &job,
            &a.token,
            Stage::Ingest,
            &serde_json::json!({}),
            &[],
            0.1,
        )
        .await;
    assert!(matches!(r, Err(DbError::Fenced)), "{r:?}");
    assert!(matches!(
        db.start_stage(&job, &a.token, Stage::Ingest, 1).await,
        Err(DbError::Fenced)
    ));
    assert!(matches!(
        db.finish_job(&job, &a.token, &RunEnd::Succeeded).await,
        Err(DbError::Fenced)
    ));
    assert_eq!(
        db.heartbeat(&job, &a.token, short, 0.5, None)
            .await
            .expect("hb"),
        Heartbeat::Lost
    );
    // B writes its checkpoint; a later claim resumes after it.
    run_ingest(&db, (&job, &b.token), 2, serde_json::json!({"n": 1}), 0.05).await;
    tokio::time::sleep(Duration::from_millis(80)).await;
    let c = claimed(&db, "C", short, 5).await;
    assert_eq!(c.done, vec!["ingest".to_string()]);
    assert!(c.progress >= 0.05);
    let j = db.get_job(&job).await.expect("get").expect("job");
    assert_eq!(j.stages[0].metrics, Some(serde_json::json!({"n": 1})));
}
on_both_backends!(a_worker_that_lost_its_lease_cannot_write);

async fn a_job_whose_workers_keep_dying_fails_after_max_attempts(db: JobStore) {
    let job = with_jobs(&db, 1).await.remove(0);
    let short = Duration::from_millis(20);
    for _ in 0..2 {
        assert!(db.claim("W", short, 2).await.expect("claim").is_some());
        tokio::time::sleep(Duration::from_millis(40)).await;
    }
    assert!(db.claim("W", short, 2).await.expect("claim").is_none());
    let j = db.get_job(&job).await.expect("get").expect("job");
    assert_eq!(j.state, JobState::Failed);
    assert!(
        j.error
            .is_some_and(|e| e.to_string().contains("worker-lost"))
    );
}
on_both_backends!(a_job_whose_workers_keep_dying_fails_after_max_attempts);

async fn heartbeat_sees_cancel_and_progress_never_decreases(db: JobStore) {
    let job = with_jobs(&db, 1).await.remove(0);
    let lease = Duration::from_secs(30);
    let a = claimed(&db, "A", lease, 3).await;
    let beat = |progress| db.heartbeat(&job, &a.token, lease, progress, None);
    assert_eq!(beat(0.4).await.expect("hb"), Heartbeat::Ok);
    beat(0.2).await.expect("hb");
    assert_eq!(
        db.get_job(&job).await.expect("get").expect("job").progress,
        0.4
    );
    assert_eq!(db.cancel(&job).await.expect("cancel"), JobState::Canceling);
    assert_eq!(beat(0.5).await.expect("hb"), Heartbeat::CancelRequested);
    db.finish_job(&job, &a.token, &RunEnd::Canceled { stage: None })
        .await
        .expect("end");
    assert!(matches!(db.cancel(&job).await, Err(DbError::Conflict(_))));
    assert_eq!(db.integrity_check().await.expect("check"), "ok");
}
on_both_backends!(heartbeat_sees_cancel_and_progress_never_decreases);

async fn the_same_idempotency_key_gives_the_same_job_and_a_full_queue_refuses(db: JobStore) {
    with_jobs(&db, 0).await;
    let first = create(&db, "k1", Some("key"), "h1", 2)
        .await
        .expect("create");
    assert!(matches!(first, Created::New(ref id) if id == "k1"));
    let again = create(&db, "k2", Some("key"), "h1", 2)
        .await
        .expect("same request");
    assert!(matches!(again, Created::Existing(ref id) if id == "k1"));
    let other = create(&db, "k3", Some("key"), "h2", 2).await;
    assert!(matches!(other, Err(DbError::Invalid(_))), "{other:?}");
    create(&db, "k4", None, "h", 2).await.expect("second job");
    let full = create(&db, "k5", None, "h", 2).await;
    assert!(matches!(full, Err(DbError::QueueFull(2))), "{full:?}");
    let missing = JobInputs {
        lidar: "nope".into(),
        ..inputs()
    };
    let r = create_as(&db, "k6", &missing, None, "h", "", Admission::queue(10)).await;
    assert!(
        matches!(r, Err(DbError::Invalid(ref m)) if m.contains("does not exist")),
        "{r:?}"
    );
    let listed = db.list_jobs(None, None, None, 10).await.expect("list");
    assert_eq!(
        listed.iter().map(|j| j.id.as_str()).collect::<Vec<_>>(),
        ["k4", "k1"],
        "newest first"
    );
    let page = db
        .list_jobs(None, Some(JobState::Queued), Some(listed[0].seq), 10)
        .await
        .expect("page");
    assert_eq!(page.len(), 1);
    assert_eq!(page[0].id, "k1");
    // (serde_json's default float parsing may move the last digit of an f32 widened to f64,
    // on either backend; compare values that survive exactly.)
    assert_eq!(
        page[0].params["anchors"],
        params()["anchors"],
        "params come back"
    );
    assert_eq!(
        page[0].params["train"],
        params()["train"],
        "params come back"
    );
    assert_eq!(page[0].inputs, inputs());
}
on_both_backends!(the_same_idempotency_key_gives_the_same_job_and_a_full_queue_refuses);

async fn a_completed_upload_takes_no_more_parts(db: JobStore) {
    db.create_upload(&UploadRecord {
        size: 10,
        part_size: 4,
        ..upload("u", UploadKind::Lidar)
    })
    .await
    .expect("create");
    db.put_part("u", 1, 4, "a").await.expect("part 1");
    db.put_part("u", 1, 4, "b").await.expect("part 1 again");
    db.put_part("u", 0, 4, "c").await.expect("part 0");
    let u = db.get_upload("u").await.expect("get").expect("upload");
    assert_eq!(u.parts, vec![(0, 4), (1, 4)]);
    assert_eq!(u.missing_parts(), vec![2]);
    db.put_part("u", 2, 2, "d").await.expect("part 2");
    db.complete_upload("u", "sum", &serde_json::json!({"points": 3}))
        .await
        .expect("complete");
    let u = db.get_upload("u").await.expect("get").expect("upload");
    assert!(u.complete);
    assert_eq!(u.inspection, Some(serde_json::json!({"points": 3})));
    assert!(matches!(
        db.put_part("u", 0, 4, "e").await,
        Err(DbError::Conflict(_))
    ));
    assert!(matches!(
        db.put_part("nope", 0, 4, "e").await,
        Err(DbError::NotFound)
    ));
    assert!(db.get_upload("nope").await.expect("get").is_none());
}
on_both_backends!(a_completed_upload_takes_no_more_parts);

async fn retry_resumes_at_the_first_unfinished_stage(db: JobStore) {
    let job = with_jobs(&db, 1).await.remove(0);
    let lease = Duration::from_secs(30);
    let a = claimed(&db, "A", lease, 3).await;
    run_ingest(&db, (&job, &a.token), 1, serde_json::json!({}), 0.1).await;
    assert!(matches!(
        db.retry(&job, None).await,
        Err(DbError::Conflict(_))
    ));
    db.start_stage(&job, &a.token, Stage::Register, 1)
        .await
        .expect("start");
    let problem = serde_json::json!({"title": "Stage failed", "status": 500});
    db.finish_job(
        &job,
        &a.token,
        &RunEnd::Failed {
            stage: Some("register".into()),
            problem: problem.clone(),
        },
    )
    .await
    .expect("fail");
    let j = db.get_job(&job).await.expect("get").expect("job");
    assert_eq!(j.state, JobState::Failed);
    assert_eq!(j.error, Some(problem));
    // Stage 1 is sfm, which this job skipped; register is stage 2.
    assert_eq!(j.stages[2].state, StageState::Failed);
    assert!(matches!(
        db.retry(&job, Some(Stage::Anchors)).await,
        Err(DbError::Invalid(_))
    ));
    let reset = db.retry(&job, None).await.expect("retry");
    // The first unfinished stage: sfm, never run here.
    assert_eq!(reset.first().map(String::as_str), Some("sfm"));
    let j = db.get_job(&job).await.expect("get").expect("job");
    assert_eq!(j.state, JobState::Queued);
    assert_eq!(j.attempt, 0);
    assert!(j.error.is_none());
    assert_eq!(j.progress, Stage::Ingest.weight());
    let b = claimed(&db, "B", lease, 3).await;
    assert_eq!(b.done, vec!["ingest".to_string()]);
    db.finish_job(&job, &b.token, &RunEnd::Succeeded)
        .await
        .expect("end");
    db.delete_job(&job).await.expect("delete");
    assert!(db.get_job(&job).await.expect("get").is_none());
    assert!(matches!(db.delete_job(&job).await, Err(DbError::NotFound)));
}
on_both_backends!(retry_resumes_at_the_first_unfinished_stage);

async fn concurrent_claimers_take_each_job_once_and_logs_keep_order(db: JobStore) {
    let ids = with_jobs(&db, 20).await;
    let lease = Duration::from_secs(60);
    let mut tasks = Vec::new();
    for w in 0..6 {
        let db = db.clone();
        tasks.push(tokio::spawn(async move {
            let mut mine = Vec::new();
            while let Some(c) = db.claim(&format!("w{w}"), lease, 3).await.expect("claim") {
                db.append_log(&c.job_id, "info", None, &format!("claimed by w{w}"))
                    .await
                    .expect("log");
                db.finish_job(&c.job_id, &c.token, &RunEnd::Succeeded)
                    .await
                    .expect("finish");
                mine.push(c.job_id);
            }
            mine
        }));
    }
    let mut claimed = Vec::new();
    for t in tasks {
        claimed.extend(t.await.expect("task"));
    }
    claimed.sort();
    let mut expected = ids.clone();
    expected.sort();
    assert_eq!(claimed, expected, "every job claimed exactly once");
    // Concurrent log writers on one job get consecutive sequence numbers.
    let mut writers = Vec::new();
    for k in 0..8 {
        let db = db.clone();
        writers.push(tokio::spawn(async move {
            for n in 0..5 {
                db.append_log("j0", "info", Some("ingest"), &format!("{k}-{n}"))
                    .await
                    .expect("log");
            }
        }));
    }
    for w in writers {
        w.await.expect("writer");
    }
    let lines = db.log("j0", 0, 1000).await.expect("log");
    assert_eq!(lines.len(), 41);
    assert!(lines.iter().enumerate().all(|(i, l)| l.seq == i as i64 + 1));
    let counts = db.count_by_state().await.expect("counts");
    assert!(counts.contains(&(JobState::Succeeded, 20)), "{counts:?}");
    assert_eq!(db.integrity_check().await.expect("check"), "ok");
}
on_both_backends!(concurrent_claimers_take_each_job_once_and_logs_keep_order);

async fn workers_are_counted_and_dead_ones_recovered(db: JobStore) {
    let job = with_jobs(&db, 1).await.remove(0);
    // A pid that cannot exist on Linux (above pid_max's ceiling of 2^22).
    let dead_pid = 4_194_305;
    db.register_worker("dead", "host-a", dead_pid)
        .await
        .expect("register");
    db.register_worker("alive", "host-a", std::process::id())
        .await
        .expect("register");
    let live = async || db.live_workers(Duration::from_secs(60)).await.expect("n");
    assert_eq!(live().await, 2);
    let lease = Duration::from_secs(600);
    let c = claimed(&db, "dead", lease, 3).await;
    assert_eq!(c.job_id, job);
    assert!(db.claim("alive", lease, 3).await.expect("claim").is_none());
    let recovered = db
        .recover("host-a", Duration::from_secs(600))
        .await
        .expect("recover");
    assert_eq!(recovered, 1);
    let again = claimed(&db, "alive", lease, 3).await;
    assert_eq!(again.attempt, 2);
    assert_eq!(live().await, 1);
    db.unregister_worker("alive").await.expect("unregister");
    assert_eq!(live().await, 0);
    db.ping().await.expect("ping");
}
on_both_backends!(workers_are_counted_and_dead_ones_recovered);

#[test]
fn database_urls_pick_the_backend() {
    let pg = Database::parse("postgres://u:secret@db:5432/sylva").expect("pg");
    assert!(matches!(pg, Database::Postgres(_)));
    assert_eq!(pg.redacted(), "postgres://u:***@db:5432/sylva");
    assert!(!pg.to_string().contains("secret"));
    assert!(matches!(
        Database::parse("postgresql://db/sylva"),
        Ok(Database::Postgres(_))
    ));
    assert_eq!(
        Database::parse("sqlite:/var/lib/sylva/q.db").expect("sqlite"),
        Database::Sqlite("/var/lib/sylva/q.db".into())
    );
    assert_eq!(
        Database::parse("sqlite://q.db").expect("sqlite"),
        Database::Sqlite("q.db".into())
    );
    assert_eq!(
        Database::parse("data/sylva.db").expect("path"),
        Database::Sqlite("data/sylva.db".into())
    );
    assert!(matches!(
        Database::parse("mysql://db/sylva"),
        Err(DbError::Invalid(_))
    ));
    assert!(matches!(
        Database::parse("sqlite:"),
        Err(DbError::Invalid(_))
    ));
    assert_eq!(
        Database::parse("postgres://db/sylva")
            .expect("pg")
            .redacted(),
        "postgres://db/sylva"
    );
}

/// A waiter on `wake`, registered before this returns.
async fn waiter(wake: &std::sync::Arc<tokio::sync::Notify>) -> tokio::task::JoinHandle<()> {
    let wake = wake.clone();
    let task = tokio::spawn(async move { wake.notified().await });
    tokio::time::sleep(Duration::from_millis(100)).await;
    task
}

#[tokio::test(flavor = "multi_thread")]
async fn announcements_wake_idle_workers_on_postgres_and_cost_nothing_on_sqlite() {
    let (_keep, lite) = open_sqlite().await;
    lite.announce("j0").await.expect("no-op");
    assert!(lite.listen_for_work(Default::default()).is_none());

    let Some(pg) = test_postgres::database() else {
        return;
    };
    // Two stores, as two processes would hold: the listener of one hears the other.
    let location = Database::Postgres(pg.url.clone());
    let db = JobStore::open(&location, 4).await.expect("first store");
    let other = JobStore::open(&location, 2).await.expect("second store");
    let wake = std::sync::Arc::new(tokio::sync::Notify::new());
    let listener = other
        .listen_for_work(wake.clone())
        .expect("postgres listens");
    // Give the listener time to subscribe.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let ids = with_jobs(&db, 1).await;
    let quiet = waiter(&wake).await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert!(
        !quiet.is_finished(),
        "creating a job announces nothing by itself"
    );
    db.announce(&ids[0]).await.expect("announce");
    tokio::time::timeout(Duration::from_secs(5), quiet)
        .await
        .expect("woken by NOTIFY well before any poll")
        .expect("waiter");
    listener.abort();
}

async fn owners_have_quotas_and_retention_expires_uploads_and_purges_jobs(db: JobStore) {
    with_jobs(&db, 0).await;
    // Another owner's uploads: 1000 bytes each, one still open.
    for (id, kind, complete) in [
        ("la", UploadKind::Lidar, true),
        ("ca", UploadKind::Colmap, true),
        ("open", UploadKind::Lidar, false),
    ] {
        let u = UploadRecord {
            size: 1000,
            part_size: 1000,
            owner: "ta".into(),
            ..upload(id, kind)
        };
        db.create_upload(&u).await.expect("upload");
        if complete {
            db.put_part(id, 0, 1000, "x").await.expect("part");
            db.complete_upload(id, "x", &serde_json::json!({}))
                .await
                .expect("complete");
        }
    }
    assert_eq!(db.stored_bytes("ta").await.expect("bytes"), 3000);
    assert_eq!(db.stored_bytes("").await.expect("bytes"), 2);
    let mine = JobInputs {
        lidar: "la".into(),
        colmap: Some("ca".into()),
        photos: None,
        control_points: None,
        field_dbh: None,
    };
    let limits = Admission {
        max_queued: 100,
        max_active_per_owner: 1,
    };
    // Nobody reads another owner's uploads.
    let r = create_as(&db, "x", &inputs(), None, "h", "ta", limits).await;
    assert!(
        matches!(r, Err(DbError::Invalid(ref m)) if m.contains("does not exist")),
        "{r:?}"
    );
    create_as(&db, "a1", &mine, None, "h", "ta", limits)
        .await
        .expect("first job");
    let r = create_as(&db, "a2", &mine, None, "h", "ta", limits).await;
    assert!(matches!(r, Err(DbError::JobQuota(1))), "{r:?}");
    // The quota is per owner.
    create_as(&db, "n1", &inputs(), None, "h", "", limits)
        .await
        .expect("another owner's job");

    // a1 runs and finishes; then the quota has room again.
    let c = claimed(&db, "w", Duration::from_secs(30), 5).await;
    assert_eq!(c.job_id, "a1");
    db.finish_job("a1", &c.token, &RunEnd::Succeeded)
        .await
        .expect("finish");
    create_as(&db, "a2", &mine, None, "h", "ta", limits)
        .await
        .expect("room again");

    // The open upload expires once past its deadline; complete ones read by a job with
    // files stay.
    let now = now_ms() + 10;
    let expired = db.expire_uploads(now, now, 100).await.expect("expire");
    assert_eq!(expired, ["open"]);
    let u = db.get_upload("open").await.expect("get").expect("kept");
    assert!(u.expired && !u.complete);
    assert_eq!(db.stored_bytes("ta").await.expect("bytes"), 2000);
    // Only finished jobs are purged, and only once.
    assert_eq!(
        db.purge_jobs(now, 100).await.expect("purge"),
        vec!["a1".to_string()]
    );
    assert!(db.purge_jobs(now, 100).await.expect("again").is_empty());
    let j = db.get_job("a1").await.expect("get").expect("kept");
    assert!(j.purged_at.is_some() && j.artifacts.is_empty());
    // The orphan sweep's question: which of these still own files?
    let live = async |table: LiveTable, ids: &[&str]| {
        let ids: Vec<String> = ids.iter().map(|s| s.to_string()).collect();
        let mut live = db.live_ids(table, &ids).await.expect("live ids");
        live.sort();
        live
    };
    let jobs = live(LiveTable::Jobs, &["a1", "a2", "n1", "nope"]).await;
    assert_eq!(jobs, ["a2", "n1"]);
    let uploads = live(LiveTable::Uploads, &["open", "la", "ca", "nope"]).await;
    assert_eq!(uploads, ["ca", "la"]);
    assert!(live(LiveTable::Jobs, &[]).await.is_empty());
    // a2 (queued) still reads la and ca: they stay until it too is purged or deleted.
    assert!(
        db.expire_uploads(now, now, 100)
            .await
            .expect("expire")
            .is_empty()
    );
    db.cancel("a2").await.expect("cancel");
    db.delete_job("a2").await.expect("delete");
    let mut gone = db.expire_uploads(now, now, 100).await.expect("expire");
    gone.sort();
    assert_eq!(gone, ["ca", "la"]);
    // An expired upload cannot feed a new job: 410, not "incomplete".
    let r = create_as(&db, "a3", &mine, None, "h", "ta", limits).await;
    assert!(matches!(r, Err(DbError::Gone(_))), "{r:?}");
    assert_eq!(db.stored_bytes("ta").await.expect("bytes"), 0);
    assert_eq!(db.integrity_check().await.expect("check"), "ok");
}
on_both_backends!(owners_have_quotas_and_retention_expires_uploads_and_purges_jobs);

/// Queues job `id` (over the uploads of [`with_jobs`]) with a webhook wanting `events`.
async fn create_with_webhook(db: &JobStore, id: &str, events: &[WebhookEvent]) {
    let params = params();
    let spec = WebhookSpec {
        url: format!("http://hooks.example/{id}"),
        events: events.to_vec(),
    };
    let job = NewJob {
        id,
        inputs: &inputs(),
        params: &params,
        stages: &Stage::ALL,
        idempotency_key: None,
        request_hash: "h",
        owner: "",
        webhook: Some(&spec),
    };
    db.create_job(&job, Admission::queue(1000))
        .await
        .expect("job");
}

fn body(d: &Delivery) -> serde_json::Value {
    serde_json::from_str(&d.body).expect("body is JSON")
}

async fn webhook_deliveries_are_written_with_the_change_and_claimed_once(db: JobStore) {
    let plain = with_jobs(&db, 1).await.remove(0);
    create_with_webhook(&db, "hooked", WebhookEvent::DEFAULT).await;
    let j = db.get_job("hooked").await.expect("get").expect("job");
    assert_eq!(
        j.webhook.as_ref().map(|w| w.url.as_str()),
        Some("http://hooks.example/hooked")
    );
    assert!(
        db.get_job(&plain)
            .await
            .expect("get")
            .expect("job")
            .webhook
            .is_none()
    );
    // Nothing to announce before the end.
    assert!(
        due_deliveries(&db, Duration::from_secs(60))
            .await
            .is_empty()
    );
    db.cancel(&plain).await.expect("cancel");
    db.cancel("hooked").await.expect("cancel");
    assert!(db.job_deliveries(&plain).await.expect("list").is_empty());
    let listed = db.job_deliveries("hooked").await.expect("list");
    assert_eq!(listed.len(), 1);
    assert_eq!(listed[0].state, DeliveryState::Pending);
    assert_eq!(listed[0].event, "job.canceled");

    // One claim holds it: a second dispatcher gets nothing while the lease lives.
    let lease = Duration::from_secs(60);
    let mut got = due_deliveries(&db, lease).await;
    assert_eq!(got.len(), 1);
    let d = got.remove(0);
    assert_eq!(
        (d.attempts, d.owner.as_str(), d.job_id.as_str()),
        (1, "", "hooked")
    );
    assert_eq!(d.url, "http://hooks.example/hooked");
    let b = body(&d);
    assert_eq!(b["id"], d.id.as_str());
    assert_eq!(b["type"], "job.canceled");
    assert_eq!(b["data"]["job"]["state"], "canceled");
    assert!(due_deliveries(&db, lease).await.is_empty());
    // The attempt in flight is not counted yet: only an answered or failed one is.
    let in_flight = db.job_deliveries("hooked").await.expect("list");
    assert_eq!(in_flight[0].attempts, 0);

    // Only the claim's token records an outcome; a retry is due after its delay.
    let retry = |delay_ms| DeliveryOutcome::Retry {
        status: Some(500),
        error: "the receiver answered 500".into(),
        delay_ms,
    };
    assert!(!finish_delivery(&db, (&d.id, "not-the-token"), &retry(0)).await);
    assert!(finish_delivery(&db, (&d.id, &d.token), &retry(0)).await);
    let again = due_deliveries(&db, lease).await;
    assert_eq!(again.len(), 1);
    assert_eq!(again[0].attempts, 2);
    assert_eq!(again[0].body, d.body, "every attempt sends the same bytes");
    assert!(finish_delivery(&db, (&d.id, &again[0].token), &retry(60_000)).await);
    assert!(due_deliveries(&db, lease).await.is_empty(), "not yet due");
    let listed = db.job_deliveries("hooked").await.expect("list");
    assert_eq!(listed[0].attempts, 2);
    assert_eq!(listed[0].last_status, Some(500));
    assert!(
        listed[0]
            .next_attempt_at
            .is_some_and(|t| t > now_ms() + 50_000)
    );

    // A lease that runs out lets another dispatcher take over; the first is fenced.
    create_with_webhook(&db, "second", WebhookEvent::DEFAULT).await;
    db.cancel("second").await.expect("cancel");
    let first = due_deliveries(&db, Duration::from_millis(1)).await;
    assert_eq!(first.len(), 1);
    tokio::time::sleep(Duration::from_millis(30)).await;
    let taken = due_deliveries(&db, lease).await;
    assert_eq!(taken.len(), 1);
    assert_eq!(taken[0].id, first[0].id);
    // The first dispatcher's attempt was never recorded (as if it died with it): the
    // newcomer makes attempt 1 again.
    assert_eq!(taken[0].attempts, 1);
    let delivered = DeliveryOutcome::Delivered { status: 204 };
    assert!(!finish_delivery(&db, (&first[0].id, &first[0].token), &delivered).await);
    assert!(finish_delivery(&db, (&taken[0].id, &taken[0].token), &delivered).await);
    assert!(!finish_delivery(&db, (&taken[0].id, &taken[0].token), &delivered).await);
    let rec = db.job_deliveries("second").await.expect("list").remove(0);
    assert_eq!(rec.state, DeliveryState::Delivered);
    assert_eq!((rec.last_status, rec.next_attempt_at), (Some(204), None));
    assert_eq!(rec.attempts, 1, "the fenced attempt is not counted");
    assert!(rec.finished_at.is_some());

    // Given up: failed, never claimed again.
    create_with_webhook(&db, "third", WebhookEvent::DEFAULT).await;
    db.cancel("third").await.expect("cancel");
    let d = due_deliveries(&db, lease).await.remove(0);
    let give_up = DeliveryOutcome::GiveUp {
        status: None,
        error: "refused: 10.0.0.1 is a private address".into(),
    };
    assert!(finish_delivery(&db, (&d.id, &d.token), &give_up).await);
    let rec = db.job_deliveries("third").await.expect("list").remove(0);
    assert_eq!(rec.state, DeliveryState::Failed);
    assert!(rec.last_error.is_some_and(|e| e.contains("private")));
    let counts = db.count_deliveries().await.expect("counts");
    for (state, n) in [
        (DeliveryState::Pending, 1),
        (DeliveryState::Delivered, 1),
        (DeliveryState::Failed, 1),
    ] {
        assert!(counts.contains(&(state, n)), "{counts:?}");
    }

    // Deleting a job forgets its past deliveries but still sends its pending ones.
    db.delete_job("second").await.expect("delete");
    assert!(db.job_deliveries("second").await.expect("list").is_empty());
    db.delete_job("hooked").await.expect("delete");
    assert_eq!(db.job_deliveries("hooked").await.expect("list").len(), 1);
}
on_both_backends!(webhook_deliveries_are_written_with_the_change_and_claimed_once);

async fn stages_and_the_end_of_a_run_are_announced_as_the_webhook_asks(db: JobStore) {
    with_jobs(&db, 0).await;
    create_with_webhook(
        &db,
        "run",
        &[WebhookEvent::StageFinished, WebhookEvent::JobSucceeded],
    )
    .await;
    let lease = Duration::from_secs(30);
    let c = claimed(&db, "W", lease, 3).await;
    run_ingest(&db, ("run", &c.token), 1, serde_json::json!({}), 0.1).await;
    db.finish_job("run", &c.token, &RunEnd::Succeeded)
        .await
        .expect("end");
    let sent = due_deliveries(&db, lease).await;
    let events: Vec<&str> = sent.iter().map(|d| d.event.as_str()).collect();
    assert_eq!(events, ["stage.finished", "job.succeeded"]);
    assert_eq!(body(&sent[0])["data"]["stage"]["name"], "ingest");
    assert_eq!(body(&sent[1])["data"]["job"]["state"], "succeeded");

    // A job failed by the queue (its workers kept dying) is announced too, and a webhook
    // that did not ask for stages hears only the end.
    create_with_webhook(&db, "dies", WebhookEvent::DEFAULT).await;
    let short = Duration::from_millis(20);
    assert!(db.claim("W", short, 1).await.expect("claim").is_some());
    tokio::time::sleep(Duration::from_millis(40)).await;
    assert!(db.claim("W", short, 1).await.expect("claim").is_none());
    let sent = due_deliveries(&db, lease).await;
    assert_eq!(sent.len(), 1);
    assert_eq!(sent[0].event, "job.failed");
    assert!(
        body(&sent[0])["data"]["job"]["error"]
            .to_string()
            .contains("worker-lost")
    );

    // The signing key setting: the first value stored wins.
    assert_eq!(
        db.setting_or_insert("k", "first").await.expect("set"),
        "first"
    );
    assert_eq!(
        db.setting_or_insert("k", "second").await.expect("set"),
        "first"
    );
}
on_both_backends!(stages_and_the_end_of_a_run_are_announced_as_the_webhook_asks);

async fn retention_forgets_finished_deliveries_and_keeps_pending_ones(db: JobStore) {
    with_jobs(&db, 0).await;
    for id in ["sent", "owed"] {
        create_with_webhook(&db, id, WebhookEvent::DEFAULT).await;
        db.cancel(id).await.expect("cancel");
    }
    let claimed = due_deliveries(&db, Duration::from_secs(60)).await;
    let sent = claimed
        .iter()
        .find(|d| d.job_id == "sent")
        .expect("a delivery for `sent`");
    let delivered = DeliveryOutcome::Delivered { status: 204 };
    assert!(finish_delivery(&db, (&sent.id, &sent.token), &delivered).await);
    let mut purged = db.purge_jobs(now_ms() + 10, 100).await.expect("purge");
    purged.sort();
    assert_eq!(purged, ["owed", "sent"]);
    assert!(db.job_deliveries("sent").await.expect("list").is_empty());
    let owed = db.job_deliveries("owed").await.expect("list");
    assert_eq!(owed.len(), 1, "a pending delivery is still owed");
    assert_eq!(owed[0].state, DeliveryState::Pending);
}
on_both_backends!(retention_forgets_finished_deliveries_and_keeps_pending_ones);
