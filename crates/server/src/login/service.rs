//! The login service: the accept loop, the connection caps, and one login's exchange
//! (TLS, request, limits, password check, join through the tick loop); see the
//! [module docs](super).

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use myriad_protocol::login::{
    FRAME_PREFIX_LEN, LoginAccepted, LoginRefused, LoginRequest, LoginResponse, MAX_REQUEST_FRAME,
    MIN_SERVED_LOGIN_VERSION, MapDescription, RefusalReason, frame_len,
};
use myriad_store::{MapId, Store, StoreError};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Semaphore;
use tokio_rustls::TlsAcceptor;
use tokio_rustls::server::TlsStream;

use super::hash_gate::HashGate;
use super::limits::{ACCOUNT_CHECKS_IN_FLIGHT, AccountsInFlight, ConnectionCounts, RateLimiter};
use crate::config::ServerConfig;
use crate::status::{ServerShared, bump};
use crate::tick::Command;

/// Deadline of a whole login exchange (handshake, request, check, response).
const LOGIN_DEADLINE: Duration = Duration::from_secs(15);

/// Login connections handled at once; more are closed immediately.
const MAX_LOGIN_CONNECTIONS: usize = 4096;

/// The map a login hands out.
pub(crate) struct ServedMap {
    /// The store's id of the map (player states are kept per map).
    pub id: MapId,
    /// Sent in every accepted login.
    pub description: MapDescription,
    /// The `MapData` frame, encoded once, sent to clients that ask for it.
    pub frame: Arc<Vec<u8>>,
}

/// Everything a login task needs.
pub(crate) struct LoginService {
    acceptor: TlsAcceptor,
    store: Store,
    map: ServedMap,
    udp_port: u16,
    tick_rate_hz: u16,
    /// Join requests to the tick loop.
    commands: std::sync::mpsc::Sender<Command>,
    limiter: RateLimiter,
    hashing: HashGate,
    /// Login connections in flight (handshake to close), in all.
    connections: Arc<Semaphore>,
    /// Login connections in flight per address.
    per_addr: Arc<ConnectionCounts>,
    /// Most connections in flight per address.
    per_addr_cap: u32,
    /// Deadline of the TLS handshake and the request.
    handshake_timeout: Duration,
    /// Password checks in flight (queued or running) per account.
    accounts_in_flight: Arc<AccountsInFlight>,
    shared: Arc<ServerShared>,
}

impl LoginService {
    /// A login service with `config`'s limits (the `login_*` keys, `hashing_threads()`
    /// and the tick rate it announces), presenting `acceptor`'s certificate, checking
    /// passwords in `store`, handing out `map` and the game's `udp_port`, and sending
    /// joins to the tick loop on `commands`.
    pub fn new(
        config: &ServerConfig,
        acceptor: TlsAcceptor,
        store: Store,
        map: ServedMap,
        udp_port: u16,
        commands: std::sync::mpsc::Sender<Command>,
        shared: Arc<ServerShared>,
    ) -> LoginService {
        LoginService {
            acceptor,
            store,
            map,
            udp_port,
            tick_rate_hz: config.tick_rate.round() as u16,
            commands,
            limiter: RateLimiter::new(
                Duration::from_secs(config.login_window_s),
                config.login_failures_per_addr,
                config.login_failures_per_account,
            ),
            hashing: HashGate::new(
                config.hashing_threads(),
                config.login_queue,
                Duration::from_millis(config.login_queue_deadline_ms),
            ),
            connections: Arc::new(Semaphore::new(MAX_LOGIN_CONNECTIONS)),
            per_addr: Arc::default(),
            per_addr_cap: config.login_connections_per_addr,
            handshake_timeout: Duration::from_millis(config.login_handshake_timeout_ms),
            accounts_in_flight: Arc::default(),
            shared,
        }
    }

