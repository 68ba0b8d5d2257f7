//! The TLS login service.
//!
//! # How it works
//!
//! A tokio task accepts TCP connections and runs each on its own task: TLS 1.3
//! handshake, one bounded [`LoginRequest`] frame, a rate-limit check (failures per
//! address and per account within a window), then the password check against the store
//! (Argon2id on the blocking pool, at most `login_concurrency` at once, never on the
//! tick thread). An authenticated user is handed to the tick loop, which creates the
//! session keys and the player's object and answers with them; the response goes back
//! over TLS, followed by the map data when asked. The whole exchange has a deadline, so
//! a slow or silent client cannot hold a task forever.
//!
//! Passwords never reach a log: [`LoginRequest`]'s `Debug` hides them and only the
//! username and address are logged.

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use myriad_protocol::login::{
    FRAME_PREFIX_LEN, LoginAccepted, LoginRefused, LoginRequest, LoginResponse, MAX_REQUEST_FRAME, MapDescription,
    RefusalReason, frame_len,
};
use myriad_store::{MapId, Store, StoreError};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Semaphore;
use tokio_rustls::TlsAcceptor;

use crate::status::Shared;
use crate::tick::Command;

/// Deadline of a whole login exchange (handshake, request, check, response).
const LOGIN_DEADLINE: Duration = Duration::from_secs(15);

/// Failed-login counters per address and per account over a sliding window.
#[derive(Debug)]
pub struct RateLimiter {
    window: Duration,
    per_addr: u32,
    per_account: u32,
    addrs: Mutex<HashMap<IpAddr, (u32, Instant)>>,
    accounts: Mutex<HashMap<String, (u32, Instant)>>,
}

impl RateLimiter {
    /// Allows `per_addr` and `per_account` failures per `window`.
    pub fn new(window: Duration, per_addr: u32, per_account: u32) -> Self {
        Self { window, per_addr, per_account, addrs: Mutex::default(), accounts: Mutex::default() }
    }

    /// `Some(retry after)` if this address or account is locked out now.
    pub fn check(&self, addr: IpAddr, account: &str, now: Instant) -> Option<Duration> {
        let key = account.to_ascii_lowercase();
        let a = Self::blocked(&self.addrs, &addr, self.per_addr, self.window, now);
        let b = Self::blocked(&self.accounts, &key, self.per_account, self.window, now);
        a.max(b)
    }

    fn blocked<K: std::hash::Hash + Eq>(
        map: &Mutex<HashMap<K, (u32, Instant)>>,
        key: &K,
        limit: u32,
        window: Duration,
        now: Instant,
    ) -> Option<Duration> {
        let map = map.lock().unwrap_or_else(|p| p.into_inner());
        let &(count, since) = map.get(key)?;
        let age = now.saturating_duration_since(since);
        (count >= limit && age < window).then(|| window - age)
    }

    /// Counts a failed login.
    pub fn failed(&self, addr: IpAddr, account: &str, now: Instant) {
        Self::bump(&self.addrs, addr, self.window, now);
        Self::bump(&self.accounts, account.to_ascii_lowercase(), self.window, now);
    }

    /// A successful login clears the account's failures (not the address's: one address
    /// guessing many accounts must stay limited).
    pub fn succeeded(&self, account: &str) {
        self.accounts.lock().unwrap_or_else(|p| p.into_inner()).remove(&account.to_ascii_lowercase());
    }

    fn bump<K: std::hash::Hash + Eq>(map: &Mutex<HashMap<K, (u32, Instant)>>, key: K, window: Duration, now: Instant) {
        let mut map = map.lock().unwrap_or_else(|p| p.into_inner());
        // Bound the memory an attacker with many addresses or names can make us use.
        if map.len() > 100_000 {
            map.retain(|_, (_, since)| now.saturating_duration_since(*since) < window);
        }
        let entry = map.entry(key).or_insert((0, now));
        if now.saturating_duration_since(entry.1) >= window {
            *entry = (0, now);
        }
        entry.0 += 1;
    }
}

/// Everything a login task needs.
pub(crate) struct LoginService {
    pub acceptor: TlsAcceptor,
    pub store: Store,
    pub map_id: MapId,
    pub map: MapDescription,
    pub map_frame: Arc<Vec<u8>>,
    pub udp_port: u16,
    pub tick_rate_hz: u16,
    pub commands: std::sync::mpsc::Sender<Command>,
    pub limiter: RateLimiter,
    pub hashing: Semaphore,
    /// Login connections in flight (handshake to close).
    pub connections: Arc<Semaphore>,
    pub shared: Arc<Shared>,
}

