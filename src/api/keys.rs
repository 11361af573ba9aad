//! Key routes for admin keys: list, create and revoke managed API keys over HTTP, as
//! `sylva keys` does on the command line (a cloud backend that serves several customers makes
//! one key per customer). Other callers get 403 on the collection and 404 on a key, as on any
//! record they do not own.

use axum::Json;
use axum::extract::{Extension, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use serde_json::{Value, json};

use super::auth::Caller;
use super::problem::ApiError;
use super::{AppState, IdRequest};
use crate::jobs::keys::{self, ApiKey};
use crate::jobs::{DbError, now_ms, rfc3339};

fn forbidden() -> ApiError {
    ApiError::new(
        StatusCode::FORBIDDEN,
        "forbidden",
        "managing API keys needs an admin key (sylva keys create --admin)",
    )
}

/// A key as the API shows it: never the key itself, nor its hash.
pub fn view(k: &ApiKey) -> Value {
    let ts = |t: Option<i64>| t.map(rfc3339);
    json!({
        "id": k.id,
        "name": k.name,
        "prefix": k.prefix,
        "admin": k.admin,
        "quota_jobs": k.quota_jobs,
        "quota_bytes": k.quota_bytes,
        "created_at": rfc3339(k.created_at),
        "expires_at": ts(k.expires_at),
        "revoked_at": ts(k.revoked_at),
        "owner": k.owner(),
    })
}

/// `GET /v1/keys`: every managed key (admin only).
pub async fn list(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
) -> Result<Response, ApiError> {
    if !caller.admin {
        return Err(forbidden());
    }
    let all: Vec<Value> = state.db.api_keys().await?.iter().map(view).collect();
    Ok(Json(json!({ "keys": all })).into_response())
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KeyCreate {
    name: String,
    #[serde(default)]
    admin: bool,
    /// Read as numbers, so that `5.0` is the integer 5 as JSON Schema has it.
    #[serde(default)]
    quota_jobs: Option<f64>,
    #[serde(default)]
    quota_bytes: Option<f64>,
    /// RFC 3339.
    #[serde(default)]
    expires_at: Option<String>,
}

/// A whole number in `0..=max` from a JSON number (`5` or `5.0`).
fn whole(field: &str, v: Option<f64>, max: f64) -> Result<Option<i64>, ApiError> {
    match v {
        None => Ok(None),
        Some(x) if x.is_finite() && x.fract() == 0.0 && (0.0..=max).contains(&x) => {
            Ok(Some(x as i64))
        }
        Some(_) => Err(ApiError::unprocessable(format!(
            "{field} must be a whole number from 0 to {max}"
        ))
        .with_error(field, "not a whole number in range")),
    }
}

/// `POST /v1/keys`: a new key, shown once in the answer (admin only).
pub async fn create(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
    body: axum::body::Bytes,
) -> Result<Response, ApiError> {
    // The right first, then the body: a non-admin learns nothing from its request's shape.
    if !caller.admin {
        return Err(forbidden());
    }
    let Json(req) = Json::<KeyCreate>::from_bytes(&body)
        .map_err(|e| ApiError::unprocessable(format!("the body: {}", e.body_text())))?;
    let now = now_ms();
    let expires_at = match req.expires_at.as_deref() {
        None => None,
        Some(t) => Some(keys::expiry_from_rfc3339(t, now).map_err(|e| {
            match e {
                keys::ExpiryError::NotRfc3339 => {
                    ApiError::unprocessable("expires_at must be an RFC 3339 time")
                        .with_error("expires_at", "not RFC 3339")
                }
                keys::ExpiryError::InThePast => {
                    ApiError::unprocessable("expires_at is in the past")
                        .with_error("expires_at", "in the past")
                }
            }
        })?),
    };
    let quota_jobs = whole("quota_jobs", req.quota_jobs, f64::from(u32::MAX))?;
    let quota_bytes = whole("quota_bytes", req.quota_bytes, i64::MAX as f64)?;
    let (key, record) = keys::generate(
        &req.name,
        req.admin,
        quota_jobs,
        quota_bytes,
        expires_at,
        now,
    )
    .map_err(|e| ApiError::unprocessable(e.to_string()).with_error("name", e.to_string()))?;
    state
        .db
        .create_api_key(&record)
        .await
        .map_err(|e| match e {
            DbError::Conflict(m) => ApiError::new(StatusCode::CONFLICT, "conflict", m),
            other => other.into(),
        })?;
    keys::audit("created", &record, &caller.owner);
    let mut v = view(&record);
    v["key"] = Value::String(key);
    Ok((StatusCode::CREATED, Json(v)).into_response())
}

/// `DELETE /v1/keys/{id}`: revokes a key (admin only; others get 404, as for any record they
/// do not own). An admin may not revoke the key it is calling with.
pub async fn revoke(IdRequest { state, caller, id }: IdRequest) -> Result<Response, ApiError> {
    let missing = || ApiError::not_found(format!("no key {id}"));
    if !caller.admin || !id.starts_with("key_") {
        return Err(missing());
    }
    if caller.owner == id {
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            "conflict",
            "an admin key cannot revoke itself; revoke it with another admin key or `sylva keys revoke`",
        ));
    }
    let k = state
        .db
        .revoke_api_key(&id, now_ms())
        .await
        .map_err(|e| match e {
            DbError::NotFound => missing(),
            other => other.into(),
        })?;
    keys::audit("revoked", &k, &caller.owner);
    Ok(Json(view(&k)).into_response())
}
