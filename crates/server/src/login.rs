//! The TLS login service.
//!
//! # How it works
//!
//! A tokio task accepts TCP connections and runs each on its own task: TLS 1.3
//! handshake, one bounded [`LoginRequest`] frame, a rate-limit check, then the password
//! check against the store, then the join through the tick loop, which creates the
//! session keys and the player's object; the response goes back over TLS, followed by
//! the map data when asked.
//!
//! # What a login may cost (issue 14)
//!
//! Every step is bounded, and the cheap checks come before the dear ones:
//!
//! 1. **Connections**: at most `login_connections_per_addr` in flight per client
//!    address (an IPv6 client is keyed by its /64) and 4,096 in all; beyond either the
//!    connection is closed at once, before any TLS work. One address can therefore never
//!    hold the global cap and lock out everyone else.
//! 2. **Handshake and request** within `login_handshake_timeout_ms`, so an idle or slow
//!    connection is gone quickly; the whole exchange within 15 s.
//! 3. **Failed-login limits** ([`RateLimiter`]), checked before any hashing: per
//!    (account, address) with exponential backoff, and per address. Nothing is counted
//!    per account alone, so a stranger can never lock the owner out.
//! 4. **Unknown users** are refused without hashing, after a pause as long as a typical
//!    verification, so the answer's timing still does not tell them apart.
//! 5. **Password checks** run on the store's verification pool (`hashing_threads()`
//!    threads, the cores less one for the tick by default), behind `HashGate`: at most
//!    that many at once, at most `login_queue` waiting, each for at most
//!    `login_queue_deadline_ms`; beyond that the answer is "busy, retry" (with a
//!    retry hint) at once. The queue serves addresses with fewer recent failures first,
//!    so a storm of wrong passwords cannot crowd out a client whose address has none,
//!    and at most `ACCOUNT_CHECKS_IN_FLIGHT` (2) checks of one account are in flight (a
//!    storm on one account is refused before hashing beyond that).
//!
//! Passwords never reach a log: [`LoginRequest`]'s `Debug` hides them and only the
//! username and address are logged.

use std::collections::HashMap;
use std::hash::Hash;
use std::net::{IpAddr, Ipv6Addr, SocketAddr};
use std::sync::atomic::{AtomicU64, Ordering};
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
use tokio_rustls::server::TlsStream;

use crate::status::{Shared, bump};
use crate::tick::Command;

/// Deadline of a whole login exchange (handshake, request, check, response).
const LOGIN_DEADLINE: Duration = Duration::from_secs(15);

/// The key limits are counted under: an IPv4 address as is (an IPv4-mapped IPv6 one as
/// IPv4), an IPv6 address by its /64, the block one subscriber usually holds.
pub fn limit_key(ip: IpAddr) -> IpAddr {
    match ip {
        IpAddr::V4(v4) => IpAddr::V4(v4),
        IpAddr::V6(v6) => match v6.to_ipv4_mapped() {
            Some(v4) => IpAddr::V4(v4),
            None => {
                let s = v6.segments();
                IpAddr::V6(Ipv6Addr::new(s[0], s[1], s[2], s[3], 0, 0, 0, 0))
            }
        },
    }
}

/// One (account, address)'s failures.
#[derive(Debug, Clone, Copy)]
struct Failures {
    count: u32,
    last: Instant,
}

/// Failed-login limits, checked before any password is hashed.
///
/// - Per **(account, address)**: after `per_account` failures the pair is locked for
///   1 s, and each further failure doubles the lock (2 s, 4 s, … up to the window).
///   The pair is forgotten two windows after its last failure, and at a success.
/// - Per **address**: `per_addr` failures within the window lock the address for every
///   account (one address guessing many accounts).
///
/// Nothing is counted per account alone: a stranger's failures never lock the owner out
/// from the owner's address. `docs/server.md` argues the choice.
#[derive(Debug)]
pub struct RateLimiter {
    window: Duration,
    per_addr: u32,
    per_account: u32,
    addrs: Mutex<HashMap<IpAddr, (u32, Instant)>>,
    pairs: Mutex<HashMap<(String, IpAddr), Failures>>,
}

/// Entries each table may hold before expired ones are swept.
const LIMITER_SWEEP: usize = 100_000;

impl RateLimiter {
    /// Allows `per_addr` failures per address per `window`, and `per_account` free
    /// failures per (account, address) before the backoff starts.
    pub fn new(window: Duration, per_addr: u32, per_account: u32) -> Self {
        Self { window, per_addr, per_account, addrs: Mutex::default(), pairs: Mutex::default() }
    }

