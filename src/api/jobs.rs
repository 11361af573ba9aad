//! Jobs: create (JSON or one multipart request), list, get, log, cancel, retry, delete,
//! results.

use std::collections::HashMap;

use axum::Json;
use axum::body::Bytes;
use axum::extract::{Extension, FromRequest, Multipart, Query, Request, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use serde_json::{Value, json};
use sha2::{Digest, Sha256};

use super::auth::Caller;
use super::problem::ApiError;
use super::uploads::{self, new_id};
use super::{AppState, IdRequest, count_upload_bytes, views};
use crate::jobs::{Admission, Created, NewJob, WebhookSpec};
use crate::jobs::{JobInputs, JobRecord, JobState, UploadKind, UploadRecord, now_ms};
use crate::pipeline::{PipelineParams, Stage};

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct JobCreate {
    inputs: JobInputs,
    #[serde(default)]
    params: Option<Value>,
    #[serde(default)]
    webhook: Option<Value>,
}

/// The job `id` if `caller` may see it; another owner's job answers exactly as a missing one
/// (404, the same body), so existence does not leak.
pub async fn load(state: &AppState, caller: &Caller, id: &str) -> Result<JobRecord, ApiError> {
    caller
        .load_visible("job", id, || state.db.get_job(id), |j: &JobRecord| &j.owner)
        .await
}

fn json_error(e: serde_json::Error, what: &str) -> ApiError {
    use serde_json::error::Category;
    match e.classify() {
        Category::Data => ApiError::unprocessable(format!("{what}: {e}")),
        _ => ApiError::bad_request(format!("{what} is not valid JSON: {e}")),
    }
}

/// Parses job parameters, filling defaults; unknown keys are refused.
fn effective_params(params: Option<Value>) -> Result<Value, ApiError> {
    let parsed: PipelineParams = match params {
        None | Some(Value::Null) => PipelineParams::default(),
        Some(v @ Value::Object(_)) => serde_json::from_value(v).map_err(|e| {
            ApiError::unprocessable(format!("params: {e}")).with_error("params", e.to_string())
        })?,
        Some(_) => {
            return Err(ApiError::unprocessable("params must be a JSON object")
                .with_error("params", "not an object"));
        }
    };
    if let Some(text) = &parsed.crs
        && let Err(e) = crate::io::crs::Crs::parse_projected(text)
    {
        return Err(ApiError::unprocessable(format!("params.crs: {e}"))
            .with_error("params.crs", e.to_string()));
    }
    if let Err(e) = parsed.segment.allometry.validate() {
        return Err(
            ApiError::unprocessable(format!("params.segment.allometry: {e}"))
                .with_error("params.segment.allometry", e.to_string()),
        );
    }
    serde_json::to_value(parsed).map_err(ApiError::internal)
}

fn idempotency_key(req: &Request) -> Result<Option<String>, ApiError> {
    let Some(v) = req.headers().get("idempotency-key") else {
        return Ok(None);
    };
    // Printable ASCII, as openapi.yaml says (`to_str` alone would also let tabs through).
    let s = v
        .to_str()
        .ok()
        .filter(|s| s.bytes().all(|b| (b' '..=b'~').contains(&b)))
        .ok_or_else(|| ApiError::bad_request("Idempotency-Key must be printable ASCII"))?;
    if s.is_empty() || s.len() > 255 {
        return Err(ApiError::bad_request(
            "Idempotency-Key must be 1 to 255 characters",
        ));
    }
    Ok(Some(s.to_string()))
}

pub async fn create(State(state): State<AppState>, req: Request) -> Result<Response, ApiError> {
    let key = idempotency_key(&req)?;
    let caller = Caller::of(&req);
    let content_type = req
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_ascii_lowercase();
    let (inputs, params, hash, webhook) = if content_type.starts_with("application/json") {
        let limit = state.args.max_json_bytes as usize;
        let body = axum::body::to_bytes(req.into_body(), limit)
            .await
            .map_err(|_| {
                ApiError::too_large(format!("a JSON body may have at most {limit} bytes"))
            })?;
        let create: JobCreate =
            serde_json::from_slice(&body).map_err(|e| json_error(e, "the body"))?;
        if let Some(why) = create.inputs.problem() {
            return Err(ApiError::unprocessable(why).with_error("inputs", why));
        }
        let params = effective_params(create.params)?;
        let webhook = accept_webhook(&state, create.webhook).await?;
        let hash = request_hash(&hashed(
            json!({ "inputs": create.inputs, "params": params }),
            webhook.as_ref(),
        ));
        (create.inputs, params, hash, webhook)
    } else if content_type.starts_with("multipart/form-data") {
        let multipart = Multipart::from_request(req, &state)
            .await
            .map_err(|e| ApiError::bad_request(format!("multipart body: {e}")))?;
        multipart_inputs(&state, &caller, multipart).await?
    } else {
        return Err(ApiError::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported-media-type",
            "send application/json (inputs by upload id) or multipart/form-data (files)",
        ));
    };
    let parsed: PipelineParams =
        serde_json::from_value(params.clone()).map_err(ApiError::internal)?;
    let id = new_id();
    let stages = parsed.stages();
    // Idempotency keys are per owner: two keys may use the same value without meeting.
    let scoped_key = key
        .as_deref()
        .map(|k| scope_idempotency_key(&caller.owner, k));
    let job = NewJob {
        id: &id,
        inputs: &inputs,
        params: &params,
        stages: &stages,
        idempotency_key: scoped_key.as_deref(),
        request_hash: &hash,
        owner: &caller.owner,
        webhook: webhook.as_ref(),
    };
    let limits = Admission {
        max_queued: state.args.max_queued_jobs as i64,
        max_active_per_owner: caller.quota_jobs.unwrap_or(state.args.quota_jobs as i64),
    };
    let created = state.db.create_job(&job, limits).await?;
    let (id, new) = match created {
        Created::New(id) => (id, true),
        Created::Existing(id) => (id, false),
    };
    // Read the job before waking the workers, so the answer shows it as created (queued)
    // rather than whatever a worker did in between (a polling worker may still be quicker).
    let job = load(&state, &caller, &id).await?;
    if new {
        wake_workers(&state, &id).await;
        tracing::info!(job = %id, "job queued");
    }
    let mut resp = (
        StatusCode::ACCEPTED,
        Json(views::job(&job, state.retention())),
    )
        .into_response();
    if let Ok(loc) = HeaderValue::from_str(&format!("/v1/jobs/{id}")) {
        resp.headers_mut().insert(header::LOCATION, loc);
    }
    Ok(resp)
}

