//! Resumable uploads: create, put parts (idempotent), ask what arrived, complete (verify
//! size and checksum, inspect the content).

use std::collections::HashSet;
use std::sync::{LazyLock, Mutex};

use axum::body::Body;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::{Extension, Json};
use serde::Deserialize;
use serde_json::json;

use super::auth::Caller;
use super::problem::ApiError;
use super::{AppState, IdRequest, count_upload_bytes, views};
use crate::jobs::{UploadKind, UploadRecord, now_ms};
use crate::pipeline::inspect::{self, InspectError};
use crate::progress::NoProgress;

/// Body of `POST /v1/uploads` (openapi.yaml `UploadCreate`).
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UploadCreate {
    pub kind: UploadKind,
    pub filename: String,
    /// Declared total size, bytes.
    #[serde(deserialize_with = "json_integer")]
    pub size: u64,
    /// Expected SHA-256 of the whole file; may be left out, but not sent as `null`.
    #[serde(default, deserialize_with = "present_string")]
    pub sha256: Option<String>,
}

/// A JSON Schema `integer` in `0..=i64::MAX` (openapi.yaml: `format: int64, minimum: 0`): any
/// number without a fractional part, so `3` and `3.0` alike (JSON Schema counts mathematical
/// values, not spellings).
fn json_integer<'de, D: serde::Deserializer<'de>>(d: D) -> Result<u64, D::Error> {
    let n = serde_json::Number::deserialize(d)?;
    // 2^63 as f64: every integral f64 below it converts exactly.
    const LIMIT: f64 = 9_223_372_036_854_775_808.0;
    let v = match (n.as_u64(), n.as_f64()) {
        (Some(v), _) => Some(v),
        (None, Some(f)) if f.fract() == 0.0 && (0.0..LIMIT).contains(&f) => Some(f as u64),
        _ => None,
    };
    v.filter(|v| i64::try_from(*v).is_ok()).ok_or_else(|| {
        serde::de::Error::custom(format!(
            "invalid value: {n}, expected an integer from 0 to {}",
            i64::MAX
        ))
    })
}

/// An optional field that, when present, must be a string (`null` is refused).
pub(crate) fn present_string<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> Result<Option<String>, D::Error> {
    String::deserialize(d).map(Some)
}

/// Ids are UUIDv7 in simple form: 32 lowercase hex digits.
pub fn valid_id(id: &str) -> bool {
    id.len() == 32
        && id
            .bytes()
            .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
}

pub fn new_id() -> String {
    uuid::Uuid::now_v7().simple().to_string()
}

/// The upload `id` if `caller` may see it; another owner's upload answers exactly as a
/// missing one (404, the same body), so existence does not leak.
pub async fn load(state: &AppState, caller: &Caller, id: &str) -> Result<UploadRecord, ApiError> {
    caller
        .load_visible(
            "upload",
            id,
            || state.db.get_upload(id),
            |u: &UploadRecord| &u.owner,
        )
        .await
}

/// Checks an upload request and records it; shared by `POST /v1/uploads` and one-request
/// job submissions.
/// 429 when `adding` more bytes would take `caller` past its byte quota (its key's own, or
/// `--quota-bytes`).
pub async fn check_byte_quota(
    state: &AppState,
    caller: &Caller,
    adding: u64,
) -> Result<(), ApiError> {
    let owner = caller.owner.as_str();
    let quota = caller
        .quota_bytes
        .map_or(state.args.quota_bytes, |q| q.max(0) as u64);
    if quota == 0 {
        return Ok(());
    }
    let used = state.db.stored_bytes(owner).await?.max(0) as u64;
    if used.saturating_add(adding) <= quota {
        return Ok(());
    }
    // Space comes back when a job is deleted or retention removes old files; the sweep runs
    // every --gc-interval-secs, which is when asking again can first succeed unaided.
    let retry = state.args.retention.gc_interval_secs.clamp(60, 3600);
    Err(ApiError::new(
        StatusCode::TOO_MANY_REQUESTS,
        "quota-exceeded",
        format!(
            "this token keeps {used} bytes on the server and may keep {quota}; {adding} more \
             would exceed its quota: delete finished jobs (DELETE /v1/jobs/{{id}}) or wait for \
             retention to remove old ones"
        ),
    )
    .with_header(header::RETRY_AFTER, &retry.to_string()))
}

