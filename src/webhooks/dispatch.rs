//! The dispatcher: claims due deliveries from the outbox, sends them, records the outcome.
//!
//! One round claims up to [`BATCH`] due deliveries for a lease of twice the attempt timeout
//! plus [`LEASE_MARGIN`], sends them concurrently, and records each outcome with the
//! claim's token, so a dispatcher whose lease ran out (and whose delivery another took)
//! writes nothing. The HTTP client follows no redirects (a 3xx counts as a failure), uses no
//! proxy, and resolves names through [`PolicyResolver`], so every attempt re-checks the
//! target's addresses.

use std::error::Error as _;
use std::sync::Arc;
use std::time::Duration;

use reqwest::header::CONTENT_TYPE;
use tokio::sync::watch;

use super::Webhooks;
use super::sign::{
    DELIVERY_HEADER, EVENT_HEADER, SIGNATURE_HEADER, TIMESTAMP_HEADER, signature_header_all,
};
use super::target::PolicyResolver;
use crate::config::WebhookArgs;
use crate::jobs::{DbError, Delivery, DeliveryOutcome, JobStore, now_ms};

/// Deliveries claimed per round (and sent at the same time).
pub const BATCH: i64 = 16;

/// Time a claim's lease leaves, beyond its attempt, to record the outcome.
pub const LEASE_MARGIN: Duration = Duration::from_secs(5);

/// Header with the attempt number (1 on the first), for receivers' logs.
pub const ATTEMPT_HEADER: &str = "Sylva-Attempt";

/// The delay before the next attempt after `attempts` failed ones (>= 1), in milliseconds:
/// `base_ms` doubled per earlier failure, at most `cap_ms`, then drawn from the upper half
/// of that by `jitter` in [0, 1] ("equal jitter": receivers that failed together do not
/// retry together, and each delay stays at least half the nominal one).
pub fn backoff_ms(attempts: i64, base_ms: u64, cap_ms: u64, jitter: f64) -> i64 {
    let doublings = (attempts - 1).clamp(0, 63) as u32;
    let nominal = base_ms
        .saturating_mul(1u64 << doublings.min(62))
        .min(cap_ms);
    let half = nominal / 2;
    let extra = ((nominal - half) as f64 * jitter.clamp(0.0, 1.0)) as u64;
    i64::try_from(half + extra).unwrap_or(i64::MAX)
}

/// A uniform draw in [0, 1) from the operating system's random source: the 48 top bits of
/// a UUID v4 are random.
fn jitter() -> f64 {
    let bits = (uuid::Uuid::new_v4().as_u128() >> 80) as u64;
    bits as f64 / (1u64 << 48) as f64
}

/// `e` with its causes, without the URL (the delivery record names it already).
fn describe(e: reqwest::Error, timeout: Duration) -> String {
    if e.is_timeout() {
        return format!("no answer within {} s", timeout.as_secs());
    }
    let e = e.without_url();
    let mut text = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        let more = c.to_string();
        if !text.contains(&more) {
            text.push_str(": ");
            text.push_str(&more);
        }
        cause = c.source();
    }
    text
}

/// Sends the outbox's deliveries; see the module docs.
pub struct Dispatcher {
    db: JobStore,
    hooks: Webhooks,
    args: WebhookArgs,
    client: reqwest::Client,
}

impl Dispatcher {
    pub fn new(db: JobStore, hooks: Webhooks, args: WebhookArgs) -> Result<Self, reqwest::Error> {
        let client = reqwest::Client::builder()
            .timeout(args.timeout())
            .redirect(reqwest::redirect::Policy::none())
            .no_proxy()
            .dns_resolver(Arc::new(PolicyResolver {
                policy: hooks.policy.clone(),
            }))
            .user_agent(concat!("sylva-webhooks/", env!("CARGO_PKG_VERSION")))
            .build()?;
        Ok(Self {
            db,
            hooks,
            args,
            client,
        })
    }

    /// Sends due deliveries until `shutdown` turns true, looking for them every
    /// `--webhook-poll-ms` (at once again after a full round).
    pub async fn run(self, mut shutdown: watch::Receiver<bool>) {
        let poll = Duration::from_millis(self.args.webhook_poll_ms.max(10));
        while !*shutdown.borrow() {
            let full = match self.dispatch_due().await {
                Ok(n) => n as i64 == BATCH,
                Err(e) => {
                    tracing::warn!(error = %e, "claiming webhook deliveries failed");
                    false
                }
            };
            if full {
                continue;
            }
            tokio::select! {
                _ = tokio::time::sleep(poll) => {}
                _ = shutdown.changed() => {}
            }
        }
    }

    /// One round: claims due deliveries, sends them concurrently and records how each went.
    /// Returns how many it claimed.
    pub async fn dispatch_due(&self) -> Result<usize, DbError> {
        let lease = self.args.timeout() * 2 + LEASE_MARGIN;
        let claimed = self.db.claim_deliveries(lease, BATCH).await?;
        futures::future::join_all(claimed.iter().map(|d| self.deliver(d))).await;
        Ok(claimed.len())
    }