    /// `Some(retry after)` if this address, or this account from this address, is
    /// locked out now.
    pub fn check(&self, addr: IpAddr, account: &str, now: Instant) -> Option<Duration> {
        let addr = limit_key(addr);
        let by_addr = {
            let map = self.addrs.lock().unwrap_or_else(|p| p.into_inner());
            map.get(&addr).and_then(|&(count, since)| {
                let age = now.saturating_duration_since(since);
                (count >= self.per_addr && age < self.window).then(|| self.window - age)
            })
        };
        let by_pair = {
            let map = self.pairs.lock().unwrap_or_else(|p| p.into_inner());
            map.get(&(account.to_ascii_lowercase(), addr)).and_then(|f| {
                let lock = self.lock_for(f.count)?;
                let age = now.saturating_duration_since(f.last);
                (age < lock).then(|| lock - age)
            })
        };
        by_addr.max(by_pair)
    }

    /// How long `count` failures lock their pair (none while under the free ones).
    fn lock_for(&self, count: u32) -> Option<Duration> {
        let over = count.checked_sub(self.per_account)?;
        let secs = 1u64.checked_shl(over.min(30)).unwrap_or(u64::MAX);
        Some(Duration::from_secs(secs).min(self.window))
    }

    /// Counts a failed login.
    pub fn failed(&self, addr: IpAddr, account: &str, now: Instant) {
        let addr = limit_key(addr);
        let window = self.window;
        {
            let mut map = self.addrs.lock().unwrap_or_else(|p| p.into_inner());
            // Bound the memory an attacker with many addresses can make us use.
            if map.len() > LIMITER_SWEEP {
                map.retain(|_, (_, since)| now.saturating_duration_since(*since) < window);
            }
            let entry = map.entry(addr).or_insert((0, now));
            if now.saturating_duration_since(entry.1) >= window {
                *entry = (0, now);
            }
            entry.0 += 1;
        }
        let mut map = self.pairs.lock().unwrap_or_else(|p| p.into_inner());
        if map.len() > LIMITER_SWEEP {
            map.retain(|_, f| now.saturating_duration_since(f.last) < window * 2);
        }
        let entry = map.entry((account.to_ascii_lowercase(), addr)).or_insert(Failures { count: 0, last: now });
        if now.saturating_duration_since(entry.last) >= window * 2 {
            entry.count = 0;
        }
        entry.count += 1;
        entry.last = now;
    }

    /// Failures counted against `addr` in the current window (the hashing queue's
    /// priority: fewer goes first).
    pub fn address_failures(&self, addr: IpAddr, now: Instant) -> u32 {
        let map = self.addrs.lock().unwrap_or_else(|p| p.into_inner());
        map.get(&limit_key(addr))
            .filter(|(_, since)| now.saturating_duration_since(*since) < self.window)
            .map_or(0, |(count, _)| *count)
    }

    /// A successful login clears the (account, address) pair (not the address's count:
    /// one address guessing many accounts must stay limited).
    pub fn succeeded(&self, addr: IpAddr, account: &str) {
        let key = (account.to_ascii_lowercase(), limit_key(addr));
        self.pairs.lock().unwrap_or_else(|p| p.into_inner()).remove(&key);
    }
}

/// Admission to the password-hashing pool: at most `threads` checks run at once, at most
/// `queue` wait, none waits past `deadline`; see the module docs.
///
/// The queue is ordered by **priority** (lower first; the login service uses the
/// failures of the client's address), then by arrival. When it is full, a newcomer of
/// better priority takes the place of the worst waiter, which is told "busy". So a storm
/// of wrong passwords, whose addresses collect failures, cannot keep a client from an
/// address with none out of the queue: that client waits at most for the checks already
/// running.
#[derive(Debug)]
pub(crate) struct HashGate {
    state: Mutex<GateState>,
    threads: usize,
    queue: usize,
    deadline: Duration,
    /// Mean time of one check in µs (a moving average), for retry hints and for the
    /// pause before refusing an unknown user.
    mean_us: AtomicU64,
}

#[derive(Debug, Default)]
struct GateState {
    running: usize,
    /// Waiters by (priority, arrival): granted a slot by sending `()`, refused by
    /// dropping the sender.
    waiters: std::collections::BTreeMap<(u32, u64), tokio::sync::oneshot::Sender<()>>,
    arrivals: u64,
}

/// A running slot of the [`HashGate`]; handed to the best waiter when dropped.
#[derive(Debug)]
pub(crate) struct GatePermit<'a>(&'a HashGate);

impl Drop for GatePermit<'_> {
    fn drop(&mut self) {
        self.0.release();
    }
}

