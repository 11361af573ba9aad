//! The HTTP API (docs/api.md, openapi.yaml): thin handlers over the job store and the blob
//! store, with the cross-cutting concerns — auth, body limits, timeouts, request ids,
//! tracing, problem+json — as layers.

pub mod artifacts;
pub mod auth;
pub mod events;
pub mod jobs;
pub mod keys;
pub mod problem;
pub mod service;
pub mod uploads;
pub mod views;
pub mod web;
pub mod webhooks;

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::Router;
use axum::extract::{DefaultBodyLimit, Extension, FromRequestParts, Path, Request, State};
use axum::http::request::Parts;
use axum::http::{Method, StatusCode};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post, put};
use tokio::sync::Notify;
use tower_http::request_id::{MakeRequestUuid, PropagateRequestIdLayer, SetRequestIdLayer};
use tower_http::timeout::TimeoutLayer;
use tower_http::trace::TraceLayer;

use crate::config::ApiArgs;
use crate::gpu::GpuInfo;
use crate::jobs::JobStore;
use crate::store::BlobStore;
use problem::ApiError;

/// Counters kept by this API process (Prometheus counters restart at zero with the process).
#[derive(Default)]
pub struct Counters {
    pub upload_bytes: AtomicU64,
    pub http_requests: Mutex<BTreeMap<u16, u64>>,
}

/// What a handler of a route with one `{id}` starts from: the state, the caller (set by
/// [`auth::require_token`]) and the id, extracted in that order.
pub struct IdRequest {
    pub state: AppState,
    pub caller: auth::Caller,
    pub id: String,
}

impl FromRequestParts<AppState> for IdRequest {
    type Rejection = Response;

    async fn from_request_parts(parts: &mut Parts, state: &AppState) -> Result<Self, Response> {
        let Extension(caller) = Extension::<auth::Caller>::from_request_parts(parts, state)
            .await
            .map_err(IntoResponse::into_response)?;
        let Path(id) = Path::<String>::from_request_parts(parts, state)
            .await
            .map_err(IntoResponse::into_response)?;
        Ok(IdRequest {
            state: state.clone(),
            caller,
            id,
        })
    }
}

/// Everything a handler may use.
#[derive(Clone)]
pub struct AppState {
    pub db: JobStore,
    pub blobs: BlobStore,
    pub args: Arc<ApiArgs>,
    /// Wakes in-process workers when a job is queued.
    pub wake: Arc<Notify>,
    pub counters: Arc<Counters>,
    pub gpu: Option<GpuInfo>,
    /// Lease length of the workers, used to count live workers.
    pub lease: Duration,
    /// Webhook target policy and signing secrets.
    pub webhooks: crate::webhooks::Webhooks,
    /// Set once a managed API key has been seen in the database: authentication stays on
    /// from then on ([`auth::require_token`]).
    pub keys_exist: Arc<std::sync::atomic::AtomicBool>,
}

impl AppState {
    /// How long a finished job keeps its files (`None`: for ever).
    pub fn retention(&self) -> Option<Duration> {
        self.args.retention.job_retention()
    }
}

/// Every (method, path) the router serves, in axum's path syntax. The router below is built
/// from the same handlers; a test checks this list against openapi.yaml both ways and
/// another that every entry is really routed.
pub const ROUTES: &[(&str, &str)] = &[
    ("GET", "/"),
    ("GET", "/assets/{name}"),
    ("GET", "/livez"),
    ("GET", "/readyz"),
    ("GET", "/metrics"),
    ("GET", "/openapi.yaml"),
    ("GET", "/v1/info"),
    ("GET", "/v1/options"),
    ("POST", "/v1/uploads"),
    ("GET", "/v1/uploads/{id}"),
    ("HEAD", "/v1/uploads/{id}"),
    ("PUT", "/v1/uploads/{id}/parts/{n}"),
    ("POST", "/v1/uploads/{id}/complete"),
    ("POST", "/v1/jobs"),
    ("GET", "/v1/jobs"),
    ("GET", "/v1/jobs/{id}"),
    ("DELETE", "/v1/jobs/{id}"),
    ("GET", "/v1/jobs/{id}/events"),
    ("GET", "/v1/jobs/{id}/log"),
    ("POST", "/v1/jobs/{id}/cancel"),
    ("POST", "/v1/jobs/{id}/retry"),
    ("GET", "/v1/jobs/{id}/results"),
    ("GET", "/v1/jobs/{id}/trees.csv"),
    ("GET", "/v1/jobs/{id}/trees.geojson"),
    ("GET", "/v1/jobs/{id}/artifacts/{*name}"),
    ("GET", "/v1/jobs/{id}/webhooks"),
    ("GET", "/v1/webhooks/secret"),
    ("POST", "/v1/webhooks/secret/rotate"),
    ("GET", "/v1/keys"),
    ("POST", "/v1/keys"),
    ("DELETE", "/v1/keys/{id}"),
];

