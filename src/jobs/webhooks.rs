//! Webhook records of the job store: what a job asked to be told ([`WebhookSpec`]), the
//! events it may be told of ([`WebhookEvent`]), and the outbox rows ([`Delivery`]) that
//! dispatchers claim, send and reschedule.
//!
//! A delivery row is written in the same transaction as the state change it reports (a job
//! ending, a stage finishing), so a crash can lose neither. Its body is fixed when it is
//! written: every attempt sends (and signs) the same bytes, and receivers deduplicate by the
//! delivery id, since delivery is at least once (a dispatcher that dies after the receiver
//! answered but before it recorded the answer sends again once its lease runs out).

use serde::{Deserialize, Deserializer, Serialize, Serializer};
use serde_json::{Value, json};

use super::{JobState, rfc3339};

/// What a webhook can announce.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum WebhookEvent {
    JobSucceeded,
    JobFailed,
    JobCanceled,
    /// A stage finished (its outputs are written; the job goes on).
    StageFinished,
}

impl WebhookEvent {
    pub const ALL: &'static [WebhookEvent] = &[
        WebhookEvent::JobSucceeded,
        WebhookEvent::JobFailed,
        WebhookEvent::JobCanceled,
        WebhookEvent::StageFinished,
    ];

    /// The events a webhook gets when it names none: the job's end, whichever it is.
    pub const DEFAULT: &'static [WebhookEvent] = &[
        WebhookEvent::JobSucceeded,
        WebhookEvent::JobFailed,
        WebhookEvent::JobCanceled,
    ];

    pub fn as_str(self) -> &'static str {
        match self {
            WebhookEvent::JobSucceeded => "job.succeeded",
            WebhookEvent::JobFailed => "job.failed",
            WebhookEvent::JobCanceled => "job.canceled",
            WebhookEvent::StageFinished => "stage.finished",
        }
    }

    pub fn parse(s: &str) -> Option<Self> {
        Self::ALL.iter().copied().find(|e| e.as_str() == s)
    }

    /// The event announcing that a job reached `state`, if that state ends it.
    pub fn for_end(state: JobState) -> Option<Self> {
        match state {
            JobState::Succeeded => Some(WebhookEvent::JobSucceeded),
            JobState::Failed => Some(WebhookEvent::JobFailed),
            JobState::Canceled => Some(WebhookEvent::JobCanceled),
            _ => None,
        }
    }
}

impl Serialize for WebhookEvent {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.as_str())
    }
}

impl<'de> Deserialize<'de> for WebhookEvent {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let text = String::deserialize(d)?;
        WebhookEvent::parse(&text).ok_or_else(|| {
            let known: Vec<&str> = WebhookEvent::ALL.iter().map(|e| e.as_str()).collect();
            serde::de::Error::custom(format!(
                "unknown event {text:?}; expected one of {}",
                known.join(", ")
            ))
        })
    }
}

/// A job's webhook, as accepted at submission (the URL already checked by the API).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WebhookSpec {
    pub url: String,
    /// Events to deliver (default [`WebhookEvent::DEFAULT`]).
    #[serde(default = "default_events")]
    pub events: Vec<WebhookEvent>,
}

fn default_events() -> Vec<WebhookEvent> {
    WebhookEvent::DEFAULT.to_vec()
}

impl WebhookSpec {
    pub fn wants(&self, event: WebhookEvent) -> bool {
        self.events.contains(&event)
    }
}

macro_rules! delivery_states {
    ($($variant:ident => $text:literal),+ $(,)?) => {
        /// Where a delivery stands.
        #[derive(Debug, Clone, Copy, PartialEq, Eq)]
        pub enum DeliveryState { $($variant),+ }

        impl DeliveryState {
            pub const ALL: &'static [DeliveryState] = &[$(DeliveryState::$variant),+];
            pub fn as_str(self) -> &'static str {
                match self { $(DeliveryState::$variant => $text),+ }
            }
            pub fn parse(s: &str) -> Option<Self> {
                match s { $($text => Some(DeliveryState::$variant),)+ _ => None }
            }
        }
    };
}

delivery_states! {
    // Not yet delivered: waiting for its next attempt, or being sent.
    Pending => "pending",
    // The receiver answered 2xx.
    Delivered => "delivered",
    // Given up after the last attempt allowed.
    Failed => "failed",
}

/// A delivery claimed by a dispatcher, to send now.
#[derive(Debug, Clone)]
pub struct Delivery {
    pub id: String,
    pub job_id: String,
    /// Owner of the job: whose secret signs the body.
    pub owner: String,
    pub url: String,
    pub event: String,
    pub body: String,
    /// Attempts so far, this one included (1 on the first).
    pub attempts: i64,
    /// When the event happened (ms since the epoch).
    pub created_at: i64,
    /// Fencing token of this claim: only its holder may record the outcome.
    pub token: String,
}

