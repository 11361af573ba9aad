//! Bearer-token authentication: managed API keys (records in the job database, looked up by
//! their SHA-256) and static tokens from configuration (compared in constant time); neither
//! is ever logged. With no token configured and no key ever created, authentication is off
//! (a local single-user run).

use axum::extract::{Request, State};
use axum::http::{StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use std::sync::atomic::Ordering;

use subtle::ConstantTimeEq;

use super::AppState;
use super::problem::ApiError;
use crate::jobs::{keys, now_ms};

/// True when `presented` equals one of `tokens`. Every token is compared, whatever the
/// outcome, so timing reveals neither which token matched nor how much of one did.
pub fn token_matches(tokens: &[String], presented: &str) -> bool {
    let mut ok = subtle::Choice::from(0u8);
    for t in tokens {
        ok |= t.as_bytes().ct_eq(presented.as_bytes());
    }
    ok.into()
}

/// Who is calling, set by [`require_token`] on every authenticated route.
#[derive(Debug, Clone, Default)]
pub struct Caller {
    /// Owner id of the caller's records: the key's id (`key_…`) for a managed key, [`crate::jobs::owner_id`]
    /// of a static `--token`, "" with authentication off.
    pub owner: String,
    /// An admin key: sees and manages every owner's records.
    pub admin: bool,
    /// The managed key's name (`None` for static tokens and with authentication off).
    pub key_name: Option<String>,
    /// The key's own quotas, where it has them (else the server's `--quota-jobs`/`--quota-bytes`).
    pub quota_jobs: Option<i64>,
    pub quota_bytes: Option<i64>,
}

impl Caller {
    /// The caller of a request that went through [`require_token`] (anonymous otherwise).
    pub fn of<B>(req: &axum::http::Request<B>) -> Caller {
        req.extensions()
            .get::<Caller>()
            .cloned()
            .unwrap_or_default()
    }

    /// Whether this caller may see a record owned by `owner`: its own, or any for an admin.
    /// Everything else answers exactly as a missing record would.
    pub fn sees(&self, owner: &str) -> bool {
        self.admin || self.owner == owner
    }

    /// The record `id` as `fetch` finds it, if this caller may see it (`owner` gives a record's
    /// owner). A malformed id (not looked up), a missing record and another owner's record all
    /// answer the same 404 ("no {what} {id}"), so existence does not leak.
    pub async fn load_visible<T, Fut>(
        &self,
        what: &str,
        id: &str,
        fetch: impl FnOnce() -> Fut,
        owner: impl Fn(&T) -> &str,
    ) -> Result<T, ApiError>
    where
        Fut: std::future::Future<Output = Result<Option<T>, crate::jobs::DbError>>,
    {
        let found = if super::uploads::valid_id(id) {
            fetch().await?
        } else {
            None
        };
        found
            .filter(|r| self.sees(owner(r)))
            .ok_or_else(|| ApiError::not_found(format!("no {what} {id}")))
    }

    /// The owner filter of a list: `None` (everyone's) for an admin.
    pub fn list_owner(&self) -> Option<&str> {
        (!self.admin).then_some(self.owner.as_str())
    }
}

/// Whether the server asks for a bearer token: static `--token` values are configured, or
/// a managed key was ever created in the database. Once keys exist the answer stays yes (a
/// flag that only ever turns on), so revoking every key never opens the server.
pub(crate) async fn auth_required(state: &AppState) -> Result<bool, ApiError> {
    if !state.args.token.is_empty() || state.keys_exist.load(Ordering::Relaxed) {
        return Ok(true);
    }
    let any = !state.db.api_keys().await?.is_empty();
    if any {
        state.keys_exist.store(true, Ordering::Relaxed);
    }
    Ok(any)
}

fn unauthorized(detail: &str, challenge: &'static str) -> Response {
    ApiError::new(StatusCode::UNAUTHORIZED, "unauthorized", detail)
        .with_header(header::WWW_AUTHENTICATE, challenge)
        .into_response()
}

/// Who presented `token`: a managed key (looked up by its hash on every request, so a
/// revocation is seen by every API process at once), or a static token.
async fn identify(state: &AppState, token: &str) -> Result<Option<Caller>, Response> {
    if keys::looks_like_key(token) {
        let found = state
            .db
            .api_key_by_hash(&keys::key_hash(token))
            .await
            .map_err(|e| ApiError::from(e).into_response())?;
        return match found {
            None => Ok(None),
            Some(k) if k.revoked_at.is_some() => Err(unauthorized(
                "this API key was revoked",
                "Bearer error=\"invalid_token\"",
            )),
            Some(k) if !k.usable_at(now_ms()) => Err(unauthorized(
                "this API key has expired",
                "Bearer error=\"invalid_token\"",
            )),
            Some(k) => Ok(Some(Caller {
                owner: k.owner(),
                admin: k.admin,
                key_name: Some(k.name.clone()),
                quota_jobs: k.quota_jobs,
                quota_bytes: k.quota_bytes,
            })),
        };
    }
    Ok(token_matches(&state.args.token, token).then(|| Caller {
        owner: crate::jobs::owner_id(token),
        ..Caller::default()
    }))
}

pub async fn require_token(
    State(state): State<AppState>,
    mut req: Request,
    next: Next,
) -> Response {
    match auth_required(&state).await {
        Ok(false) => {
            req.extensions_mut().insert(Caller::default());
            return next.run(req).await;
        }
        Ok(true) => {}
        Err(e) => return e.into_response(),
    }
    let presented = req
        .headers()
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| {
            v.strip_prefix("Bearer ")
                .or_else(|| v.strip_prefix("bearer "))
        })
        .map(str::trim);
    let Some(token) = presented else {
        return unauthorized(
            "this server needs an `Authorization: Bearer <token>` header",
            "Bearer",
        );
    };
    match identify(&state, token).await {
        Ok(Some(caller)) => {
            req.extensions_mut().insert(caller);
            next.run(req).await
        }
        Ok(None) => unauthorized(
            "the bearer token is not valid",
            "Bearer error=\"invalid_token\"",
        ),
        Err(resp) => resp,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_exact_tokens_match() {
        let tokens = vec!["alpha".to_string(), "beta-token".to_string()];
        assert!(token_matches(&tokens, "alpha"));
        assert!(token_matches(&tokens, "beta-token"));
        assert!(!token_matches(&tokens, "alph"));
        assert!(!token_matches(&tokens, "alphaa"));
        assert!(!token_matches(&tokens, ""));
        assert!(!token_matches(&[], "alpha"));
    }
}
