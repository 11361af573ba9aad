//! Settings: command-line flags, each mirrored by a `SYLVA_*` environment variable
//! (flags win over the environment, the environment over the defaults written here).
//!
//! The structs are plain data for the library. With the `cli` feature (on by default; the
//! binary needs it) they also derive clap's `Args`, and their `#[arg]` attributes give each
//! field its flag, its variable and its default; without it the library has no clap.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use crate::io::archive::ExtractLimits;
use crate::jobs::{Database, DbError};
use crate::stage::Stage;

#[cfg(feature = "cli")]
const MIB: u64 = 1 << 20;
#[cfg(feature = "cli")]
const GIB: u64 = 1 << 30;

/// Settings shared by every process that touches the job database.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "cli", derive(clap::Args))]
pub struct StoreArgs {
    /// Data directory: every blob (uploads, job outputs) lives under it, and so does the
    /// SQLite database (`sylva.db`, WAL mode) unless --database names another.
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_DATA", default_value = "sylva-data")
    )]
    pub data: PathBuf,

    /// Job database: `postgres://user:password@host:port/database` for PostgreSQL (many API
    /// replicas and workers on many machines sharing one queue), or an SQLite file as
    /// `sqlite:PATH` or a plain path. Default: SQLite in `sylva.db` under --data.
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_DATABASE", hide_env_values = true)
    )]
    pub database: Option<String>,

    /// Object store for uploads and job outputs when processes run on several machines:
    /// `s3://bucket/prefix` (any S3-compatible store; credentials, region and endpoint from
    /// the standard `AWS_*` variables, e.g. `AWS_ENDPOINT_URL` and `AWS_ALLOW_HTTP=true` for
    /// a MinIO on plain HTTP) or `file:///folder` (a folder every process sees). Default: local
    /// files under --data only. --data still holds each machine's working copies.
    #[cfg_attr(feature = "cli", arg(long, env = "SYLVA_STORE"))]
    pub store: Option<String>,

    /// Log filter in tracing's syntax, e.g. `info` or `sylva=debug,tower_http=info`.
    #[cfg_attr(feature = "cli", arg(long, env = "SYLVA_LOG", default_value = "info"))]
    pub log: String,

    /// Log lines as JSON objects instead of text.
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_LOG_JSON", default_value_t = false)
    )]
    pub log_json: bool,
}

impl StoreArgs {
    /// The default SQLite file: `sylva.db` under --data.
    pub fn database_path(&self) -> PathBuf {
        self.data.join("sylva.db")
    }

    /// The job database --database names, or the default SQLite file.
    pub fn database(&self) -> Result<Database, DbError> {
        match self.database.as_deref() {
            Some(text) if !text.trim().is_empty() => Database::parse(text),
            _ => Ok(Database::Sqlite(self.database_path())),
        }
    }
}

/// Settings of the worker pool (in `sylva serve` and `sylva worker`).
#[derive(Debug, Clone)]
#[cfg_attr(feature = "cli", derive(clap::Args))]
pub struct WorkerArgs {
    /// Jobs this process runs at the same time (0: run no worker, API only).
    #[cfg_attr(feature = "cli", arg(long, env = "SYLVA_WORKERS", default_value_t = 1))]
    pub workers: u32,

    /// Stages that need the GPU (training) run at most this many at a time per process.
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_GPU_SLOTS", default_value_t = 1)
    )]
    pub gpu_slots: u32,

    /// Lease of a claimed job in seconds; the worker renews it by heartbeat, and another
    /// worker may take the job over once it has run out.
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_LEASE_SECS", default_value_t = 30)
    )]
    pub lease_secs: u64,

    /// A job whose worker died this many times fails instead of being claimed again.
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_MAX_ATTEMPTS", default_value_t = 3)
    )]
    pub max_attempts: u32,

    /// How often an idle worker looks for work, in milliseconds. On PostgreSQL a newly
    /// queued job also wakes idle workers at once (LISTEN/NOTIFY); this poll is the fallback.
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_POLL_MS", default_value_t = 500)
    )]
    pub poll_ms: u64,

    /// Longest a stage may run, in seconds, after which it is cancelled and the job fails
    /// with a clear "stage timed out" problem: one number for every stage and/or
    /// `stage=seconds` overrides, comma-separated (e.g. `7200,train=172800`). Default 172800
    /// (48 h, beyond any plot's training on a real GPU) so a hung stage never holds a worker
    /// for ever.
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_MAX_STAGE_SECS", default_value = "172800")
    )]
    pub max_stage_secs: String,

    /// Fault injection for tests: a stage waits this many milliseconds (cancellably, and
    /// holding its GPU slot if it uses the GPU) before it starts; one number for every stage
    /// and/or `stage=ms` overrides, e.g. `train=60000`. 0 in production.
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_DEBUG_STAGE_PAUSE_MS", default_value = "0")
    )]
    pub debug_stage_pause_ms: String,

    /// Fault injection for tests only: `STAGE[:FRACTION]` makes this process kill itself with
    /// SIGKILL inside stage STAGE, at the stage's first progress report at or above FRACTION
    /// in [0, 1] (default 0.5), to prove that a crash mid-stage loses nothing. Only in builds
    /// with the `fault-injection` feature (the test suite's); a user's binary has no such flag.
    #[cfg(feature = "fault-injection")]
    #[cfg_attr(feature = "cli", arg(long, env = "SYLVA_DEBUG_CRASH_AT"))]
    pub debug_crash_at: Option<CrashPoint>,
}