/// A delivery as the API shows it.
#[derive(Debug, Clone)]
pub struct DeliveryRecord {
    pub id: String,
    pub event: String,
    pub url: String,
    pub state: DeliveryState,
    pub attempts: i64,
    /// When the next attempt is due (pending deliveries only), ms since the epoch.
    pub next_attempt_at: Option<i64>,
    /// HTTP status of the last answer, if the receiver answered at all.
    pub last_status: Option<i64>,
    /// Why the last attempt failed.
    pub last_error: Option<String>,
    pub created_at: i64,
    /// When it was delivered or given up.
    pub finished_at: Option<i64>,
}

/// How one attempt went, as the dispatcher records it.
#[derive(Debug, Clone)]
pub enum DeliveryOutcome {
    /// The receiver answered 2xx.
    Delivered { status: u16 },
    /// Try again after `delay_ms` milliseconds.
    Retry {
        status: Option<u16>,
        error: String,
        delay_ms: i64,
    },
    /// The last attempt allowed failed.
    GiveUp { status: Option<u16>, error: String },
}

/// The job as an event reports it, read inside the transaction that changed it.
#[derive(Debug, Clone)]
pub(crate) struct EventJob {
    pub id: String,
    pub owner: String,
    pub webhook: Option<String>,
    pub state: String,
    pub stage: Option<String>,
    pub attempt: i64,
    pub error: Option<Value>,
}

/// A delivery row to insert.
#[derive(Debug, Clone)]
pub(crate) struct NewDelivery {
    pub id: String,
    pub url: String,
    pub event: &'static str,
    pub body: String,
}

/// The delivery announcing `event` of `job` at `now` (ms), or `None` when the job has no
/// webhook or its webhook does not want this event. `stage` names the finished stage of a
/// `stage.finished` event.
pub(crate) fn new_delivery(
    job: &EventJob,
    event: WebhookEvent,
    stage: Option<&str>,
    now: i64,
) -> Option<NewDelivery> {
    let spec: WebhookSpec = serde_json::from_str(job.webhook.as_deref()?).ok()?;
    if !spec.wants(event) {
        return None;
    }
    let id = uuid::Uuid::now_v7().simple().to_string();
    let mut data = json!({
        "job": {
            "id": job.id,
            "state": job.state,
            "stage": job.stage,
            "attempt": job.attempt,
            "error": job.error,
            "href": format!("/v1/jobs/{}", job.id),
        }
    });
    if let Some(stage) = stage {
        data["stage"] = json!({ "name": stage });
    }
    let body = json!({
        "id": id,
        "type": event.as_str(),
        "created_at": rfc3339(now),
        "data": data,
    });
    Some(NewDelivery {
        id,
        url: spec.url,
        event: event.as_str(),
        body: body.to_string(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job(webhook: Option<&str>) -> EventJob {
        EventJob {
            id: "j1".into(),
            owner: String::new(),
            webhook: webhook.map(String::from),
            state: "succeeded".into(),
            stage: Some("export".into()),
            attempt: 1,
            error: None,
        }
    }

    #[test]
    fn events_default_to_the_end_of_the_job_and_unknown_ones_are_refused() {
        let spec: WebhookSpec = serde_json::from_str(r#"{"url": "http://h/x"}"#).expect("spec");
        assert_eq!(spec.events, WebhookEvent::DEFAULT);
        assert!(!spec.wants(WebhookEvent::StageFinished));
        let e = serde_json::from_str::<WebhookSpec>(r#"{"url": "u", "events": ["job.done"]}"#);
        assert!(e.is_err_and(|e| e.to_string().contains("job.succeeded")));
        for e in WebhookEvent::ALL {
            assert_eq!(WebhookEvent::parse(e.as_str()), Some(*e));
        }
    }

    #[test]
    fn a_delivery_is_made_only_for_wanted_events() {
        assert!(new_delivery(&job(None), WebhookEvent::JobSucceeded, None, 0).is_none());
        let j = job(Some(r#"{"url": "http://h/x"}"#));
        assert!(new_delivery(&j, WebhookEvent::StageFinished, Some("ingest"), 0).is_none());
        let d = new_delivery(&j, WebhookEvent::JobSucceeded, None, 0).expect("delivery");
        let body: Value = serde_json::from_str(&d.body).expect("json");
        assert_eq!(body["id"], d.id.as_str());
        assert_eq!(body["type"], "job.succeeded");
        assert_eq!(body["data"]["job"]["href"], "/v1/jobs/j1");
        assert_eq!(d.url, "http://h/x");
    }
}
