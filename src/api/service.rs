//! Service routes: the page, health, readiness, metrics, the contract, info and options.

use std::fmt::Write as _;

use axum::Json;
use axum::extract::{Extension, State};
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde_json::json;

use super::AppState;
use super::auth::Caller;
use super::problem::ApiError;
use crate::jobs::DeliveryState;
use crate::pipeline::{PipelineParams, Stage};

/// The contract, compiled in so the binary always serves the one it implements.
pub const OPENAPI_YAML: &str = include_str!("../../openapi.yaml");

pub async fn livez() -> Response {
    Json(json!({ "status": "ok" })).into_response()
}

pub async fn readyz(State(state): State<AppState>) -> Result<Response, ApiError> {
    if let Err(e) = state.db.ping().await {
        return Err(ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "not-ready",
            format!("the database is not answering: {e}"),
        ));
    }
    if let Some(remote) = state.blobs.remote()
        && let Err(e) = remote.ping().await
    {
        return Err(ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "not-ready",
            format!("the object store is not answering: {e}"),
        ));
    }
    let free = state.blobs.free_bytes()?;
    if free < state.args.min_free_bytes {
        return Err(ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "not-ready",
            format!(
                "only {free} bytes free on the data disk; at least {} are required",
                state.args.min_free_bytes
            ),
        ));
    }
    Ok(
        Json(
            json!({ "status": "ready", "database": "ok", "store": "ok", "disk_free_bytes": free }),
        )
        .into_response(),
    )
}

pub async fn openapi() -> Response {
    ([(header::CONTENT_TYPE, "application/yaml")], OPENAPI_YAML).into_response()
}

/// Upper bounds (seconds) of the stage duration histogram: from a quick ingest to a long
/// training run.
const BUCKETS: &[f64] = &[1.0, 5.0, 15.0, 60.0, 300.0, 900.0, 3600.0, 14400.0];

pub async fn metrics(State(state): State<AppState>) -> Result<Response, ApiError> {
    let mut out = String::new();
    let counts = state.db.count_by_state().await?;
    let _ = writeln!(
        out,
        "# HELP sylva_jobs Jobs by state.\n# TYPE sylva_jobs gauge"
    );
    for (s, n) in &counts {
        let _ = writeln!(out, "sylva_jobs{{state=\"{}\"}} {n}", s.as_str());
    }
    let queued = counts
        .iter()
        .find(|(s, _)| s.as_str() == "queued")
        .map(|(_, n)| *n)
        .unwrap_or(0);
    let _ = writeln!(
        out,
        "# HELP sylva_queue_depth Jobs waiting for a worker.\n# TYPE sylva_queue_depth gauge\nsylva_queue_depth {queued}"
    );
    let workers = state.db.live_workers(state.lease * 2).await?;
    let _ = writeln!(
        out,
        "# HELP sylva_workers Worker slots seen recently.\n# TYPE sylva_workers gauge\nsylva_workers {workers}"
    );
    let deliveries = state.db.count_deliveries().await?;
    let _ = writeln!(
        out,
        "# HELP sylva_webhook_deliveries Webhook deliveries by state (pending: not yet acknowledged).\n# TYPE sylva_webhook_deliveries gauge"
    );
    for s in DeliveryState::ALL {
        let n = deliveries
            .iter()
            .find(|(st, _)| st == s)
            .map(|(_, n)| *n)
            .unwrap_or(0);
        let _ = writeln!(
            out,
            "sylva_webhook_deliveries{{state=\"{}\"}} {n}",
            s.as_str()
        );
    }
    let _ = writeln!(
        out,
        "# HELP sylva_stage_duration_seconds Duration of finished stages.\n# TYPE sylva_stage_duration_seconds histogram"
    );
    let durations = state.db.stage_durations().await?;
    for stage in Stage::ALL {
        let ds: Vec<f64> = durations
            .iter()
            .filter(|(n, _)| n == stage.name())
            .map(|(_, d)| *d)
            .collect();
        for b in BUCKETS {
            let c = ds.iter().filter(|d| **d <= *b).count();
            let _ = writeln!(
                out,
                "sylva_stage_duration_seconds_bucket{{stage=\"{stage}\",le=\"{b}\"}} {c}"
            );
        }
        let _ = writeln!(
            out,
            "sylva_stage_duration_seconds_bucket{{stage=\"{stage}\",le=\"+Inf\"}} {}",
            ds.len()
        );
        let _ = writeln!(
            out,
            "sylva_stage_duration_seconds_sum{{stage=\"{stage}\"}} {}",
            ds.iter().sum::<f64>()
        );
        let _ = writeln!(
            out,
            "sylva_stage_duration_seconds_count{{stage=\"{stage}\"}} {}",
            ds.len()
        );
    }
    let bytes = state
        .counters
        .upload_bytes
        .load(std::sync::atomic::Ordering::Relaxed);
    let _ = writeln!(
        out,
        "# HELP sylva_upload_bytes_total Upload bytes received by this process.\n# TYPE sylva_upload_bytes_total counter\nsylva_upload_bytes_total {bytes}"
    );
    let _ = writeln!(
        out,
        "# HELP sylva_http_requests_total HTTP responses by status.\n# TYPE sylva_http_requests_total counter"
    );
    if let Ok(m) = state.counters.http_requests.lock() {
        for (status, n) in m.iter() {
            let _ = writeln!(out, "sylva_http_requests_total{{status=\"{status}\"}} {n}");
        }
    }
    Ok(([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], out).into_response())
}

