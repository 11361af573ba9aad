//! [`JobStore`]: the one queue type the API and the workers hold, over SQLite or PostgreSQL.
//!
//! An enum rather than a trait object: there are exactly two backends, both known here, and
//! an enum keeps the methods `async fn` without boxing every future. Each public method of
//! the backends is forwarded by the `forward!` macro below, so the two can only drift apart
//! by failing to compile.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::Notify;

use super::postgres::PgJobs;
use super::sqlite::SqliteJobs;
use super::*;
use crate::stage::{OutputFile, Stage};

/// Where the job database lives, as given by `--database` (or its default).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Database {
    /// An SQLite file (created if missing).
    Sqlite(PathBuf),
    /// A PostgreSQL connection URL (`postgres://` or `postgresql://`).
    Postgres(String),
}

impl Database {
    /// Reads a `--database` value: `postgres://...` or `postgresql://...` for PostgreSQL;
    /// `sqlite://PATH`, `sqlite:PATH` or a plain file path for SQLite.
    pub fn parse(text: &str) -> Result<Self, DbError> {
        let text = text.trim();
        if text.starts_with("postgres://") || text.starts_with("postgresql://") {
            return Ok(Database::Postgres(text.to_string()));
        }
        let path = text
            .strip_prefix("sqlite://")
            .or_else(|| text.strip_prefix("sqlite:"))
            .unwrap_or(text);
        if let Some((scheme, _)) = path.split_once("://") {
            return Err(DbError::Invalid(format!(
                "--database: `{scheme}://` is not a database Sylva knows; give a postgres:// URL \
                 or an SQLite file path"
            )));
        }
        if path.is_empty() {
            return Err(DbError::Invalid(
                "--database: the SQLite file path is empty".into(),
            ));
        }
        Ok(Database::Sqlite(PathBuf::from(path)))
    }

    /// The location with any password replaced by `***`, for messages and logs.
    pub fn redacted(&self) -> String {
        match self {
            Database::Sqlite(path) => path.display().to_string(),
            Database::Postgres(url) => redact_password(url),
        }
    }
}

impl std::fmt::Display for Database {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.redacted())
    }
}

/// `scheme://user:secret@host/db` → `scheme://user:***@host/db`; other URLs unchanged.
fn redact_password(url: &str) -> String {
    let Some((scheme, rest)) = url.split_once("://") else {
        return url.to_string();
    };
    let authority_end = rest.find(['/', '?']).unwrap_or(rest.len());
    let (authority, tail) = rest.split_at(authority_end);
    match authority.rsplit_once('@') {
        Some((userinfo, host)) => match userinfo.split_once(':') {
            Some((user, _password)) => format!("{scheme}://{user}:***@{host}{tail}"),
            None => url.to_string(),
        },
        None => url.to_string(),
    }
}

/// One database's store: its connection pool. The methods are `src/jobs/queries.rs`, included
/// once per database by `sqlite.rs` ([`SqliteJobs`]) and `postgres.rs` ([`PgJobs`]) beside the
/// few pieces each spells its own way.
pub struct SqlStore<DB: sqlx::Database> {
    pub(super) pool: sqlx::Pool<DB>,
}

// By hand: a derive would ask `DB: Clone`, which the database marker types are not.
impl<DB: sqlx::Database> Clone for SqlStore<DB> {
    fn clone(&self) -> Self {
        Self {
            pool: self.pool.clone(),
        }
    }
}

#[derive(Clone)]
enum Backend {
    Sqlite(SqliteJobs),
    Postgres(PgJobs),
}

/// The job queue, upload records and job log, on whichever database `--database` chose.
/// Cheap to clone (a connection pool inside).
#[derive(Clone)]
pub struct JobStore {
    backend: Backend,
}

impl JobStore {
    /// Opens the database (creating an SQLite file if needed, connecting to PostgreSQL) and
    /// applies its migrations.
    pub async fn open(db: &Database, max_connections: u32) -> Result<Self, DbError> {
        let backend = match db {
            Database::Sqlite(path) => {
                Backend::Sqlite(SqliteJobs::open(path, max_connections).await?)
            }
            Database::Postgres(url) => Backend::Postgres(PgJobs::open(url, max_connections).await?),
        };
        Ok(Self { backend })
    }

    /// Opens an SQLite file (the single-machine default).
    pub async fn open_sqlite(path: &Path, max_connections: u32) -> Result<Self, DbError> {
        Self::open(&Database::Sqlite(path.to_path_buf()), max_connections).await
    }

