//! Job and upload records, their states, and the queue that hands jobs to workers.
//!
//! A job moves queued → running → succeeded | failed, or (on cancel) canceling → canceled.
//! A worker claims a job in one statement that sets a lease (`lease_until`) and a fresh
//! fencing token; it renews the lease by heartbeat. When a worker dies its lease runs out and
//! another worker claims the job with attempt + 1; the dead worker's token no longer matches,
//! so nothing it might still write lands (fencing). Each finished stage leaves a checkpoint
//! row (`job_stages.state = 'done'`), so a re-claimed or retried job resumes at the first
//! unfinished stage.
//!
//! The queue lives in SQLite (one machine, the default) or PostgreSQL (many API replicas
//! and workers, `--database postgres://...`). [`JobStore`] hides which: callers hold one type,
//! and both backends keep the same semantics, checked by the same tests.

/// The SQL the two databases spell differently, side by side; `queries.rs` splices these into
/// its `concat!`s through each backend's `sql!` (`sql!(for_update)` is
/// `dialect!(sqlite for_update)` in `sqlite.rs`). Everything else is SQL both speak.
///
/// - `for_update`, `for_share`, `skip_locked`: row locks. PostgreSQL runs writers
///   concurrently under READ COMMITTED, so a reader that writes next locks what it read, and
///   claimers and sweepers skip rows another transaction holds; SQLite's `BEGIN IMMEDIATE`
///   already makes each writing transaction the only writer, so they are empty there.
/// - `any_of "$N"`: "is one of the ids bound to `$N`" (a PostgreSQL array; on SQLite a JSON
///   array, see `SqliteJobs::id_list`).
/// - `inputs_mention`: "job `j`'s inputs name upload `u`" (the inputs are JSONB on
///   PostgreSQL, text on SQLite).
macro_rules! dialect {
    (sqlite for_update) => {
        ""
    };
    (postgres for_update) => {
        " FOR UPDATE"
    };
    (sqlite for_share) => {
        ""
    };
    (postgres for_share) => {
        " FOR SHARE"
    };
    (sqlite skip_locked) => {
        ""
    };
    (postgres skip_locked) => {
        " FOR UPDATE SKIP LOCKED"
    };
    (sqlite any_of $p:literal) => {
        concat!("IN (SELECT value FROM json_each(", $p, "))")
    };
    (postgres any_of $p:literal) => {
        concat!("= ANY(", $p, ")")
    };
    (sqlite inputs_mention) => {
        "instr(j.inputs, u.id) > 0"
    };
    (postgres inputs_mention) => {
        "strpos(CAST(j.inputs AS TEXT), u.id) > 0"
    };
}

pub mod keys;
pub mod postgres;
pub mod sqlite;
mod store;
pub mod webhooks;

use std::time::Duration;

use serde::{Deserialize, Serialize};

use crate::stage::Stage;

pub use store::{Database, JobStore};
pub use webhooks::{
    Delivery, DeliveryOutcome, DeliveryRecord, DeliveryState, WebhookEvent, WebhookSpec,
};

/// Milliseconds since the Unix epoch, UTC.
pub fn now_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_millis() as i64)
        .unwrap_or(0)
}

/// RFC 3339 text of a millisecond timestamp.
pub fn rfc3339(ms: i64) -> String {
    let t = time::OffsetDateTime::from_unix_timestamp_nanos(ms as i128 * 1_000_000)
        .unwrap_or(time::OffsetDateTime::UNIX_EPOCH);
    t.format(&time::format_description::well_known::Rfc3339)
        .unwrap_or_default()
}

macro_rules! string_enum {
    ($(#[$m:meta])* $name:ident { $($variant:ident => $text:literal),+ $(,)? }) => {
        $(#[$m])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
        #[serde(rename_all = "lowercase")]
        pub enum $name { $($variant),+ }

        impl $name {
            pub const ALL: &'static [$name] = &[$($name::$variant),+];
            pub fn as_str(self) -> &'static str {
                match self { $($name::$variant => $text),+ }
            }
            pub fn parse(s: &str) -> Option<Self> {
                match s { $($text => Some($name::$variant),)+ _ => None }
            }
        }
    };
}

string_enum!(
    /// The state of a job (docs/api.md).
    JobState {
        Queued => "queued",
        Running => "running",
        Succeeded => "succeeded",
        Failed => "failed",
        Canceling => "canceling",
        Canceled => "canceled",
    }
);

impl JobState {
    pub fn is_terminal(self) -> bool {
        matches!(
            self,
            JobState::Succeeded | JobState::Failed | JobState::Canceled
        )
    }
}

string_enum!(
    /// The state of one stage of one job.
    StageState {
        Pending => "pending",
        Running => "running",
        Done => "done",
        Failed => "failed",
        Canceled => "canceled",
    }
);

pub use crate::stage::UploadKind;

/// The uploads a job reads, by upload id: the LiDAR cloud, and either a COLMAP project or
/// photos for stage `sfm`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobInputs {
    pub lidar: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub colmap: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub photos: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub control_points: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub field_dbh: Option<String>,
}