pub async fn create_record(
    state: &AppState,
    caller: &Caller,
    req: UploadCreate,
) -> Result<UploadRecord, ApiError> {
    let a = &state.args;
    if req.filename.is_empty() || req.filename.chars().count() > 255 {
        return Err(
            ApiError::unprocessable("filename must be 1 to 255 characters")
                .with_error("filename", "length must be 1..255"),
        );
    }
    if req.filename.chars().any(char::is_control) {
        return Err(
            ApiError::unprocessable("filename must not contain control characters")
                .with_error("filename", "control character"),
        );
    }
    if req.size == 0 {
        return Err(
            ApiError::unprocessable("size must be at least 1 byte").with_error("size", "minimum 1")
        );
    }
    if let Some(s) = &req.sha256
        && (s.len() != 64
            || !s
                .bytes()
                .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b)))
    {
        return Err(
            ApiError::unprocessable("sha256 must be 64 lowercase hex digits")
                .with_error("sha256", "pattern ^[0-9a-f]{64}$"),
        );
    }
    // Only a well-formed request meets the configured limit: a malformed one is 422 whatever
    // size it declares.
    if req.size > a.max_upload_bytes {
        return Err(ApiError::too_large(format!(
            "{} bytes declared; this server accepts uploads up to {} bytes",
            req.size, a.max_upload_bytes
        )));
    }
    check_byte_quota(state, caller, req.size).await?;
    let free = state.blobs.free_bytes()?;
    // The upload needs room for its parts and its assembled copy.
    if free < a.min_free_bytes.saturating_add(req.size.saturating_mul(2)) {
        return Err(ApiError::storage_full(format!(
            "{} bytes declared but only {free} bytes are free on the server",
            req.size
        )));
    }
    let now = now_ms();
    let rec = UploadRecord {
        id: new_id(),
        kind: req.kind,
        filename: req.filename,
        size: req.size as i64,
        sha256: req.sha256,
        part_size: a.part_size.max(1) as i64,
        complete: false,
        inspection: None,
        created_at: now,
        expires_at: now + a.upload_ttl_secs as i64 * 1000,
        completed_at: None,
        parts: Vec::new(),
        owner: caller.owner.clone(),
        expired: false,
    };
    state.db.create_upload(&rec).await?;
    Ok(rec)
}

pub async fn create(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
    Json(req): Json<UploadCreate>,
) -> Result<Response, ApiError> {
    let rec = create_record(&state, &caller, req).await?;
    let mut resp = (StatusCode::CREATED, Json(views::upload(&rec))).into_response();
    if let Ok(loc) = HeaderValue::from_str(&format!("/v1/uploads/{}", rec.id)) {
        resp.headers_mut().insert(header::LOCATION, loc);
    }
    Ok(resp)
}

fn status_headers(u: &UploadRecord) -> HeaderMap {
    let mut h = HeaderMap::new();
    let state = if u.complete { "complete" } else { "open" };
    h.insert("upload-state", HeaderValue::from_static(state));
    if let Ok(v) = HeaderValue::from_str(&u.bytes_received().to_string()) {
        h.insert("upload-bytes-received", v);
    }
    if let Ok(v) = HeaderValue::from_str(&u.size.to_string()) {
        h.insert("upload-length", v);
    }
    h
}

pub async fn status(IdRequest { state, caller, id }: IdRequest) -> Result<Response, ApiError> {
    let u = load(&state, &caller, &id).await?;
    Ok((status_headers(&u), Json(views::upload(&u))).into_response())
}

/// An open upload past its `expires_at` can no longer be resumed.
fn expired(u: &UploadRecord) -> Result<(), ApiError> {
    if !u.complete && now_ms() > u.expires_at {
        return Err(ApiError::new(
            StatusCode::GONE,
            "upload-expired",
            format!(
                "upload {} expired at {}; start a new upload",
                u.id,
                crate::jobs::rfc3339(u.expires_at)
            ),
        ));
    }
    Ok(())
}

pub async fn put_part(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
    Path((id, n)): Path<(String, i64)>,
    body: Body,
) -> Result<Response, ApiError> {
    let u = load(&state, &caller, &id).await?;
    if u.complete {
        return Err(ApiError::conflict("the upload is already complete"));
    }
    expired(&u)?;
    if n < 0 || n >= u.parts_total() {
        return Err(ApiError::unprocessable(format!(
            "part {n} is out of range: this upload has parts 0..{}",
            u.parts_total() - 1
        ))
        .with_error("n", "out of range"));
    }
    let expected = u.part_len(n);
    let (size, sha) = state
        .blobs
        .write_part(&id, n, body.into_data_stream(), u.part_size as u64)
        .await?;
    if size as i64 != expected {
        return Err(ApiError::unprocessable(format!(
            "part {n} has {size} bytes; it must have exactly {expected}"
        ))
        .with_error("body", "wrong part length"));
    }
    state.db.put_part(&id, n, size as i64, &sha).await?;
    count_upload_bytes(&state, size);
    Ok(Json(json!({ "n": n, "size": size, "sha256": sha })).into_response())
}

/// Uploads being completed in this process (a second concurrent complete gets 409).
static COMPLETING: LazyLock<Mutex<HashSet<String>>> = LazyLock::new(Default::default);