async fn count_requests(State(state): State<AppState>, req: Request, next: Next) -> Response {
    let resp = next.run(req).await;
    if let Ok(mut m) = state.counters.http_requests.lock() {
        *m.entry(resp.status().as_u16()).or_default() += 1;
    }
    resp
}

async fn no_such_route() -> ApiError {
    ApiError::new(StatusCode::NOT_FOUND, "no-such-route", "no such route")
}

/// Request headers a page on another origin may send (preflights name them).
const CORS_REQUEST_HEADERS: [&str; 7] = [
    "authorization",
    "content-type",
    "idempotency-key",
    "last-event-id",
    "range",
    "if-none-match",
    "x-request-id",
];
/// Answer headers such a page may read.
const CORS_EXPOSED_HEADERS: [&str; 10] = [
    "etag",
    "location",
    "retry-after",
    "content-length",
    "content-range",
    "content-disposition",
    "accept-ranges",
    "upload-bytes-received",
    "upload-length",
    "x-request-id",
];
/// How long a browser may keep a preflight's answer, seconds (an hour: origins change
/// with a restart only).
const CORS_MAX_AGE_SECS: u64 = 3600;

/// The CORS layer for `--cors-origin` (see [`ApiArgs::cors_origin`]): `None` without
/// origins; an error names an origin that is not `scheme://host[:port]`.
pub fn cors_layer(origins: &[String]) -> Result<Option<tower_http::cors::CorsLayer>, String> {
    use axum::http::HeaderValue;
    use tower_http::cors::{AllowOrigin, CorsLayer};
    let origins: Vec<&str> = origins
        .iter()
        .map(|o| o.trim().trim_end_matches('/'))
        .filter(|o| !o.is_empty())
        .collect();
    if origins.is_empty() {
        return Ok(None);
    }
    let allow = if origins.contains(&"*") {
        AllowOrigin::any()
    } else {
        let mut list = Vec::new();
        for o in origins {
            let rest = o
                .strip_prefix("https://")
                .or_else(|| o.strip_prefix("http://"))
                .ok_or_else(|| {
                    format!("--cors-origin {o:?}: an origin starts with http:// or https://")
                })?;
            if rest.is_empty() || rest.contains(['/', '?', '#', ' ', '@']) {
                return Err(format!(
                    "--cors-origin {o:?}: an origin is scheme://host[:port], without a path"
                ));
            }
            let v = HeaderValue::from_str(o)
                .map_err(|e| format!("--cors-origin {o:?}: not a header value ({e})"))?;
            list.push(v);
        }
        AllowOrigin::list(list)
    };
    let names = |n: &[&'static str]| {
        n.iter()
            .map(|h| axum::http::HeaderName::from_static(h))
            .collect::<Vec<_>>()
    };
    Ok(Some(
        CorsLayer::new()
            .allow_origin(allow)
            .allow_methods([
                Method::GET,
                Method::HEAD,
                Method::POST,
                Method::PUT,
                Method::DELETE,
            ])
            .allow_headers(names(&CORS_REQUEST_HEADERS))
            .expose_headers(names(&CORS_EXPOSED_HEADERS))
            .max_age(Duration::from_secs(CORS_MAX_AGE_SECS)),
    ))
}

