//! Bearer-token authentication: tokens from configuration, compared in constant time,
//! never logged. With no token configured, authentication is off (a local single-user run).

use axum::extract::{Request, State};
use axum::http::{StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use subtle::ConstantTimeEq;

use super::AppState;
use super::problem::ApiError;

/// True when `presented` equals one of `tokens`. Every token is compared, whatever the
/// outcome, so timing reveals neither which token matched nor how much of one did.
pub fn token_matches(tokens: &[String], presented: &str) -> bool {
    let mut ok = subtle::Choice::from(0u8);
    for t in tokens {
        ok |= t.as_bytes().ct_eq(presented.as_bytes());
    }
    ok.into()
}

/// Who is calling, set by [`require_token`] on every authenticated route: the owner id of
/// the presented token (see [`crate::jobs::owner_id`]), "" with authentication off.
#[derive(Debug, Clone, Default)]
pub struct Caller {
    pub owner: String,
}

impl Caller {
    /// The caller of a request that went through [`require_token`] (anonymous otherwise).
    pub fn of<B>(req: &axum::http::Request<B>) -> Caller {
        req.extensions()
            .get::<Caller>()
            .cloned()
            .unwrap_or_default()
    }
}

pub async fn require_token(
    State(state): State<AppState>,
    mut req: Request,
    next: Next,
) -> Response {
    if state.args.token.is_empty() {
        req.extensions_mut().insert(Caller::default());
        return next.run(req).await;
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
    match presented {
        Some(t) if token_matches(&state.args.token, t) => {
            let caller = Caller {
                owner: crate::jobs::owner_id(t),
            };
            req.extensions_mut().insert(caller);
            next.run(req).await
        }
        Some(_) => ApiError::new(
            StatusCode::UNAUTHORIZED,
            "unauthorized",
            "the bearer token is not valid",
        )
        .with_header(header::WWW_AUTHENTICATE, "Bearer error=\"invalid_token\"")
        .into_response(),
        None => ApiError::new(
            StatusCode::UNAUTHORIZED,
            "unauthorized",
            "this server needs an `Authorization: Bearer <token>` header",
        )
        .with_header(header::WWW_AUTHENTICATE, "Bearer")
        .into_response(),
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
