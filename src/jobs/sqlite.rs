//! The job queue and upload records on SQLite (WAL, busy timeout, `BEGIN IMMEDIATE` for
//! every transaction that reads before it writes, so concurrent API writes and claims wait
//! for each other instead of failing with "database is locked").
//!
//! This is the default backend: one file under the data directory, nothing else to run. The
//! queries are written once for both databases in `src/jobs/queries.rs` and included here
//! below the few pieces SQLite spells its own way.

use std::path::Path;
use std::time::Duration;

use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePoolOptions, SqliteSynchronous};
use sqlx::{Row, Sqlite, Transaction};

use super::store::SqlStore;
use super::*;
use crate::stage::{OutputFile, Stage};

/// How long a connection waits for another writer before giving up (SQLite busy_timeout).
const BUSY_TIMEOUT: Duration = Duration::from_secs(30);

/// The job queue, upload records and job log in one SQLite file.
pub type SqliteJobs = SqlStore<Sqlite>;

type Db = Sqlite;

impl SqliteJobs {
    /// Opens (creating if needed) the database file and applies migrations.
    pub async fn open(path: &Path, max_connections: u32) -> Result<Self, DbError> {
        let options = SqliteConnectOptions::new()
            .filename(path)
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            .synchronous(SqliteSynchronous::Normal)
            .busy_timeout(BUSY_TIMEOUT)
            .foreign_keys(true);
        let pool = SqlitePoolOptions::new()
            .max_connections(max_connections.max(2))
            .acquire_timeout(BUSY_TIMEOUT)
            // A COMMIT that failed (SQLITE_FULL on a full disk) leaves its connection inside
            // the transaction; such a connection is closed (SQLite rolls back) and replaced
            // instead of failing every later `BEGIN` that draws it from the pool.
            .before_acquire(|conn, _| {
                let clean = !sqlx::Connection::is_in_transaction(conn);
                Box::pin(async move { Ok(clean) })
            })
            .connect_with(options)
            .await?;
        sqlx::migrate!("./migrations/sqlite").run(&pool).await?;
        Ok(Self { pool })
    }

    async fn begin(&self) -> Result<Transaction<'static, Sqlite>, DbError> {
        Ok(self.pool.begin_with("BEGIN IMMEDIATE").await?)
    }

    /// A trivial query: is the database answering?
    pub async fn ping(&self) -> Result<(), DbError> {
        sqlx::query("SELECT 1").execute(&self.pool).await?;
        Ok(())
    }

    /// `PRAGMA integrity_check` result ("ok" when healthy).
    pub async fn integrity_check(&self) -> Result<String, DbError> {
        let row = sqlx::query("PRAGMA integrity_check")
            .fetch_one(&self.pool)
            .await?;
        Ok(row.try_get(0)?)
    }

    /// This process's clock: SQLite serves one machine, whose processes share it.
    async fn clock<'c, E>(_conn: E) -> Result<i64, DbError>
    where
        E: sqlx::SqliteExecutor<'c>,
    {
        Ok(now_ms())
    }

    /// Nothing to do: `BEGIN IMMEDIATE` already makes job creation the only writer.
    async fn lock_creation(_tx: &mut Transaction<'static, Sqlite>) -> Result<(), DbError> {
        Ok(())
    }

    /// Nothing to announce: SQLite's workers live on this machine and poll.
    async fn notify(_tx: &mut Transaction<'static, Sqlite>, _job_id: &str) -> Result<(), DbError> {
        Ok(())
    }

    /// Ids bound to one parameter, as a JSON array read back with `json_each`.
    fn id_list<S: AsRef<str>>(ids: impl IntoIterator<Item = S>) -> String {
        let v: Vec<String> = ids.into_iter().map(|s| s.as_ref().to_string()).collect();
        serde_json::Value::from(v).to_string()
    }
}

/// This database's column of [`dialect!`].
macro_rules! sql {
    ($($t:tt)*) => { dialect!(sqlite $($t)*) };
}

include!("queries.rs");
