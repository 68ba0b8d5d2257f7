//! The routes that read: the server's state, the players online, the map, the audit
//! trail, and the console's files; the router and the errors every route shares. The
//! routes that change accounts are in `accounts`.

use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use axum::Json;
use axum::Router;
use axum::extract::rejection::QueryRejection;
use axum::extract::{Path, Query, State};
use axum::http::{StatusCode, header};
use axum::middleware::from_fn_with_state;
use axum::response::{IntoResponse, Response};
use axum::routing::{delete, get, post};
use myriad_store::{MAX_AUDIT_LIST, Store, StoreError};
use serde_json::{Value, json};
use tokio::sync::mpsc;

use super::allow::AllowList;
use super::audit::Auditor;
use super::commands::AdminCommand;
use super::snapshot::{FINE_CELLS, SNAPSHOT_EVERY, Snapshot};
use super::token::Token;
use super::{AdminShared, accounts, auth, console, rfc3339};
use crate::status::ServerShared;

/// Everything a route may use (cheap to clone).
#[derive(Debug, Clone)]
pub(crate) struct ApiState {
    pub shared: Arc<AdminShared>,
    pub server: Arc<ServerShared>,
    pub store: Store,
    pub commands: mpsc::Sender<AdminCommand>,
    pub audit: Auditor,
    pub token: Arc<Token>,
    pub allow: Arc<AllowList>,
    pub tick_rate: f32,
}

/// An error answer: `{"error": message}` with a 4xx or 5xx status.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct ApiError {
    pub status: StatusCode,
    pub message: String,
}

impl ApiError {
    pub(crate) fn new(status: StatusCode, message: impl Into<String>) -> Self {
        ApiError { status, message: message.into() }
    }

    pub(crate) fn bad_request(message: impl Into<String>) -> Self {
        Self::new(StatusCode::BAD_REQUEST, message)
    }

    pub(crate) fn busy(message: impl Into<String>) -> Self {
        Self::new(StatusCode::SERVICE_UNAVAILABLE, message)
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        (self.status, Json(json!({ "error": self.message }))).into_response()
    }
}

impl From<StoreError> for ApiError {
    fn from(e: StoreError) -> Self {
        let status = match &e {
            StoreError::NotFound(_) => StatusCode::NOT_FOUND,
            StoreError::InvalidInput(_) => StatusCode::BAD_REQUEST,
            StoreError::Unavailable(_) => StatusCode::SERVICE_UNAVAILABLE,
            _ => StatusCode::INTERNAL_SERVER_ERROR,
        };
        ApiError::new(status, e.to_string())
    }
}

/// The API's router: the console's files and `/api`, all behind `auth::guard` (the
/// address check, the token on `/api`, the counting).
pub(crate) fn router(state: ApiState) -> Router {
    let api = Router::new()
        .route("/state", get(server_state))
        .route("/players", get(players))
        .route("/map", get(map))
        .route("/audit", get(audit))
        .route("/players/{account}/kick", post(accounts::kick))
        .route("/accounts", get(accounts::list))
        .route("/accounts/{account}", delete(accounts::delete))
        .route("/accounts/{account}/ban", post(accounts::ban))
        .route("/accounts/{account}/unban", post(accounts::unban))
        .route("/accounts/{account}/disable", post(accounts::disable))
        .route("/accounts/{account}/enable", post(accounts::enable))
        .route("/accounts/{account}/password", post(accounts::password))
        .fallback(|| async { ApiError::new(StatusCode::NOT_FOUND, "no such route") });
    Router::new()
        .route("/", get(|| async { console_file("index.html") }))
        .route("/console/{*file}", get(|Path(file): Path<String>| async move { console_file(&file) }))
        .nest("/api", api)
        .fallback(|| async { ApiError::new(StatusCode::NOT_FOUND, "no such page") })
        .layer(from_fn_with_state(state.clone(), auth::guard))
        .with_state(state)
}

fn console_file(path: &str) -> Response {
    match console::asset(path) {
        Some((content_type, body)) => ([(header::CONTENT_TYPE, content_type)], body).into_response(),
        None => ApiError::new(StatusCode::NOT_FOUND, "no such file").into_response(),
    }
}

/// `GET /api/state`.
async fn server_state(State(s): State<ApiState>) -> Json<Value> {
    let status = s.server.status.lock().unwrap_or_else(|p| p.into_inner()).clone();
    let stages: serde_json::Map<String, Value> =
        status.stages.iter().map(|(stage, ms)| (stage.name().to_string(), json!(ms))).collect();
    let dilation = f64::from(s.server.dilation_permille.load(Ordering::Relaxed)) / 1000.0;
    Json(json!({
        "version": env!("CARGO_PKG_VERSION"),
        "backend": s.shared.backend.get().map_or("starting", String::as_str),
        "tick": s.server.tick.load(Ordering::Relaxed),
        "tick_hz": status.ticks_per_s,
        "tick_rate": s.tick_rate,
        "players": s.server.players.load(Ordering::Relaxed),
        "dilation": dilation,
        "stages_ms": stages,
        "tick_ms": status.tick_ms,
        "uptime_s": s.shared.started.elapsed().as_secs_f64(),
        "snapshot_ms": s.shared.snapshot_us.load(Ordering::Relaxed) as f64 / 1000.0,
        "role": s.shared.role.name(),
    }))
}

