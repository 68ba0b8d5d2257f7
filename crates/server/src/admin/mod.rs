//! The admin API and console (issue 29): JSON over HTTP on a listener of its own
//! (`admin_addr`), for operators of a live world. The contract, route by route, is in
//! `docs/server.md` ("Admin API").
//!
//! - [`allow`]: the `admin_allow` check, on every request (403, counted, audited).
//! - `token`: the bearer token (generated 0600 or `admin_token_file`), compared in
//!   constant time; every `/api` route needs it (401, counted, audited).
//! - `routes`, `accounts`: the routes; `audit`: every action and refusal written to the
//!   store's audit table (migration 4).
//! - `snapshot`, `commands`: how the API reaches the tick without slowing it. The tick
//!   thread owns the sessions; it publishes a snapshot (players, NPC density) while
//!   someone asks, with a `try_lock`, and drains a bounded channel of commands (end a
//!   session) at the start of each tick. The tick never waits on the admin.
//! - [`console`]: the web console's files, served without the token (they hold no data).
//!
//! It runs on the server's tokio runtime (two workers, below the tick's priority).

mod accounts;
pub mod allow;
mod audit;
mod auth;
mod commands;
pub mod console;
pub mod rfc3339;
mod routes;
mod snapshot;
#[cfg(test)]
mod tick_tests;
mod token;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Instant;

use myriad_store::Store;

pub(crate) use commands::TickAdmin;
pub use token::{TOKEN_FILE_NAME, token_path};

use crate::config::ServerConfig;
use crate::error::ServerError;
use crate::status::ServerShared;
use snapshot::Snapshot;

/// What kind of process serves the API.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// `myriad serve` (or `demo`): the world is stepped here.
    Server,
    /// `myriad gateway`: the world is stepped by zones.
    Gateway,
}

impl Role {
    /// The name the API reports.
    pub fn name(self) -> &'static str {
        match self {
            Role::Server => "server",
            Role::Gateway => "gateway",
        }
    }
}

/// Counters of the admin API's answers since start (also in the metrics as
/// `myriad_admin_requests_total{outcome}`; kept here so tests and tools in the same
/// process can read them).
#[derive(Debug, Default)]
pub struct AdminCounters {
    ok: AtomicU64,
    no_token: AtomicU64,
    wrong_token: AtomicU64,
    forbidden: AtomicU64,
    bad_request: AtomicU64,
    not_found: AtomicU64,
    busy: AtomicU64,
    errors: AtomicU64,
    audits_suppressed: AtomicU64,
    audit_failures: AtomicU64,
}

/// A snapshot of [`AdminCounters`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct AdminStats {
    /// Requests answered with success.
    pub ok: u64,
    /// `/api` requests without a bearer token (401).
    pub no_token: u64,
    /// `/api` requests with a wrong token (401).
    pub wrong_token: u64,
    /// Requests from an address `admin_allow` does not list (403).
    pub forbidden: u64,
    /// Malformed requests: bad JSON, bad names, bad times (400).
    pub bad_request: u64,
    /// Unknown routes, accounts, or players not online (404).
    pub not_found: u64,
    /// Commands refused because the tick's queue was full or it did not answer (503).
    pub busy: u64,
    /// Failures of the server (5xx other than busy): the database, mostly.
    pub errors: u64,
    /// Refusals not written to the audit table because refusals came faster than
    /// `audit::REFUSALS_AUDITED_PER_S` (still counted above).
    pub audits_suppressed: u64,
    /// Audit entries the database did not take.
    pub audit_failures: u64,
}

impl AdminCounters {
    /// The counters now.
    pub fn snapshot(&self) -> AdminStats {
        let r = |c: &AtomicU64| c.load(Ordering::Relaxed);
        AdminStats {
            ok: r(&self.ok),
            no_token: r(&self.no_token),
            wrong_token: r(&self.wrong_token),
            forbidden: r(&self.forbidden),
            bad_request: r(&self.bad_request),
            not_found: r(&self.not_found),
            busy: r(&self.busy),
            errors: r(&self.errors),
            audits_suppressed: r(&self.audits_suppressed),
            audit_failures: r(&self.audit_failures),
        }
    }
}

fn bump(counter: &AtomicU64) {
    counter.fetch_add(1, Ordering::Relaxed);
}

