//! Webhook routes: a caller's signing secret and its rotation, and a job's deliveries.

use axum::Json;
use axum::extract::{Extension, State};
use axum::response::{IntoResponse, Response};
use serde_json::{Value, json};

use super::auth::Caller;
use super::problem::ApiError;
use super::{AppState, IdRequest, jobs, views};
use crate::jobs::keys::SecretGeneration;
use crate::jobs::{now_ms, rfc3339};
use crate::webhooks::sign::{DELIVERY_HEADER, EVENT_HEADER, SIGNATURE_HEADER, TIMESTAMP_HEADER};

/// The caller's webhook secret state as the API shows it.
fn secret_view(state: &AppState, caller: &Caller, g: &SecretGeneration) -> Value {
    // The same rule that picks the secrets deliveries are signed with: current, then the
    // previous one while its grace period lasts.
    let secrets = state
        .webhooks
        .signer
        .signing_secrets(&caller.owner, g, now_ms());
    let previous = secrets.get(1).map(|old| {
        json!({
            "secret": old,
            "valid_until": rfc3339(g.previous_until),
        })
    });
    json!({
        "secret": secrets.first(),
        "generation": g.generation,
        "rotated_at": (g.rotated_at > 0).then(|| rfc3339(g.rotated_at)),
        "previous": previous,
        "algorithm": "HMAC-SHA256",
        "signed_content": "<t>.<body>: the Unix-seconds timestamp t of the signature header, a full stop, then the raw request body",
        "rotation": "POST /v1/webhooks/secret/rotate gives this key a new secret; for the grace period after it, deliveries carry two v1= signatures (new secret, then old), so a receiver holding either verifies",
        "headers": {
            "signature": SIGNATURE_HEADER,
            "timestamp": TIMESTAMP_HEADER,
            "event": EVENT_HEADER,
            "delivery": DELIVERY_HEADER,
        },
    })
}

/// `GET /v1/webhooks/secret`: the secret that signs the deliveries of the caller's jobs (and,
/// during a rotation's grace period, the previous one).
pub async fn secret(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
) -> Result<Response, ApiError> {
    let g = state.db.secret_generation(&caller.owner).await?;
    Ok(Json(secret_view(&state, &caller, &g)).into_response())
}

/// `POST /v1/webhooks/secret/rotate`: a new secret for the caller's key alone; the old one
/// still signs (beside the new) for `--webhook-rotation-grace-secs`.
pub async fn rotate(
    State(state): State<AppState>,
    Extension(caller): Extension<Caller>,
) -> Result<Response, ApiError> {
    let grace_ms = (state.args.webhook_rotation_grace_secs as i64).saturating_mul(1000);
    let g = state
        .db
        .rotate_secret(&caller.owner, now_ms(), grace_ms)
        .await?;
    tracing::info!(
        target: "audit",
        owner = %caller.owner,
        generation = g.generation,
        "webhook secret rotated"
    );
    Ok(Json(secret_view(&state, &caller, &g)).into_response())
}

/// `GET /v1/jobs/{id}/webhooks`: the job's webhook and every delivery made for it.
pub async fn deliveries(IdRequest { state, caller, id }: IdRequest) -> Result<Response, ApiError> {
    let job = jobs::load(&state, &caller, &id).await?;
    let deliveries: Vec<Value> = state
        .db
        .job_deliveries(&job.id)
        .await?
        .iter()
        .map(views::delivery)
        .collect();
    Ok(Json(json!({
        "job_id": job.id,
        "webhook": job.webhook.as_ref().map(views::webhook).unwrap_or(Value::Null),
        "deliveries": deliveries,
    }))
    .into_response())
}
