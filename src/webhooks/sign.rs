//! Signing: every delivery carries `Sylva-Signature: t=<unix seconds>,v1=<hex>`, where the
//! hex is HMAC-SHA256, keyed with the job owner's secret, of `<t>.<body>` (the timestamp, a
//! full stop, then the raw body bytes). Signing the timestamp with the body lets a receiver
//! refuse replays: it recomputes the HMAC, compares in constant time, and rejects a `t` too
//! far from its own clock (five minutes is usual).
//!
//! Each token has its own secret, derived on the server as HMAC-SHA256(server key,
//! "sylva-webhook-secret/v1:" + owner id), so nothing per token is stored and every process
//! with the same key derives the same secrets. The key is `--webhook-key`, or else a random
//! one generated once and kept in the job database.
//!
//! Rotation is per owner (`POST /v1/webhooks/secret/rotate`): the database keeps each owner's
//! generation, the derivation appends `#<generation>` after the first rotation, and for
//! [`crate::config::WebhookArgs::webhook_rotation_grace_secs`] after a rotation deliveries
//! carry two `v1=` signatures, the new secret's and the old one's, so receivers can switch
//! at their own pace.

use std::sync::Arc;

use hmac::{Hmac, KeyInit, Mac};
use sha2::Sha256;

use crate::jobs::keys::SecretGeneration;
use crate::jobs::{DbError, JobStore};

type HmacSha256 = Hmac<Sha256>;

/// Header with the timestamp and the signature(s).
pub const SIGNATURE_HEADER: &str = "Sylva-Signature";
/// Header with the same timestamp alone (Unix seconds), for receivers' logs.
pub const TIMESTAMP_HEADER: &str = "Sylva-Timestamp";
/// Header naming the event (`job.succeeded`, ...).
pub const EVENT_HEADER: &str = "Sylva-Event";
/// Header with the delivery id, the same on every attempt: receivers deduplicate by it.
pub const DELIVERY_HEADER: &str = "Sylva-Delivery";

/// Prefix of every secret, so one pasted in the wrong place is recognisable.
const SECRET_PREFIX: &str = "whsec_";
/// Domain separation of the secret derivation.
const SECRET_CONTEXT: &str = "sylva-webhook-secret/v1:";
/// Name of the generated key in the database's settings.
const KEY_SETTING: &str = "webhook_key";

fn mac(key: &[u8]) -> HmacSha256 {
    // HMAC takes keys of any length, so this never fails; the fallback keeps it total.
    HmacSha256::new_from_slice(key).unwrap_or_else(|_| HmacSha256::new(&Default::default()))
}

/// Derives the per-owner webhook secrets from the server's key.
#[derive(Clone)]
pub struct Signer {
    key: Arc<[u8]>,
}

impl std::fmt::Debug for Signer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Signer { key: *** }")
    }
}

impl Signer {
    pub fn from_key(key: &[u8]) -> Self {
        Self { key: key.into() }
    }

    /// The key `configured` (`--webhook-key`), or the one kept in the job database, created
    /// there (random) by the first process that needs it.
    pub async fn load(db: &JobStore, configured: Option<&str>) -> Result<Self, DbError> {
        if let Some(key) = configured.filter(|k| !k.is_empty()) {
            return Ok(Self::from_key(key.as_bytes()));
        }
        // UUID v4s come from the operating system's random source (getrandom): two hold 244
        // random bits.
        let fresh = format!(
            "{}{}",
            uuid::Uuid::new_v4().simple(),
            uuid::Uuid::new_v4().simple()
        );
        let key = db.setting_or_insert(KEY_SETTING, &fresh).await?;
        Ok(Self::from_key(key.as_bytes()))
    }

    /// The webhook secret of `owner` ([`crate::jobs::owner_id`] of a token; "" with
    /// authentication off): `whsec_` and 64 hex digits.
    pub fn secret(&self, owner: &str) -> String {
        self.secret_at(owner, 0)
    }

    /// The webhook secret of `owner` at rotation `generation` (0: never rotated, the same as
    /// [`Signer::secret`]; each `POST /v1/webhooks/secret/rotate` moves one owner to the next).
    pub fn secret_at(&self, owner: &str, generation: i64) -> String {
        let mut m = mac(&self.key);
        m.update(SECRET_CONTEXT.as_bytes());
        m.update(owner.as_bytes());
        if generation > 0 {
            m.update(format!("#{generation}").as_bytes());
        }
        format!("{SECRET_PREFIX}{}", hex::encode(m.finalize().into_bytes()))
    }

    /// The secrets that sign `owner`'s deliveries at `now_ms`: the current one, then the
    /// previous one while its grace period lasts.
    pub fn signing_secrets(&self, owner: &str, g: &SecretGeneration, now_ms: i64) -> Vec<String> {
        let mut out = vec![self.secret_at(owner, g.generation)];
        if g.generation > 0 && now_ms < g.previous_until {
            out.push(self.secret_at(owner, g.generation - 1));
        }
        out
    }
}

/// Hex HMAC-SHA256 under `secret` (its UTF-8 bytes, prefix included) of `<t>.<body>`.
pub fn signature(secret: &str, timestamp: i64, body: &[u8]) -> String {
    let mut m = mac(secret.as_bytes());
    m.update(timestamp.to_string().as_bytes());
    m.update(b".");
    m.update(body);
    hex::encode(m.finalize().into_bytes())
}

/// The `Sylva-Signature` value: `t=<timestamp>,v1=<signature>`.
pub fn signature_header(secret: &str, timestamp: i64, body: &[u8]) -> String {
    signature_header_all(&[secret], timestamp, body)
}