    /// Accepts connections until the listener fails or the task is dropped.
    pub(crate) async fn serve(self: Arc<Self>, listener: TcpListener) {
        loop {
            let (stream, peer) = match listener.accept().await {
                Ok(c) => c,
                Err(e) => {
                    // Out of file descriptors and the like: back off instead of spinning.
                    tracing::warn!(error = %e, "login accept failed");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            };
            // Bound the connections in flight, per address first (so one address can
            // never take the global cap), then in all: beyond either, the connection is
            // closed at once (no TLS work, no reply) rather than queued.
            let Some(slot) = self.per_addr.try_take(peer.ip(), self.per_addr_cap) else {
                self.connection_refused("too_many_connections_from_address", stream);
                continue;
            };
            let Ok(permit) = self.connections.clone().try_acquire_owned() else {
                self.connection_refused("too_many_connections", stream);
                continue;
            };
            let this = self.clone();
            tokio::spawn(async move {
                let _held = (permit, slot);
                match tokio::time::timeout(LOGIN_DEADLINE, this.handle(stream, peer)).await {
                    Ok(Ok(())) => {}
                    Ok(Err(e)) => tracing::debug!(%peer, error = %e, "login connection failed"),
                    Err(_) => tracing::debug!(%peer, "login timed out"),
                }
            });
        }
    }

    fn connection_refused(&self, label: &'static str, stream: TcpStream) {
        metrics::counter!("myriad_logins_total", "result" => label).increment(1);
        bump(&self.shared.defence.connections_refused);
        drop(stream);
    }

    /// The TLS handshake and the request, within the handshake deadline. `Ok(None)`: a
    /// malformed request (answered, counted).
    async fn read_request(&self, stream: TcpStream) -> std::io::Result<(TlsStream<TcpStream>, Option<LoginRequest>)> {
        let mut tls = self.acceptor.accept(stream).await?;
        let mut prefix = [0u8; FRAME_PREFIX_LEN];
        tls.read_exact(&mut prefix).await?;
        let Ok(len) = frame_len(prefix, MAX_REQUEST_FRAME) else { return Ok((tls, None)) };
        let mut body = vec![0u8; len];
        tls.read_exact(&mut body).await?;
        Ok((tls, LoginRequest::decode(&body).ok()))
    }

    async fn handle(&self, stream: TcpStream, peer: SocketAddr) -> std::io::Result<()> {
        let _ = stream.set_nodelay(true);
        let (mut tls, request) = match tokio::time::timeout(self.handshake_timeout, self.read_request(stream)).await {
            Ok(r) => r?,
            Err(_) => {
                metrics::counter!("myriad_logins_total", "result" => "handshake_timeout").increment(1);
                bump(&self.shared.defence.handshake_timeouts);
                return Err(std::io::ErrorKind::TimedOut.into());
            }
        };
        let response = match request {
            None => {
                count_login(&self.shared, Err(RefusalReason::BadRequest));
                refuse(RefusalReason::BadRequest, 0)
            }
            Some(req) => self.login(&req, peer).await.map(|a| (a, req.want_map)),
        };
        let mut out = Vec::with_capacity(256);
        let want_map = match response {
            Ok((accepted, want_map)) => {
                LoginResponse::Accepted(Box::new(accepted)).encode(&mut out);
                want_map
            }
            Err(refused) => {
                refused.encode(&mut out);
                false
            }
        };
        tls.write_all(&out).await?;
        if want_map {
            tls.write_all(&self.map.frame).await?;
        }
        tls.shutdown().await
    }

    async fn login(&self, req: &LoginRequest, peer: SocketAddr) -> Result<LoginAccepted, LoginRefused> {
        let result = self.check(req, peer).await;
        count_login(&self.shared, result.as_ref().map(|_| ()).map_err(|r| r.reason));
        // A client of an older login version gets only reasons it knows.
        result.map_err(|r| LoginRefused { reason: r.reason.understood_by(req.version), ..r })
    }

    async fn check(&self, req: &LoginRequest, peer: SocketAddr) -> Result<LoginAccepted, LoginRefused> {
        if self.shared.stop.load(Ordering::Acquire) {
            return refuse(RefusalReason::ShuttingDown, 0);
        }
        // Before the limiter and the store: an outdated client costs nothing, and its
        // credentials are not judged (it could not play even if they were right).
        if req.version < MIN_SERVED_LOGIN_VERSION {
            tracing::info!(%peer, version = req.version, "login refused: outdated client (an older datagram protocol)");
            return refuse(RefusalReason::OutdatedClient, 0);
        }
        if let Some(wait) = self.limiter.check(peer.ip(), &req.username, Instant::now()) {
            tracing::info!(%peer, user = %req.username, "login rate-limited");
            return refuse(RefusalReason::RateLimited, millis(wait));
        }
        // Unknown (or malformed) user names cost a lookup, never a hash: they are refused
        // after a pause as long as a typical check, as a wrong password would be.
        match self.store.find_user(&req.username).await {
            Ok(Some(_)) => {}
            Ok(None) | Err(StoreError::InvalidInput(_)) => {
                bump(&self.shared.defence.unknown_users_refused);
                tokio::time::sleep(self.hashing.typical()).await;
                return self.wrong_credentials(req, peer);
            }
            Err(e) => {
                tracing::warn!(%peer, error = %e, "login failed: store unavailable");
                return refuse(RefusalReason::Unavailable, 1000);
            }
        }
        let info = {
            // One account's checks in flight are capped: a storm on one account takes
            // at most that much of the pool, and the rest is refused before hashing.
            let Some(_account_slot) = self.accounts_in_flight.try_take(&req.username, ACCOUNT_CHECKS_IN_FLIGHT) else {
                return refuse(RefusalReason::Busy, millis(self.hashing.typical().max(Duration::from_millis(100))));
            };
            // Addresses without failures go first (see `HashGate`).
            let priority = self.limiter.address_failures(peer.ip(), Instant::now());
            let _permit = match self.hashing.enter(priority).await {
                Ok(p) => p,
                Err(retry) => {
                    tracing::debug!(%peer, user = %req.username, "login refused: hashing busy");
                    return refuse(RefusalReason::Busy, millis(retry));
                }
            };
            let started = Instant::now();
            let info = self.store.login(&req.username, &req.password, self.map.id).await;
            self.hashing.record(started.elapsed());
            info
        };
        let info = match info {
            Ok(info) => info,
            Err(StoreError::WrongCredentials | StoreError::InvalidInput(_) | StoreError::NotFound(_)) => {
                return self.wrong_credentials(req, peer);
            }
            // The password was right: not a failure for the rate limiter, and the
            // operator's decision is told (to a client that knows the reason).
            Err(StoreError::AccountDisabled) => {
                tracing::info!(%peer, user = %req.username, "login refused: account disabled");
                return refuse(RefusalReason::Disabled, 0);
            }
            Err(StoreError::AccountBanned { until_ms }) => {
                tracing::info!(%peer, user = %req.username, ?until_ms, "login refused: account banned");
                let left = until_ms
                    .map_or(0, |until| u32::try_from((until - myriad_store::now_ms()).max(1)).unwrap_or(u32::MAX));
                return refuse(RefusalReason::Banned, left);
            }
            Err(e) => {
                tracing::warn!(%peer, error = %e, "login failed: store unavailable");
                return refuse(RefusalReason::Unavailable, 1000);
            }
        };
        self.limiter.succeeded(peer.ip(), &req.username);
        let (reply, answer) = tokio::sync::oneshot::channel();
        let command =
            Command::Join { user_id: info.user_id, username: info.username.clone(), state: info.state, reply };
        if self.commands.send(command).is_err() {
            return refuse(RefusalReason::ShuttingDown, 0);
        }
        let joined = match answer.await {
            Ok(Ok(j)) => j,
            Ok(Err(reason)) => return refuse(reason, if reason == RefusalReason::ServerFull { 5000 } else { 0 }),
            Err(_) => return refuse(RefusalReason::ShuttingDown, 0),
        };
        tracing::info!(%peer, user = %info.username, entity = joined.entity, "login ok");
        Ok(LoginAccepted {
            keys: joined.keys,
            udp_port: self.udp_port,
            entity_id: joined.entity,
            position: joined.position,
            shape: joined.shape,
            tick_rate_hz: self.tick_rate_hz,
            dilation_permille: joined.dilation_permille,
            tick: joined.tick,
            map: self.map.description.clone(),
        })
    }

    fn wrong_credentials<T>(&self, req: &LoginRequest, peer: SocketAddr) -> Result<T, LoginRefused> {
        self.limiter.failed(peer.ip(), &req.username, Instant::now());
        tracing::info!(%peer, user = %req.username, "login failed: wrong credentials");
        refuse(RefusalReason::WrongCredentials, 0)
    }
}

/// Counts a login's outcome in `myriad_logins_total{result}` (and the defence counters).
fn count_login(shared: &ServerShared, result: Result<(), RefusalReason>) {
    let label = match result {
        Ok(()) => "ok",
        Err(reason) => match reason {
            RefusalReason::WrongCredentials => "wrong_credentials",
            RefusalReason::RateLimited => {
                bump(&shared.defence.logins_rate_limited);
                "rate_limited"
            }
            RefusalReason::ServerFull => "server_full",
            RefusalReason::BadRequest => {
                bump(&shared.defence.bad_requests);
                "bad_request"
            }
            RefusalReason::Unavailable => "unavailable",
            RefusalReason::ShuttingDown => "shutting_down",
            RefusalReason::Busy => {
                bump(&shared.defence.logins_busy);
                "busy"
            }
            RefusalReason::Disabled => "disabled",
            RefusalReason::Banned => "banned",
            RefusalReason::OutdatedClient => "outdated_client",
        },
    };
    metrics::counter!("myriad_logins_total", "result" => label).increment(1);
}

fn millis(d: Duration) -> u32 {
    d.as_millis().min(u32::MAX as u128) as u32
}

fn refuse<T>(reason: RefusalReason, retry_after_ms: u32) -> Result<T, LoginRefused> {
    Err(LoginRefused { reason, retry_after_ms })
}