/// Where `--debug-crash-at` kills the worker process: inside `stage`, once the stage reports
/// progress at or above `fraction` (of the stage, in [0, 1]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CrashPoint {
    pub stage: Stage,
    pub fraction: f64,
}

impl CrashPoint {
    /// The fraction when `STAGE` is given alone: half-way through the stage.
    pub const DEFAULT_FRACTION: f64 = 0.5;
}

impl std::str::FromStr for CrashPoint {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, String> {
        let (name, fraction) = match text.split_once(':') {
            Some((n, f)) => (n.trim(), Some(f.trim())),
            None => (text.trim(), None),
        };
        let stage = Stage::from_name(name).ok_or_else(|| {
            let names: Vec<&str> = Stage::ALL.iter().map(|s| s.name()).collect();
            format!("{name:?} is not a stage; stages: {}", names.join(", "))
        })?;
        let fraction = match fraction {
            None => Self::DEFAULT_FRACTION,
            Some(f) => f
                .parse::<f64>()
                .ok()
                .filter(|f| (0.0..=1.0).contains(f))
                .ok_or_else(|| format!("{f:?} is not a fraction in [0, 1]"))?,
        };
        Ok(Self { stage, fraction })
    }
}

/// The value for `stage` in a per-stage setting of `flag`: comma-separated items, each a
/// number (for every stage) or `stage=number` (for that stage, winning over the former).
fn per_stage(flag: &str, text: &str, stage: &str) -> Result<Option<u64>, String> {
    let mut default = None;
    let mut own = None;
    for item in text.split(',').map(str::trim).filter(|s| !s.is_empty()) {
        let (name, value) = match item.split_once('=') {
            Some((n, v)) => (Some(n.trim()), v.trim()),
            None => (None, item),
        };
        let value: u64 = value
            .parse()
            .map_err(|_| format!("{flag}: {item:?} is not a whole number"))?;
        match name {
            None => default = Some(value),
            Some(n) if n == stage => own = Some(value),
            Some(_) => {}
        }
    }
    Ok(own.or(default))
}

impl WorkerArgs {
    pub fn lease(&self) -> Duration {
        Duration::from_secs(self.lease_secs.max(1))
    }

    /// The runtime limit of `stage` from --max-stage-secs.
    pub fn max_stage_runtime(&self, stage: &str) -> Result<Duration, String> {
        let secs = per_stage("--max-stage-secs", &self.max_stage_secs, stage)?;
        Ok(Duration::from_secs(secs.unwrap_or(172_800).max(1)))
    }

    /// The injected pause before `stage` from --debug-stage-pause-ms.
    pub fn debug_stage_pause(&self, stage: &str) -> Result<Duration, String> {
        let ms = per_stage("--debug-stage-pause-ms", &self.debug_stage_pause_ms, stage)?;
        Ok(Duration::from_millis(ms.unwrap_or(0)))
    }

    /// Checks the per-stage settings once, at start, so a typo stops the process with a
    /// clear message instead of being ignored.
    pub fn validate(&self) -> Result<(), String> {
        self.max_stage_runtime("")?;
        self.debug_stage_pause("")?;
        Ok(())
    }
}