/// The stored form of an idempotency key: the owner id, a unit separator, then the key (the
/// key alone with authentication off, as before tenancy), so keys never meet across owners.
pub fn scope_idempotency_key(owner: &str, key: &str) -> String {
    if owner.is_empty() {
        key.to_string()
    } else {
        format!("{owner}\u{1f}{key}")
    }
}

/// 410 Gone for a job whose files retention removed.
pub fn files_kept(job: &JobRecord) -> Result<(), ApiError> {
    match job.purged_at {
        Some(at) => Err(ApiError::gone(format!(
            "job {} ended more than the retention time ago; its files were removed at {}",
            job.id,
            crate::jobs::rfc3339(at)
        ))),
        None => Ok(()),
    }
}

/// Checks a submitted webhook: its shape and events, then its URL against the target policy
/// (the host resolved; private targets refused unless configured).
async fn accept_webhook(
    state: &AppState,
    webhook: Option<Value>,
) -> Result<Option<WebhookSpec>, ApiError> {
    let Some(v) = webhook.filter(|v| !v.is_null()) else {
        return Ok(None);
    };
    let mut spec: WebhookSpec = serde_json::from_value(v).map_err(|e| {
        ApiError::unprocessable(format!("webhook: {e}")).with_error("webhook", e.to_string())
    })?;
    if spec.events.is_empty() {
        return Err(ApiError::unprocessable(
            "webhook.events is empty; name at least one event, or leave it out for the end of the job",
        )
        .with_error("webhook.events", "empty"));
    }
    let mut seen = std::collections::HashSet::new();
    spec.events.retain(|e| seen.insert(*e));
    state.webhooks.policy.check(&spec.url).await.map_err(|e| {
        ApiError::unprocessable(format!("webhook.url: {e}"))
            .with_error("webhook.url", e.to_string())
    })?;
    Ok(Some(spec))
}

