//! Retention: the sweep that removes what no one may ask for any more.
//!
//! Three kinds of leftovers, each found through the job database and removed from the blob
//! store (local folder and object store alike):
//! - open uploads past their `expires_at` (a client that never came back), and complete
//!   uploads, finished longer ago than the job retention, that no job with files still reads;
//!   their record stays, marked `expired`, so the API answers 410 Gone rather than 404;
//! - finished jobs older than the job retention: their files and artifact rows go, the job
//!   record, its stage metrics and its log stay (`purged_at` set; artifacts answer 410);
//! - folders under the local data directory that belong to no live record (a crash between
//!   the database and the file system), once older than [`ORPHAN_MIN_AGE`] so a transfer
//!   that is still writing is never touched.
//!
//! The database is marked first and the files removed after, so a crash in between only
//! leaves orphans, which the next sweep removes.

use std::path::Path;
use std::time::{Duration, SystemTime};

use serde::Serialize;

use crate::config::RetentionArgs;
use crate::jobs::{DbError, JobStore, LiveTable, now_ms};
use crate::store::BlobStore;

/// Records handled per database round trip: a sweep after a long pause works in bounded
/// transactions.
const BATCH: i64 = 200;
/// Folders asked about in one `live_ids` query by the orphan sweep.
const ORPHAN_BATCH: usize = 500;

/// A folder with no live record is removed only once it is this old (a multipart submission
/// writes its files before its record exists). One hour: longer than any single request.
pub const ORPHAN_MIN_AGE: Duration = Duration::from_secs(3600);

/// What one sweep removed.
#[derive(Debug, Default, Clone, PartialEq, Eq, Serialize)]
pub struct SweepReport {
    /// Uploads marked expired (open past their deadline, or complete and unused).
    pub uploads_expired: u64,
    /// Finished jobs whose files were removed.
    pub jobs_purged: u64,
    /// Local folders removed that no record owned.
    pub orphans_removed: u64,
    /// Bytes freed on the local disk (the object store's are not counted).
    pub bytes_freed: u64,
}

impl SweepReport {
    pub fn is_empty(&self) -> bool {
        self.uploads_expired == 0 && self.jobs_purged == 0 && self.orphans_removed == 0
    }
}

/// One retention sweep, at the time `now_ms()`.
pub async fn sweep(
    db: &JobStore,
    blobs: &BlobStore,
    retention: &RetentionArgs,
) -> Result<SweepReport, DbError> {
    let now = now_ms();
    let keep = retention
        .job_retention()
        .map(|d| i64::try_from(d.as_millis()).unwrap_or(i64::MAX));
    // With retention off, no complete upload and no finished job is ever old enough.
    let before = keep.map(|k| now.saturating_sub(k)).unwrap_or(i64::MIN);
    let mut report = SweepReport::default();

    // Jobs first: the uploads their purge leaves unread expire in the same sweep.
    for table in [LiveTable::Jobs, LiveTable::Uploads] {
        loop {
            let ids = match table {
                LiveTable::Jobs => db.purge_jobs(before, BATCH).await?,
                LiveTable::Uploads => db.expire_uploads(now, before, BATCH).await?,
            };
            for id in &ids {
                report.bytes_freed += remove_files(blobs, table, id).await;
            }
            let n = ids.len() as u64;
            match table {
                LiveTable::Jobs => report.jobs_purged += n,
                LiveTable::Uploads => report.uploads_expired += n,
            }
            if (ids.len() as i64) < BATCH {
                break;
            }
        }
    }
    remove_orphans(db, blobs, &mut report).await?;
    Ok(report)
}

/// Removes the files of the job or upload `id` that the database has just marked purged or
/// expired; returns the bytes its local folder held. A failure is logged, not returned: the
/// record is marked already, so the next sweep finds the folder as an orphan.
async fn remove_files(blobs: &BlobStore, table: LiveTable, id: &str) -> u64 {
    let bytes = dir_size(&match table {
        LiveTable::Jobs => blobs.job_dir(id),
        LiveTable::Uploads => blobs.upload_dir(id),
    });
    let removed = match table {
        LiveTable::Jobs => blobs.remove_job(id).await,
        LiveTable::Uploads => blobs.remove_upload(id).await,
    };
    match removed {
        Ok(()) => tracing::info!(?table, id, "past retention; files removed"),
        Err(e) => {
            tracing::warn!(?table, id, error = %e, "could not remove the files of a record past retention")
        }
    }
    bytes
}

/// Removes local folders under `uploads/` and `jobs/` that no live record owns.
async fn remove_orphans(
    db: &JobStore,
    blobs: &BlobStore,
    report: &mut SweepReport,
) -> Result<(), DbError> {
    for table in [LiveTable::Uploads, LiveTable::Jobs] {
        let sub = match table {
            LiveTable::Uploads => "uploads",
            LiveTable::Jobs => "jobs",
        };
        let Ok(entries) = std::fs::read_dir(blobs.root().join(sub)) else {
            continue;
        };
        // The folders old enough to judge, then one question to the database per batch.
        let mut old: Vec<(String, std::path::PathBuf)> = entries
            .flatten()
            .filter(|e| old_enough(&e.path()))
            .filter_map(|e| Some((e.file_name().to_str()?.to_string(), e.path())))
            .collect();
        old.sort();
        for batch in old.chunks(ORPHAN_BATCH) {
            let ids: Vec<String> = batch.iter().map(|(id, _)| id.clone()).collect();
            let live: std::collections::HashSet<String> =
                db.live_ids(table, &ids).await?.into_iter().collect();
            for (id, path) in batch {
                if live.contains(id) {
                    continue;
                }
                report.bytes_freed += dir_size(path);
                match std::fs::remove_dir_all(path) {
                    Ok(()) => {
                        report.orphans_removed += 1;
                        tracing::info!(folder = %path.display(), "orphaned folder removed");
                    }
                    Err(e) => {
                        tracing::warn!(folder = %path.display(), error = %e, "could not remove an orphaned folder");
                    }
                }
            }
        }
    }
    Ok(())
}

fn old_enough(path: &Path) -> bool {
    std::fs::metadata(path)
        .and_then(|m| m.modified())
        .ok()
        .and_then(|t| SystemTime::now().duration_since(t).ok())
        .is_some_and(|age| age >= ORPHAN_MIN_AGE)
}

/// Bytes of the files under `path` (0 when it does not exist).
fn dir_size(path: &Path) -> u64 {
    let Ok(meta) = std::fs::symlink_metadata(path) else {
        return 0;
    };
    if !meta.is_dir() {
        return meta.len();
    }
    std::fs::read_dir(path)
        .map(|entries| entries.flatten().map(|e| dir_size(&e.path())).sum())
        .unwrap_or(0)
}

/// Sweeps every `interval` until `stop` turns true (the first sweep one interval after
/// start, so start-up is not slowed).
pub async fn run_periodically(
    db: JobStore,
    blobs: BlobStore,
    retention: RetentionArgs,
    interval: Duration,
    mut stop: tokio::sync::watch::Receiver<bool>,
) {
    loop {
        tokio::select! {
            _ = tokio::time::sleep(interval) => {}
            _ = stop.changed() => return,
        }
        match sweep(&db, &blobs, &retention).await {
            Ok(r) if !r.is_empty() => tracing::info!(
                uploads_expired = r.uploads_expired,
                jobs_purged = r.jobs_purged,
                orphans_removed = r.orphans_removed,
                bytes_freed = r.bytes_freed,
                "retention sweep"
            ),
            Ok(_) => {}
            Err(e) => tracing::warn!(error = %e, "retention sweep failed; trying again later"),
        }
    }
}