    async fn deliver(&self, d: &Delivery) {
        let outcome = match self.attempt(d).await {
            Ok(status) => {
                tracing::info!(delivery = %d.id, job = %d.job_id, event = %d.event,
                    attempt = d.attempts, status, "webhook delivered");
                DeliveryOutcome::Delivered { status }
            }
            Err((status, error)) => self.after_failure(d, status, error),
        };
        match self.db.finish_delivery(&d.id, &d.token, &outcome).await {
            Ok(true) => {}
            Ok(false) => tracing::warn!(delivery = %d.id,
                "a webhook delivery's lease ran out before its outcome was recorded"),
            Err(e) => tracing::warn!(delivery = %d.id, error = %e,
                "could not record a webhook delivery's outcome; it will be sent again"),
        }
    }

    /// A retry after the backoff, or giving up once the attempts or the age run out.
    fn after_failure(&self, d: &Delivery, status: Option<u16>, error: String) -> DeliveryOutcome {
        let a = &self.args;
        let delay_ms = backoff_ms(
            d.attempts,
            a.webhook_backoff_ms.max(1),
            a.webhook_backoff_max_ms.max(1),
            jitter(),
        );
        let max_age_ms =
            i64::try_from(a.webhook_max_age_secs.saturating_mul(1000)).unwrap_or(i64::MAX / 2);
        let age_ms = now_ms() - d.created_at;
        if d.attempts >= i64::from(a.webhook_max_attempts.max(1))
            || age_ms.saturating_add(delay_ms) > max_age_ms
        {
            tracing::warn!(delivery = %d.id, job = %d.job_id, event = %d.event,
                attempt = d.attempts, error = %error, "webhook delivery given up");
            DeliveryOutcome::GiveUp { status, error }
        } else {
            tracing::info!(delivery = %d.id, job = %d.job_id, event = %d.event,
                attempt = d.attempts, retry_in_ms = delay_ms, error = %error,
                "webhook attempt failed");
            DeliveryOutcome::Retry {
                status,
                error,
                delay_ms,
            }
        }
    }

    /// Sends `d` once: the status of a 2xx answer, or the status (if any) and the reason
    /// of a failure.
    async fn attempt(&self, d: &Delivery) -> Result<u16, (Option<u16>, String)> {
        let url = self
            .hooks
            .policy
            .check_url(&d.url)
            .map_err(|e| (None, format!("refused: {e}")))?;
        let now = now_ms();
        let t = now.div_euclid(1000);
        let generation = self
            .db
            .secret_generation(&d.owner)
            .await
            .map_err(|e| (None, format!("cannot read the owner's webhook secret: {e}")))?;
        let secrets = self
            .hooks
            .signer
            .signing_secrets(&d.owner, &generation, now);
        let resp = self
            .client
            .post(url)
            .header(CONTENT_TYPE, "application/json")
            .header(
                SIGNATURE_HEADER,
                signature_header_all(&secrets, t, d.body.as_bytes()),
            )
            .header(TIMESTAMP_HEADER, t.to_string())
            .header(EVENT_HEADER, &d.event)
            .header(DELIVERY_HEADER, &d.id)
            .header(ATTEMPT_HEADER, d.attempts.to_string())
            .body(d.body.clone())
            .send()
            .await
            .map_err(|e| (None, describe(e, self.args.timeout())))?;
        let status = resp.status();
        if status.is_success() {
            Ok(status.as_u16())
        } else {
            Err((
                Some(status.as_u16()),
                format!("the receiver answered {status}"),
            ))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backoff_doubles_from_the_base_up_to_the_cap_within_its_upper_half() {
        assert_eq!(backoff_ms(1, 1000, 3_600_000, 1.0), 1000);
        assert_eq!(backoff_ms(1, 1000, 3_600_000, 0.0), 500);
        assert_eq!(backoff_ms(2, 1000, 3_600_000, 1.0), 2000);
        assert_eq!(backoff_ms(4, 1000, 3_600_000, 1.0), 8000);
        assert_eq!(backoff_ms(13, 1000, 3_600_000, 1.0), 3_600_000);
        assert_eq!(backoff_ms(500, 1000, 3_600_000, 0.0), 1_800_000);
        assert_eq!(backoff_ms(0, 1000, 3_600_000, 1.0), 1000);
        for a in 1..40 {
            let lo = backoff_ms(a, 1000, 3_600_000, 0.0);
            let hi = backoff_ms(a, 1000, 3_600_000, 1.0);
            let mid = backoff_ms(a, 1000, 3_600_000, jitter());
            assert!(
                lo <= mid && mid <= hi && hi <= 2 * lo + 1,
                "{a}: {lo} {mid} {hi}"
            );
            // The next delay is never shorter than this one's longest.
            assert!(backoff_ms(a + 1, 1000, 3_600_000, 0.0) >= hi.min(1_800_000));
        }
    }

    #[test]
    fn jitter_is_in_the_unit_interval_and_varies() {
        let draws: Vec<f64> = (0..64).map(|_| jitter()).collect();
        assert!(draws.iter().all(|j| (0.0..1.0).contains(j)));
        assert!(draws.iter().any(|j| (j - draws[0]).abs() > 1e-6));
    }
}