impl LoginService {
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
            // Bound the connections in flight: beyond that, new ones are closed at once
            // (no TLS work, no reply) rather than queueing without limit.
            let Ok(permit) = self.connections.clone().try_acquire_owned() else {
                metrics::counter!("myriad_logins_total", "result" => "too_many_connections").increment(1);
                drop(stream);
                continue;
            };
            let this = self.clone();
            tokio::spawn(async move {
                let _permit = permit;
                match tokio::time::timeout(LOGIN_DEADLINE, this.handle(stream, peer)).await {
                    Ok(Ok(())) => {}
                    Ok(Err(e)) => tracing::debug!(%peer, error = %e, "login connection failed"),
                    Err(_) => tracing::debug!(%peer, "login timed out"),
                }
            });
        }
    }

    async fn handle(&self, stream: TcpStream, peer: SocketAddr) -> std::io::Result<()> {
        let _ = stream.set_nodelay(true);
        let mut tls = self.acceptor.accept(stream).await?;
        let mut prefix = [0u8; FRAME_PREFIX_LEN];
        tls.read_exact(&mut prefix).await?;
        let response = match frame_len(prefix, MAX_REQUEST_FRAME) {
            Err(_) => refuse(RefusalReason::BadRequest, 0),
            Ok(len) => {
                let mut body = vec![0u8; len];
                tls.read_exact(&mut body).await?;
                match LoginRequest::decode(&body) {
                    Err(_) => refuse(RefusalReason::BadRequest, 0),
                    Ok(req) => self.login(&req, peer).await.map(|a| (a, req.want_map)),
                }
            }
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
            tls.write_all(&self.map_frame).await?;
        }
        tls.shutdown().await
    }

    async fn login(&self, req: &LoginRequest, peer: SocketAddr) -> Result<LoginAccepted, LoginRefused> {
        let result = self.check(req, peer).await;
        let label = match &result {
            Ok(_) => "ok",
            Err(r) => match r.reason {
                RefusalReason::WrongCredentials => "wrong_credentials",
                RefusalReason::RateLimited => "rate_limited",
                RefusalReason::ServerFull => "server_full",
                RefusalReason::BadRequest => "bad_request",
                RefusalReason::Unavailable => "unavailable",
                RefusalReason::ShuttingDown => "shutting_down",
            },
        };
        metrics::counter!("myriad_logins_total", "result" => label).increment(1);
        result
    }

    async fn check(&self, req: &LoginRequest, peer: SocketAddr) -> Result<LoginAccepted, LoginRefused> {
        if self.shared.stop.load(Ordering::Acquire) {
            return refuse(RefusalReason::ShuttingDown, 0);
        }
        if let Some(wait) = self.limiter.check(peer.ip(), &req.username, Instant::now()) {
            tracing::info!(%peer, user = %req.username, "login rate-limited");
            return refuse(RefusalReason::RateLimited, wait.as_millis().min(u32::MAX as u128) as u32);
        }
        let info = {
            let _permit = self
                .hashing
                .acquire()
                .await
                .map_err(|_| LoginRefused { reason: RefusalReason::ShuttingDown, retry_after_ms: 0 })?;
            self.store.login(&req.username, &req.password, self.map_id).await
        };
        let info = match info {
            Ok(info) => info,
            Err(StoreError::WrongCredentials | StoreError::InvalidInput(_) | StoreError::NotFound(_)) => {
                self.limiter.failed(peer.ip(), &req.username, Instant::now());
                tracing::info!(%peer, user = %req.username, "login failed: wrong credentials");
                return refuse(RefusalReason::WrongCredentials, 0);
            }
            Err(e) => {
                tracing::warn!(%peer, error = %e, "login failed: store unavailable");
                return refuse(RefusalReason::Unavailable, 1000);
            }
        };
        self.limiter.succeeded(&req.username);
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
            map: self.map.clone(),
        })
    }
}

fn refuse<T>(reason: RefusalReason, retry_after_ms: u32) -> Result<T, LoginRefused> {
    Err(LoginRefused { reason, retry_after_ms })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn limits_per_address_and_account_and_expire() {
        let l = RateLimiter::new(Duration::from_secs(60), 3, 2);
        let t0 = Instant::now();
        let a: IpAddr = "10.0.0.1".parse().unwrap();
        let b: IpAddr = "10.0.0.2".parse().unwrap();
        assert!(l.check(a, "bob", t0).is_none());
        l.failed(a, "bob", t0);
        l.failed(b, "BOB", t0);
        // Two failures for the account (case-insensitive): locked from any address.
        assert!(l.check(b, "bob", t0).is_some());
        assert!(l.check(a, "alice", t0).is_none());
        l.failed(a, "carol", t0);
        l.failed(a, "dave", t0);
        // Three failures from address a: locked for any account.
        assert!(l.check(a, "erin", t0).is_some());
        assert!(l.check(b, "erin", t0).is_none());
        let later = t0 + Duration::from_secs(61);
        assert!(l.check(a, "erin", later).is_none());
        assert!(l.check(b, "bob", later).is_none());
    }

    #[test]
    fn success_clears_the_account_only() {
        let l = RateLimiter::new(Duration::from_secs(60), 2, 2);
        let t0 = Instant::now();
        let a: IpAddr = "10.0.0.1".parse().unwrap();
        l.failed(a, "bob", t0);
        l.failed(a, "bob", t0);
        assert!(l.check(a, "bob", t0).is_some());
        l.succeeded("bob");
        // The address still has its two failures.
        assert!(l.check(a, "zed", t0).is_some());
    }
}
