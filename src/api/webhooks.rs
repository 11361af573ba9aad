//! Webhook routes: a caller's signing secret, and a job's deliveries.

use axum::Json;
use axum::extract::{Path, Request, State};
use axum::response::{IntoResponse, Response};
use serde_json::{Value, json};

use super::auth::Caller;
use super::problem::ApiError;
use super::{AppState, jobs, views};
use crate::webhooks::sign::{DELIVERY_HEADER, EVENT_HEADER, SIGNATURE_HEADER, TIMESTAMP_HEADER};

/// `GET /v1/webhooks/secret`: the secret that signs the deliveries of the caller's jobs.
pub async fn secret(State(state): State<AppState>, req: Request) -> Response {
    let caller = Caller::of(&req);
    Json(json!({
        "secret": state.webhooks.signer.secret(&caller.owner),
        "algorithm": "HMAC-SHA256",
        "signed_content": "<t>.<body>: the Unix-seconds timestamp t of the signature header, a full stop, then the raw request body",
        "headers": {
            "signature": SIGNATURE_HEADER,
            "timestamp": TIMESTAMP_HEADER,
            "event": EVENT_HEADER,
            "delivery": DELIVERY_HEADER,
        },
    }))
    .into_response()
}

/// `GET /v1/jobs/{id}/webhooks`: the job's webhook and every delivery made for it.
pub async fn deliveries(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let job = jobs::load(&state, &id).await?;
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
