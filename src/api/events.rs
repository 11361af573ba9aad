//! Server-sent events of one job: `job` (the job whenever state, stage or progress changes),
//! `log` (each new log line) and a final `end` when the job is terminal.
//!
//! Workers may run in other processes, so the stream watches the database (every 250 ms)
//! rather than an in-process channel; the `id:` of each event is the last log sequence sent,
//! so a client reconnecting with `Last-Event-ID` misses no line.

use std::convert::Infallible;
use std::time::Duration;

use axum::http::HeaderMap;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use futures::stream::{self, Stream};
use serde_json::Value;

use super::jobs::{load, log_line};
use super::problem::ApiError;
use super::views;
use super::{AppState, IdRequest};

const POLL: Duration = Duration::from_millis(250);

struct Cursor {
    state: AppState,
    id: String,
    last_seq: i64,
    last_job: Option<Value>,
    pending: std::collections::VecDeque<Event>,
    done: bool,
}

/// The fields whose change is worth an event (not `updated_at`, which heartbeats touch).
fn signature(job: &Value) -> Value {
    let mut j = job.clone();
    if let Some(o) = j.as_object_mut() {
        o.remove("updated_at");
        o.remove("eta_seconds");
    }
    j
}

async fn next_events(mut c: Cursor) -> Option<(Result<Event, Infallible>, Cursor)> {
    loop {
        if let Some(ev) = c.pending.pop_front() {
            return Some((Ok(ev), c));
        }
        if c.done {
            return None;
        }
        let job = match c.state.db.get_job(&c.id).await {
            Ok(Some(j)) => j,
            Ok(None) => {
                c.pending
                    .push_back(Event::default().event("end").data("{\"deleted\":true}"));
                c.done = true;
                continue;
            }
            Err(e) => {
                tracing::warn!(error = %e, "event stream read failed");
                tokio::time::sleep(POLL).await;
                continue;
            }
        };
        if let Ok(lines) = c.state.db.log(&c.id, c.last_seq, 1000).await {
            for l in &lines {
                c.last_seq = l.seq;
                c.pending.push_back(
                    Event::default()
                        .event("log")
                        .id(l.seq.to_string())
                        .data(log_line(l).to_string()),
                );
            }
        }
        let view = views::job(&job, c.state.retention());
        let sig = signature(&view);
        if c.last_job.as_ref() != Some(&sig) {
            c.last_job = Some(sig);
            c.pending.push_back(
                Event::default()
                    .event("job")
                    .id(c.last_seq.to_string())
                    .data(view.to_string()),
            );
        }
        if job.state.is_terminal() {
            c.pending.push_back(
                Event::default()
                    .event("end")
                    .id(c.last_seq.to_string())
                    .data(format!("{{\"state\":\"{}\"}}", job.state.as_str())),
            );
            c.done = true;
        }
        if c.pending.is_empty() {
            tokio::time::sleep(POLL).await;
        }
    }
}

pub async fn events(
    IdRequest { state, caller, id }: IdRequest,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    load(&state, &caller, &id).await?;
    let last_seq = headers
        .get("last-event-id")
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.trim().parse::<i64>().ok())
        .filter(|n| *n >= 0)
        .unwrap_or(0);
    let cursor = Cursor {
        state,
        id,
        last_seq,
        last_job: None,
        pending: Default::default(),
        done: false,
    };
    let stream: std::pin::Pin<Box<dyn Stream<Item = Result<Event, Infallible>> + Send>> =
        Box::pin(stream::unfold(cursor, next_events));
    Ok(Sse::new(stream)
        .keep_alive(KeepAlive::new().interval(Duration::from_secs(15)))
        .into_response())
}
