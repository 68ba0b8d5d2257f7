//! The routes that act: kick a player, ban, unban, disable, enable, delete an account,
//! set its password, and list accounts. Every action, done or refused, is audited with
//! the caller, the target and the outcome (never a password).
//!
//! Changes to an account are made in the database first and the session (if any) is
//! ended after, so that the player's next login already meets the change: a banned,
//! disabled or deleted account cannot slip back in between.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::time::Duration;

use axum::Json;
use axum::body::Bytes;
use axum::extract::rejection::QueryRejection;
use axum::extract::{ConnectInfo, FromRequestParts, Path, Query, State};
use axum::http::StatusCode;
use axum::http::request::Parts;
use axum::response::{IntoResponse, Response};
use myriad_protocol::DisconnectReason;
use myriad_store::{validate_ban_reason, validate_username};
use serde::Deserialize;
use serde_json::{Value, json};
use tokio::sync::oneshot;

use super::commands::AdminCommand;
use super::rfc3339;
use super::routes::{ApiError, ApiState, query_param};

/// Longest a route waits for the tick to carry out a command.
const COMMAND_TIMEOUT: Duration = Duration::from_secs(5);

/// Header naming who acts, for the audit trail (`myriad admin` sends the login name).
pub const ACTOR_HEADER: &str = "x-myriad-actor";

/// The caller: who (the actor header, or `token`), from where.
pub(crate) struct Caller {
    actor: String,
    from: SocketAddr,
}

impl<S: Send + Sync> FromRequestParts<S> for Caller {
    type Rejection = std::convert::Infallible;

    async fn from_request_parts(parts: &mut Parts, _: &S) -> Result<Self, Self::Rejection> {
        let from =
            parts.extensions.get::<ConnectInfo<SocketAddr>>().map_or(SocketAddr::from(([0, 0, 0, 0], 0)), |c| c.0);
        // Only a short, plain name: it is printed on operators' terminals.
        let actor = parts
            .headers
            .get(ACTOR_HEADER)
            .and_then(|v| v.to_str().ok())
            .map(str::trim)
            .filter(|a| {
                !a.is_empty() && a.len() <= 64 && a.chars().all(|c| c.is_ascii_alphanumeric() || "._@-".contains(c))
            })
            .map_or_else(|| "token".to_string(), |a| format!("token:{a}"));
        Ok(Caller { actor, from })
    }
}

/// Runs `work`, audits it as `action` on `target` (with `detail`, and the error when it
/// failed), and answers with its outcome.
async fn audited(
    s: &ApiState,
    caller: &Caller,
    action: &str,
    target: &str,
    detail: String,
    work: impl Future<Output = Result<Value, ApiError>>,
) -> Response {
    let result = work.await;
    let (ok, detail) = match &result {
        Ok(_) => (true, detail),
        Err(e) if detail.is_empty() => (false, e.message.clone()),
        Err(e) => (false, format!("{detail}; {}", e.message)),
    };
    s.audit.record(&caller.actor, action, target, &detail, caller.from, ok).await;
    match result {
        Ok(body) => Json(body).into_response(),
        Err(e) => e.into_response(),
    }
}

/// Parses a JSON body (an empty body is `T::default()` when `optional`).
fn body<T: serde::de::DeserializeOwned + Default>(bytes: &Bytes, optional: bool) -> Result<T, ApiError> {
    if bytes.is_empty() && optional {
        return Ok(T::default());
    }
    serde_json::from_slice(bytes).map_err(|e| ApiError::bad_request(format!("bad JSON body: {e}")))
}

fn name(account: &str) -> Result<(), ApiError> {
    validate_username(account).map_err(ApiError::from)
}

