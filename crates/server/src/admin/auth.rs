//! The two gates of every request: the address (`admin_allow`, on every route) and the
//! bearer token (on every `/api` path, known or not). Both refusals are counted and
//! audited, and every answer is counted by outcome (`myriad_admin_requests_total{outcome}`).

use std::net::SocketAddr;

use axum::extract::{ConnectInfo, Request, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use super::bump;
use super::routes::{ApiError, ApiState};

/// Why a request was refused before any route saw it (kept on the response, so the
/// outer gate counts it under its own outcome).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Refusal {
    NoToken,
    WrongToken,
    Forbidden,
}

impl Refusal {
    fn why(self) -> &'static str {
        match self {
            Refusal::NoToken => "no token",
            Refusal::WrongToken => "wrong token",
            Refusal::Forbidden => "address not allowed",
        }
    }
}

/// Both gates, on every request: refuses addresses `admin_allow` does not list, then
/// `/api` requests without the token; counts the answer by outcome. (One layer on the
/// whole router, so the refusals are audited with the path as the client sent it.)
pub(crate) async fn guard(
    State(s): State<ApiState>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    request: Request,
    next: Next,
) -> Response {
    let path = request.uri().path().to_string();
    let response = if !s.allow.allows(peer.ip()) {
        tracing::warn!(%peer, path, "admin request from an address not allowed");
        s.audit.refusal(&path, Refusal::Forbidden.why(), peer).await;
        refused(Refusal::Forbidden, StatusCode::FORBIDDEN, "this address may not use the admin API")
    } else if let Some(refusal) = token_refusal(&s, &path, request.headers()) {
        tracing::warn!(%peer, path, why = refusal.why(), "admin request refused");
        s.audit.refusal(&path, refusal.why(), peer).await;
        let mut response = refused(refusal, StatusCode::UNAUTHORIZED, "a valid bearer token is required");
        response.headers_mut().insert(header::WWW_AUTHENTICATE, header::HeaderValue::from_static("Bearer"));
        response
    } else {
        next.run(request).await
    };
    count(&s, &response);
    response
}

/// Why an `/api` request may not pass (`Authorization: Bearer <token>`, compared in
/// constant time); `None` when it may, or is not for `/api`.
fn token_refusal(s: &ApiState, path: &str, headers: &HeaderMap) -> Option<Refusal> {
    if path != "/api" && !path.starts_with("/api/") {
        return None;
    }
    match bearer(headers) {
        None => Some(Refusal::NoToken),
        Some(presented) if !s.token.matches(presented) => Some(Refusal::WrongToken),
        Some(_) => None,
    }
}

/// The token of an `Authorization: Bearer …` header.
fn bearer(headers: &HeaderMap) -> Option<&str> {
    let value = headers.get(header::AUTHORIZATION)?.to_str().ok()?;
    let (scheme, token) = value.split_once(' ')?;
    scheme.eq_ignore_ascii_case("bearer").then(|| token.trim())
}

fn refused(refusal: Refusal, status: StatusCode, message: &str) -> Response {
    let mut response = ApiError::new(status, message).into_response();
    response.extensions_mut().insert(refusal);
    response
}

/// Counts `response` under its outcome.
fn count(s: &ApiState, response: &Response) {
    let c = &s.shared.counters;
    let status = response.status();
    let (counter, outcome) = match response.extensions().get::<Refusal>() {
        Some(Refusal::NoToken) => (&c.no_token, "no_token"),
        Some(Refusal::WrongToken) => (&c.wrong_token, "wrong_token"),
        Some(Refusal::Forbidden) => (&c.forbidden, "forbidden"),
        None if status.is_success() => (&c.ok, "ok"),
        None if status == StatusCode::NOT_FOUND => (&c.not_found, "not_found"),
        None if status == StatusCode::SERVICE_UNAVAILABLE => (&c.busy, "busy"),
        None if status.is_client_error() => (&c.bad_request, "bad_request"),
        None => (&c.errors, "error"),
    };
    bump(counter);
    metrics::counter!("myriad_admin_requests_total", "outcome" => outcome).increment(1);
}