/// Longest a request waits for the tick's next snapshot.
const SNAPSHOT_WAIT: Duration = Duration::from_secs(2);

/// A snapshot at most [`SNAPSHOT_EVERY`] old and taken after the last session an
/// operator ended (so a kick is never undone by a stale list); asks the tick for one
/// and waits for it when there is none.
async fn fresh_snapshot(s: &ApiState) -> Result<Arc<Snapshot>, ApiError> {
    let asked = Instant::now();
    s.shared.want();
    let oldest = asked.checked_sub(SNAPSHOT_EVERY).unwrap_or(asked);
    loop {
        let newest = s.shared.snapshot.lock().unwrap_or_else(|p| p.into_inner()).clone();
        if let Some(snap) = newest
            && snap.taken >= oldest
            && snap.taken >= s.shared.last_change()
        {
            return Ok(snap);
        }
        if asked.elapsed() > SNAPSHOT_WAIT {
            return Err(ApiError::busy("the tick published no snapshot in 2 s (is it stalled?)"));
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// `GET /api/players`.
async fn players(State(s): State<ApiState>) -> Result<Json<Value>, ApiError> {
    let snap = fresh_snapshot(&s).await?;
    let rows: Vec<Value> = snap
        .players
        .iter()
        .map(|p| {
            json!({
                "account": p.account,
                "user_id": p.user_id,
                "entity": p.entity,
                "addr": p.addr.map(|a| a.to_string()),
                "connected_since": rfc3339::format_system(p.connected_since),
                "position": p.position,
                "bytes_per_s": p.bytes_per_s,
            })
        })
        .collect();
    Ok(Json(Value::Array(rows)))
}

/// A query parameter as a number within `range` (`default` when absent).
pub(crate) fn query_param(
    q: &Result<Query<HashMap<String, String>>, QueryRejection>,
    name: &str,
    default: u32,
    range: std::ops::RangeInclusive<u32>,
) -> Result<u32, ApiError> {
    let q = q.as_ref().map_err(|e| ApiError::bad_request(e.body_text()))?;
    let Some(text) = q.get(name) else { return Ok(default) };
    text.parse::<u32>().ok().filter(|v| range.contains(v)).ok_or_else(|| {
        ApiError::bad_request(format!("{name}={text:?}: a number from {} to {}", range.start(), range.end()))
    })
}

/// `GET /api/map?cells=N`: the fine grid summed into N×N cells (each fine cell goes
/// whole to the coarse cell holding its index; exact when N divides 256), and the zone
/// cuts on a gateway (`null` elsewhere).
async fn map(
    State(s): State<ApiState>,
    q: Result<Query<HashMap<String, String>>, QueryRejection>,
) -> Result<Json<Value>, ApiError> {
    let n = query_param(&q, "cells", 64, 1..=FINE_CELLS as u32)? as usize;
    let snap = fresh_snapshot(&s).await?;
    let mut density = vec![0u32; n * n];
    for (i, count) in snap.density.iter().enumerate() {
        let (fz, fx) = (i / FINE_CELLS, i % FINE_CELLS);
        density[fz * n / FINE_CELLS * n + fx * n / FINE_CELLS] += count;
    }
    let [min_x, min_z, max_x, max_z] = snap.bounds;
    let players: Vec<Value> =
        snap.players.iter().map(|p| json!({"account": p.account, "x": p.position[0], "z": p.position[2]})).collect();
    let cuts = snap
        .cuts
        .as_ref()
        .map(|c| json!({"xs": c.xs, "zs": c.zs, "run": c.run, "zone_tick": c.zone_tick, "since_tick": c.since_tick}));
    Ok(Json(json!({
        "bounds": {"min_x": min_x, "min_z": min_z, "max_x": max_x, "max_z": max_z},
        "cells": n,
        "npc_density": density,
        "players": players,
        "cuts": cuts,
        "tick": snap.tick,
    })))
}

/// `GET /api/audit?limit=N` (default 100), newest first.
async fn audit(
    State(s): State<ApiState>,
    q: Result<Query<HashMap<String, String>>, QueryRejection>,
) -> Result<Json<Value>, ApiError> {
    let limit = query_param(&q, "limit", 100, 1..=MAX_AUDIT_LIST)?;
    let entries = s.store.list_audit(limit).await?;
    let rows: Vec<Value> = entries
        .into_iter()
        .map(|e| {
            json!({
                "at": rfc3339::format_ms(e.at_ms),
                "actor": e.actor,
                "action": e.action,
                "target": e.target,
                "detail": e.detail,
                "from": e.from,
                "ok": e.ok,
            })
        })
        .collect();
    Ok(Json(Value::Array(rows)))
}