impl JobInputs {
    /// Why these inputs cannot make a job: neither or both of `colmap` and `photos`.
    pub fn problem(&self) -> Option<&'static str> {
        match (&self.colmap, &self.photos) {
            (Some(_), Some(_)) => Some(
                "give either `colmap` (a COLMAP project) or `photos` (for stage sfm to \
                 reconstruct), not both",
            ),
            (None, None) => Some(
                "`lidar` and one of `colmap` (a COLMAP project) or `photos` (photos for stage \
                 sfm) are required",
            ),
            _ => None,
        }
    }

    /// (kind, upload id) of every input given.
    pub fn all(&self) -> Vec<(UploadKind, &str)> {
        let mut v = vec![(UploadKind::Lidar, self.lidar.as_str())];
        if let Some(id) = &self.colmap {
            v.push((UploadKind::Colmap, id));
        }
        if let Some(id) = &self.photos {
            v.push((UploadKind::Photos, id));
        }
        if let Some(id) = &self.control_points {
            v.push((UploadKind::ControlPoints, id));
        }
        if let Some(id) = &self.field_dbh {
            v.push((UploadKind::FieldDbh, id));
        }
        v
    }
}

/// One job row with its stages and artifacts.
#[derive(Debug, Clone)]
pub struct JobRecord {
    pub seq: i64,
    pub id: String,
    pub state: JobState,
    pub stage: Option<String>,
    pub progress: f64,
    pub attempt: i64,
    pub inputs: JobInputs,
    pub params: serde_json::Value,
    pub error: Option<serde_json::Value>,
    pub created_at: i64,
    pub updated_at: i64,
    pub started_at: Option<i64>,
    pub finished_at: Option<i64>,
    /// Who submitted it: the managed key's id, [`owner_id`] of a static token, "" with
    /// authentication off.
    pub owner: String,
    /// When retention removed its files (ms since the epoch); its artifacts are then gone.
    pub purged_at: Option<i64>,
    /// Where to announce its events, if the submitter asked.
    pub webhook: Option<WebhookSpec>,
    pub stages: Vec<StageRecord>,
    pub artifacts: Vec<ArtifactRecord>,
}

/// A job to queue, as the API accepted it.
#[derive(Debug, Clone, Copy)]
pub struct NewJob<'a> {
    pub id: &'a str,
    pub inputs: &'a JobInputs,
    pub params: &'a serde_json::Value,
    pub stages: &'a [Stage],
    pub idempotency_key: Option<&'a str>,
    /// SHA-256 of the request, so a reused Idempotency-Key with another body is refused.
    pub request_hash: &'a str,
    /// Who submits it ([`owner_id`]); its inputs must be this owner's uploads.
    pub owner: &'a str,
    /// Where to announce its events (its URL already checked).
    pub webhook: Option<&'a WebhookSpec>,
}

/// The records whose files the retention sweep asks about (see `JobStore::live_ids`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LiveTable {
    Uploads,
    Jobs,
}

/// Limits checked in the same transaction that queues a job, so concurrent submissions
/// cannot both slip under them.
#[derive(Debug, Clone, Copy)]
pub struct Admission {
    /// Queued jobs (all owners) at which new jobs are refused.
    pub max_queued: i64,
    /// Unfinished jobs (queued, running, canceling) one owner may have; 0: no limit.
    pub max_active_per_owner: i64,
}

impl Admission {
    /// Only the queue length limits admission.
    pub fn queue(max_queued: i64) -> Self {
        Self {
            max_queued,
            max_active_per_owner: 0,
        }
    }
}