/// The request as hashed for the Idempotency-Key check: `base`, with the webhook when there
/// is one (so requests without one hash as they always did).
fn hashed(mut base: Value, webhook: Option<&WebhookSpec>) -> Value {
    if let Some(w) = webhook {
        base["webhook"] = json!(w);
    }
    base
}

fn request_hash(v: &Value) -> String {
    hex::encode(Sha256::digest(v.to_string().as_bytes()))
}

/// Stores each file part of a one-request submission as a completed upload.
async fn multipart_inputs(
    state: &AppState,
    caller: &Caller,
    mut mp: Multipart,
) -> Result<(JobInputs, Value, String, Option<WebhookSpec>), ApiError> {
    let mut files: HashMap<UploadKind, (String, String)> = HashMap::new();
    let mut params: Option<Value> = None;
    let mut webhook: Option<Value> = None;
    while let Some(field) = mp
        .next_field()
        .await
        .map_err(|e| ApiError::bad_request(format!("multipart body: {e}")))?
    {
        let name = field.name().unwrap_or("").to_string();
        if name == "params" {
            let text = field
                .text()
                .await
                .map_err(|e| ApiError::bad_request(format!("multipart params: {e}")))?;
            // The part is text holding JSON; text that is not JSON is unusable content (422,
            // as openapi.yaml says), unlike a JSON body that does not parse (400).
            params = Some(serde_json::from_str(&text).map_err(|e| {
                ApiError::unprocessable(format!("params is not a JSON object: {e}"))
                    .with_error("params", e.to_string())
            })?);
            continue;
        }
        if name == "webhook" {
            let text = field
                .text()
                .await
                .map_err(|e| ApiError::bad_request(format!("multipart webhook: {e}")))?;
            webhook = Some(serde_json::from_str(&text).map_err(|e| json_error(e, "webhook"))?);
            continue;
        }
        let Some(kind) = UploadKind::parse(&name) else {
            return Err(ApiError::unprocessable(format!(
                "unknown part `{name}`; expected lidar, colmap, photos, control_points, field_dbh, params or webhook"
            )));
        };
        let filename = field
            .file_name()
            .filter(|f| !f.is_empty())
            .unwrap_or(kind.as_str())
            .chars()
            .filter(|c| !c.is_control())
            .take(255)
            .collect::<String>();
        let id = new_id();
        let (size, sha) = state
            .blobs
            .write_part(&id, 0, field, state.args.max_multipart_bytes)
            .await?;
        if size == 0 {
            return Err(ApiError::unprocessable(format!(
                "part `{name}` ({filename}) is empty"
            )));
        }
        if let Err(e) = uploads::check_byte_quota(state, caller, size).await {
            state.blobs.drop_parts(&id).await;
            return Err(e);
        }
        let now = now_ms();
        let rec = UploadRecord {
            id: id.clone(),
            kind,
            filename,
            size: size as i64,
            sha256: Some(sha.clone()),
            part_size: size as i64,
            complete: false,
            inspection: None,
            created_at: now,
            expires_at: now + state.args.upload_ttl_secs as i64 * 1000,
            completed_at: None,
            parts: vec![(0, size as i64)],
            owner: caller.owner.clone(),
            expired: false,
        };
        state.db.create_upload(&rec).await?;
        state.db.put_part(&id, 0, size as i64, &sha).await?;
        count_upload_bytes(state, size);
        uploads::finish_upload(state, &rec).await?;
        files.insert(kind, (id, sha));
    }
    let take = |k: UploadKind| files.get(&k).map(|(id, _)| id.clone());
    let Some(lidar) = take(UploadKind::Lidar) else {
        return Err(ApiError::unprocessable(
            "part `lidar` and one of `colmap` or `photos` are required",
        ));
    };
    let inputs = JobInputs {
        lidar,
        colmap: take(UploadKind::Colmap),
        photos: take(UploadKind::Photos),
        control_points: take(UploadKind::ControlPoints),
        field_dbh: take(UploadKind::FieldDbh),
    };
    if let Some(why) = inputs.problem() {
        return Err(ApiError::unprocessable(why));
    }
    let params = effective_params(params)?;
    let webhook = accept_webhook(state, webhook).await?;
    let mut hashes: Vec<(&str, &str)> = files
        .iter()
        .map(|(k, (_, sha))| (k.as_str(), sha.as_str()))
        .collect();
    hashes.sort_unstable();
    let hash = request_hash(&hashed(
        json!({ "files": hashes, "params": params }),
        webhook.as_ref(),
    ));
    Ok((inputs, params, hash, webhook))
}