/// State shared by the admin API's tasks and the tick.
#[derive(Debug)]
pub(crate) struct AdminShared {
    started: Instant,
    role: Role,
    /// The physics backend's name, set by the tick when it starts.
    pub backend: OnceLock<String>,
    /// The newest snapshot the tick published.
    pub snapshot: Mutex<Option<Arc<Snapshot>>>,
    /// Milliseconds after `started` until which the tick takes snapshots.
    wanted_until_ms: AtomicU64,
    /// Milliseconds after `started` when the tick last ended a session for the admin.
    last_change_ms: AtomicU64,
    /// Microseconds the tick spent on its last snapshot.
    snapshot_us: AtomicU64,
    pub counters: AdminCounters,
}

impl AdminShared {
    fn new(role: Role) -> Self {
        AdminShared {
            started: Instant::now(),
            role,
            backend: OnceLock::new(),
            snapshot: Mutex::new(None),
            wanted_until_ms: AtomicU64::new(0),
            last_change_ms: AtomicU64::new(0),
            snapshot_us: AtomicU64::new(0),
            counters: AdminCounters::default(),
        }
    }

    fn now_ms(&self) -> u64 {
        self.started.elapsed().as_millis() as u64
    }

    /// Asks the tick for snapshots for the next [`snapshot::WANTED_FOR`].
    fn want(&self) {
        let until = self.now_ms() + snapshot::WANTED_FOR.as_millis() as u64;
        self.wanted_until_ms.fetch_max(until, Ordering::Relaxed);
    }

    /// Records that the tick just ended a session: older snapshots no longer show the
    /// world as it is.
    fn mark_change(&self) {
        // One millisecond later than now, rounding up: a snapshot taken in the same
        // millisecond as the change may predate it.
        self.last_change_ms.fetch_max(self.now_ms() + 1, Ordering::Relaxed);
    }

    /// When the tick last ended a session for the admin.
    fn last_change(&self) -> Instant {
        self.started + std::time::Duration::from_millis(self.last_change_ms.load(Ordering::Relaxed))
    }

    /// Whether someone asked for snapshots lately.
    fn wanted(&self) -> bool {
        self.wanted_until_ms.load(Ordering::Relaxed) > self.now_ms()
    }
}

/// The running admin API, as the server handle keeps it.
#[derive(Debug)]
pub(crate) struct AdminRunning {
    pub addr: SocketAddr,
    pub token_path: PathBuf,
    pub shared: Arc<AdminShared>,
}

/// Binds `admin_addr` and serves the API on `runtime`; returns what the handle keeps and
/// the tick's side. `None` when `admin_addr` is not set.
pub(crate) fn start(
    config: &ServerConfig,
    runtime: &tokio::runtime::Runtime,
    store: Store,
    server: Arc<ServerShared>,
    role: Role,
) -> Result<Option<(AdminRunning, TickAdmin)>, ServerError> {
    let Some(addr) = config.admin_addr else { return Ok(None) };
    let allow = allow::AllowList::parse(&config.admin_allow)
        .map_err(|reason| ServerError::Config(crate::ConfigError::Value { key: "admin_allow".into(), reason }))?;
    let (token, token_path) = token::Token::load_or_create(config)?;
    let listener = runtime
        .block_on(tokio::net::TcpListener::bind(addr))
        .map_err(|e| ServerError::io(format!("binding the admin API to {addr}"), e))?;
    let addr = listener.local_addr().map_err(|e| ServerError::io("admin address", e))?;
    let shared = Arc::new(AdminShared::new(role));
    let (commands, receiver) = tokio::sync::mpsc::channel(commands::COMMAND_QUEUE);
    let state = routes::ApiState {
        shared: shared.clone(),
        server,
        store: store.clone(),
        commands,
        audit: audit::Auditor::new(store, shared.clone()),
        token: Arc::new(token),
        allow: Arc::new(allow),
        tick_rate: config.tick_rate,
    };
    let app = routes::router(state).into_make_service_with_connect_info::<SocketAddr>();
    runtime.spawn(async move {
        if let Err(e) = axum::serve(listener, app).await {
            tracing::error!(error = %e, "the admin API stopped");
        }
    });
    tracing::info!(%addr, token = %token_path.display(), "admin API and console");
    Ok(Some((AdminRunning { addr, token_path, shared: shared.clone() }, TickAdmin::new(receiver, shared))))
}