pub async fn info(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
) -> Result<Response, ApiError> {
    let a = &state.args;
    let auth = super::auth::auth_required(&state).await?;
    let queued = state
        .db
        .count_by_state()
        .await?
        .into_iter()
        .find(|(s, _)| s.as_str() == "queued")
        .map(|(_, n)| n)
        .unwrap_or(0);
    let workers = state.db.live_workers(state.lease * 2).await?;
    Ok(Json(json!({
        "version": env!("CARGO_PKG_VERSION"),
        "database": state.db.backend_name(),
        "store": state.blobs.kind(),
        "queue_depth": queued,
        "workers": workers,
        "gpu": state.gpu,
        "auth": auth,
        "caller": {
            "owner": caller.owner,
            "admin": caller.admin,
            "key": caller.key_name,
        },
        "stages": Stage::ALL.iter().map(|s| s.name()).collect::<Vec<_>>(),
        "limits": {
            "part_size": a.part_size,
            "max_upload_bytes": a.max_upload_bytes,
            "max_json_bytes": a.max_json_bytes,
            "max_multipart_bytes": a.max_multipart_bytes,
            "max_archive_entries": a.max_archive_entries,
            "max_unpacked_bytes": a.max_unpacked_bytes,
            "max_queued_jobs": a.max_queued_jobs,
            "quota_bytes": caller.quota_bytes.map_or(a.quota_bytes, |q| q.max(0) as u64),
            "quota_jobs": caller.quota_jobs.map_or(a.quota_jobs as i64, |q| q),
            "job_retention_secs": a.retention.job_retention_secs,
            "upload_ttl_secs": a.upload_ttl_secs,
        },
    }))
    .into_response())
}

pub async fn options() -> Response {
    Json(json!({
        "stages": Stage::ALL.iter().map(|s| s.name()).collect::<Vec<_>>(),
        "inputs": {
            "required": ["lidar"],
            "one_of": ["photos", "colmap"],
            "optional": ["control_points", "field_dbh"],
            "kinds": {
                "lidar": "point cloud in metres: LAS, LAZ, PLY, E57 or XYZ",
                "photos": "zip or tar of JPEG, PNG or TIFF photos (at least 3); stage sfm runs COLMAP on them",
                "colmap": "zip or tar of a COLMAP project: images/ and sparse/0 (or sparse/)",
                "control_points": "CSV sfm_x,sfm_y,sfm_z,lidar_x,lidar_y,lidar_z, at least 4 pairs",
                "field_dbh": "CSV x,y,dbh_cm of tape-measured trees",
            },
        },
        "defaults": PipelineParams::default(),
        "schema": PipelineParams::schema(),
    }))
    .into_response()
}