/// Refuses an input upload of the wrong kind or not (or no longer) complete; `kind` and
/// `state` are the upload's row.
pub(crate) fn check_input(
    want: UploadKind,
    upload: &str,
    kind: &str,
    state: &str,
) -> Result<(), DbError> {
    let field = want.as_str();
    if kind != field {
        return Err(DbError::Invalid(format!(
            "inputs.{field}: upload {upload} holds `{kind}`, not `{field}`"
        )));
    }
    match state {
        "complete" => Ok(()),
        "expired" => Err(DbError::Gone(format!(
            "inputs.{field}: upload {upload} has expired and its bytes were removed; upload it again"
        ))),
        _ => Err(DbError::Invalid(format!(
            "inputs.{field}: upload {upload} is not complete"
        ))),
    }
}

/// The opaque owner id of a bearer token: `t` and the first 16 hex digits of its SHA-256, so
/// records can be attributed and counted per token without storing the token.
pub fn owner_id(token: &str) -> String {
    use sha2::Digest;
    let digest = sha2::Sha256::digest(token.as_bytes());
    format!("t{}", &hex::encode(digest)[..16])
}

#[derive(Debug, Clone)]
pub struct StageRecord {
    pub name: String,
    pub state: StageState,
    pub progress: f64,
    pub attempt: i64,
    pub started_at: Option<i64>,
    pub finished_at: Option<i64>,
    pub metrics: Option<serde_json::Value>,
}

#[derive(Debug, Clone, PartialEq)]
pub struct ArtifactRecord {
    pub name: String,
    pub stage: String,
    pub kind: String,
    pub size: i64,
    pub sha256: String,
    pub content_type: String,
}

#[derive(Debug, Clone)]
pub struct UploadRecord {
    pub id: String,
    pub kind: UploadKind,
    pub filename: String,
    pub size: i64,
    pub sha256: Option<String>,
    pub part_size: i64,
    pub complete: bool,
    pub inspection: Option<serde_json::Value>,
    pub created_at: i64,
    pub expires_at: i64,
    pub completed_at: Option<i64>,
    /// Received parts: (index, size in bytes).
    pub parts: Vec<(i64, i64)>,
    /// Who created it: the managed key's id, [`owner_id`] of a static token, "" with
    /// authentication off.
    pub owner: String,
    /// Removed by retention (an open upload past `expires_at`, or a finished one no job
    /// needs any more): its bytes are gone and it answers 410.
    pub expired: bool,
}

impl UploadRecord {
    pub fn parts_total(&self) -> i64 {
        (self.size + self.part_size - 1) / self.part_size
    }

    /// Exact length part `n` must have.
    pub fn part_len(&self, n: i64) -> i64 {
        (self.size - n * self.part_size).min(self.part_size)
    }

    pub fn bytes_received(&self) -> i64 {
        self.parts.iter().map(|p| p.1).sum()
    }

    pub fn missing_parts(&self) -> Vec<i64> {
        let have: std::collections::HashSet<i64> = self.parts.iter().map(|p| p.0).collect();
        (0..self.parts_total())
            .filter(|n| !have.contains(n))
            .collect()
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct LogLine {
    pub seq: i64,
    pub ts: i64,
    pub level: String,
    pub stage: Option<String>,
    pub message: String,
}

/// A job handed to a worker.
#[derive(Debug, Clone)]
pub struct Claim {
    pub job_id: String,
    /// Fencing token: every write of this run must present it.
    pub token: String,
    pub attempt: i64,
    pub inputs: JobInputs,
    pub params: serde_json::Value,
    /// Stages already finished (checkpoints), by name.
    pub done: Vec<String>,
    pub progress: f64,
}

/// What a heartbeat learned.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Heartbeat {
    Ok,
    /// The user asked to cancel; stop the stage.
    CancelRequested,
    /// Another worker owns the job now (or it was deleted); stop without writing.
    Lost,
}

/// How a run ended, as the worker reports it.
#[derive(Debug, Clone)]
pub enum RunEnd {
    Succeeded,
    Failed {
        stage: Option<String>,
        problem: serde_json::Value,
    },
    Canceled {
        stage: Option<String>,
    },
}

/// The outcome of creating a job.
#[derive(Debug)]
pub enum Created {
    New(String),
    /// The Idempotency-Key was seen before with the same request: the job it created.
    Existing(String),
}

/// What a retry resets, worked out from the job's stage rows (name, index, state) in order.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct RetryPlan {
    /// Stages with this index or a higher one run again.
    pub from_idx: i64,
    /// Names of the stages that are reset.
    pub reset: Vec<String>,
    /// Job progress [0, 1] of the stages kept (their weights).
    pub done_weight: f64,
}