/// Settings of the HTTP API.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "cli", derive(clap::Args))]
pub struct ApiArgs {
    /// Address to listen on (port 0 picks a free port; the chosen address is printed).
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_LISTEN", default_value = "127.0.0.1:8080")
    )]
    pub listen: SocketAddr,

    /// Static bearer tokens accepted by the API, comma-separated, each its own owner (for
    /// fixed set-ups; `sylva keys create` makes managed keys with quotas, expiry and
    /// revocation). With none and no managed key ever created, authentication is off (a local
    /// single-user run).
    #[cfg_attr(
        feature = "cli",
        arg(
            long,
            env = "SYLVA_TOKEN",
            value_delimiter = ',',
            hide_env_values = true
        )
    )]
    pub token: Vec<String>,

    /// Web origins (`scheme://host[:port]`) whose pages may call the API from a browser,
    /// comma-separated, e.g. a CesiumJS or other digital-twin front end at
    /// `https://twin.example.org` loading a job's tileset with the caller's key; `*` allows
    /// any origin. Answers then carry CORS headers (preflights included) that allow the
    /// `Authorization` header and expose `ETag`, `Location` and the rate-limit headers. Default
    /// none: only the server's own page (same origin) calls it from a browser.
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_CORS_ORIGIN", value_delimiter = ',')
    )]
    pub cors_origin: Vec<String>,

    /// Seconds after `POST /v1/webhooks/secret/rotate` during which deliveries are signed with
    /// the old secret too (a second `v1=` entry), so a receiver can switch without missing
    /// one. Default 86400 (a day), as long as a receiver's operator may need to notice.
    #[cfg_attr(
        feature = "cli",
        arg(
            long,
            env = "SYLVA_WEBHOOK_ROTATION_GRACE_SECS",
            default_value_t = 86_400
        )
    )]
    pub webhook_rotation_grace_secs: u64,

    /// Upload part size in bytes (default 8 MiB: large enough for throughput, small enough
    /// that a dropped connection loses little).
    #[cfg_attr(feature = "cli", arg(long, env = "SYLVA_PART_SIZE", default_value_t = 8 * MIB))]
    pub part_size: u64,

    /// Largest upload accepted, in bytes (default 100 GiB).
    #[cfg_attr(feature = "cli", arg(long, env = "SYLVA_MAX_UPLOAD_BYTES", default_value_t = 100 * GIB))]
    pub max_upload_bytes: u64,

    /// Largest JSON request body, in bytes (default 1 MiB).
    #[cfg_attr(feature = "cli", arg(long, env = "SYLVA_MAX_JSON_BYTES", default_value_t = MIB))]
    pub max_json_bytes: u64,

    /// Largest one-request multipart job submission, in bytes (default 2 GiB; use resumable
    /// uploads for more).
    #[cfg_attr(feature = "cli", arg(long, env = "SYLVA_MAX_MULTIPART_BYTES", default_value_t = 2 * GIB))]
    pub max_multipart_bytes: u64,

    /// Most entries an uploaded archive may hold.
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_MAX_ARCHIVE_ENTRIES", default_value_t = 100_000)
    )]
    pub max_archive_entries: u64,

    /// Most bytes an uploaded archive may unpack to (default 200 GiB).
    #[cfg_attr(feature = "cli", arg(long, env = "SYLVA_MAX_UNPACKED_BYTES", default_value_t = 200 * GIB))]
    pub max_unpacked_bytes: u64,

    /// Largest unpacked/packed ratio of an archive (default 200: photos barely compress, a
    /// zip bomb compresses a thousandfold).
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_MAX_UNPACK_RATIO", default_value_t = 200.0)
    )]
    pub max_unpack_ratio: f64,

    /// Queued jobs above which new submissions get 429 with Retry-After.
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_MAX_QUEUED_JOBS", default_value_t = 1000)
    )]
    pub max_queued_jobs: u64,

    /// Timeout of ordinary requests in seconds (uploads of parts and event streams excepted).
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_REQUEST_TIMEOUT_SECS", default_value_t = 30)
    )]
    pub request_timeout_secs: u64,

    /// Timeout of one upload part or multipart submission in seconds.
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_UPLOAD_TIMEOUT_SECS", default_value_t = 3600)
    )]
    pub upload_timeout_secs: u64,

    /// /readyz fails and uploads get 507 when free disk drops below this many bytes.
    #[cfg_attr(feature = "cli", arg(long, env = "SYLVA_MIN_FREE_BYTES", default_value_t = GIB))]
    pub min_free_bytes: u64,

    /// Seconds an incomplete upload stays resumable (default 86400: a day, enough for a
    /// field laptop on a poor connection).
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_UPLOAD_TTL_SECS", default_value_t = 86_400)
    )]
    pub upload_ttl_secs: u64,

    /// With an S3 store, artifacts of at least this many bytes are downloaded through a
    /// redirect to a presigned URL instead of through the API (default 16 MiB: splat files,
    /// clouds; CSVs and reports stay on the API).
    #[cfg_attr(feature = "cli", arg(long, env = "SYLVA_PRESIGN_MIN_BYTES", default_value_t = 16 * MIB))]
    pub presign_min_bytes: u64,

    /// Bytes one token may keep on the server: its uploads (declared sizes, open or complete)
    /// plus its jobs' artifacts. Past it, new uploads get 429 with Retry-After. 0 (the
    /// default): no quota.
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_QUOTA_BYTES", default_value_t = 0)
    )]
    pub quota_bytes: u64,

    /// Unfinished jobs (queued, running or canceling) one token may have at a time; past it,
    /// submissions get 429 with Retry-After. 0 (the default): no quota.
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_QUOTA_JOBS", default_value_t = 0)
    )]
    pub quota_jobs: u64,

    #[cfg_attr(feature = "cli", command(flatten))]
    pub retention: RetentionArgs,

    /// Seconds a presigned download URL stays valid (default 900: long enough to start a
    /// large download, short enough that a leaked link soon dies).
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_PRESIGN_TTL_SECS", default_value_t = 900)
    )]
    pub presign_ttl_secs: u64,
}