fn query_int(
    q: &HashMap<String, String>,
    name: &str,
    default: i64,
    lo: i64,
    hi: i64,
) -> Result<i64, ApiError> {
    match q.get(name) {
        None => Ok(default),
        Some(v) => v
            .parse::<i64>()
            .ok()
            .filter(|n| (lo..=hi).contains(n))
            .ok_or_else(|| {
                ApiError::bad_request(format!("{name} must be an integer in {lo}..={hi}"))
            }),
    }
}

/// A page cursor as this server gives them out (openapi.yaml `cursor`: `^[1-9][0-9]{0,17}$`,
/// the job sequence number to continue below); anything else is refused, even what Rust's
/// integer parser would take (`+7`, `007`).
fn parse_cursor(c: &str) -> Option<i64> {
    let digits =
        (1..=18).contains(&c.len()) && c.bytes().all(|b| b.is_ascii_digit()) && !c.starts_with('0');
    digits.then(|| c.parse().ok()).flatten()
}

pub async fn list(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
    Query(q): Query<HashMap<String, String>>,
) -> Result<Response, ApiError> {
    let filter = match q.get("state") {
        None => None,
        Some(s) => Some(JobState::parse(s).ok_or_else(|| {
            ApiError::bad_request(format!(
                "state must be one of queued, running, succeeded, failed, canceling, canceled; got {s:?}"
            ))
        })?),
    };
    let cursor = match q.get("cursor") {
        None => None,
        Some(c) => Some(
            parse_cursor(c)
                .ok_or_else(|| ApiError::bad_request("cursor is not one this server gave out"))?,
        ),
    };
    let limit = query_int(&q, "limit", 50, 1, 200)?;
    let jobs = state
        .db
        .list_jobs(caller.list_owner(), filter, cursor, limit)
        .await?;
    let next = (jobs.len() as i64 == limit)
        .then(|| jobs.last().map(|j| j.seq.to_string()))
        .flatten();
    let views: Vec<Value> = jobs
        .iter()
        .map(|j| views::job(j, state.retention()))
        .collect();
    Ok(Json(json!({ "jobs": views, "next_cursor": next })).into_response())
}

pub async fn get(IdRequest { state, caller, id }: IdRequest) -> Result<Response, ApiError> {
    Ok(Json(views::job(
        &load(&state, &caller, &id).await?,
        state.retention(),
    ))
    .into_response())
}

pub async fn delete(IdRequest { state, caller, id }: IdRequest) -> Result<Response, ApiError> {
    load(&state, &caller, &id).await?;
    state.db.delete_job(&id).await?;
    state.blobs.remove_job(&id).await?;
    tracing::info!(job = %id, "job deleted");
    Ok(StatusCode::NO_CONTENT.into_response())
}

pub async fn log(
    IdRequest { state, caller, id }: IdRequest,
    Query(q): Query<HashMap<String, String>>,
) -> Result<Response, ApiError> {
    let since = query_int(&q, "since", 0, 0, i64::MAX)?;
    let limit = query_int(&q, "limit", 1000, 1, 10_000)?;
    load(&state, &caller, &id).await?;
    let lines = state.db.log(&id, since, limit).await?;
    let next = lines.last().map(|l| l.seq).unwrap_or(since);
    let lines: Vec<Value> = lines.iter().map(log_line).collect();
    Ok(Json(json!({ "lines": lines, "next": next })).into_response())
}