impl HashGate {
    /// A gate for `threads` hashing threads, `queue` waiters and a wait `deadline`.
    pub fn new(threads: usize, queue: usize, deadline: Duration) -> Self {
        HashGate { state: Mutex::default(), threads: threads.max(1), queue, deadline, mean_us: AtomicU64::new(25_000) }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, GateState> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// A running slot for a check of `priority` (lower is served first), or
    /// `Err(retry after)` when the queue is full of better or equal waiters, when this
    /// waiter is pushed out by a better one, or when the wait passes the deadline.
    pub async fn enter(&self, priority: u32) -> Result<GatePermit<'_>, Duration> {
        let (key, granted) = {
            let mut st = self.lock();
            if st.running < self.threads {
                st.running += 1;
                return Ok(GatePermit(self));
            }
            if st.waiters.len() >= self.queue {
                // Full: push out the worst waiter if this one is better.
                match st.waiters.last_key_value() {
                    Some((&(worst, _), _)) if worst > priority => {
                        st.waiters.pop_last();
                    }
                    _ => return Err(self.retry_hint(st.waiters.len())),
                }
            }
            let key = (priority, st.arrivals);
            st.arrivals += 1;
            let (tx, rx) = tokio::sync::oneshot::channel();
            st.waiters.insert(key, tx);
            (key, rx)
        };
        let mut granted = granted;
        match tokio::time::timeout(self.deadline, &mut granted).await {
            Ok(Ok(())) => Ok(GatePermit(self)),
            Ok(Err(_)) => Err(self.retry_hint(self.queue)),
            Err(_) => {
                let mut st = self.lock();
                if st.waiters.remove(&key).is_some() {
                    return Err(self.retry_hint(st.waiters.len()));
                }
                drop(st);
                // Granted (or pushed out) just as the deadline passed.
                match granted.try_recv() {
                    Ok(()) => Ok(GatePermit(self)),
                    Err(_) => Err(self.retry_hint(self.queue)),
                }
            }
        }
    }

    /// Hands the slot to the best waiter still waiting, or frees it.
    fn release(&self) {
        let mut st = self.lock();
        while let Some((_, tx)) = st.waiters.pop_first() {
            if tx.send(()).is_ok() {
                return;
            }
        }
        st.running = st.running.saturating_sub(1);
    }

    /// Waiters now.
    #[cfg(test)]
    fn waiting(&self) -> usize {
        self.lock().waiters.len()
    }

    /// Records how long one check took.
    pub fn record(&self, took: Duration) {
        let us = took.as_micros().min(u64::MAX as u128) as u64;
        let old = self.mean_us.load(Ordering::Relaxed);
        self.mean_us.store((old * 7 + us) / 8, Ordering::Relaxed);
    }

    /// The typical time of one check.
    pub fn typical(&self) -> Duration {
        Duration::from_micros(self.mean_us.load(Ordering::Relaxed))
    }

    /// When a refused check might get in: the time to drain `ahead` waiters, at least
    /// 100 ms.
    fn retry_hint(&self, ahead: usize) -> Duration {
        (self.typical() * (ahead as u32 + 1) / self.threads as u32).max(Duration::from_millis(100))
    }
}

/// Password checks of one account that may be queued or running at once; more are
/// refused with "busy" before any hashing.
pub(crate) const ACCOUNT_CHECKS_IN_FLIGHT: u32 = 2;

/// Things in flight per key (password checks per account, connections per address),
/// each counted by a slot that gives its place back on drop.
#[derive(Debug)]
pub(crate) struct InFlight<K> {
    counts: Mutex<HashMap<K, u32>>,
}

impl<K> Default for InFlight<K> {
    fn default() -> Self {
        InFlight { counts: Mutex::default() }
    }
}

/// One thing counted against its key; released on drop.
pub(crate) struct InFlightSlot<K: Eq + Hash> {
    owner: Arc<InFlight<K>>,
    key: K,
}

impl<K: Eq + Hash + Clone> InFlight<K> {
    /// A slot for one more under `key`, unless `cap` are in flight.
    fn take(self: &Arc<Self>, key: K, cap: u32) -> Option<InFlightSlot<K>> {
        let mut map = self.counts.lock().unwrap_or_else(|p| p.into_inner());
        let n = map.entry(key.clone()).or_insert(0);
        if *n >= cap {
            return None;
        }
        *n += 1;
        Some(InFlightSlot { owner: self.clone(), key })
    }
}

impl<K: Eq + Hash> Drop for InFlightSlot<K> {
    fn drop(&mut self) {
        let mut map = self.owner.counts.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(n) = map.get_mut(&self.key) {
            *n -= 1;
            if *n == 0 {
                map.remove(&self.key);
            }
        }
    }
}

