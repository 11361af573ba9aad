//! RFC 9457 problem details: the only shape an error leaves the API in.
//!
//! Handlers return [`ApiError`]; library errors map to it in one place (the `From` impls
//! below). A last middleware, [`problem_fallback`], rewrites any other error response that
//! the framework produced itself (unknown route, method not allowed, body too large, bad
//! JSON, timeout) into problem+json, keeping its status and headers.

use axum::body::Body;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Serialize;

use crate::jobs::DbError;
use crate::store::StoreError;

pub const PROBLEM_JSON: &str = "application/problem+json";

/// One field or file that is wrong, inside a problem.
#[derive(Debug, Clone, Serialize)]
pub struct FieldError {
    pub field: String,
    pub message: String,
}

/// An error answer: status, a problem type slug and a human detail.
#[derive(Debug)]
pub struct ApiError {
    pub status: StatusCode,
    pub slug: &'static str,
    pub detail: String,
    /// Field errors and extra headers, boxed to keep `Result<_, ApiError>` small.
    pub extra: Box<(Vec<FieldError>, HeaderMap)>,
}

impl ApiError {
    pub fn new(status: StatusCode, slug: &'static str, detail: impl Into<String>) -> Self {
        Self {
            status,
            slug,
            detail: detail.into(),
            extra: Box::default(),
        }
    }
    pub fn bad_request(detail: impl Into<String>) -> Self {
        Self::new(StatusCode::BAD_REQUEST, "bad-request", detail)
    }
    pub fn not_found(detail: impl Into<String>) -> Self {
        Self::new(StatusCode::NOT_FOUND, "not-found", detail)
    }
    pub fn conflict(detail: impl Into<String>) -> Self {
        Self::new(StatusCode::CONFLICT, "conflict", detail)
    }
    pub fn unprocessable(detail: impl Into<String>) -> Self {
        Self::new(StatusCode::UNPROCESSABLE_ENTITY, "unprocessable", detail)
    }
    pub fn gone(detail: impl Into<String>) -> Self {
        Self::new(StatusCode::GONE, "gone", detail)
    }
    pub fn too_large(detail: impl Into<String>) -> Self {
        Self::new(StatusCode::PAYLOAD_TOO_LARGE, "payload-too-large", detail)
    }
    pub fn storage_full(detail: impl Into<String>) -> Self {
        Self::new(
            StatusCode::INSUFFICIENT_STORAGE,
            "insufficient-storage",
            detail,
        )
    }
    pub fn internal(detail: impl std::fmt::Display) -> Self {
        tracing::error!(error = %detail, "internal error");
        Self::new(
            StatusCode::INTERNAL_SERVER_ERROR,
            "internal",
            "an internal error occurred; the request id identifies it in the server log",
        )
    }
    pub fn with_error(mut self, field: impl Into<String>, message: impl Into<String>) -> Self {
        self.extra.0.push(FieldError {
            field: field.into(),
            message: message.into(),
        });
        self
    }
    pub fn with_header(mut self, name: header::HeaderName, value: &str) -> Self {
        if let Ok(v) = HeaderValue::from_str(value) {
            self.extra.1.insert(name, v);
        }
        self
    }
}

#[derive(Serialize)]
struct ProblemBody<'a> {
    #[serde(rename = "type")]
    type_: String,
    title: &'a str,
    status: u16,
    detail: &'a str,
    #[serde(skip_serializing_if = "<[_]>::is_empty")]
    errors: &'a [FieldError],
}

/// Builds a problem+json response.
pub fn problem_response(
    status: StatusCode,
    slug: &str,
    detail: &str,
    errors: &[FieldError],
    mut headers: HeaderMap,
) -> Response {
    let body = ProblemBody {
        type_: format!("urn:sylva:problem:{slug}"),
        title: status.canonical_reason().unwrap_or("Error"),
        status: status.as_u16(),
        detail,
        errors,
    };
    let bytes = serde_json::to_vec(&body).unwrap_or_default();
    headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(PROBLEM_JSON));
    headers.remove(header::CONTENT_LENGTH);
    let mut resp = Response::new(Body::from(bytes));
    *resp.status_mut() = status;
    *resp.headers_mut() = headers;
    resp
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let (errors, headers) = *self.extra;
        problem_response(self.status, self.slug, &self.detail, &errors, headers)
    }
}