/// Settings of outgoing webhooks: `sylva serve` checks a job's webhook when it is submitted
/// and sends deliveries, `sylva worker` sends them too (every process that shares the
/// database must be given the same values).
#[derive(Debug, Clone)]
#[cfg_attr(feature = "cli", derive(clap::Args))]
pub struct WebhookArgs {
    /// Server key from which each API key's webhook signing secret is derived (HMAC-SHA256
    /// of the owner id and rotation generation under this key; `GET /v1/webhooks/secret`
    /// shows a caller its secret). Every API replica and worker must have the same key. Default: a random key
    /// generated by the first process and kept in the job database, so all processes that
    /// share the database agree; changing it changes every secret.
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_WEBHOOK_KEY", hide_env_values = true)
    )]
    pub webhook_key: Option<String>,

    /// Allow webhook URLs whose host is (or resolves to) a private, loopback, link-local,
    /// unique-local, multicast, reserved or unspecified address. Off by default, so a job's
    /// webhook cannot reach into the server's own network.
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_WEBHOOK_ALLOW_PRIVATE", default_value_t = false)
    )]
    pub webhook_allow_private: bool,

    /// Networks allowed as webhook targets although not public, comma-separated CIDRs
    /// (e.g. `10.20.0.0/16,fd00:1::/64`), for receivers inside the operator's network.
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_WEBHOOK_ALLOW_CIDR", value_delimiter = ',')
    )]
    pub webhook_allow_cidr: Vec<String>,

    /// Seconds one delivery attempt may take (connect, send, answer) before it counts as
    /// failed (default 10).
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_WEBHOOK_TIMEOUT_SECS", default_value_t = 10)
    )]
    pub webhook_timeout_secs: u64,

    /// Delay before the first retry, in milliseconds; it doubles with each failed attempt,
    /// with jitter (each delay is drawn from its upper half). Default 1000.
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_WEBHOOK_BACKOFF_MS", default_value_t = 1000)
    )]
    pub webhook_backoff_ms: u64,

    /// Longest delay between two attempts, in milliseconds (default 3600000: an hour).
    #[cfg_attr(
        feature = "cli",
        arg(
            long,
            env = "SYLVA_WEBHOOK_BACKOFF_MAX_MS",
            default_value_t = 3_600_000
        )
    )]
    pub webhook_backoff_max_ms: u64,

    /// Attempts after which a delivery is given up (default 30: with the default backoff,
    /// about 19 hours of trying).
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_WEBHOOK_MAX_ATTEMPTS", default_value_t = 30)
    )]
    pub webhook_max_attempts: u32,

    /// Seconds after its event past which a failing delivery is given up, whatever its
    /// attempts (default 86400: a day).
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_WEBHOOK_MAX_AGE_SECS", default_value_t = 86_400)
    )]
    pub webhook_max_age_secs: u64,

    /// How often a process looks for due deliveries, in milliseconds (default 1000).
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_WEBHOOK_POLL_MS", default_value_t = 1000)
    )]
    pub webhook_poll_ms: u64,
}

