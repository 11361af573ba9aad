//! Artifact downloads with ETag (the file's SHA-256), conditional requests and single byte
//! ranges, streamed from disk or from the object store; with an S3 store, artifacts of at least
//! `--presign-min-bytes` are answered with a redirect to a short-lived presigned URL so the
//! bytes flow from the store, not through the API.

use std::time::Duration;

use axum::body::Body;
use axum::extract::{Extension, Path, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use tokio::io::{AsyncReadExt, AsyncSeekExt};
use tokio_util::io::ReaderStream;

use super::auth::Caller;
use super::jobs::{files_kept, load};
use super::problem::ApiError;
use super::{AppState, IdRequest};
use crate::jobs::ArtifactRecord;

/// A parsed `Range` header against a resource of `size` bytes.
#[derive(Debug, PartialEq, Eq)]
pub enum ByteRange {
    /// Serve the whole body (no header, several ranges, or a header we ignore).
    Full,
    /// Inclusive byte positions.
    Part(u64, u64),
    Unsatisfiable,
}

/// Parses a single `bytes=` range (RFC 9110 14.1.2); anything else is served in full.
pub fn parse_range(value: Option<&str>, size: u64) -> ByteRange {
    let Some(spec) = value.and_then(|v| v.trim().strip_prefix("bytes=")) else {
        return ByteRange::Full;
    };
    if spec.contains(',') {
        return ByteRange::Full;
    }
    let Some((a, b)) = spec.split_once('-') else {
        return ByteRange::Full;
    };
    let (a, b) = (a.trim(), b.trim());
    match (a.parse::<u64>().ok(), b.parse::<u64>().ok()) {
        (None, Some(n)) if a.is_empty() => {
            if n == 0 || size == 0 {
                ByteRange::Unsatisfiable
            } else {
                ByteRange::Part(size.saturating_sub(n), size - 1)
            }
        }
        (Some(start), end) if b.is_empty() || end.is_some() => {
            if start >= size {
                return ByteRange::Unsatisfiable;
            }
            let last = end.map(|e| e.min(size - 1)).unwrap_or(size - 1);
            if last < start {
                ByteRange::Full
            } else {
                ByteRange::Part(start, last)
            }
        }
        _ => ByteRange::Full,
    }
}

async fn serve(
    state: &AppState,
    job_id: &str,
    a: &ArtifactRecord,
    headers: &HeaderMap,
) -> Result<Response, ApiError> {
    if a.name.split('/').any(|c| c == ".." || c.is_empty()) {
        return Err(ApiError::not_found("no such artifact"));
    }
    let size = a.size as u64;
    let etag = format!("\"{}\"", a.sha256);
    let mut h = HeaderMap::new();
    let put = |h: &mut HeaderMap, k: header::HeaderName, v: &str| {
        if let Ok(v) = HeaderValue::from_str(v) {
            h.insert(k, v);
        }
    };
    put(&mut h, header::ETAG, &etag);
    put(&mut h, header::ACCEPT_RANGES, "bytes");
    let not_modified = headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|t| t.trim() == etag || t.trim() == "*"));
    if not_modified {
        return Ok((StatusCode::NOT_MODIFIED, h).into_response());
    }
    let range = parse_range(
        headers.get(header::RANGE).and_then(|v| v.to_str().ok()),
        size,
    );
    let (status, start, len) = match range {
        ByteRange::Full => (StatusCode::OK, 0, size),
        ByteRange::Part(s, e) => {
            put(
                &mut h,
                header::CONTENT_RANGE,
                &format!("bytes {s}-{e}/{size}"),
            );
            (StatusCode::PARTIAL_CONTENT, s, e - s + 1)
        }
        ByteRange::Unsatisfiable => {
            return Err(ApiError::new(
                StatusCode::RANGE_NOT_SATISFIABLE,
                "range-not-satisfiable",
                format!("the artifact has {size} bytes"),
            )
            .with_header(header::CONTENT_RANGE, &format!("bytes */{size}")));
        }
    };
    let rel = format!("jobs/{job_id}/{}", a.name);
    if let Some(remote) = state.blobs.remote() {
        if size >= state.args.presign_min_bytes
            && let Some(url) = remote
                .presigned_get(&rel, Duration::from_secs(state.args.presign_ttl_secs))
                .await
        {
            put(&mut h, header::LOCATION, &url);
            put(&mut h, header::CACHE_CONTROL, "no-store");
            return Ok((StatusCode::TEMPORARY_REDIRECT, h).into_response());
        }
        put(&mut h, header::CONTENT_TYPE, &a.content_type);
        put(&mut h, header::CONTENT_LENGTH, &len.to_string());
        if len == 0 {
            return Ok((status, h, Body::empty()).into_response());
        }
        let stream = remote.get_range_stream(&rel, start, len).await?;
        return Ok((status, h, Body::from_stream(stream)).into_response());
    }
    let path = state.blobs.job_dir(job_id).join(&a.name);
    let mut file = tokio::fs::File::open(&path)
        .await
        .map_err(|_| ApiError::not_found(format!("artifact {} is gone from the server", a.name)))?;
    put(&mut h, header::CONTENT_TYPE, &a.content_type);
    put(&mut h, header::CONTENT_LENGTH, &len.to_string());
    file.seek(std::io::SeekFrom::Start(start))
        .await
        .map_err(ApiError::internal)?;
    let body = Body::from_stream(ReaderStream::new(file.take(len)));
    Ok((status, h, body).into_response())
}