/// Password checks in flight per (case-folded) account.
pub(crate) type AccountsInFlight = InFlight<String>;

impl AccountsInFlight {
    /// A slot for one more check of `account`, unless `cap` are in flight.
    pub fn try_take(self: &Arc<Self>, account: &str, cap: u32) -> Option<InFlightSlot<String>> {
        self.take(account.to_ascii_lowercase(), cap)
    }
}

/// Login connections in flight per client address (see [`limit_key`]).
pub(crate) type ConnectionCounts = InFlight<IpAddr>;

impl ConnectionCounts {
    /// A slot for one more connection from `ip`, unless it already holds `cap`.
    pub fn try_take(self: &Arc<Self>, ip: IpAddr, cap: u32) -> Option<InFlightSlot<IpAddr>> {
        self.take(limit_key(ip), cap)
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
    pub hashing: HashGate,
    /// Login connections in flight (handshake to close), in all.
    pub connections: Arc<Semaphore>,
    /// Login connections in flight per address.
    pub per_addr: Arc<ConnectionCounts>,
    /// Most connections in flight per address.
    pub per_addr_cap: u32,
    /// Deadline of the TLS handshake and the request.
    pub handshake_timeout: Duration,
    /// Password checks in flight (queued or running) per account.
    pub accounts_in_flight: Arc<AccountsInFlight>,
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
            tls.write_all(&self.map_frame).await?;
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
            let info = self.store.login(&req.username, &req.password, self.map_id).await;
            self.hashing.record(started.elapsed());
            info
        };
        let info = match info {
            Ok(info) => info,
            Err(StoreError::WrongCredentials | StoreError::InvalidInput(_) | StoreError::NotFound(_)) => {
                return self.wrong_credentials(req, peer);
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
            map: self.map.clone(),
        })
    }

    fn wrong_credentials<T>(&self, req: &LoginRequest, peer: SocketAddr) -> Result<T, LoginRefused> {
        self.limiter.failed(peer.ip(), &req.username, Instant::now());
        tracing::info!(%peer, user = %req.username, "login failed: wrong credentials");
        refuse(RefusalReason::WrongCredentials, 0)
    }
}

