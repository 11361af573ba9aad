//! Webhooks: a job may name a URL to be told when it ends (or when each stage finishes).
//!
//! The job store writes each notification as a row of an outbox (`webhook_deliveries`) in
//! the same transaction as the change it reports, so neither a crash nor a restart loses
//! one. A [`Dispatcher`] in every `sylva serve` and `sylva worker` process claims due rows
//! with a lease (two dispatchers never send the same row at once), POSTs each body signed
//! (see [`sign`]), and on an error or a non-2xx answer reschedules it with exponential
//! backoff and jitter, until it is delivered or its attempts or age run out. Targets are
//! checked against the address policy (see [`target`]) at submission and again on every
//! attempt.
//!
//! Delivery is at least once: a process that dies after the receiver answered but before
//! it recorded the answer leaves the row to be sent again after its lease. Receivers
//! deduplicate by the `Sylva-Delivery` id.

pub mod dispatch;
pub mod sign;
pub mod target;

use std::sync::Arc;

pub use dispatch::{Dispatcher, backoff_ms};
pub use sign::Signer;
pub use target::{TargetError, TargetPolicy};

use crate::config::WebhookArgs;
use crate::jobs::{DbError, JobStore};

/// Why webhooks could not be set up at start.
#[derive(Debug, thiserror::Error)]
pub enum SetupError {
    #[error("{0}")]
    Config(String),
    #[error("webhook signing key: {0}")]
    Db(#[from] DbError),
}

/// What the API needs of webhooks: the target policy and the secrets.
#[derive(Debug, Clone)]
pub struct Webhooks {
    pub policy: Arc<TargetPolicy>,
    pub signer: Signer,
}

impl Webhooks {
    /// Reads the policy from `args` and loads (or creates) the signing key.
    pub async fn open(db: &JobStore, args: &WebhookArgs) -> Result<Self, SetupError> {
        let policy = TargetPolicy::from_args(args).map_err(SetupError::Config)?;
        let signer = Signer::load(db, args.webhook_key.as_deref()).await?;
        Ok(Self {
            policy: Arc::new(policy),
            signer,
        })
    }
}
