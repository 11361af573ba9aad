//! The job queue and upload records on PostgreSQL, for many API replicas and workers on
//! many machines (`--database postgres://...`).
//!
//! The queries are SQLite's, written once in `src/jobs/queries.rs` and included here; what
//! this file adds is how concurrent transactions are kept apart. SQLite runs one writer at a time, so a
//! read followed by a write is atomic. PostgreSQL runs many at once under READ COMMITTED,
//! so every transaction that reads before it writes locks what it read:
//! - a claim picks its job with `FOR UPDATE SKIP LOCKED`: concurrent workers take different
//!   jobs and never wait for each other;
//! - a fenced write (`start_stage`, `finish_stage`, `finish_job`) locks the job row while it
//!   checks the lease token, so a claim cannot slip in between the check and the write;
//! - cancel, retry, delete and part uploads lock the row whose state they check;
//! - job creation takes a transaction-scoped advisory lock, so the queue-depth limit and the
//!   Idempotency-Key check see every job created before them.
//!
//! Leases are measured on the database server's clock, not the worker's: workers on several
//! machines then agree on when a lease runs out even if their own clocks drift apart.
//!
//! New and re-queued jobs are announced with `pg_notify` on [`QUEUE_CHANNEL`] (see
//! [`PgJobs::announce`]); idle workers listen on it (see [`PgJobs::listen_for_work`]) and
//! still poll, so a lost notification only delays a claim by one poll interval.

use std::sync::Arc;
use std::time::Duration;

use sqlx::postgres::{PgConnectOptions, PgConnection, PgListener, PgPool, PgPoolOptions};
use sqlx::{Connection, Postgres, Row, Transaction};
use tokio::sync::Notify;

use super::store::SqlStore;
use super::*;
use crate::stage::{OutputFile, Stage};

/// The channel `pg_notify` announces claimable jobs on. The payload (the job id, or the
/// dead worker whose jobs became claimable) is for people watching; workers just claim.
pub const QUEUE_CHANNEL: &str = "sylva_jobs";

/// How long a request waits for a free connection from the pool.
const ACQUIRE_TIMEOUT: Duration = Duration::from_secs(30);

/// Key of the advisory lock that serialises job creation (the queue-depth check and the
/// Idempotency-Key lookup); "SYLVJOBS" in ASCII.
const CREATE_LOCK: i64 = 0x5359_4c56_4a4f_4253;

/// Pause before a lost notification listener connects again.
const LISTEN_RETRY: Duration = Duration::from_secs(2);

/// The job queue, upload records and job log in a PostgreSQL database.
pub type PgJobs = SqlStore<Postgres>;

type Db = Postgres;

impl PgJobs {
    /// Connects to the database at `url` (`postgres://user:password@host:port/database`) and
    /// applies migrations; concurrent processes wait for each other's migrations (sqlx holds
    /// an advisory lock while it migrates).
    pub async fn open(url: &str, max_connections: u32) -> Result<Self, DbError> {
        let options: PgConnectOptions = url.parse()?;
        // One direct connection first: an unreachable server or a refused login then reports
        // its own error at once, not a pool timeout after ACQUIRE_TIMEOUT.
        PgConnection::connect_with(&options).await?.close().await?;
        let pool = PgPoolOptions::new()
            .max_connections(max_connections.max(2))
            .acquire_timeout(ACQUIRE_TIMEOUT)
            .connect_with(options)
            .await?;
        sqlx::migrate!("./migrations/postgres").run(&pool).await?;
        Ok(Self { pool })
    }

    /// A trivial query: is the database answering?
    pub async fn ping(&self) -> Result<(), DbError> {
        sqlx::query("SELECT 1").execute(&self.pool).await?;
        Ok(())
    }