/// Asks the tick to end `account`'s session with `reason`; whether there was one.
async fn end_session(s: &ApiState, account: &str, reason: DisconnectReason) -> Result<bool, ApiError> {
    let (reply, answer) = oneshot::channel();
    s.commands
        .try_send(AdminCommand::End { account: account.to_string(), reason, reply })
        .map_err(|_| ApiError::busy("the tick's command queue is full; retry"))?;
    match tokio::time::timeout(COMMAND_TIMEOUT, answer).await {
        Ok(Ok(found)) => {
            s.shared.mark_change();
            Ok(found)
        }
        Ok(Err(_)) => Err(ApiError::busy("the tick is stopping")),
        Err(_) => Err(ApiError::busy("the tick did not answer within 5 s")),
    }
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct KickBody {
    #[serde(default)]
    reason: String,
}

/// `POST /api/players/{account}/kick` `{"reason": "…"}` (the body may be empty).
pub(crate) async fn kick(
    State(s): State<ApiState>,
    caller: Caller,
    Path(account): Path<String>,
    bytes: Bytes,
) -> Response {
    let parsed = body::<KickBody>(&bytes, true);
    let detail = parsed.as_ref().map(|b| b.reason.clone()).unwrap_or_default();
    audited(&s, &caller, "kick", &account, detail, async {
        let b = parsed?;
        name(&account)?;
        if !b.reason.is_empty() {
            validate_ban_reason(&b.reason)?;
        }
        if end_session(&s, &account, DisconnectReason::Kicked).await? {
            Ok(json!({"kicked": true}))
        } else {
            Err(ApiError::new(StatusCode::NOT_FOUND, format!("{account} is not online")))
        }
    })
    .await
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct BanBody {
    reason: String,
    #[serde(default)]
    until: Option<String>,
}

/// `POST /api/accounts/{account}/ban` `{"reason": "…", "until": null | "RFC 3339"}`.
pub(crate) async fn ban(
    State(s): State<ApiState>,
    caller: Caller,
    Path(account): Path<String>,
    bytes: Bytes,
) -> Response {
    let parsed = body::<BanBody>(&bytes, false);
    let detail = match &parsed {
        Ok(b) => format!("{} (until {})", b.reason, b.until.as_deref().unwrap_or("lifted")),
        Err(_) => String::new(),
    };
    audited(&s, &caller, "ban", &account, detail, async {
        let b = parsed?;
        name(&account)?;
        let until_ms = b.until.as_deref().map(rfc3339::parse_ms).transpose().map_err(ApiError::bad_request)?;
        s.store.ban(&account, &b.reason, until_ms).await?;
        let kicked = end_session(&s, &account, DisconnectReason::Banned).await?;
        Ok(json!({
            "account": account,
            "banned": true,
            "until": until_ms.map(rfc3339::format_ms),
            "kicked": kicked,
        }))
    })
    .await
}

/// `POST /api/accounts/{account}/unban`.
pub(crate) async fn unban(State(s): State<ApiState>, caller: Caller, Path(account): Path<String>) -> Response {
    audited(&s, &caller, "unban", &account, String::new(), async {
        name(&account)?;
        s.store.unban(&account).await?;
        Ok(json!({"account": account, "banned": false}))
    })
    .await
}

/// `POST /api/accounts/{account}/disable`: refused at login from now on; a session in
/// play ends (Kicked).
pub(crate) async fn disable(State(s): State<ApiState>, caller: Caller, Path(account): Path<String>) -> Response {
    audited(&s, &caller, "disable", &account, String::new(), async {
        name(&account)?;
        s.store.set_disabled(&account, true).await?;
        let kicked = end_session(&s, &account, DisconnectReason::Kicked).await?;
        Ok(json!({"account": account, "disabled": true, "kicked": kicked}))
    })
    .await
}

/// `POST /api/accounts/{account}/enable`.
pub(crate) async fn enable(State(s): State<ApiState>, caller: Caller, Path(account): Path<String>) -> Response {
    audited(&s, &caller, "enable", &account, String::new(), async {
        name(&account)?;
        s.store.set_disabled(&account, false).await?;
        Ok(json!({"account": account, "disabled": false}))
    })
    .await
}

/// `DELETE /api/accounts/{account}`: disabled first (no login slips in), its session
/// ended, then deleted with its saved positions.
pub(crate) async fn delete(State(s): State<ApiState>, caller: Caller, Path(account): Path<String>) -> Response {
    audited(&s, &caller, "delete", &account, String::new(), async {
        name(&account)?;
        s.store.set_disabled(&account, true).await?;
        let kicked = end_session(&s, &account, DisconnectReason::Kicked).await?;
        s.store.delete_user(&account).await?;
        Ok(json!({"account": account, "deleted": true, "kicked": kicked}))
    })
    .await
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct PasswordBody {
    password: String,
}

/// `POST /api/accounts/{account}/password` `{"password": "…"}` (never logged or audited).
pub(crate) async fn password(
    State(s): State<ApiState>,
    caller: Caller,
    Path(account): Path<String>,
    bytes: Bytes,
) -> Response {
    // The error of a body that does not parse could quote the password: say only that.
    let parsed = body::<PasswordBody>(&bytes, false)
        .map_err(|_| ApiError::bad_request("the body must be {\"password\": \"…\"}"));
    audited(&s, &caller, "password", &account, String::new(), async {
        let b = parsed?;
        name(&account)?;
        s.store.set_password(&account, &b.password).await?;
        Ok(json!({"account": account, "password_changed": true}))
    })
    .await
}

/// `GET /api/accounts?limit=&offset=` (limit default 100, at most 1000), by id.
pub(crate) async fn list(
    State(s): State<ApiState>,
    q: Result<Query<HashMap<String, String>>, QueryRejection>,
) -> Result<Json<Value>, ApiError> {
    let limit = query_param(&q, "limit", 100, 1..=1000)?;
    let offset = query_param(&q, "offset", 0, 0..=u32::MAX)?;
    let now = myriad_store::now_ms();
    let accounts = s.store.accounts_page(offset, limit).await?;
    let rows: Vec<Value> = accounts
        .into_iter()
        .map(|a| {
            let ban = a.ban.filter(|b| b.in_force_at(now));
            json!({
                "account": a.username,
                "user_id": a.id.0,
                "disabled": a.disabled,
                "banned": ban.is_some(),
                "banned_until": ban.as_ref().and_then(|b| b.until_ms).map(rfc3339::format_ms),
                "ban_reason": ban.map(|b| b.reason),
                "created_at": rfc3339::format_ms(a.created_at_ms),
            })
        })
        .collect();
    Ok(Json(Value::Array(rows)))
}