impl WebhookArgs {
    /// The time one attempt may take.
    pub fn timeout(&self) -> Duration {
        Duration::from_secs(self.webhook_timeout_secs.max(1))
    }
}

/// How long finished work is kept (in `sylva serve`, which sweeps periodically, and in
/// `sylva gc`, which sweeps once).
#[derive(Debug, Clone)]
#[cfg_attr(feature = "cli", derive(clap::Args))]
pub struct RetentionArgs {
    /// Seconds a finished job keeps its files (artifacts, stage outputs) after it ends; then
    /// they are removed and its artifacts answer 410 Gone (the job record stays). A complete
    /// upload that no job with files still reads is removed the same time after completion.
    /// 0: keep everything. Default 2592000 (30 days); each job shows its `expires_at`.
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_JOB_RETENTION_SECS", default_value_t = 2_592_000)
    )]
    pub job_retention_secs: u64,

    /// Seconds between two retention sweeps in `sylva serve` (0: never; run `sylva gc`
    /// instead, e.g. from cron). Default 600.
    #[cfg_attr(
        feature = "cli",
        arg(long, env = "SYLVA_GC_INTERVAL_SECS", default_value_t = 600)
    )]
    pub gc_interval_secs: u64,
}

impl RetentionArgs {
    /// How long a finished job keeps its files; `None`: for ever.
    pub fn job_retention(&self) -> Option<Duration> {
        (self.job_retention_secs > 0).then(|| Duration::from_secs(self.job_retention_secs))
    }
}

impl ApiArgs {
    pub fn extract_limits(&self) -> ExtractLimits {
        ExtractLimits {
            max_entries: self.max_archive_entries,
            max_unpacked_bytes: self.max_unpacked_bytes,
            max_ratio: self.max_unpack_ratio,
        }
    }
}

/// Sets up logging to stderr. Tokens never reach the log: no layer records headers.
pub fn init_tracing(args: &StoreArgs) {
    let filter = tracing_subscriber::EnvFilter::try_new(&args.log)
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    if args.log_json {
        let _ = builder.json().try_init();
    } else {
        let _ = builder.try_init();
    }
}

// The tests parse flags, so they need clap.
#[cfg(all(test, feature = "cli"))]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct W {
        #[command(flatten)]
        w: WorkerArgs,
    }

    #[test]
    fn stage_limits_take_a_default_and_per_stage_overrides() {
        let w = W::parse_from(["x", "--max-stage-secs", "7200, train=172800"]).w;
        assert_eq!(w.max_stage_runtime("ingest"), Ok(Duration::from_secs(7200)));
        assert_eq!(
            w.max_stage_runtime("train"),
            Ok(Duration::from_secs(172_800))
        );
        let w = W::parse_from(["x", "--max-stage-secs", "dbh=60"]).w;
        assert_eq!(w.max_stage_runtime("dbh"), Ok(Duration::from_secs(60)));
        assert_eq!(
            w.max_stage_runtime("train"),
            Ok(Duration::from_secs(172_800))
        );
        let w = W::parse_from(["x", "--max-stage-secs", "train=soon"]).w;
        assert!(w.max_stage_runtime("ingest").is_err());
        let w = W::parse_from(["x", "--debug-stage-pause-ms", "train=500"]).w;
        assert_eq!(w.debug_stage_pause("train"), Ok(Duration::from_millis(500)));
        assert_eq!(w.debug_stage_pause("ingest"), Ok(Duration::ZERO));
        assert!(w.validate().is_ok());
    }

    #[test]
    #[cfg(feature = "fault-injection")]
    fn crash_points_name_a_stage_and_an_optional_fraction() {
        let w = W::parse_from(["x", "--debug-crash-at", "train:0.25"]).w;
        assert_eq!(
            w.debug_crash_at,
            Some(CrashPoint {
                stage: Stage::Train,
                fraction: 0.25
            })
        );
        let w = W::parse_from(["x", "--debug-crash-at", "dbh"]).w;
        assert_eq!(
            w.debug_crash_at,
            Some(CrashPoint {
                stage: Stage::Dbh,
                fraction: CrashPoint::DEFAULT_FRACTION
            })
        );
        assert_eq!(W::parse_from(["x"]).w.debug_crash_at, None);
        for bad in ["fly", "train:2", "train:half", "train:-0.1"] {
            assert!(
                W::try_parse_from(["x", "--debug-crash-at", bad]).is_err(),
                "{bad}"
            );
        }
    }
}