    /// PostgreSQL checks its own storage, so this checks the queue's invariant instead: a job
    /// holds a lease exactly while it is running or canceling. "ok" when it holds, else what
    /// is wrong.
    pub async fn integrity_check(&self) -> Result<String, DbError> {
        let bad: i64 = sqlx::query_scalar(
            "SELECT COUNT(*) FROM jobs \
             WHERE (state IN ('running', 'canceling')) <> (lease_token IS NOT NULL AND lease_until IS NOT NULL)",
        )
        .fetch_one(&self.pool)
        .await?;
        Ok(if bad == 0 {
            "ok".to_string()
        } else {
            format!("{bad} job(s) hold a lease in a state that has none, or lack one while running")
        })
    }

    /// Forwards queue notifications to `wake` until the pool closes: every job inserted or
    /// re-queued by any process wakes this process's idle workers (their poll remains the
    /// fallback). Reconnects after a lost connection.
    pub fn listen_for_work(&self, wake: Arc<Notify>) -> tokio::task::JoinHandle<()> {
        let pool = self.pool.clone();
        tokio::spawn(async move {
            while !pool.is_closed() {
                match Self::forward_notifications(&pool, &wake).await {
                    Ok(()) => return,
                    Err(e) if pool.is_closed() => {
                        tracing::debug!(error = %e, "queue listener stopped");
                        return;
                    }
                    Err(e) => {
                        tracing::warn!(error = %e, "queue listener lost; polling until it is back");
                    }
                }
                tokio::time::sleep(LISTEN_RETRY).await;
            }
        })
    }

    async fn forward_notifications(pool: &PgPool, wake: &Notify) -> Result<(), sqlx::Error> {
        let mut listener = PgListener::connect_with(pool).await?;
        listener.listen(QUEUE_CHANNEL).await?;
        loop {
            // `recv` reconnects (and listens again) by itself after a dropped connection.
            listener.recv().await?;
            wake.notify_waiters();
        }
    }

    /// The database server's clock in milliseconds since the Unix epoch: the one clock every
    /// process compares leases and worker liveness against.
    async fn clock<'c, E>(conn: E) -> Result<i64, DbError>
    where
        E: sqlx::PgExecutor<'c>,
    {
        Ok(
            sqlx::query_scalar("SELECT (EXTRACT(EPOCH FROM clock_timestamp()) * 1000)::bigint")
                .fetch_one(conn)
                .await?,
        )
    }

    /// Tells the idle workers of every process that `job_id` can be claimed. The API calls
    /// this once a new or retried job is ready to run (after it has answered with the job's
    /// state and removed the folders of reset stages), not inside the transaction that
    /// queued it.
    pub async fn announce(&self, job_id: &str) -> Result<(), DbError> {
        sqlx::query("SELECT pg_notify($1, $2)")
            .bind(QUEUE_CHANNEL)
            .bind(job_id)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// Announces claimable work to listening workers when `tx` commits.
    async fn notify(tx: &mut Transaction<'static, Postgres>, job_id: &str) -> Result<(), DbError> {
        sqlx::query("SELECT pg_notify($1, $2)")
            .bind(QUEUE_CHANNEL)
            .bind(job_id)
            .execute(&mut **tx)
            .await?;
        Ok(())
    }

    /// Serialises job creation for the rest of `tx` (the queue-depth check and the
    /// Idempotency-Key lookup then see every job created before).
    async fn lock_creation(tx: &mut Transaction<'static, Postgres>) -> Result<(), DbError> {
        sqlx::query("SELECT pg_advisory_xact_lock($1)")
            .bind(CREATE_LOCK)
            .execute(&mut **tx)
            .await?;
        Ok(())
    }

    /// A writing transaction (READ COMMITTED; the queries lock the rows they read).
    async fn begin(&self) -> Result<Transaction<'static, Postgres>, DbError> {
        Ok(self.pool.begin().await?)
    }

    /// Ids bound to one parameter, as a PostgreSQL text array (`= ANY($N)`).
    fn id_list<S: AsRef<str>>(ids: impl IntoIterator<Item = S>) -> Vec<String> {
        ids.into_iter().map(|s| s.as_ref().to_string()).collect()
    }
}

/// This database's column of [`dialect!`].
macro_rules! sql {
    ($($t:tt)*) => { dialect!(postgres $($t)*) };
}

include!("queries.rs");
