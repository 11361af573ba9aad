// The job store's queries, written once for both databases (issue 26). This file is not a
// module: `sqlite.rs` and `postgres.rs` each `include!` it after naming their types and the
// few SQL pieces the two databases spell differently:
//
// - `Db`: the backend's sqlx database (the store is then `SqlStore<Db>`);
// - `Store::begin`, `Store::clock`, `Store::lock_creation`, `Store::notify`, `Store::id_list`:
//   how a writing transaction starts, whose clock leases are measured on, how job creation is
//   serialised, how idle workers hear of new work, how a list of ids is bound to one parameter;
// - `sql!(…)`: the SQL pieces the two spell differently, in one table (`dialect!` in
//   `src/jobs/mod.rs`): row locks, "is one of the ids bound to `$N`", "job `j`'s inputs name
//   upload `u`".
//
// Everything else is SQL both databases speak: `$N` placeholders (sqlx binds SQLite's `$N` by
// number too), `CAST`, `CASE` for the greater or lesser of two values, `ON CONFLICT`,
// `RETURNING`. JSON documents bind and read as `serde_json::Value` (JSONB on PostgreSQL, text
// on SQLite). Run `rustfmt --edition 2024 src/jobs/queries.rs` after editing: `cargo fmt` does
// not reach an included file.

use super::keys::{ApiKey, KEY_COLUMNS, SecretGeneration};

type Store = SqlStore<Db>;
type DbRow = <Db as sqlx::Database>::Row;

fn parse_webhook(text: Option<String>) -> Result<Option<WebhookSpec>, DbError> {
    text.map(|t| serde_json::from_str(&t))
        .transpose()
        .map_err(|e| DbError::Invalid(format!("bad webhook: {e}")))
}

fn job_from_row(r: &DbRow) -> Result<JobRecord, DbError> {
    let state: String = r.try_get("state")?;
    let inputs: serde_json::Value = r.try_get("inputs")?;
    Ok(JobRecord {
        seq: r.try_get("seq")?,
        id: r.try_get("id")?,
        state: JobState::parse(&state)
            .ok_or_else(|| DbError::Invalid(format!("bad job state {state:?}")))?,
        stage: r.try_get("stage")?,
        progress: r.try_get("progress")?,
        attempt: r.try_get("attempt")?,
        inputs: serde_json::from_value(inputs)
            .map_err(|e| DbError::Invalid(format!("bad inputs: {e}")))?,
        params: r.try_get("params")?,
        error: r.try_get("error")?,
        created_at: r.try_get("created_at")?,
        updated_at: r.try_get("updated_at")?,
        started_at: r.try_get("started_at")?,
        finished_at: r.try_get("finished_at")?,
        owner: r.try_get("owner")?,
        purged_at: r.try_get("purged_at")?,
        webhook: parse_webhook(r.try_get("webhook")?)?,
        stages: Vec::new(),
        artifacts: Vec::new(),
    })
}

/// A log line whose sequence number was taken by a concurrent writer is retried this often
/// (PostgreSQL; SQLite's single writer never collides).
const LOG_INSERT_TRIES: usize = 16;

const JOB_COLUMNS: &str = "seq, id, state, stage, progress, attempt, inputs, params, error, \
                           created_at, updated_at, started_at, finished_at, owner, purged_at, webhook";

impl Store {
    // ---------------------------------------------------------------- uploads

