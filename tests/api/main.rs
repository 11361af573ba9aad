//! The API against a real server process, a real HTTP client and a real job database: the
//! tests that exercise the queue and the upload records run on SQLite and on PostgreSQL.
//! `lifecycle`: jobs from submission to results, failure, retry, cancel, idempotency;
//! `uploads`: resumable uploads, checksums, inspection, expiry; `errors`: auth, problem+json,
//! hostile archives.

#[path = "../common/mod.rs"]
mod common;
mod errors;
mod lifecycle;
mod uploads;

use std::time::Duration;

/// Longest a test waits for a job to end.
const LONG: Duration = Duration::from_secs(120);
