//! Managed API keys and per-owner webhook secret generations (issue 25), over both databases.
//!
//! A key is `sylva_` and 64 hex digits: 256 bits from the operating system's random source.
//! Only its SHA-256 is stored; the key is printed once by `sylva keys create`. The records a
//! key creates carry the key's id as their owner id ([`key_owner`]); static `--token` values keep
//! theirs ([`super::owner_id`]).
//!
//! Their queries are the job store's (`src/jobs/queries.rs`, written once for both databases;
//! flags are integer columns there).

use serde::Serialize;
use sha2::{Digest, Sha256};

use super::DbError;

/// Prefix of every managed key, so one pasted in the wrong place is recognisable.
pub const KEY_PREFIX: &str = "sylva_";
/// Random bytes in a key (256 bits, the floor).
pub const KEY_BYTES: usize = 32;
/// Characters of a key kept in its record and shown in lists (`sylva_` and 6 hex digits:
/// 24 bits, useless to an attacker).
pub const SHOWN_PREFIX_CHARS: usize = 12;

/// A managed API key as stored (without the key itself).
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ApiKey {
    /// Stable id (`key_` and 16 hex digits), also the owner id of its records.
    pub id: String,
    /// Unique human name (`sylva keys create --name`).
    pub name: String,
    /// Hex SHA-256 of the key.
    #[serde(skip)]
    pub hash: String,
    /// The key's first [`SHOWN_PREFIX_CHARS`] characters.
    pub prefix: String,
    /// Sees and manages every owner's records.
    pub admin: bool,
    /// Unfinished jobs this key may have (`None`: the server's `--quota-jobs`).
    pub quota_jobs: Option<i64>,
    /// Bytes this key may keep on the server (`None`: the server's `--quota-bytes`).
    pub quota_bytes: Option<i64>,
    /// Unix milliseconds.
    pub created_at: i64,
    /// Unix milliseconds after which the key is refused (`None`: never).
    pub expires_at: Option<i64>,
    /// Unix milliseconds at which it was revoked.
    pub revoked_at: Option<i64>,
}

impl ApiKey {
    /// The owner id of the records this key creates.
    pub fn owner(&self) -> String {
        key_owner(&self.id)
    }

    /// Whether the key is accepted at `now_ms`.
    pub fn usable_at(&self, now_ms: i64) -> bool {
        self.revoked_at.is_none() && self.expires_at.is_none_or(|e| now_ms < e)
    }
}

/// The owner id of key `id`'s records: the id itself (`key_…`, never the shape of a static
/// token's owner id, `t` and hex).
pub fn key_owner(id: &str) -> String {
    id.to_string()
}

/// Hex SHA-256 of a presented key: what [`ApiKey::hash`] stores. The key carries 256 random
/// bits, so a fast hash is enough (no password stretching needed).
pub fn key_hash(key: &str) -> String {
    hex::encode(Sha256::digest(key.as_bytes()))
}

/// Whether `presented` has the shape of a managed key (it may still be unknown or revoked).
pub fn looks_like_key(presented: &str) -> bool {
    presented.len() == KEY_PREFIX.len() + 2 * KEY_BYTES
        && presented.starts_with(KEY_PREFIX)
        && presented[KEY_PREFIX.len()..]
            .bytes()
            .all(|b| b.is_ascii_hexdigit())
}

/// Why a key's expiry time was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ExpiryError {
    /// Not an RFC 3339 time.
    NotRfc3339,
    /// At or before now.
    InThePast,
}

/// An expiry given as an RFC 3339 time, in Unix milliseconds; it must lie after `now_ms`.
/// Shared by `sylva keys create --expires` and `POST /v1/keys`.
pub fn expiry_from_rfc3339(text: &str, now_ms: i64) -> Result<i64, ExpiryError> {
    let at =
        time::OffsetDateTime::parse(text.trim(), &time::format_description::well_known::Rfc3339)
            .map_err(|_| ExpiryError::NotRfc3339)?;
    let ms = i64::try_from(at.unix_timestamp_nanos() / 1_000_000).unwrap_or(i64::MAX);
    if ms <= now_ms {
        return Err(ExpiryError::InThePast);
    }
    Ok(ms)
}

/// A new random key and its record (not yet stored).
pub fn generate(
    name: &str,
    admin: bool,
    quota_jobs: Option<i64>,
    quota_bytes: Option<i64>,
    expires_at: Option<i64>,
    now_ms: i64,
) -> Result<(String, ApiKey), DbError> {
    let name = name.trim();
    if name.is_empty() || name.len() > 100 || name.chars().any(char::is_control) {
        return Err(DbError::Invalid(
            "a key's name must be 1 to 100 printable characters".into(),
        ));
    }
    let mut secret = [0u8; KEY_BYTES];
    getrandom::fill(&mut secret)
        .map_err(|e| DbError::Invalid(format!("no random source for a new key: {e}")))?;
    let mut id = [0u8; 8];
    getrandom::fill(&mut id)
        .map_err(|e| DbError::Invalid(format!("no random source for a new key: {e}")))?;
    let key = format!("{KEY_PREFIX}{}", hex::encode(secret));
    let record = ApiKey {
        id: format!("key_{}", hex::encode(id)),
        name: name.to_string(),
        hash: key_hash(&key),
        prefix: key[..SHOWN_PREFIX_CHARS].to_string(),
        admin,
        quota_jobs,
        quota_bytes,
        created_at: now_ms,
        expires_at,
        revoked_at: None,
    };
    Ok((key, record))
}

/// The audit line of a key's creation or revocation (`by`: the owner id of the admin key that
/// did it, or `"cli"` for `sylva keys`). Never the key itself.
pub fn audit(event: &str, k: &ApiKey, by: &str) {
    tracing::info!(
        target: "audit",
        key_id = %k.id,
        name = %k.name,
        admin = k.admin,
        by = %by,
        "API key {event}"
    );
}

/// Where an owner's webhook secret stands: its generation (0 until the first rotation) and,
/// for a grace period after a rotation, the previous generation still signed with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
pub struct SecretGeneration {
    pub generation: i64,
    /// Unix ms of the last rotation (0: never rotated).
    pub rotated_at: i64,
    /// Unix ms until which the previous generation's secret is still used (0: none).
    pub previous_until: i64,
}

pub(super) const KEY_COLUMNS: &str = "id, name, hash, prefix, admin, quota_jobs, quota_bytes, created_at, \
                           expires_at, revoked_at";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_are_256_random_bits_and_only_their_hash_is_kept() {
        let (a, ra) = generate("alice", false, None, None, None, 5).expect("key");
        let (b, rb) = generate("bob", true, Some(3), None, Some(10), 5).expect("key");
        assert!(looks_like_key(&a) && looks_like_key(&b));
        assert_eq!(a.len(), KEY_PREFIX.len() + 64);
        assert_ne!(a, b);
        assert_ne!(ra.id, rb.id);
        assert_eq!(ra.hash, key_hash(&a));
        assert!(!ra.hash.contains(&a[KEY_PREFIX.len()..]));
        assert_eq!(ra.prefix, a[..SHOWN_PREFIX_CHARS]);
        assert!(ra.usable_at(6));
        assert!(rb.usable_at(9) && !rb.usable_at(10));
        assert!(!looks_like_key("sylva_xyz"));
        assert!(generate(" ", false, None, None, None, 0).is_err());
    }
}