    /// Records a new upload (no parts yet).
    pub async fn create_upload(&self, u: &UploadRecord) -> Result<(), DbError> {
        sqlx::query(
            "INSERT INTO uploads (id, kind, filename, size, sha256, part_size, state, created_at, expires_at, owner) \
             VALUES ($1, $2, $3, $4, $5, $6, 'open', $7, $8, $9)",
        )
        .bind(&u.id)
        .bind(u.kind.as_str())
        .bind(&u.filename)
        .bind(u.size)
        .bind(&u.sha256)
        .bind(u.part_size)
        .bind(u.created_at)
        .bind(u.expires_at)
        .bind(&u.owner)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    /// An upload with the parts received so far.
    pub async fn get_upload(&self, id: &str) -> Result<Option<UploadRecord>, DbError> {
        let Some(r) = sqlx::query("SELECT * FROM uploads WHERE id = $1")
            .bind(id)
            .fetch_optional(&self.pool)
            .await?
        else {
            return Ok(None);
        };
        let kind: String = r.try_get("kind")?;
        let state: String = r.try_get("state")?;
        let parts = sqlx::query("SELECT n, size FROM upload_parts WHERE upload_id = $1 ORDER BY n")
            .bind(id)
            .fetch_all(&self.pool)
            .await?
            .iter()
            .map(|p| Ok((p.try_get("n")?, p.try_get("size")?)))
            .collect::<Result<Vec<_>, sqlx::Error>>()?;
        Ok(Some(UploadRecord {
            id: r.try_get("id")?,
            kind: UploadKind::parse(&kind)
                .ok_or_else(|| DbError::Invalid(format!("bad upload kind {kind:?}")))?,
            filename: r.try_get("filename")?,
            size: r.try_get("size")?,
            sha256: r.try_get("sha256")?,
            part_size: r.try_get("part_size")?,
            complete: state == "complete",
            inspection: r.try_get("inspection")?,
            created_at: r.try_get("created_at")?,
            expires_at: r.try_get("expires_at")?,
            completed_at: r.try_get("completed_at")?,
            parts,
            owner: r.try_get("owner")?,
            expired: state == "expired",
        }))
    }

    /// Records a received part (replacing an earlier copy); refused once the upload is complete.
    pub async fn put_part(&self, id: &str, n: i64, size: i64, sha256: &str) -> Result<(), DbError> {
        let mut tx = self.begin().await?;
        let state: Option<String> = sqlx::query_scalar(concat!(
            "SELECT state FROM uploads WHERE id = $1",
            sql!(for_update)
        ))
        .bind(id)
        .fetch_optional(&mut *tx)
        .await?;
        match state.as_deref() {
            None => return Err(DbError::NotFound),
            Some("complete") => {
                return Err(DbError::Conflict("the upload is already complete".into()));
            }
            _ => {}
        }
        sqlx::query(
            "INSERT INTO upload_parts (upload_id, n, size, sha256) VALUES ($1, $2, $3, $4) \
             ON CONFLICT (upload_id, n) DO UPDATE SET size = excluded.size, sha256 = excluded.sha256",
        )
        .bind(id)
        .bind(n)
        .bind(size)
        .bind(sha256)
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(())
    }

    /// Marks an upload complete with its verified checksum and what inspection found.
    pub async fn complete_upload(
        &self,
        id: &str,
        sha256: &str,
        inspection: &serde_json::Value,
    ) -> Result<(), DbError> {
        sqlx::query(
            "UPDATE uploads SET state = 'complete', sha256 = $1, inspection = $2, completed_at = $3 \
             WHERE id = $4 AND state = 'open'",
        )
        .bind(sha256)
        .bind(inspection)
        .bind(now_ms())
        .bind(id)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    // ---------------------------------------------------------------- jobs

    /// Creates a job with its stage rows. With an idempotency key seen before, returns the
    /// earlier job if the request was the same, and a conflict otherwise.
    pub async fn create_job(
        &self,
        job: &NewJob<'_>,
        limits: Admission,
    ) -> Result<Created, DbError> {
        let mut tx = self.begin().await?;
        Self::lock_creation(&mut tx).await?;
        if let Some(key) = job.idempotency_key {
            let row = sqlx::query("SELECT id, request_hash FROM jobs WHERE idempotency_key = $1")
                .bind(key)
                .fetch_optional(&mut *tx)
                .await?;
            if let Some(row) = row {
                let hash: Option<String> = row.try_get("request_hash")?;
                return if hash.as_deref() == Some(job.request_hash) {
                    Ok(Created::Existing(row.try_get("id")?))
                } else {
                    Err(DbError::Invalid(
                        "this Idempotency-Key was already used with a different request".into(),
                    ))
                };
            }
        }
        let queued: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM jobs WHERE state = 'queued'")
            .fetch_one(&mut *tx)
            .await?;
        if queued >= limits.max_queued {
            return Err(DbError::QueueFull(queued));
        }
        if limits.max_active_per_owner > 0 {
            let active: i64 = sqlx::query_scalar(
                "SELECT COUNT(*) FROM jobs WHERE owner = $1 AND state IN ('queued', 'running', 'canceling')",
            )
            .bind(job.owner)
            .fetch_one(&mut *tx)
            .await?;
            if active >= limits.max_active_per_owner {
                return Err(DbError::JobQuota(active));
            }
        }
        for (kind, upload) in job.inputs.all() {
            let row = sqlx::query(concat!(
                "SELECT kind, state FROM uploads WHERE id = $1 AND owner = $2",
                sql!(for_share)
            ))
            .bind(upload)
            .bind(job.owner)
            .fetch_optional(&mut *tx)
            .await?;
            let Some(row) = row else {
                return Err(DbError::Invalid(format!(
                    "inputs.{}: upload {upload} does not exist",
                    kind.as_str()
                )));
            };
            let (k, s): (String, String) = (row.try_get("kind")?, row.try_get("state")?);
            check_input(kind, upload, &k, &s)?;
        }
        let now = now_ms();
        sqlx::query(
            "INSERT INTO jobs (id, state, progress, attempt, inputs, params, idempotency_key, request_hash, created_at, updated_at, owner, webhook) \
             VALUES ($1, 'queued', 0, 0, $2, $3, $4, $5, $6, $6, $7, $8)",
        )
        .bind(job.id)
        .bind(sqlx::types::Json(job.inputs))
        .bind(job.params)
        .bind(job.idempotency_key)
        .bind(job.request_hash)
        .bind(now)
        .bind(job.owner)
        .bind(job.webhook.map(|w| serde_json::to_string(w).unwrap_or_default()))
        .execute(&mut *tx)
        .await?;
        for s in job.stages {
            sqlx::query("INSERT INTO job_stages (job_id, idx, name) VALUES ($1, $2, $3)")
                .bind(job.id)
                .bind(s.index() as i64)
                .bind(s.name())
                .execute(&mut *tx)
                .await?;
        }
        tx.commit().await?;
        Ok(Created::New(job.id.to_string()))
    }

    async fn fill(&self, job: JobRecord) -> Result<JobRecord, DbError> {
        let mut jobs = self.fill_many(vec![job]).await?;
        jobs.pop()
            .ok_or_else(|| DbError::Invalid("a filled job went missing".into()))
    }

    /// Adds their stages and artifacts to `jobs` with two queries in all (a page of a listing
    /// costs three queries, not two per job).
    async fn fill_many(&self, mut jobs: Vec<JobRecord>) -> Result<Vec<JobRecord>, DbError> {
        if jobs.is_empty() {
            return Ok(jobs);
        }
        let ids: Vec<String> = jobs.iter().map(|j| j.id.clone()).collect();
        let stage_rows = sqlx::query(concat!(
            "SELECT * FROM job_stages WHERE job_id ",
            sql!(any_of "$1"),
            " ORDER BY job_id, idx"
        ))
        .bind(Self::id_list(&ids))
        .fetch_all(&self.pool)
        .await?;
        let artifact_rows = sqlx::query(concat!(
            "SELECT a.* FROM artifacts a JOIN job_stages s ON s.job_id = a.job_id AND s.name = a.stage \
             WHERE a.job_id ",
            sql!(any_of "$1"),
            " ORDER BY a.job_id, s.idx, a.name"
        ))
        .bind(Self::id_list(&ids))
        .fetch_all(&self.pool)
        .await?;
        let mut stages: std::collections::HashMap<String, Vec<StageRecord>> = Default::default();
        for r in &stage_rows {
            let state: String = r.try_get("state")?;
            let job_id: String = r.try_get("job_id")?;
            stages.entry(job_id).or_default().push(StageRecord {
                name: r.try_get("name")?,
                state: StageState::parse(&state).unwrap_or(StageState::Pending),
                progress: r.try_get("progress")?,
                attempt: r.try_get("attempt")?,
                started_at: r.try_get("started_at")?,
                finished_at: r.try_get("finished_at")?,
                metrics: r.try_get("metrics")?,
            });
        }
        let mut artifacts: std::collections::HashMap<String, Vec<ArtifactRecord>> =
            Default::default();
        for r in &artifact_rows {
            let job_id: String = r.try_get("job_id")?;
            artifacts
                .entry(job_id)
                .or_default()
                .push(artifact_from_row(r)?);
        }
        for j in &mut jobs {
            j.stages = stages.remove(&j.id).unwrap_or_default();
            j.artifacts = artifacts.remove(&j.id).unwrap_or_default();
        }
        Ok(jobs)
    }

    /// A job with its stages and artifacts.
    pub async fn get_job(&self, id: &str) -> Result<Option<JobRecord>, DbError> {
        let sql = format!("SELECT {JOB_COLUMNS} FROM jobs WHERE id = $1");
        let row = sqlx::query(sqlx::AssertSqlSafe(sql))
            .bind(id)
            .fetch_optional(&self.pool)
            .await?;
        match row {
            Some(r) => Ok(Some(self.fill(job_from_row(&r)?).await?)),
            None => Ok(None),
        }
    }

    /// Jobs newest first; `before_seq` is the cursor (the last seq of the previous page).
    pub async fn list_jobs(
        &self,
        owner: Option<&str>,
        state: Option<JobState>,
        before_seq: Option<i64>,
        limit: i64,
    ) -> Result<Vec<JobRecord>, DbError> {
        let sql = format!(
            "SELECT {JOB_COLUMNS} FROM jobs WHERE (CAST($1 AS TEXT) IS NULL OR state = $1) \
             AND (CAST($2 AS BIGINT) IS NULL OR seq < $2) AND (CAST($4 AS TEXT) IS NULL OR owner = $4) \
             ORDER BY seq DESC LIMIT $3"
        );
        let rows = sqlx::query(sqlx::AssertSqlSafe(sql))
            .bind(state.map(|s| s.as_str()))
            .bind(before_seq)
            .bind(limit)
            .bind(owner)
            .fetch_all(&self.pool)
            .await?;
        let jobs = rows
            .iter()
            .map(job_from_row)
            .collect::<Result<Vec<_>, _>>()?;
        self.fill_many(jobs).await
    }

    /// A job's artifacts in stage order.
    pub async fn artifacts(&self, job_id: &str) -> Result<Vec<ArtifactRecord>, DbError> {
        let rows = sqlx::query(
            "SELECT a.* FROM artifacts a JOIN job_stages s ON s.job_id = a.job_id AND s.name = a.stage \
             WHERE a.job_id = $1 ORDER BY s.idx, a.name",
        )
        .bind(job_id)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(artifact_from_row)
            .collect::<Result<_, sqlx::Error>>()
            .map_err(DbError::from)
    }

    /// Appends a line with the next sequence number of the job's log. Two writers that pick
    /// the same number at once (the worker's stage thread and its heartbeat) do not fail: the
    /// second finds the number taken and takes the next.
    pub async fn append_log(
        &self,
        job_id: &str,
        level: &str,
        stage: Option<&str>,
        message: &str,
    ) -> Result<(), DbError> {
        for _ in 0..LOG_INSERT_TRIES {
            let res = sqlx::query(
                "INSERT INTO job_log (job_id, seq, ts, level, stage, message) \
                 SELECT $1, COALESCE(MAX(seq), 0) + 1, $2, $3, $4, $5 FROM job_log WHERE job_id = $1 \
                 ON CONFLICT (job_id, seq) DO NOTHING",
            )
            .bind(job_id)
            .bind(now_ms())
            .bind(level)
            .bind(stage)
            .bind(message)
            .execute(&self.pool)
            .await?;
            if res.rows_affected() == 1 {
                return Ok(());
            }
        }
        Err(DbError::Conflict(format!(
            "job {job_id}: no free log sequence number after {LOG_INSERT_TRIES} tries"
        )))
    }

    /// Log lines after sequence number `since`, at most `limit`.
    pub async fn log(&self, job_id: &str, since: i64, limit: i64) -> Result<Vec<LogLine>, DbError> {
        let rows = sqlx::query(
            "SELECT seq, ts, level, stage, message FROM job_log WHERE job_id = $1 AND seq > $2 ORDER BY seq LIMIT $3",
        )
        .bind(job_id)
        .bind(since)
        .bind(limit)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| {
                Ok(LogLine {
                    seq: r.try_get("seq")?,
                    ts: r.try_get("ts")?,
                    level: r.try_get("level")?,
                    stage: r.try_get("stage")?,
                    message: r.try_get("message")?,
                })
            })
            .collect::<Result<_, sqlx::Error>>()
            .map_err(DbError::from)
    }

    /// The state of a job, locking its row until `tx` ends; `NotFound` without one.
    async fn lock_job(tx: &mut Transaction<'static, Db>, id: &str) -> Result<JobState, DbError> {
        let state: Option<String> = sqlx::query_scalar(concat!(
            "SELECT state FROM jobs WHERE id = $1",
            sql!(for_update)
        ))
        .bind(id)
        .fetch_optional(&mut **tx)
        .await?;
        state
            .and_then(|s| JobState::parse(&s))
            .ok_or(DbError::NotFound)
    }

    /// Cancels a job: a queued one at once, a running one by asking its worker (canceling).
    pub async fn cancel(&self, id: &str) -> Result<JobState, DbError> {
        let mut tx = self.begin().await?;
        let state = Self::lock_job(&mut tx, id).await?;
        let now = now_ms();
        let next = match state {
            JobState::Queued => {
                sqlx::query(
                    "UPDATE jobs SET state = 'canceled', finished_at = $1, updated_at = $1 WHERE id = $2",
                )
                .bind(now)
                .bind(id)
                .execute(&mut *tx)
                .await?;
                Self::record_end(&mut tx, id, now).await?;
                JobState::Canceled
            }
            JobState::Running => {
                sqlx::query("UPDATE jobs SET state = 'canceling', updated_at = $1 WHERE id = $2")
                    .bind(now)
                    .bind(id)
                    .execute(&mut *tx)
                    .await?;
                JobState::Canceling
            }
            JobState::Canceling => JobState::Canceling,
            s => {
                return Err(DbError::Conflict(format!(
                    "the job is already {}; nothing to cancel",
                    s.as_str()
                )));
            }
        };
        tx.commit().await?;
        Ok(next)
    }

    /// Queues a finished job again from `from` (or its first unfinished stage). Returns the
    /// stages that were reset, whose output folders the caller removes.
    pub async fn retry(&self, id: &str, from: Option<Stage>) -> Result<Vec<String>, DbError> {
        let mut tx = self.begin().await?;
        let state = Self::lock_job(&mut tx, id).await?;
        if !state.is_terminal() {
            return Err(DbError::Conflict(format!(
                "the job is {}; only a failed, canceled or succeeded job can be retried",
                state.as_str()
            )));
        }
        let stages =
            sqlx::query("SELECT name, idx, state FROM job_stages WHERE job_id = $1 ORDER BY idx")
                .bind(id)
                .fetch_all(&mut *tx)
                .await?
                .iter()
                .map(|r| Ok((r.try_get("name")?, r.try_get("idx")?, r.try_get("state")?)))
                .collect::<Result<Vec<(String, i64, String)>, sqlx::Error>>()?;
        let RetryPlan {
            from_idx,
            reset,
            done_weight,
        } = RetryPlan::new(&stages, from)?;
        sqlx::query(
            "UPDATE job_stages SET state = 'pending', progress = 0, started_at = NULL, finished_at = NULL, metrics = NULL \
             WHERE job_id = $1 AND idx >= $2",
        )
        .bind(id)
        .bind(from_idx)
        .execute(&mut *tx)
        .await?;
        sqlx::query(
            "DELETE FROM artifacts WHERE job_id = $1 AND stage IN (SELECT name FROM job_stages WHERE job_id = $1 AND idx >= $2)",
        )
        .bind(id)
        .bind(from_idx)
        .execute(&mut *tx)
        .await?;
        sqlx::query(
            "UPDATE jobs SET state = 'queued', stage = NULL, progress = $1, attempt = 0, error = NULL, worker_id = NULL, \
             lease_until = NULL, lease_token = NULL, finished_at = NULL, updated_at = $2 WHERE id = $3",
        )
        .bind(done_weight)
        .bind(now_ms())
        .bind(id)
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(reset)
    }

    /// Deletes a finished job's rows (its files are the caller's to remove).
    pub async fn delete_job(&self, id: &str) -> Result<(), DbError> {
        let mut tx = self.begin().await?;
        let state = Self::lock_job(&mut tx, id).await?;
        if !state.is_terminal() {
            return Err(DbError::Conflict(format!(
                "the job is {}; cancel it before deleting it",
                state.as_str()
            )));
        }
        sqlx::query("DELETE FROM jobs WHERE id = $1")
            .bind(id)
            .execute(&mut *tx)
            .await?;
        // Its pending notifications still go out; the record of past ones goes with it.
        sqlx::query("DELETE FROM webhook_deliveries WHERE job_id = $1 AND state != 'pending'")
            .bind(id)
            .execute(&mut *tx)
            .await?;
        tx.commit().await?;
        Ok(())
    }

    // ---------------------------------------------------------------- retention and quotas

    /// Bytes an owner keeps on the server: its open and complete uploads (declared sizes) and
    /// the artifacts of its jobs whose files retention has not removed.
    pub async fn stored_bytes(&self, owner: &str) -> Result<i64, DbError> {
        Ok(sqlx::query_scalar(
            "SELECT CAST(COALESCE((SELECT SUM(size) FROM uploads WHERE owner = $1 AND state IN ('open', 'complete')), 0) AS BIGINT) \
                  + CAST(COALESCE((SELECT SUM(a.size) FROM artifacts a JOIN jobs j ON j.id = a.job_id WHERE j.owner = $1), 0) AS BIGINT)",
        )
        .bind(owner)
        .fetch_one(&self.pool)
        .await?)
    }

    /// Marks as expired (at most `limit`) the open uploads whose `expires_at` is before `now`
    /// and the complete ones finished before `unused_before` that no job with files still
    /// reads; their parts' rows go. Returns their ids, whose files the caller removes.
    pub async fn expire_uploads(
        &self,
        now: i64,
        unused_before: i64,
        limit: i64,
    ) -> Result<Vec<String>, DbError> {
        let mut tx = self.begin().await?;
        let ids: Vec<String> = sqlx::query_scalar(concat!(
            "SELECT id FROM uploads u WHERE (state = 'open' AND expires_at < $1) \
             OR (state = 'complete' AND completed_at < $2 AND NOT EXISTS \
                 (SELECT 1 FROM jobs j WHERE j.purged_at IS NULL AND ",
            sql!(inputs_mention),
            ")) ORDER BY created_at LIMIT $3",
            sql!(skip_locked)
        ))
        .bind(now)
        .bind(unused_before)
        .bind(limit)
        .fetch_all(&mut *tx)
        .await?;
        // One statement per table for the whole batch.
        let list = Self::id_list(&ids);
        sqlx::query(concat!(
            "UPDATE uploads SET state = 'expired', \
             expires_at = CASE WHEN expires_at < $1 THEN expires_at ELSE $1 END WHERE id ",
            sql!(any_of "$2")
        ))
        .bind(now)
        .bind(&list)
        .execute(&mut *tx)
        .await?;
        sqlx::query(concat!(
            "DELETE FROM upload_parts WHERE upload_id ",
            sql!(any_of "$1")
        ))
        .bind(&list)
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(ids)
    }

    /// Marks as purged (at most `limit`) the finished jobs that ended before `finished_before`
    /// and still have their files, and forgets their artifacts and finished webhook
    /// deliveries. Returns their ids, whose files
    /// the caller removes.
    pub async fn purge_jobs(
        &self,
        finished_before: i64,
        limit: i64,
    ) -> Result<Vec<String>, DbError> {
        let mut tx = self.begin().await?;
        let ids: Vec<String> = sqlx::query_scalar(concat!(
            "SELECT id FROM jobs WHERE purged_at IS NULL AND finished_at < $1 \
             AND state IN ('succeeded', 'failed', 'canceled') ORDER BY finished_at LIMIT $2",
            sql!(skip_locked)
        ))
        .bind(finished_before)
        .bind(limit)
        .fetch_all(&mut *tx)
        .await?;
        let now = now_ms();
        let list = Self::id_list(&ids);
        sqlx::query(concat!(
            "UPDATE jobs SET purged_at = $1 WHERE id ",
            sql!(any_of "$2")
        ))
        .bind(now)
        .bind(&list)
        .execute(&mut *tx)
        .await?;
        sqlx::query(concat!(
            "DELETE FROM artifacts WHERE job_id ",
            sql!(any_of "$1")
        ))
        .bind(&list)
        .execute(&mut *tx)
        .await?;
        // Finished webhook deliveries go with the files; pending ones are still owed.
        sqlx::query(concat!(
            "DELETE FROM webhook_deliveries WHERE state != 'pending' AND job_id ",
            sql!(any_of "$1")
        ))
        .bind(&list)
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(ids)
    }

    /// Which of `ids` name an upload (`uploads`) or a job (`jobs`) whose files are still
    /// wanted: an upload not expired, a job not purged. One query for the whole list.
    pub async fn live_ids(&self, table: LiveTable, ids: &[String]) -> Result<Vec<String>, DbError> {
        let sql = match table {
            LiveTable::Uploads => {
                concat!(
                    "SELECT id FROM uploads WHERE state != 'expired' AND id ",
                    sql!(any_of "$1")
                )
            }
            LiveTable::Jobs => {
                concat!(
                    "SELECT id FROM jobs WHERE purged_at IS NULL AND id ",
                    sql!(any_of "$1")
                )
            }
        };
        Ok(sqlx::query_scalar(sql)
            .bind(Self::id_list(ids))
            .fetch_all(&self.pool)
            .await?)
    }

    // ---------------------------------------------------------------- queue (workers)

    /// Claims the oldest claimable job: a queued one, or a running one whose lease expired
    /// (its worker died). In the same transaction, canceling jobs with an expired lease become
    /// canceled, and jobs that lost their worker `max_attempts` times fail. Rows another
    /// transaction holds are skipped, never waited for.
    pub async fn claim(
        &self,
        worker_id: &str,
        lease: Duration,
        max_attempts: i64,
    ) -> Result<Option<Claim>, DbError> {
        let mut tx = self.begin().await?;
        let now = Self::clock(&mut *tx).await?;
        let mut ended: Vec<String> = sqlx::query_scalar(concat!(
            "UPDATE jobs SET state = 'canceled', finished_at = $1, updated_at = $1, worker_id = NULL, lease_until = NULL, lease_token = NULL \
             WHERE seq IN (SELECT seq FROM jobs WHERE state = 'canceling' AND lease_until < $1",
            sql!(skip_locked),
            ") RETURNING id"
        ))
        .bind(now)
        .fetch_all(&mut *tx)
        .await?;
        let failed: Vec<String> = sqlx::query_scalar(concat!(
            "UPDATE jobs SET state = 'failed', error = $2, finished_at = $1, updated_at = $1, worker_id = NULL, lease_until = NULL, lease_token = NULL \
             WHERE seq IN (SELECT seq FROM jobs WHERE state = 'running' AND lease_until < $1 AND attempt >= $3",
            sql!(skip_locked),
            ") RETURNING id"
        ))
        .bind(now)
        .bind(worker_lost_problem(max_attempts))
        .bind(max_attempts)
        .fetch_all(&mut *tx)
        .await?;
        ended.extend(failed);
        for id in &ended {
            Self::record_end(&mut tx, id, now).await?;
        }
        let token = uuid::Uuid::new_v4().simple().to_string();
        let row = sqlx::query(concat!(
            "UPDATE jobs SET state = 'running', worker_id = $1, lease_token = $2, lease_until = $3, attempt = attempt + 1, \
             updated_at = $4, started_at = COALESCE(started_at, $4) \
             WHERE seq = (SELECT seq FROM jobs WHERE state = 'queued' OR (state = 'running' AND lease_until < $4) \
                          ORDER BY seq LIMIT 1",
            sql!(skip_locked),
            ") RETURNING id, attempt, inputs, params, progress"
        ))
        .bind(worker_id)
        .bind(&token)
        .bind(now + lease_ms(lease))
        .bind(now)
        .fetch_optional(&mut *tx)
        .await?;
        let Some(row) = row else {
            tx.commit().await?;
            return Ok(None);
        };
        let job_id: String = row.try_get("id")?;
        let inputs: serde_json::Value = row.try_get("inputs")?;
        let done: Vec<String> = sqlx::query_scalar(
            "SELECT name FROM job_stages WHERE job_id = $1 AND state = 'done' ORDER BY idx",
        )
        .bind(&job_id)
        .fetch_all(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(Some(Claim {
            job_id,
            token,
            attempt: row.try_get("attempt")?,
            inputs: serde_json::from_value(inputs)
                .map_err(|e| DbError::Invalid(format!("bad inputs: {e}")))?,
            params: row.try_get("params")?,
            done,
            progress: row.try_get("progress")?,
        }))
    }

    /// Renews the lease and records progress (never lower than before).
    pub async fn heartbeat(
        &self,
        job_id: &str,
        token: &str,
        lease: Duration,
        progress: f64,
        stage: Option<(&str, f64)>,
    ) -> Result<Heartbeat, DbError> {
        let mut tx = self.begin().await?;
        let now = Self::clock(&mut *tx).await?;
        let state: Option<String> = sqlx::query_scalar(
            "UPDATE jobs SET lease_until = $1, updated_at = CASE WHEN $2 > progress THEN $3 ELSE updated_at END, \
             progress = CASE WHEN $2 > progress THEN $2 ELSE progress END WHERE id = $4 AND lease_token = $5 RETURNING state",
        )
        .bind(now + lease_ms(lease))
        .bind(progress)
        .bind(now)
        .bind(job_id)
        .bind(token)
        .fetch_optional(&mut *tx)
        .await?;
        let Some(state) = state else {
            return Ok(Heartbeat::Lost);
        };
        if let Some((name, p)) = stage {
            sqlx::query(
                "UPDATE job_stages SET progress = CASE WHEN $1 > progress THEN $1 ELSE progress END WHERE job_id = $2 AND name = $3 AND state = 'running'",
            )
            .bind(p)
            .bind(job_id)
            .bind(name)
            .execute(&mut *tx)
            .await?;
        }
        tx.commit().await?;
        Ok(match state.as_str() {
            "canceling" => Heartbeat::CancelRequested,
            "running" => Heartbeat::Ok,
            _ => Heartbeat::Lost,
        })
    }

    /// Checks the fencing token and locks the job row until `tx` ends, so no claim can take
    /// the job between the check and this run's writes; `Fenced` if this run lost the job.
    async fn fence(
        tx: &mut Transaction<'static, Db>,
        job_id: &str,
        token: &str,
    ) -> Result<(), DbError> {
        let held = sqlx::query(concat!(
            "SELECT 1 FROM jobs WHERE id = $1 AND lease_token = $2",
            sql!(for_update)
        ))
        .bind(job_id)
        .bind(token)
        .fetch_optional(&mut **tx)
        .await?;
        held.map(|_| ()).ok_or(DbError::Fenced)
    }

    /// Marks a stage running; `Fenced` if this run lost the job.
    pub async fn start_stage(
        &self,
        job_id: &str,
        token: &str,
        stage: Stage,
        attempt: i64,
    ) -> Result<(), DbError> {
        let now = now_ms();
        let mut tx = self.begin().await?;
        Self::fence(&mut tx, job_id, token).await?;
        sqlx::query(
            "UPDATE job_stages SET state = 'running', progress = 0, attempt = $1, started_at = $2, finished_at = NULL \
             WHERE job_id = $3 AND name = $4",
        )
        .bind(attempt)
        .bind(now)
        .bind(job_id)
        .bind(stage.name())
        .execute(&mut *tx)
        .await?;
        sqlx::query("UPDATE jobs SET stage = $1, updated_at = $2 WHERE id = $3")
            .bind(stage.name())
            .bind(now)
            .bind(job_id)
            .execute(&mut *tx)
            .await?;
        tx.commit().await?;
        Ok(())
    }

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
    ) -> Result<(), DbError> {
        let now = now_ms();
        let mut tx = self.begin().await?;
        Self::fence(&mut tx, job_id, token).await?;
        sqlx::query("DELETE FROM artifacts WHERE job_id = $1 AND stage = $2")
            .bind(job_id)
            .bind(stage.name())
            .execute(&mut *tx)
            .await?;
        for f in files {
            sqlx::query(
                "INSERT INTO artifacts (job_id, name, stage, kind, size, sha256, content_type) \
                 VALUES ($1, $2, $3, $4, $5, $6, $7)",
            )
            .bind(job_id)
            .bind(&f.name)
            .bind(stage.name())
            .bind(&f.kind)
            .bind(f.size as i64)
            .bind(&f.sha256)
            .bind(&f.content_type)
            .execute(&mut *tx)
            .await?;
        }
        sqlx::query(
            "UPDATE job_stages SET state = 'done', progress = 1, finished_at = $1, metrics = $2 WHERE job_id = $3 AND name = $4",
        )
        .bind(now)
        .bind(metrics)
        .bind(job_id)
        .bind(stage.name())
        .execute(&mut *tx)
        .await?;
        sqlx::query(
            "UPDATE jobs SET progress = CASE WHEN $1 > progress THEN $1 ELSE progress END, updated_at = $2 WHERE id = $3",
        )
        .bind(job_progress)
        .bind(now)
        .bind(job_id)
        .execute(&mut *tx)
        .await?;
        Self::record_event(
            &mut tx,
            job_id,
            WebhookEvent::StageFinished,
            Some(stage.name()),
            now,
        )
        .await?;
        tx.commit().await?;
        Ok(())
    }

    /// Ends a run: succeeded, failed (with a problem object) or canceled.
    pub async fn finish_job(&self, job_id: &str, token: &str, end: &RunEnd) -> Result<(), DbError> {
        let now = now_ms();
        let mut tx = self.begin().await?;
        Self::fence(&mut tx, job_id, token).await?;
        let (state, error, stage, stage_state) = match end {
            RunEnd::Succeeded => ("succeeded", None, None, None),
            RunEnd::Failed { stage, problem } => {
                ("failed", Some(problem), stage.clone(), Some("failed"))
            }
            RunEnd::Canceled { stage } => ("canceled", None, stage.clone(), Some("canceled")),
        };
        if let (Some(stage), Some(st)) = (&stage, stage_state) {
            sqlx::query(
                "UPDATE job_stages SET state = $1, finished_at = $2 WHERE job_id = $3 AND name = $4 AND state != 'done'",
            )
            .bind(st)
            .bind(now)
            .bind(job_id)
            .bind(stage)
            .execute(&mut *tx)
            .await?;
        }
        let progress_done = if state == "succeeded" { 1.0 } else { 0.0 };
        sqlx::query(
            "UPDATE jobs SET state = $1, error = $2, progress = CASE WHEN $3 > progress THEN $3 ELSE progress END, finished_at = $4, updated_at = $4, \
             worker_id = NULL, lease_until = NULL, lease_token = NULL WHERE id = $5",
        )
        .bind(state)
        .bind(error)
        .bind(progress_done)
        .bind(now)
        .bind(job_id)
        .execute(&mut *tx)
        .await?;
        Self::record_end(&mut tx, job_id, now).await?;
        tx.commit().await?;
        Ok(())
    }

    // ---------------------------------------------------------------- webhooks

    /// Writes the delivery announcing `event` of `job_id`, inside the transaction that made
    /// it happen (which holds the job's row); nothing when the job has no webhook or its
    /// webhook does not want `event`.
    async fn record_event(
        tx: &mut Transaction<'static, Db>,
        job_id: &str,
        event: WebhookEvent,
        stage: Option<&str>,
        now: i64,
    ) -> Result<(), DbError> {
        let Some(r) = sqlx::query(
            "SELECT id, owner, webhook, state, stage, attempt, error FROM jobs WHERE id = $1",
        )
        .bind(job_id)
        .fetch_optional(&mut **tx)
        .await?
        else {
            return Ok(());
        };
        let job = webhooks::EventJob {
            id: r.try_get("id")?,
            owner: r.try_get("owner")?,
            webhook: r.try_get("webhook")?,
            state: r.try_get("state")?,
            stage: r.try_get("stage")?,
            attempt: r.try_get("attempt")?,
            error: r.try_get("error")?,
        };
        let Some(d) = webhooks::new_delivery(&job, event, stage, now) else {
            return Ok(());
        };
        sqlx::query(
            "INSERT INTO webhook_deliveries (id, job_id, owner, url, event, body, next_attempt_at, created_at, updated_at) \
             VALUES ($1, $2, $3, $4, $5, $6, $7, $7, $7)",
        )
        .bind(&d.id)
        .bind(&job.id)
        .bind(&job.owner)
        .bind(&d.url)
        .bind(d.event)
        .bind(&d.body)
        .bind(now)
        .execute(&mut **tx)
        .await?;
        Ok(())
    }

    /// Records the event announcing the end of `job_id` (succeeded, failed or canceled: the
    /// state it now has).
    async fn record_end(
        tx: &mut Transaction<'static, Db>,
        job_id: &str,
        now: i64,
    ) -> Result<(), DbError> {
        let state: Option<String> = sqlx::query_scalar("SELECT state FROM jobs WHERE id = $1")
            .bind(job_id)
            .fetch_optional(&mut **tx)
            .await?;
        match state
            .as_deref()
            .and_then(JobState::parse)
            .and_then(WebhookEvent::for_end)
        {
            Some(event) => Self::record_event(tx, job_id, event, None, now).await,
            None => Ok(()),
        }
    }

    /// Claims up to `limit` due deliveries (pending, next attempt due, no live lease) for
    /// `lease`; only the returned token may record their outcome. Each comes with the number
    /// of the attempt about to be made, which is stored only with its outcome
    /// ([`Self::finish_delivery`]): a delivery's `attempts` counts attempts that were answered
    /// or failed, never one still in flight or lost with its dispatcher. Rows another
    /// dispatcher is claiming are skipped, never waited for.
    pub async fn claim_deliveries(
        &self,
        lease: Duration,
        limit: i64,
    ) -> Result<Vec<Delivery>, DbError> {
        let token = uuid::Uuid::new_v4().simple().to_string();
        let mut tx = self.begin().await?;
        let now = Self::clock(&mut *tx).await?;
        let rows = sqlx::query(concat!(
            "UPDATE webhook_deliveries SET lease_until = $1, lease_token = $2, updated_at = $3 \
             WHERE seq IN (SELECT seq FROM webhook_deliveries WHERE state = 'pending' AND next_attempt_at <= $3 \
                           AND (lease_until IS NULL OR lease_until < $3) ORDER BY next_attempt_at, seq LIMIT $4",
            sql!(skip_locked),
            ") RETURNING id, job_id, owner, url, event, body, attempts + 1 AS attempts, created_at"
        ))
        .bind(now + lease_ms(lease))
        .bind(&token)
        .bind(now)
        .bind(limit)
        .fetch_all(&mut *tx)
        .await?;
        tx.commit().await?;
        rows.iter()
            .map(|r| delivery_from_row(r, &token))
            .collect::<Result<_, sqlx::Error>>()
            .map_err(DbError::from)
    }

    /// Records how an attempt went, counting it; `false` (and nothing written) when `token`
    /// no longer holds the delivery (its lease ran out and another dispatcher took it).
    pub async fn finish_delivery(
        &self,
        id: &str,
        token: &str,
        outcome: &DeliveryOutcome,
    ) -> Result<bool, DbError> {
        let now = Self::clock(&self.pool).await?;
        let (state, status, error, next) = match outcome {
            DeliveryOutcome::Delivered { status } => ("delivered", Some(*status), None, now),
            DeliveryOutcome::Retry {
                status,
                error,
                delay_ms,
            } => ("pending", *status, Some(error.as_str()), now + delay_ms),
            DeliveryOutcome::GiveUp { status, error } => {
                ("failed", *status, Some(error.as_str()), now)
            }
        };
        let done = (state != "pending").then_some(now);
        let res = sqlx::query(
            "UPDATE webhook_deliveries SET state = $1, last_status = $2, last_error = $3, next_attempt_at = $4, \
             finished_at = $5, updated_at = $6, lease_until = NULL, lease_token = NULL, attempts = attempts + 1 \
             WHERE id = $7 AND lease_token = $8 AND state = 'pending'",
        )
        .bind(state)
        .bind(status.map(i64::from))
        .bind(error)
        .bind(next)
        .bind(done)
        .bind(now)
        .bind(id)
        .bind(token)
        .execute(&self.pool)
        .await?;
        Ok(res.rows_affected() == 1)
    }

    /// A job's deliveries, oldest first.
    pub async fn job_deliveries(&self, job_id: &str) -> Result<Vec<DeliveryRecord>, DbError> {
        let rows = sqlx::query("SELECT * FROM webhook_deliveries WHERE job_id = $1 ORDER BY seq")
            .bind(job_id)
            .fetch_all(&self.pool)
            .await?;
        rows.iter().map(delivery_record_from_row).collect()
    }

    /// Deliveries in each state.
    pub async fn count_deliveries(&self) -> Result<Vec<(DeliveryState, i64)>, DbError> {
        let rows =
            sqlx::query("SELECT state, COUNT(*) AS n FROM webhook_deliveries GROUP BY state")
                .fetch_all(&self.pool)
                .await?;
        let mut out = Vec::new();
        for r in &rows {
            let s: String = r.try_get("state")?;
            if let Some(st) = DeliveryState::parse(&s) {
                out.push((st, r.try_get("n")?));
            }
        }
        Ok(out)
    }

    /// The server-wide setting `name`: its stored value, or `value` stored now if it had
    /// none (the first process to ask wins; every later one reads the same).
    pub async fn setting_or_insert(&self, name: &str, value: &str) -> Result<String, DbError> {
        sqlx::query(
            "INSERT INTO settings (name, value) VALUES ($1, $2) ON CONFLICT (name) DO NOTHING",
        )
        .bind(name)
        .bind(value)
        .execute(&self.pool)
        .await?;
        Ok(
            sqlx::query_scalar("SELECT value FROM settings WHERE name = $1")
                .bind(name)
                .fetch_one(&self.pool)
                .await?,
        )
    }

    // ---------------------------------------------------------------- workers and metrics

    /// Records (or refreshes) a live worker slot; `last_seen` is the database's clock.
    pub async fn register_worker(&self, id: &str, host: &str, pid: u32) -> Result<(), DbError> {
        let now = Self::clock(&self.pool).await?;
        sqlx::query(
            "INSERT INTO workers (id, host, pid, started_at, last_seen) VALUES ($1, $2, $3, $4, $4) \
             ON CONFLICT (id) DO UPDATE SET last_seen = excluded.last_seen",
        )
        .bind(id)
        .bind(host)
        .bind(i64::from(pid))
        .bind(now)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    /// Forgets a worker slot that stopped cleanly.
    pub async fn unregister_worker(&self, id: &str) -> Result<(), DbError> {
        sqlx::query("DELETE FROM workers WHERE id = $1")
            .bind(id)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// Start-up recovery: forgets workers silent for longer than `stale`, and expires at once
    /// the leases of jobs held by worker processes of this host that no longer exist (a
    /// crashed `sylva serve`), so they are re-claimed without waiting for the lease.
    pub async fn recover(&self, host: &str, stale: Duration) -> Result<u64, DbError> {
        let now = Self::clock(&self.pool).await?;
        let rows = sqlx::query("SELECT id, pid FROM workers WHERE host = $1")
            .bind(host)
            .fetch_all(&self.pool)
            .await?;
        let mut expired = 0;
        for r in &rows {
            let (id, pid): (String, i64) = (r.try_get("id")?, r.try_get("pid")?);
            if !process_alive(pid) {
                let mut tx = self.begin().await?;
                let res = sqlx::query(
                    "UPDATE jobs SET lease_until = 0 WHERE worker_id = $1 AND state IN ('running', 'canceling')",
                )
                .bind(&id)
                .execute(&mut *tx)
                .await?;
                if res.rows_affected() > 0 {
                    Self::notify(&mut tx, &id).await?;
                }
                tx.commit().await?;
                expired += res.rows_affected();
                self.unregister_worker(&id).await?;
            }
        }
        sqlx::query("DELETE FROM workers WHERE last_seen < $1")
            .bind(now - lease_ms(stale))
            .execute(&self.pool)
            .await?;
        Ok(expired)
    }

    /// Workers seen within `window`.
    pub async fn live_workers(&self, window: Duration) -> Result<i64, DbError> {
        let now = Self::clock(&self.pool).await?;
        Ok(
            sqlx::query_scalar("SELECT COUNT(*) FROM workers WHERE last_seen >= $1")
                .bind(now - lease_ms(window))
                .fetch_one(&self.pool)
                .await?,
        )
    }

    /// Number of jobs in each state.
    pub async fn count_by_state(&self) -> Result<Vec<(JobState, i64)>, DbError> {
        let rows = sqlx::query("SELECT state, COUNT(*) AS n FROM jobs GROUP BY state")
            .fetch_all(&self.pool)
            .await?;
        let mut out: Vec<(JobState, i64)> = JobState::ALL.iter().map(|s| (*s, 0)).collect();
        for r in &rows {
            let s: String = r.try_get("state")?;
            if let Some(entry) = out.iter_mut().find(|(st, _)| st.as_str() == s) {
                entry.1 = r.try_get("n")?;
            }
        }
        Ok(out)
    }

    /// Durations in seconds of finished stages, per stage name.
    pub async fn stage_durations(&self) -> Result<Vec<(String, f64)>, DbError> {
        let rows = sqlx::query(
            "SELECT name, CAST(finished_at - started_at AS DOUBLE PRECISION) / 1000.0 AS d FROM job_stages \
             WHERE state = 'done' AND started_at IS NOT NULL AND finished_at IS NOT NULL",
        )
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| Ok((r.try_get("name")?, r.try_get("d")?)))
            .collect::<Result<_, sqlx::Error>>()
            .map_err(DbError::from)
    }
}

fn artifact_from_row(r: &DbRow) -> Result<ArtifactRecord, sqlx::Error> {
    Ok(ArtifactRecord {
        name: r.try_get("name")?,
        stage: r.try_get("stage")?,
        kind: r.try_get("kind")?,
        size: r.try_get("size")?,
        sha256: r.try_get("sha256")?,
        content_type: r.try_get("content_type")?,
    })
}

fn delivery_from_row(r: &DbRow, token: &str) -> Result<Delivery, sqlx::Error> {
    Ok(Delivery {
        id: r.try_get("id")?,
        job_id: r.try_get("job_id")?,
        owner: r.try_get("owner")?,
        url: r.try_get("url")?,
        event: r.try_get("event")?,
        body: r.try_get("body")?,
        attempts: r.try_get("attempts")?,
        created_at: r.try_get("created_at")?,
        token: token.to_string(),
    })
}

fn delivery_record_from_row(r: &DbRow) -> Result<DeliveryRecord, DbError> {
    let state: String = r.try_get("state")?;
    let state = DeliveryState::parse(&state)
        .ok_or_else(|| DbError::Invalid(format!("bad delivery state {state:?}")))?;
    Ok(DeliveryRecord {
        id: r.try_get("id")?,
        event: r.try_get("event")?,
        url: r.try_get("url")?,
        state,
        attempts: r.try_get("attempts")?,
        next_attempt_at: match state {
            DeliveryState::Pending => Some(r.try_get("next_attempt_at")?),
            _ => None,
        },
        last_status: r.try_get("last_status")?,
        last_error: r.try_get("last_error")?,
        created_at: r.try_get("created_at")?,
        finished_at: r.try_get("finished_at")?,
    })
}

// ---------------------------------------------------------------- managed API keys

impl Store {
    /// Stores a new key; a name already used is a conflict.
    pub async fn create_api_key(&self, k: &ApiKey) -> Result<(), DbError> {
        let taken: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM api_keys WHERE name = $1")
            .bind(&k.name)
            .fetch_one(&self.pool)
            .await?;
        if taken > 0 {
            return Err(DbError::Conflict(format!(
                "a key named {:?} exists already",
                k.name
            )));
        }
        sqlx::query(
            "INSERT INTO api_keys (id, name, hash, prefix, admin, quota_jobs, \
             quota_bytes, created_at, expires_at, revoked_at) \
             VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, NULL)",
        )
        .bind(&k.id)
        .bind(&k.name)
        .bind(&k.hash)
        .bind(&k.prefix)
        .bind(i64::from(k.admin))
        .bind(k.quota_jobs)
        .bind(k.quota_bytes)
        .bind(k.created_at)
        .bind(k.expires_at)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    /// Every key, oldest first (revoked ones included).
    pub async fn api_keys(&self) -> Result<Vec<ApiKey>, DbError> {
        let sql = format!("SELECT {KEY_COLUMNS} FROM api_keys ORDER BY created_at, id");
        let rows = sqlx::query(sqlx::AssertSqlSafe(sql))
            .fetch_all(&self.pool)
            .await?;
        rows.iter().map(key_from_row).collect()
    }

    /// The key whose hash is `hash`, usable or not.
    pub async fn api_key_by_hash(&self, hash: &str) -> Result<Option<ApiKey>, DbError> {
        let sql = format!("SELECT {KEY_COLUMNS} FROM api_keys WHERE hash = $1");
        let row = sqlx::query(sqlx::AssertSqlSafe(sql))
            .bind(hash)
            .fetch_optional(&self.pool)
            .await?;
        row.map(|r| key_from_row(&r)).transpose()
    }

    /// Revokes the key `id` at `now`; the revoked record, or `NotFound`. Revoking
    /// twice keeps the first time.
    pub async fn revoke_api_key(&self, id: &str, now: i64) -> Result<ApiKey, DbError> {
        sqlx::query("UPDATE api_keys SET revoked_at = $1 WHERE id = $2 AND revoked_at IS NULL")
            .bind(now)
            .bind(id)
            .execute(&self.pool)
            .await?;
        let sql = format!("SELECT {KEY_COLUMNS} FROM api_keys WHERE id = $1");
        let row = sqlx::query(sqlx::AssertSqlSafe(sql))
            .bind(id)
            .fetch_optional(&self.pool)
            .await?;
        row.map(|r| key_from_row(&r))
            .transpose()?
            .ok_or(DbError::NotFound)
    }

    /// The webhook secret generation of `owner` (generation 0 when never rotated).
    pub async fn secret_generation(&self, owner: &str) -> Result<SecretGeneration, DbError> {
        let row = sqlx::query(
            "SELECT generation, rotated_at, previous_until FROM webhook_secrets \
             WHERE owner = $1",
        )
        .bind(owner)
        .fetch_optional(&self.pool)
        .await?;
        match row {
            None => Ok(SecretGeneration::default()),
            Some(r) => Ok(SecretGeneration {
                generation: r.try_get("generation")?,
                rotated_at: r.try_get("rotated_at")?,
                previous_until: r.try_get("previous_until")?,
            }),
        }
    }

    /// Moves `owner` to its next webhook secret at `now`, the previous one still in
    /// use until `now + grace_ms`; the new state.
    pub async fn rotate_secret(
        &self,
        owner: &str,
        now: i64,
        grace_ms: i64,
    ) -> Result<SecretGeneration, DbError> {
        sqlx::query(
            "INSERT INTO webhook_secrets (owner, generation, rotated_at, previous_until) \
             VALUES ($1, 1, $2, $3) \
             ON CONFLICT (owner) DO UPDATE SET generation = webhook_secrets.generation + 1, \
             rotated_at = excluded.rotated_at, previous_until = excluded.previous_until",
        )
        .bind(owner)
        .bind(now)
        .bind(now.saturating_add(grace_ms))
        .execute(&self.pool)
        .await?;
        self.secret_generation(owner).await
    }
}

/// An [`ApiKey`] from a row of [`KEY_COLUMNS`].
fn key_from_row(r: &DbRow) -> Result<ApiKey, DbError> {
    Ok(ApiKey {
        id: r.try_get("id")?,
        name: r.try_get("name")?,
        hash: r.try_get("hash")?,
        prefix: r.try_get("prefix")?,
        admin: r.try_get::<i64, _>("admin")? != 0,
        quota_jobs: r.try_get("quota_jobs")?,
        quota_bytes: r.try_get("quota_bytes")?,
        created_at: r.try_get("created_at")?,
        expires_at: r.try_get("expires_at")?,
        revoked_at: r.try_get("revoked_at")?,
    })
}
