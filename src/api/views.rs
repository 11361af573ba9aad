//! The JSON shapes the API returns (openapi.yaml `components.schemas`), built from records.

use serde_json::{Value, json};

use crate::jobs::{
    DeliveryRecord, JobRecord, JobState, UploadRecord, WebhookSpec, now_ms, rfc3339,
};

fn ts(ms: Option<i64>) -> Value {
    ms.map(|m| Value::String(rfc3339(m))).unwrap_or(Value::Null)
}

/// Percent-encodes an artifact name for use in a URL path segment (keeps `/`).
fn encode_path(name: &str) -> String {
    let mut out = String::with_capacity(name.len());
    for b in name.bytes() {
        if b.is_ascii_alphanumeric() || b"-._~/".contains(&b) {
            out.push(b as char);
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}

/// Seconds left, extrapolated from elapsed time and progress while a job runs.
fn eta_seconds(job: &JobRecord) -> Value {
    match (job.state, job.started_at) {
        (JobState::Running, Some(start)) if job.progress > 0.01 && job.progress < 1.0 => {
            let elapsed = (now_ms() - start).max(0) as f64 / 1000.0;
            json!(elapsed * (1.0 - job.progress) / job.progress)
        }
        _ => Value::Null,
    }
}

/// A job as the API shows it; `retention` (how long a finished job keeps its files, `None`
/// for ever) gives its `expires_at`.
pub fn job(j: &JobRecord, retention: Option<std::time::Duration>) -> Value {
    let expires_at = match (j.finished_at, retention) {
        (Some(end), Some(keep)) if j.state.is_terminal() => {
            json!(rfc3339(end.saturating_add(keep.as_millis() as i64)))
        }
        _ => Value::Null,
    };
    let base = format!("/v1/jobs/{}", j.id);
    let stages: Vec<Value> = j
        .stages
        .iter()
        .map(|s| {
            let duration = match (s.started_at, s.finished_at) {
                (Some(a), Some(b)) if b >= a => json!((b - a) as f64 / 1000.0),
                _ => Value::Null,
            };
            json!({
                "name": s.name,
                "state": s.state.as_str(),
                "progress": s.progress.clamp(0.0, 1.0),
                "attempt": s.attempt,
                "started_at": ts(s.started_at),
                "finished_at": ts(s.finished_at),
                "duration_seconds": duration,
                "metrics": s.metrics.clone().unwrap_or(Value::Null),
            })
        })
        .collect();
    let artifacts: Vec<Value> = j
        .artifacts
        .iter()
        .map(|a| {
            json!({
                "name": a.name,
                "stage": a.stage,
                "kind": a.kind,
                "size": a.size,
                "sha256": a.sha256,
                "content_type": a.content_type,
                "href": format!("{base}/artifacts/{}", encode_path(&a.name)),
            })
        })
        .collect();
    json!({
        "id": j.id,
        "owner": j.owner,
        "state": j.state.as_str(),
        "stage": j.stage,
        "stages": stages,
        "progress": j.progress.clamp(0.0, 1.0),
        "attempt": j.attempt,
        "created_at": rfc3339(j.created_at),
        "updated_at": rfc3339(j.updated_at),
        "started_at": ts(j.started_at),
        "finished_at": ts(j.finished_at),
        "expires_at": expires_at,
        "purged_at": ts(j.purged_at),
        "eta_seconds": eta_seconds(j),
        "error": j.error.clone().unwrap_or(Value::Null),
        "inputs": j.inputs,
        "params": j.params,
        "webhook": j.webhook.as_ref().map(webhook).unwrap_or(Value::Null),
        "artifacts": artifacts,
        "links": {
            "self": base,
            "webhooks": format!("{base}/webhooks"),
            "events": format!("{base}/events"),
            "log": format!("{base}/log"),
            "results": format!("{base}/results"),
            "trees_csv": format!("{base}/trees.csv"),
        },
    })
}

/// A job's webhook as submitted.
pub fn webhook(w: &WebhookSpec) -> Value {
    json!({
        "url": w.url,
        "events": w.events,
    })
}

/// One webhook delivery.
pub fn delivery(d: &DeliveryRecord) -> Value {
    json!({
        "id": d.id,
        "event": d.event,
        "url": d.url,
        "state": d.state.as_str(),
        "attempts": d.attempts,
        "next_attempt_at": ts(d.next_attempt_at),
        "last_status": d.last_status,
        "last_error": d.last_error,
        "created_at": rfc3339(d.created_at),
        "finished_at": ts(d.finished_at),
    })
}

pub fn upload(u: &UploadRecord) -> Value {
    let received: Vec<i64> = u.parts.iter().map(|p| p.0).collect();
    json!({
        "id": u.id,
        "owner": u.owner,
        "kind": u.kind.as_str(),
        "filename": u.filename,
        "size": u.size,
        "sha256": u.sha256,
        "part_size": u.part_size,
        "parts_total": u.parts_total(),
        "parts_received": received,
        "bytes_received": u.bytes_received(),
        "state": if u.complete {
            "complete"
        } else if u.expired || crate::jobs::now_ms() > u.expires_at {
            "expired"
        } else {
            "open"
        },
        "created_at": rfc3339(u.created_at),
        "expires_at": rfc3339(u.expires_at),
        "completed_at": ts(u.completed_at),
        "inspection": u.inspection.clone().unwrap_or(Value::Null),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn artifact_names_are_encoded_but_keep_slashes() {
        assert_eq!(encode_path("ingest/report.json"), "ingest/report.json");
        assert_eq!(encode_path("a b/c#d"), "a%20b/c%23d");
    }
}