/// The whole application.
pub fn router(state: AppState) -> Router {
    let a = &state.args;
    // Checked when `sylva serve` starts; a bad origin left here only logs.
    let cors = cors_layer(&a.cors_origin).unwrap_or_else(|e| {
        tracing::error!("{e}; CORS stays off");
        None
    });
    let timeout = Duration::from_secs(a.request_timeout_secs.max(1));
    let upload_timeout = Duration::from_secs(a.upload_timeout_secs.max(1));
    let json_limit = a.max_json_bytes as usize;

    let public = Router::new()
        .route("/", get(web::index))
        .route("/assets/{name}", get(web::asset))
        .route("/livez", get(service::livez))
        .route("/readyz", get(service::readyz))
        .route("/metrics", get(service::metrics))
        .route("/openapi.yaml", get(service::openapi))
        .layer(TimeoutLayer::with_status_code(
            StatusCode::REQUEST_TIMEOUT,
            timeout,
        ));

    let ordinary = Router::new()
        .route("/v1/info", get(service::info))
        .route("/v1/options", get(service::options))
        .route("/v1/uploads", post(uploads::create))
        .route("/v1/uploads/{id}", get(uploads::status))
        .route("/v1/uploads/{id}/complete", post(uploads::complete))
        .route("/v1/jobs", get(jobs::list))
        .route("/v1/jobs/{id}", get(jobs::get).delete(jobs::delete))
        .route("/v1/jobs/{id}/log", get(jobs::log))
        .route("/v1/jobs/{id}/cancel", post(jobs::cancel))
        .route("/v1/jobs/{id}/retry", post(jobs::retry))
        .route("/v1/jobs/{id}/results", get(jobs::results))
        .route("/v1/jobs/{id}/trees.csv", get(artifacts::trees_csv))
        .route("/v1/jobs/{id}/trees.geojson", get(artifacts::trees_geojson))
        .route("/v1/jobs/{id}/artifacts/{*name}", get(artifacts::get))
        .route("/v1/jobs/{id}/webhooks", get(webhooks::deliveries))
        .route("/v1/webhooks/secret", get(webhooks::secret))
        .route("/v1/webhooks/secret/rotate", post(webhooks::rotate))
        .route("/v1/keys", get(keys::list).post(keys::create))
        .route("/v1/keys/{id}", axum::routing::delete(keys::revoke))
        .layer(DefaultBodyLimit::max(json_limit))
        .layer(TimeoutLayer::with_status_code(
            StatusCode::REQUEST_TIMEOUT,
            timeout,
        ));

    // Parts and one-request submissions stream large bodies: their own limits and timeout.
    let uploads = Router::new()
        .route("/v1/uploads/{id}/parts/{n}", put(uploads::put_part))
        .route(
            "/v1/jobs",
            post(jobs::create).layer(DefaultBodyLimit::max(a.max_multipart_bytes as usize)),
        )
        .layer(TimeoutLayer::with_status_code(
            StatusCode::REQUEST_TIMEOUT,
            upload_timeout,
        ));

    // Event streams stay open for the life of a job: no timeout.
    let streams = Router::new().route("/v1/jobs/{id}/events", get(events::events));

    let authed =
        ordinary
            .merge(uploads)
            .merge(streams)
            .route_layer(middleware::from_fn_with_state(
                state.clone(),
                auth::require_token,
            ));

    public
        .merge(authed)
        .fallback(no_such_route)
        .layer(middleware::from_fn(problem::problem_fallback))
        .layer(middleware::from_fn_with_state(state.clone(), count_requests))
        .layer(
            TraceLayer::new_for_http().make_span_with(|req: &Request| {
                let id = req
                    .headers()
                    .get("x-request-id")
                    .and_then(|v| v.to_str().ok())
                    .unwrap_or("");
                tracing::info_span!("request", method = %req.method(), path = %req.uri().path(), request_id = %id)
            }),
        )
        .layer(PropagateRequestIdLayer::x_request_id())
        .layer(SetRequestIdLayer::x_request_id(MakeRequestUuid))
        // Outermost, so preflights are answered before authentication and every answer,
        // errors included, carries the headers.
        .layer(tower::util::option_layer(cors))
        .with_state(state)
}

/// Methods of a route from [`ROUTES`] as axum `Method`s (for tests).
pub fn route_method(m: &str) -> Method {
    Method::from_bytes(m.as_bytes()).unwrap_or(Method::GET)
}

/// Bumps the upload byte counter.
pub fn count_upload_bytes(state: &AppState, n: u64) {
    state.counters.upload_bytes.fetch_add(n, Ordering::Relaxed);
}

#[cfg(test)]
mod cors_tests {
    use super::cors_layer;

    fn origins(list: &[&str]) -> Vec<String> {
        list.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn no_origin_means_no_cors_layer() {
        assert!(matches!(cors_layer(&[]), Ok(None)));
        assert!(matches!(cors_layer(&origins(&[" ", ""])), Ok(None)));
    }

    #[test]
    fn origins_are_scheme_host_and_port() {
        for good in [
            "https://twin.example.org",
            "http://127.0.0.1:8765",
            "https://twin.example.org/",
            "*",
        ] {
            assert!(
                matches!(cors_layer(&origins(&[good])), Ok(Some(_))),
                "{good}"
            );
        }
        for (bad, says) in [
            ("twin.example.org", "starts with http"),
            ("ftp://twin.example.org", "starts with http"),
            ("https://twin.example.org/app", "without a path"),
            ("https://", "an origin"),
            ("https://user@twin.example.org", "without a path"),
        ] {
            match cors_layer(&origins(&[bad])) {
                Err(e) => assert!(e.contains(says) && e.contains(bad), "{bad}: {e}"),
                Ok(_) => panic!("{bad} was accepted"),
            }
        }
    }
}