    /// "sqlite" or "postgres".
    pub fn backend_name(&self) -> &'static str {
        match &self.backend {
            Backend::Sqlite(_) => "sqlite",
            Backend::Postgres(_) => "postgres",
        }
    }

    /// Tells idle workers in every process that `job_id` can be claimed (PostgreSQL's
    /// NOTIFY). Nothing to do on SQLite: its workers share the caller's process (woken
    /// through its `Notify`) or poll.
    pub async fn announce(&self, job_id: &str) -> Result<(), DbError> {
        match &self.backend {
            Backend::Sqlite(_) => Ok(()),
            Backend::Postgres(pg) => pg.announce(job_id).await,
        }
    }

    /// Wakes `wake`'s waiters whenever any process queues a job, where the database can say
    /// so (PostgreSQL's LISTEN/NOTIFY); the returned task runs until aborted or the database
    /// closes. SQLite has no such channel: `None`, and workers rely on their poll and on
    /// wake-ups from the API in the same process.
    pub fn listen_for_work(&self, wake: Arc<Notify>) -> Option<tokio::task::JoinHandle<()>> {
        match &self.backend {
            Backend::Sqlite(_) => None,
            Backend::Postgres(pg) => Some(pg.listen_for_work(wake)),
        }
    }
}

/// Forwards each listed method to the backend in use, with the same signature and docs.
macro_rules! forward {
    ($(
        $(#[$meta:meta])*
        pub async fn $name:ident(&self $(, $arg:ident: $ty:ty)* $(,)?) -> $ret:ty;
    )*) => {
        impl JobStore {
            $(
                $(#[$meta])*
                pub async fn $name(&self $(, $arg: $ty)*) -> $ret {
                    match &self.backend {
                        Backend::Sqlite(db) => db.$name($($arg),*).await,
                        Backend::Postgres(db) => db.$name($($arg),*).await,
                    }
                }
            )*
        }
    };
}

forward! {
    /// A trivial query: is the database answering?
    pub async fn ping(&self) -> Result<(), DbError>;

    /// A consistency check, "ok" when healthy: SQLite's `PRAGMA integrity_check`; on
    /// PostgreSQL (which checks its own storage), the queue's lease invariant.
    pub async fn integrity_check(&self) -> Result<String, DbError>;

    /// Records a new upload (no parts yet).
    pub async fn create_upload(&self, u: &UploadRecord) -> Result<(), DbError>;

    /// An upload with the parts received so far.
    pub async fn get_upload(&self, id: &str) -> Result<Option<UploadRecord>, DbError>;

    /// Records a received part (replacing an earlier copy); refused once the upload is complete.
    pub async fn put_part(&self, id: &str, n: i64, size: i64, sha256: &str) -> Result<(), DbError>;

    /// Marks an upload complete with its verified checksum and what inspection found.
    pub async fn complete_upload(
        &self,
        id: &str,
        sha256: &str,
        inspection: &serde_json::Value,
    ) -> Result<(), DbError>;

    /// Creates a job with its stage rows. With an idempotency key seen before, returns the
    /// earlier job if the request was the same, and a conflict otherwise; `QueueFull` when
    /// `limits.max_queued` jobs already wait, `JobQuota` when the owner has its quota of
    /// unfinished jobs.
    pub async fn create_job(&self, job: &NewJob<'_>, limits: Admission) -> Result<Created, DbError>;

    /// A job with its stages and artifacts.
    pub async fn get_job(&self, id: &str) -> Result<Option<JobRecord>, DbError>;

    /// Which of `ids` still own files: uploads not expired, or jobs not purged.
    pub async fn live_ids(&self, table: LiveTable, ids: &[String]) -> Result<Vec<String>, DbError>;

    /// Jobs newest first, `owner`'s only unless `None`; `before_seq` is the cursor (the last
    /// seq of the previous page).
    pub async fn list_jobs(
        &self,
        owner: Option<&str>,
        state: Option<JobState>,
        before_seq: Option<i64>,
        limit: i64,
    ) -> Result<Vec<JobRecord>, DbError>;

    /// A job's artifacts in stage order.
    pub async fn artifacts(&self, job_id: &str) -> Result<Vec<ArtifactRecord>, DbError>;

    /// Appends a line to a job's log.
    pub async fn append_log(
        &self,
        job_id: &str,
        level: &str,
        stage: Option<&str>,
        message: &str,
    ) -> Result<(), DbError>;

    /// Log lines after sequence number `since`, at most `limit`.
    pub async fn log(&self, job_id: &str, since: i64, limit: i64) -> Result<Vec<LogLine>, DbError>;

    /// Cancels a job: a queued one at once, a running one by asking its worker (canceling).
    pub async fn cancel(&self, id: &str) -> Result<JobState, DbError>;

    /// Queues a finished job again from `from` (or its first unfinished stage). Returns the
    /// stages that were reset, whose output folders the caller removes.
    pub async fn retry(&self, id: &str, from: Option<Stage>) -> Result<Vec<String>, DbError>;

    /// Deletes a finished job's rows (its files are the caller's to remove).
    pub async fn delete_job(&self, id: &str) -> Result<(), DbError>;

    /// Claims the oldest claimable job (queued, or running with an expired lease) with a
    /// fresh lease and fencing token; fails jobs whose workers died `max_attempts` times.
    pub async fn claim(
        &self,
        worker_id: &str,
        lease: Duration,
        max_attempts: i64,
    ) -> Result<Option<Claim>, DbError>;

    /// Renews the lease and records progress (never lower than before).
    pub async fn heartbeat(
        &self,
        job_id: &str,
        token: &str,
        lease: Duration,
        progress: f64,
        stage: Option<(&str, f64)>,
    ) -> Result<Heartbeat, DbError>;

    /// Marks a stage running; `Fenced` if this run lost the job.
    pub async fn start_stage(
        &self,
        job_id: &str,
        token: &str,
        stage: Stage,
        attempt: i64,
    ) -> Result<(), DbError>;

    /// The checkpoint: a finished stage with its report and files, written only while this
    /// run still holds the lease.
    pub async fn finish_stage(
        &self,
        job_id: &str,
        token: &str,
        stage: Stage,
        metrics: &serde_json::Value,
        files: &[OutputFile],
        job_progress: f64,
    ) -> Result<(), DbError>;

    /// Ends a run: succeeded, failed (with a problem object) or canceled.
    pub async fn finish_job(&self, job_id: &str, token: &str, end: &RunEnd) -> Result<(), DbError>;

    /// Records (or refreshes) a live worker slot.
    pub async fn register_worker(&self, id: &str, host: &str, pid: u32) -> Result<(), DbError>;

    /// Forgets a worker slot that stopped cleanly.
    pub async fn unregister_worker(&self, id: &str) -> Result<(), DbError>;

    /// Start-up recovery: forgets workers silent for longer than `stale`, and expires at once
    /// the leases of jobs held by dead worker processes of this host. Returns how many.
    pub async fn recover(&self, host: &str, stale: Duration) -> Result<u64, DbError>;

    /// Workers seen within `window`.
    pub async fn live_workers(&self, window: Duration) -> Result<i64, DbError>;

    /// Number of jobs in each state.
    pub async fn count_by_state(&self) -> Result<Vec<(JobState, i64)>, DbError>;

    /// Durations in seconds of finished stages, per stage name.
    pub async fn stage_durations(&self) -> Result<Vec<(String, f64)>, DbError>;

    /// Bytes an owner keeps on the server (its live uploads and its jobs' artifacts).
    pub async fn stored_bytes(&self, owner: &str) -> Result<i64, DbError>;

    /// Expires open uploads past `expires_at` and complete ones, finished before
    /// `unused_before`, that no job with files reads; returns their ids.
    pub async fn expire_uploads(
        &self,
        now: i64,
        unused_before: i64,
        limit: i64,
    ) -> Result<Vec<String>, DbError>;

    /// Marks finished jobs that ended before `finished_before` as purged and forgets their
    /// artifacts; returns their ids.
    pub async fn purge_jobs(&self, finished_before: i64, limit: i64) -> Result<Vec<String>, DbError>;

    /// Claims up to `limit` due webhook deliveries for `lease`, counting the attempt; only
    /// the token they carry may record their outcome.
    pub async fn claim_deliveries(&self, lease: Duration, limit: i64) -> Result<Vec<Delivery>, DbError>;

    /// Records how a delivery attempt went; `false` when the claim's lease was lost.
    pub async fn finish_delivery(
        &self,
        id: &str,
        token: &str,
        outcome: &DeliveryOutcome,
    ) -> Result<bool, DbError>;

    /// A job's webhook deliveries, oldest first.
    pub async fn job_deliveries(&self, job_id: &str) -> Result<Vec<DeliveryRecord>, DbError>;

    /// Webhook deliveries in each state (states with none are left out).
    pub async fn count_deliveries(&self) -> Result<Vec<(DeliveryState, i64)>, DbError>;

    /// A server-wide setting: the stored value, or `value` stored now if there was none.
    pub async fn setting_or_insert(&self, name: &str, value: &str) -> Result<String, DbError>;

    /// Stores a new managed API key; a name already used is a conflict.
    pub async fn create_api_key(&self, k: &keys::ApiKey) -> Result<(), DbError>;

    /// Every managed API key, oldest first (revoked ones included).
    pub async fn api_keys(&self) -> Result<Vec<keys::ApiKey>, DbError>;

    /// The managed key whose SHA-256 is `hash`, usable or not.
    pub async fn api_key_by_hash(&self, hash: &str) -> Result<Option<keys::ApiKey>, DbError>;

    /// Revokes the key `id` at `now` (Unix ms); `NotFound` when none.
    pub async fn revoke_api_key(&self, id: &str, now: i64) -> Result<keys::ApiKey, DbError>;

    /// The webhook secret generation of `owner`.
    pub async fn secret_generation(&self, owner: &str) -> Result<keys::SecretGeneration, DbError>;

    /// Moves `owner` to its next webhook secret, the previous one used for `grace_ms` more.
    pub async fn rotate_secret(
        &self,
        owner: &str,
        now: i64,
        grace_ms: i64,
    ) -> Result<keys::SecretGeneration, DbError>;
}