pub fn log_line(l: &crate::jobs::LogLine) -> Value {
    json!({
        "seq": l.seq,
        "ts": crate::jobs::rfc3339(l.ts),
        "level": l.level,
        "stage": l.stage,
        "message": l.message,
    })
}

pub async fn cancel(IdRequest { state, caller, id }: IdRequest) -> Result<Response, ApiError> {
    load(&state, &caller, &id).await?;
    let next = state.db.cancel(&id).await?;
    let line = format!("cancel requested; job {}", next.as_str());
    note(&state, &id, &line).await;
    accepted(&state, &caller, &id).await
}

/// Notes `message` in the job's log at level info (best effort).
async fn note(state: &AppState, id: &str, message: &str) {
    let _ = state.db.append_log(id, "info", None, message).await;
}

/// 202 Accepted with the job as it is now.
async fn accepted(state: &AppState, caller: &Caller, id: &str) -> Result<Response, ApiError> {
    let job = load(state, caller, id).await?;
    Ok((
        StatusCode::ACCEPTED,
        Json(views::job(&job, state.retention())),
    )
        .into_response())
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RetryBody {
    /// Stage to rerun from; may be left out, but not sent as `null`.
    #[serde(default, deserialize_with = "uploads::present_string")]
    from_stage: Option<String>,
}

pub async fn retry(
    IdRequest { state, caller, id }: IdRequest,
    body: Bytes,
) -> Result<Response, ApiError> {
    files_kept(&load(&state, &caller, &id).await?)?;
    let req: RetryBody = if body.iter().all(u8::is_ascii_whitespace) {
        RetryBody::default()
    } else {
        serde_json::from_slice(&body).map_err(|e| json_error(e, "the body"))?
    };
    let from = match req.from_stage.as_deref() {
        None => None,
        Some(s) => Some(Stage::from_name(s).ok_or_else(|| {
            ApiError::unprocessable(format!("from_stage: unknown stage {s:?}"))
                .with_error("from_stage", "unknown stage")
        })?),
    };
    let reset = state.db.retry(&id, from).await?;
    state.blobs.remove_stages(&id, &reset).await?;
    let first = reset.first().map(String::as_str).unwrap_or("?");
    note(&state, &id, &format!("retry requested from stage {first}")).await;
    wake_workers(&state, &id).await;
    accepted(&state, &caller, &id).await
}

/// Wakes idle workers for a job that can now be claimed: this process's own, and through
/// the database those of other processes. A lost announcement only costs a poll interval.
async fn wake_workers(state: &AppState, id: &str) {
    state.wake.notify_waiters();
    if let Err(e) = state.db.announce(id).await {
        tracing::warn!(job = %id, error = %e, "could not announce the job to other workers");
    }
}

pub async fn results(IdRequest { state, caller, id }: IdRequest) -> Result<Response, ApiError> {
    let job = load(&state, &caller, &id).await?;
    let stages: serde_json::Map<String, Value> = job
        .stages
        .iter()
        .filter_map(|s| s.metrics.clone().map(|m| (s.name.clone(), m)))
        .collect();
    // The stand figures of the latest stage that made them (dbh, else segment), and the CRS.
    let latest = |key: &str| {
        ["dbh", "segment"]
            .iter()
            .find_map(|s| {
                stages
                    .get(*s)
                    .and_then(|m| m.get(key))
                    .filter(|v| !v.is_null())
            })
            .cloned()
    };
    let plot = latest("plot");
    let crs = latest("crs");
    Ok(Json(json!({
        "job_id": job.id,
        "state": job.state.as_str(),
        "stages": stages,
        "plot": plot,
        "crs": crs,
    }))
    .into_response())
}

#[cfg(test)]
mod tests {
    use super::parse_cursor;

    #[test]
    fn cursors_are_plain_positive_decimals() {
        assert_eq!(parse_cursor("1"), Some(1));
        assert_eq!(
            parse_cursor("999999999999999999"),
            Some(999_999_999_999_999_999)
        );
        for bad in [
            "",
            "0",
            "007",
            "+7",
            "-7",
            " 7",
            "7a",
            "9999999999999999999",
        ] {
            assert_eq!(parse_cursor(bad), None, "{bad:?}");
        }
    }
}