/// The `Sylva-Signature` value with one `v1=` entry per secret, in order (during a rotation's
/// grace period: the new secret's, then the old one's), so a receiver holding either verifies.
pub fn signature_header_all<S: AsRef<str>>(secrets: &[S], timestamp: i64, body: &[u8]) -> String {
    let mut h = format!("t={timestamp}");
    for s in secrets {
        h.push_str(",v1=");
        h.push_str(&signature(s.as_ref(), timestamp, body));
    }
    h
}

/// Why a signature did not verify.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum VerifyError {
    #[error("the signature header has no t= timestamp")]
    NoTimestamp,
    #[error("the timestamp is {0} s away from now, more than the tolerance")]
    Stale(i64),
    #[error("no v1 signature matches")]
    Mismatch,
}

/// What a receiver does: checks a `Sylva-Signature` value against `body` with `secret`,
/// refusing timestamps more than `tolerance_secs` from `now_secs`. Any of several `v1=`
/// entries may match.
pub fn verify(
    secret: &str,
    header: &str,
    body: &[u8],
    now_secs: i64,
    tolerance_secs: i64,
) -> Result<(), VerifyError> {
    let mut t = None;
    let mut sigs = Vec::new();
    for part in header.split(',') {
        match part.trim().split_once('=') {
            Some(("t", v)) => t = v.parse::<i64>().ok(),
            Some(("v1", v)) => sigs.push(v),
            _ => {}
        }
    }
    let t = t.ok_or(VerifyError::NoTimestamp)?;
    if (now_secs - t).abs() > tolerance_secs {
        return Err(VerifyError::Stale(now_secs - t));
    }
    let ok = sigs.iter().any(|sig| {
        let Ok(bytes) = hex::decode(sig) else {
            return false;
        };
        let mut m = mac(secret.as_bytes());
        m.update(t.to_string().as_bytes());
        m.update(b".");
        m.update(body);
        // verify_slice compares in constant time.
        m.verify_slice(&bytes).is_ok()
    });
    if ok {
        Ok(())
    } else {
        Err(VerifyError::Mismatch)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn secrets_differ_per_owner_and_key_and_are_stable() {
        let a = Signer::from_key(b"key-a");
        let b = Signer::from_key(b"key-b");
        assert_eq!(a.secret("t1"), a.secret("t1"));
        assert_ne!(a.secret("t1"), a.secret("t2"));
        assert_ne!(a.secret("t1"), b.secret("t1"));
        assert!(a.secret("").starts_with("whsec_"));
        assert_eq!(a.secret("").len(), 6 + 64);
        assert_eq!(format!("{a:?}"), "Signer { key: *** }");
    }

    #[test]
    fn a_rotation_changes_one_owners_secret_and_signs_with_both_during_the_grace() {
        let s = Signer::from_key(b"key");
        assert_eq!(s.secret_at("t1", 0), s.secret("t1"));
        assert_ne!(s.secret_at("t1", 1), s.secret("t1"));
        assert_ne!(s.secret_at("t1", 1), s.secret_at("t1", 2));
        let g = SecretGeneration {
            generation: 2,
            rotated_at: 1_000,
            previous_until: 5_000,
        };
        let during = s.signing_secrets("t1", &g, 4_999);
        assert_eq!(during, vec![s.secret_at("t1", 2), s.secret_at("t1", 1)]);
        assert_eq!(
            s.signing_secrets("t1", &g, 5_000),
            vec![s.secret_at("t1", 2)]
        );
        let body = b"{}";
        let h = signature_header_all(&during, 100, body);
        assert_eq!(verify(&s.secret_at("t1", 1), &h, body, 100, 300), Ok(()));
        assert_eq!(verify(&s.secret_at("t1", 2), &h, body, 100, 300), Ok(()));
        assert_eq!(
            verify(&s.secret_at("t1", 0), &h, body, 100, 300),
            Err(VerifyError::Mismatch)
        );
    }

    #[test]
    fn a_signature_verifies_only_for_its_body_secret_and_time() {
        let secret = "whsec_test";
        let body = br#"{"id":"d1","type":"job.succeeded"}"#;
        let h = signature_header(secret, 1_700_000_000, body);
        assert!(h.starts_with("t=1700000000,v1="));
        assert_eq!(verify(secret, &h, body, 1_700_000_100, 300), Ok(()));
        assert_eq!(
            verify(secret, &h, b"{}", 1_700_000_100, 300),
            Err(VerifyError::Mismatch)
        );
        assert_eq!(
            verify("whsec_other", &h, body, 1_700_000_100, 300),
            Err(VerifyError::Mismatch)
        );
        assert_eq!(
            verify(secret, &h, body, 1_700_001_000, 300),
            Err(VerifyError::Stale(1000))
        );
        // A replayed body under a new timestamp needs a new signature.
        let forged = h.replace("t=1700000000", "t=1700000900");
        assert_eq!(
            verify(secret, &forged, body, 1_700_000_900, 300),
            Err(VerifyError::Mismatch)
        );
        assert_eq!(
            verify(secret, "v1=00", body, 0, 300),
            Err(VerifyError::NoTimestamp)
        );
    }

    #[test]
    fn the_signature_is_plain_hmac_sha256_of_timestamp_dot_body() {
        // The HMAC itself: RFC 4231, test case 2. Then the signed text: `<t>.<body>`.
        let mut m = mac(b"Jefe");
        m.update(b"what do ya want for nothing?");
        assert_eq!(
            hex::encode(m.finalize().into_bytes()),
            "5bdcc146bf60754e6a042426089575c75a003f089d2739839dec58b964ec3843"
        );
        let mut m = mac(b"s");
        m.update(b"42.{}");
        assert_eq!(
            signature("s", 42, b"{}"),
            hex::encode(m.finalize().into_bytes())
        );
    }
}