struct CompletingGuard(String);
impl Drop for CompletingGuard {
    fn drop(&mut self) {
        if let Ok(mut s) = COMPLETING.lock() {
            s.remove(&self.0);
        }
    }
}

pub async fn complete(IdRequest { state, caller, id }: IdRequest) -> Result<Response, ApiError> {
    let u = load(&state, &caller, &id).await?;
    if u.complete {
        return Ok((status_headers(&u), Json(views::upload(&u))).into_response());
    }
    expired(&u)?;
    let missing = u.missing_parts();
    if !missing.is_empty() {
        let shown: Vec<String> = missing.iter().take(20).map(|n| n.to_string()).collect();
        return Err(ApiError::conflict(format!(
            "{} part(s) missing: {}{}",
            missing.len(),
            shown.join(", "),
            if missing.len() > 20 { ", …" } else { "" }
        )));
    }
    let _guard = {
        let mut set = COMPLETING
            .lock()
            .map_err(|_| ApiError::internal("completion lock poisoned"))?;
        if !set.insert(id.clone()) {
            return Err(ApiError::conflict(
                "the upload is being completed by another request",
            ));
        }
        CompletingGuard(id.clone())
    };
    finish_upload(&state, &u).await?;
    let u = load(&state, &caller, &id).await?;
    Ok((status_headers(&u), Json(views::upload(&u))).into_response())
}

/// Assembles, verifies and inspects a fully received upload, then marks it complete.
pub async fn finish_upload(state: &AppState, u: &UploadRecord) -> Result<(), ApiError> {
    let blobs = state.blobs.clone();
    let limits = state.args.extract_limits();
    let (size, sha) = blobs.assemble(&u.id, &u.filename, u.parts_total()).await?;
    if size as i64 != u.size {
        blobs.discard_blob(&u.id, &u.filename).await;
        return Err(ApiError::unprocessable(format!(
            "{}: received {size} bytes but {} were declared",
            u.filename, u.size
        ))
        .with_error(&u.filename, "size mismatch"));
    }
    if let Some(want) = &u.sha256
        && *want != sha
    {
        blobs.discard_blob(&u.id, &u.filename).await;
        return Err(ApiError::unprocessable(format!(
            "{}: the SHA-256 of the received bytes is {sha}, not the declared {want}; \
             re-send the damaged parts and complete again",
            u.filename
        ))
        .with_error(&u.filename, "checksum mismatch"));
    }
    let u2 = u.clone();
    let b2 = blobs.clone();
    let inspection = tokio::task::spawn_blocking(move || {
        let blob = b2.upload_blob(&u2.id, &u2.filename);
        let unpack = b2.upload_unpacked(&u2.id);
        inspect::inspect_upload(u2.kind, &u2.filename, &blob, &unpack, &limits, &NoProgress)
    })
    .await
    .map_err(ApiError::internal)?;
    let inspection = match inspection {
        Ok(v) => v,
        Err(InspectError::Unusable(m)) => {
            blobs.discard_blob(&u.id, &u.filename).await;
            return Err(ApiError::unprocessable(m.clone()).with_error(&u.filename, m));
        }
        Err(InspectError::Io(io)) => {
            return Err(match &io {
                crate::io::IoError::Io { source, .. }
                    if source.kind() == std::io::ErrorKind::StorageFull =>
                {
                    ApiError::storage_full("the server's disk is full")
                }
                _ => ApiError::internal(io),
            });
        }
        Err(InspectError::Cancelled) => return Err(ApiError::internal("inspection cancelled")),
    };
    blobs.drop_parts(&u.id).await;
    state.db.complete_upload(&u.id, &sha, &inspection).await?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(body: &str) -> Result<UploadCreate, serde_json::Error> {
        serde_json::from_str(body)
    }

    #[test]
    fn size_is_any_integral_number_and_sha256_is_absent_or_a_string() {
        let u = parse(r#"{"kind":"lidar","filename":"a.las","size":54928.0}"#).expect("3.0");
        assert_eq!(u.size, 54928);
        assert_eq!(u.sha256, None);
        let u = parse(r#"{"kind":"lidar","filename":"a.las","size":7,"sha256":"ab"}"#)
            .expect("string sha256");
        assert_eq!(u.sha256.as_deref(), Some("ab"));
        for bad in [
            r#"{"kind":"lidar","filename":"a.las","size":1.5}"#,
            r#"{"kind":"lidar","filename":"a.las","size":-1}"#,
            r#"{"kind":"lidar","filename":"a.las","size":"1"}"#,
            r#"{"kind":"lidar","filename":"a.las","size":1e30}"#,
            r#"{"kind":"lidar","filename":"a.las","size":9223372036854775808}"#,
            r#"{"kind":"lidar","filename":"a.las","size":1,"sha256":null}"#,
        ] {
            assert!(parse(bad).is_err(), "{bad} was accepted");
        }
    }
}