impl From<DbError> for ApiError {
    fn from(e: DbError) -> Self {
        match e {
            DbError::NotFound => ApiError::not_found("no such resource"),
            DbError::Conflict(m) => ApiError::conflict(m),
            DbError::Invalid(m) => ApiError::unprocessable(m),
            DbError::QueueFull(n) => ApiError::new(
                StatusCode::TOO_MANY_REQUESTS,
                "queue-full",
                format!("{n} jobs are waiting; submit again later"),
            )
            .with_header(header::RETRY_AFTER, "60"),
            DbError::JobQuota(n) => ApiError::new(
                StatusCode::TOO_MANY_REQUESTS,
                "quota-exceeded",
                format!(
                    "this token already has {n} unfinished jobs, its quota; submit again when one \
                     has finished"
                ),
            )
            .with_header(header::RETRY_AFTER, "60"),
            DbError::Gone(m) => ApiError::gone(m),
            other if other.is_storage_full() => ApiError::storage_full("the server's disk is full"),
            other => ApiError::internal(other.to_string()),
        }
    }
}

impl From<StoreError> for ApiError {
    fn from(e: StoreError) -> Self {
        match e {
            _ if e.is_storage_full() => ApiError::storage_full("the server's disk is full"),
            StoreError::TooLarge { limit } => {
                ApiError::too_large(format!("the body is larger than {limit} bytes"))
            }
            StoreError::Body(m) => ApiError::bad_request(m),
            StoreError::NotFound(m) => {
                ApiError::not_found(format!("{m} is gone from the object store"))
            }
            StoreError::Remote(m) => ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                "store-unavailable",
                format!("the object store did not answer as expected: {m}"),
            )
            .with_header(header::RETRY_AFTER, "5"),
            other => ApiError::internal(other),
        }
    }
}

/// Slug for a status the framework answered with on its own.
fn slug_for(status: StatusCode) -> &'static str {
    match status.as_u16() {
        400 => "bad-request",
        401 => "unauthorized",
        404 => "not-found",
        405 => "method-not-allowed",
        408 => "timeout",
        413 => "payload-too-large",
        415 => "unsupported-media-type",
        422 => "unprocessable",
        _ => "error",
    }
}

/// Rewrites error responses that are not problem+json yet (framework rejections) into
/// problem+json with the same status and headers; the original text becomes the detail.
/// Whether an HTTP/1 request carries a body (a length above zero, or chunked).
fn sends_body(req: &axum::extract::Request) -> bool {
    if req.version() > axum::http::Version::HTTP_11 {
        return false;
    }
    let h = req.headers();
    h.contains_key(header::TRANSFER_ENCODING)
        || h.get(header::CONTENT_LENGTH)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.trim().parse::<u64>().ok())
            .is_some_and(|n| n > 0)
}

pub async fn problem_fallback(
    req: axum::extract::Request,
    next: axum::middleware::Next,
) -> Response {
    let is_head = req.method() == axum::http::Method::HEAD;
    let close_after = sends_body(&req);
    let mut resp = next.run(req).await;
    let status = resp.status();
    let is_error = status.is_client_error() || status.is_server_error();
    if is_error && close_after {
        // An error may be answered before the request body was read to its end (a part
        // refused at 507 or 409 mid-stream). The server then drops the connection, and a
        // client that put it back in its pool would lose its next request; saying so in
        // the answer keeps clients from reusing it.
        resp.headers_mut()
            .insert(header::CONNECTION, HeaderValue::from_static("close"));
    }
    let is_problem = resp
        .headers()
        .get(header::CONTENT_TYPE)
        .is_some_and(|v| v.as_bytes().starts_with(PROBLEM_JSON.as_bytes()));
    if !is_error || is_problem {
        return resp;
    }
    let (parts, body) = resp.into_parts();
    let text = axum::body::to_bytes(body, 64 * 1024)
        .await
        .map(|b| String::from_utf8_lossy(&b).trim().to_string())
        .unwrap_or_default();
    let detail = match (status.as_u16(), text.is_empty()) {
        (404, _) => "no such route".to_string(),
        (405, _) => "method not allowed on this route; see the Allow header".to_string(),
        (408, _) => "the request took too long".to_string(),
        (413, _) => format!("the request body is too large: {text}"),
        (_, true) => status.canonical_reason().unwrap_or("error").to_string(),
        _ => text,
    };
    let mut r = problem_response(status, slug_for(status), &detail, &[], parts.headers);
    if is_head {
        *r.body_mut() = Body::empty();
    }
    r
}
