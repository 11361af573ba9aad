//! `sylva keys`: managed API keys in the job database (create, list, revoke).
//!
//! Every API process sharing the database sees a new or revoked key on its next request: keys
//! are looked up by hash on every request, never cached.

use std::process::ExitCode;

use anyhow::Context;
use clap::{Args, Subcommand};

use sylva::config::{StoreArgs, init_tracing};
use sylva::jobs::{DbError, JobStore, keys, now_ms, rfc3339};

#[derive(Debug, Args)]
pub struct KeysArgs {
    #[command(subcommand)]
    pub action: KeysAction,
}

#[derive(Debug, Subcommand)]
pub enum KeysAction {
    /// Create a key and print it once (it is stored only as its SHA-256).
    Create {
        #[command(flatten)]
        store: StoreArgs,
        /// A unique name for the key (who or what uses it).
        #[arg(long)]
        name: String,
        /// The key sees and manages every owner's records.
        #[arg(long, default_value_t = false)]
        admin: bool,
        /// Unfinished jobs this key may have at once (default: the server's --quota-jobs).
        #[arg(long)]
        quota_jobs: Option<u32>,
        /// Bytes this key may keep on the server (default: the server's --quota-bytes).
        #[arg(long)]
        quota_bytes: Option<u64>,
        /// When the key stops working: an RFC 3339 time (`2027-01-31T00:00:00Z`) or a
        /// duration from now (`90d`, `12h`, `30m`, `45s`). Default: never.
        #[arg(long)]
        expires: Option<String>,
    },
    /// List the keys (never the keys themselves: their first characters, names, rights,
    /// quotas, expiry and revocation).
    List {
        #[command(flatten)]
        store: StoreArgs,
    },
    /// Revoke a key by its id or name; every API process refuses it from its next request.
    Revoke {
        #[command(flatten)]
        store: StoreArgs,
        /// The key's id (`key_…`) or name.
        key: String,
    },
}

/// `--expires` as Unix milliseconds, given the time `now` (Unix ms).
pub fn parse_expiry(text: &str, now: i64) -> anyhow::Result<i64> {
    let t = text.trim();
    let unit = |c: char| match c {
        's' => Some(1_000i64),
        'm' => Some(60_000),
        'h' => Some(3_600_000),
        'd' => Some(86_400_000),
        _ => None,
    };
    if let Some(last) = t.chars().last()
        && let Some(ms) = unit(last)
        && let Ok(n) = t[..t.len() - 1].parse::<i64>()
    {
        anyhow::ensure!(n > 0, "--expires {t:?}: the duration must be positive");
        return Ok(now.saturating_add(n.saturating_mul(ms)));
    }
    keys::expiry_from_rfc3339(t, now).map_err(|e| match e {
        keys::ExpiryError::NotRfc3339 => anyhow::anyhow!(
            "--expires {t:?}: give an RFC 3339 time (2027-01-31T00:00:00Z) or a duration such as 90d, 12h, 30m"
        ),
        keys::ExpiryError::InThePast => anyhow::anyhow!("--expires {t:?} is in the past"),
    })
}

fn describe(k: &keys::ApiKey, now: i64) -> String {
    let state = match (k.revoked_at, k.expires_at) {
        (Some(at), _) => format!("revoked {}", rfc3339(at)),
        (None, Some(e)) if e <= now => format!("expired {}", rfc3339(e)),
        (None, Some(e)) => format!("active until {}", rfc3339(e)),
        (None, None) => "active".to_string(),
    };
    let quota = |q: Option<i64>| q.map_or("server default".to_string(), |v| v.to_string());
    format!(
        "{}\t{}\t{}…\t{}\towner {}\tjobs {}\tbytes {}\tcreated {}\t{}",
        k.id,
        k.name,
        k.prefix,
        if k.admin { "admin" } else { "user" },
        k.owner(),
        quota(k.quota_jobs),
        quota(k.quota_bytes),
        rfc3339(k.created_at),
        state
    )
}

async fn open(store: &StoreArgs) -> anyhow::Result<JobStore> {
    init_tracing(store);
    std::fs::create_dir_all(&store.data)
        .with_context(|| format!("cannot create the data directory {}", store.data.display()))?;
    let location = store.database()?;
    JobStore::open(&location, 2)
        .await
        .with_context(|| format!("cannot open the job database {location}"))
}

pub async fn run(a: KeysArgs) -> anyhow::Result<ExitCode> {
    let now = now_ms();
    match a.action {
        KeysAction::Create {
            store,
            name,
            admin,
            quota_jobs,
            quota_bytes,
            expires,
        } => {
            let db = open(&store).await?;
            let expires_at = expires
                .as_deref()
                .map(|e| parse_expiry(e, now))
                .transpose()?;
            let quota_bytes = quota_bytes
                .map(|b| i64::try_from(b).context("--quota-bytes is too large"))
                .transpose()?;
            let (key, record) = keys::generate(
                &name,
                admin,
                quota_jobs.map(i64::from),
                quota_bytes,
                expires_at,
                now,
            )?;
            db.create_api_key(&record).await.map_err(|e| match e {
                DbError::Conflict(m) => anyhow::anyhow!("{m}; choose another --name"),
                other => other.into(),
            })?;
            keys::audit("created", &record, "cli");
            eprintln!(
                "created {} ({}); the key is shown this once, keep it secret:",
                record.id, record.name
            );
            println!("{key}");
        }
        KeysAction::List { store } => {
            let db = open(&store).await?;
            let all = db.api_keys().await?;
            if all.is_empty() {
                eprintln!("no managed keys (create one with `sylva keys create --name NAME`)");
            }
            for k in &all {
                println!("{}", describe(k, now));
            }
        }
        KeysAction::Revoke { store, key } => {
            let db = open(&store).await?;
            // An id first, then a name (names are unique; an id is never taken as a name).
            let all = db.api_keys().await?;
            let id = all
                .iter()
                .find(|k| k.id == key)
                .or_else(|| all.iter().find(|k| k.name == key))
                .map(|k| k.id.clone())
                .ok_or_else(|| {
                    anyhow::anyhow!("no key with id or name {key:?} (see `sylva keys list`)")
                })?;
            let k = db.revoke_api_key(&id, now).await?;
            keys::audit("revoked", &k, "cli");
            println!("{}", describe(&k, now));
        }
    }
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::parse_expiry;

    #[test]
    fn expiry_is_a_time_or_a_duration_from_now() {
        assert_eq!(
            parse_expiry("90d", 1_000).ok(),
            Some(1_000 + 90 * 86_400_000)
        );
        assert_eq!(parse_expiry("2s", 0).ok(), Some(2_000));
        assert_eq!(
            parse_expiry("2030-01-01T00:00:00Z", 0).ok(),
            Some(1_893_456_000_000)
        );
        assert!(parse_expiry("2001-01-01T00:00:00Z", 1_893_456_000_000).is_err());
        assert!(parse_expiry("soon", 0).is_err());
        assert!(parse_expiry("0d", 0).is_err());
    }
}