/// Counts a login's outcome in `myriad_logins_total{result}` (and the defence counters).
fn count_login(shared: &Shared, result: Result<(), RefusalReason>) {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_strangers_failures_never_lock_the_owner_out() {
        let l = RateLimiter::new(Duration::from_secs(60), 20, 3);
        let t0 = Instant::now();
        let stranger: IpAddr = "10.0.0.1".parse().unwrap();
        let owner: IpAddr = "10.0.0.2".parse().unwrap();
        for _ in 0..3 {
            assert!(l.check(stranger, "bob", t0).is_none(), "locked only after the third");
            l.failed(stranger, "BOB", t0);
        }
        // Locked for the stranger (case-insensitive account)…
        assert!(l.check(stranger, "bob", t0).is_some());
        // …never for the owner, from an address with no failures.
        assert!(l.check(owner, "bob", t0).is_none());
        // Nor for the stranger on another account (only the per-address limit spans
        // accounts).
        assert!(l.check(stranger, "alice", t0).is_none());
    }

    #[test]
    fn backoff_doubles_and_is_capped_by_the_window() {
        let l = RateLimiter::new(Duration::from_secs(10), 100, 2);
        let a: IpAddr = "10.0.0.1".parse().unwrap();
        let mut t = Instant::now();
        l.failed(a, "bob", t);
        assert!(l.check(a, "bob", t).is_none(), "one failure is free");
        let mut locks = Vec::new();
        for _ in 0..6 {
            l.failed(a, "bob", t);
            let lock = l.check(a, "bob", t).expect("locked after a failure over the free ones");
            locks.push(lock.as_secs());
            t += lock;
            assert!(l.check(a, "bob", t).is_none(), "the lock ends");
        }
        assert_eq!(locks, [1, 2, 4, 8, 10, 10]);
        // A success clears the pair.
        l.failed(a, "bob", t);
        l.succeeded(a, "bob");
        assert!(l.check(a, "bob", t).is_none());
    }

    #[test]
    fn per_address_limit_spans_accounts_and_expires() {
        let l = RateLimiter::new(Duration::from_secs(60), 3, 100);
        let t0 = Instant::now();
        let a: IpAddr = "10.0.0.1".parse().unwrap();
        for name in ["carol", "dave", "erin"] {
            l.failed(a, name, t0);
        }
        assert!(l.check(a, "zed", t0).is_some());
        l.succeeded(a, "carol");
        assert!(l.check(a, "zed", t0).is_some(), "a success does not clear the address");
        assert!(l.check("10.0.0.2".parse().unwrap(), "zed", t0).is_none());
        assert!(l.check(a, "zed", t0 + Duration::from_secs(61)).is_none());
    }

    #[test]
    fn ipv6_clients_are_keyed_by_their_64_and_mapped_v4_as_v4() {
        let a: IpAddr = "2001:db8:1:2:aaaa::1".parse().unwrap();
        let b: IpAddr = "2001:db8:1:2:bbbb::9".parse().unwrap();
        let c: IpAddr = "2001:db8:1:3::1".parse().unwrap();
        assert_eq!(limit_key(a), limit_key(b));
        assert_ne!(limit_key(a), limit_key(c));
        let mapped: IpAddr = "::ffff:10.1.2.3".parse().unwrap();
        assert_eq!(limit_key(mapped), "10.1.2.3".parse::<IpAddr>().unwrap());
    }

    #[test]
    fn connection_caps_are_per_address_and_released() {
        let accounts = Arc::new(AccountsInFlight::default());
        let two: Vec<_> = (0..2).map(|_| accounts.try_take("Bob", 2).unwrap()).collect();
        assert!(accounts.try_take("bob", 2).is_none(), "case-folded, capped");
        assert!(accounts.try_take("alice", 2).is_some());
        drop(two);
        assert!(accounts.try_take("BOB", 2).is_some());

        let counts = Arc::new(ConnectionCounts::default());
        let a: IpAddr = "127.0.0.1".parse().unwrap();
        let b: IpAddr = "127.0.0.2".parse().unwrap();
        let held: Vec<_> = (0..3).map(|_| counts.try_take(a, 3).unwrap()).collect();
        assert!(counts.try_take(a, 3).is_none(), "a's cap is full");
        assert!(counts.try_take(b, 3).is_some(), "b is not affected");
        drop(held);
        assert!(counts.try_take(a, 3).is_some(), "closing frees the slots");
    }

    #[tokio::test]
    async fn the_hash_gate_queues_up_to_its_limit_then_says_busy() {
        let gate = Arc::new(HashGate::new(1, 2, Duration::from_millis(200)));
        let running = gate.enter(0).await.unwrap();
        // Two may wait…
        let (g1, g2) = (gate.clone(), gate.clone());
        let w1 = tokio::spawn(async move { g1.enter(5).await.map(drop) });
        let w2 = tokio::spawn(async move { g2.enter(5).await.map(drop) });
        tokio::time::sleep(Duration::from_millis(20)).await;
        assert_eq!(gate.waiting(), 2);
        // …a third of the same priority is refused at once, with a retry hint.
        let t = Instant::now();
        let retry = gate.enter(5).await.unwrap_err();
        assert!(t.elapsed() < Duration::from_millis(100) && retry >= Duration::from_millis(100));
        // The waiters hit the deadline while the slot stays taken.
        assert!(w1.await.unwrap().is_err() && w2.await.unwrap().is_err());
        assert_eq!(gate.waiting(), 0);
        drop(running);
        assert!(gate.enter(0).await.is_ok(), "a free slot is taken at once");
    }

    #[tokio::test]
    async fn a_clean_address_pushes_a_failing_one_out_of_a_full_queue_and_goes_first() {
        let gate = Arc::new(HashGate::new(1, 2, Duration::from_secs(5)));
        let running = gate.enter(0).await.unwrap();
        let spawn = |prio: u32| {
            let g = gate.clone();
            tokio::spawn(async move { g.enter(prio).await.map(|p| (prio, Instant::now(), drop(p))) })
        };
        let bad1 = spawn(20);
        tokio::time::sleep(Duration::from_millis(10)).await;
        let bad2 = spawn(30);
        tokio::time::sleep(Duration::from_millis(10)).await;
        // The queue is full; a waiter with no failures pushes out the worst (30).
        let clean = spawn(0);
        let pushed_out = bad2.await.unwrap();
        assert!(pushed_out.is_err(), "the worst waiter is told busy at once");
        tokio::time::sleep(Duration::from_millis(10)).await;
        drop(running);
        let (_, clean_at, ()) = clean.await.unwrap().unwrap();
        let (_, bad_at, ()) = bad1.await.unwrap().unwrap();
        assert!(clean_at <= bad_at, "the clean address is served first");
        assert_eq!(gate.waiting(), 0);
        assert_eq!(gate.lock().running, 0, "every slot came back");
    }
}