pub async fn get(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
    Path((id, name)): Path<(String, String)>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let job = load(&state, &caller, &id).await?;
    files_kept(&job)?;
    let name = name.trim_start_matches('/');
    let a = job
        .artifacts
        .iter()
        .find(|a| a.name == name)
        .ok_or_else(|| ApiError::not_found(format!("job {id} has no artifact {name:?}")))?;
    serve(&state, &id, a, &headers).await
}

/// The job's newest artifact whose file name is `file` (later stages win).
async fn by_file_name(
    state: &AppState,
    caller: &Caller,
    id: &str,
    file: &str,
    headers: &HeaderMap,
) -> Result<Response, ApiError> {
    let job = load(state, caller, id).await?;
    files_kept(&job)?;
    let a = job
        .artifacts
        .iter()
        .rev()
        .find(|a| a.name.rsplit('/').next() == Some(file))
        .ok_or_else(|| {
            ApiError::not_found(format!(
                "job {id} has no {file} yet: the tree inventory is written by stage dbh"
            ))
        })?;
    serve(state, id, a, headers).await
}

pub async fn trees_csv(
    IdRequest { state, caller, id }: IdRequest,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    by_file_name(&state, &caller, &id, "trees.csv", &headers).await
}

pub async fn trees_geojson(
    IdRequest { state, caller, id }: IdRequest,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    by_file_name(&state, &caller, &id, "trees.geojson", &headers).await
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges_follow_rfc_9110() {
        assert_eq!(parse_range(None, 100), ByteRange::Full);
        assert_eq!(parse_range(Some("bytes=0-9"), 100), ByteRange::Part(0, 9));
        assert_eq!(parse_range(Some("bytes=90-"), 100), ByteRange::Part(90, 99));
        assert_eq!(parse_range(Some("bytes=-10"), 100), ByteRange::Part(90, 99));
        assert_eq!(parse_range(Some("bytes=-500"), 100), ByteRange::Part(0, 99));
        assert_eq!(
            parse_range(Some("bytes=50-500"), 100),
            ByteRange::Part(50, 99)
        );
        assert_eq!(
            parse_range(Some("bytes=100-"), 100),
            ByteRange::Unsatisfiable
        );
        assert_eq!(parse_range(Some("bytes=0-1,5-6"), 100), ByteRange::Full);
        assert_eq!(parse_range(Some("items=0-1"), 100), ByteRange::Full);
        assert_eq!(parse_range(Some("bytes=9-3"), 100), ByteRange::Full);
    }
}