impl RetryPlan {
    /// Checks `from` against the job's stages: a named stage must be one the job runs and
    /// must not lie past the first unfinished stage; without one, the job resumes at its first
    /// unfinished stage.
    pub(crate) fn new(
        stages: &[(String, i64, String)],
        from: Option<Stage>,
    ) -> Result<Self, DbError> {
        let first_unfinished = stages
            .iter()
            .find(|(_, _, state)| state != StageState::Done.as_str())
            .map(|(name, idx, _)| (name.clone(), *idx));
        let from_idx = match (from, &first_unfinished) {
            (Some(s), _) if !stages.iter().any(|(n, _, _)| n == s.name()) => {
                return Err(DbError::Invalid(format!(
                    "from_stage {s}: this job does not run that stage"
                )));
            }
            (Some(s), Some((name, idx))) if (s.index() as i64) > *idx => {
                return Err(DbError::Invalid(format!(
                    "from_stage {s}: stage {name} has not finished, so the job must resume there"
                )));
            }
            (Some(s), _) => s.index() as i64,
            (None, Some((_, idx))) => *idx,
            (None, None) => {
                return Err(DbError::Conflict(
                    "every stage has finished; name from_stage to run stages again".into(),
                ));
            }
        };
        let reset = stages
            .iter()
            .filter(|(_, i, _)| *i >= from_idx)
            .map(|(n, _, _)| n.clone())
            .collect();
        let done_weight = stages
            .iter()
            .filter(|(_, i, _)| *i < from_idx)
            .filter_map(|(n, _, _)| Stage::from_name(n).map(|s| s.weight()))
            .sum();
        Ok(Self {
            from_idx,
            reset,
            done_weight,
        })
    }
}

/// The problem+json a job fails with when its workers died `max_attempts` times.
pub(crate) fn worker_lost_problem(max_attempts: i64) -> serde_json::Value {
    serde_json::json!({
        "type": "urn:sylva:problem:worker-lost",
        "title": "Worker lost",
        "status": 500,
        "detail": format!("the job's worker stopped responding {max_attempts} times; giving up"),
    })
}

/// A lease's length in milliseconds, as the database stores times.
pub(crate) fn lease_ms(lease: Duration) -> i64 {
    i64::try_from(lease.as_millis()).unwrap_or(i64::MAX / 4)
}

/// Whether a process id exists on this host (Linux: /proc; elsewhere assume alive).
pub(crate) fn process_alive(pid: i64) -> bool {
    if cfg!(target_os = "linux") {
        std::path::Path::new(&format!("/proc/{pid}")).exists()
    } else {
        true
    }
}

#[derive(Debug, thiserror::Error)]
pub enum DbError {
    #[error("database: {0}")]
    Sqlx(#[from] sqlx::Error),
    #[error("database migration: {0}")]
    Migrate(#[from] sqlx::migrate::MigrateError),
    #[error("{0}")]
    Conflict(String),
    #[error("{0}")]
    Invalid(String),
    #[error("not found")]
    NotFound,
    /// This worker no longer holds the job's lease; its write was refused.
    #[error("lease lost: another worker owns the job")]
    Fenced,
    #[error("queue full: {0} jobs waiting")]
    QueueFull(i64),
    /// The owner already has this many unfinished jobs, its quota.
    #[error("quota: {0} unfinished jobs")]
    JobQuota(i64),
    /// The resource existed but retention removed it (HTTP 410).
    #[error("{0}")]
    Gone(String),
}

impl DbError {
    /// Whether the database refused a write because its disk is full (SQLite's message, or
    /// PostgreSQL's SQLSTATE 53100 `disk_full`).
    pub fn is_storage_full(&self) -> bool {
        match self {
            DbError::Sqlx(sqlx::Error::Database(e)) => {
                e.code().as_deref() == Some("53100")
                    || e.message().contains("database or disk is full")
            }
            other => other.to_string().contains("database or disk is full"),
        }
    }
}

#[cfg(test)]
mod tests;
