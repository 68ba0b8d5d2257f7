//! One task driving a group of bots that share a UDP socket.
//!
//! Why groups: with a task and a socket per bot, every datagram costs a wake-up of its
//! bot's task and a receive call of its own, and a 2,500-bot swarm took more of a
//! two-core machine than the server it loaded. A group's task wakes once for every
//! datagram queued on its socket, reads them all, and hands each to the bot its header's
//! session id names ([`Connection::handle_datagram`]); the server tells sessions apart
//! by id, not by address. With one bot a group (`bots_per_socket = 1`) every bot has a
//! socket and a task of its own, as a real player would.
//!
//! Logins run as tasks of their own (a login waits for the server's hashing queue), and
//! hand their answer back to the group, which starts (or resumes) the bot's session on
//! the group's socket.

use std::io::ErrorKind;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use myriad_protocol::login::{LoginAccepted, MapData};
use myriad_protocol::{ActionMask, Direction, DisconnectReason, MAX_DATAGRAM, peek_header};
use tokio::net::UdpSocket;
use tokio::sync::watch;
use tokio::task::JoinSet;

use super::{Behaviour, Ctx, FORGET_AFTER, HOLD, SHUTTLE_HOLDS};
use crate::connection::{Connection, Credentials, Event, SessionEnd, login, server_socket};
use crate::error::ClientError;

/// Receive buffer asked for a group's socket, per bot (two datagrams of a tick and
/// slack), within [`MIN_RECV_BUFFER`] and [`MAX_RECV_BUFFER`].
const RECV_BUFFER_PER_BOT: usize = 16 << 10;
const MIN_RECV_BUFFER: usize = 256 << 10;
const MAX_RECV_BUFFER: usize = 8 << 20;

/// The receive buffer asked for the socket of a group of `members` bots.
fn recv_buffer(members: usize) -> usize {
    members.saturating_mul(RECV_BUFFER_PER_BOT).clamp(MIN_RECV_BUFFER, MAX_RECV_BUFFER)
}

/// How often a bot samples the staleness of the states it holds (every object of its
/// AOI each time: a second keeps the swarm's cost small).
const STALENESS_EVERY: Duration = Duration::from_secs(1);

/// Datagrams read in one wake-up at most, so that the group's ticker is not starved.
const MAX_READS: usize = 4096;

/// What a login task hands back: the bot's place in the group and the server's answer.
type LoginDone = (usize, Result<(LoginAccepted, Option<MapData>), ClientError>);

/// One bot of a group, with what it measured since it last published.
struct Player {
    /// The bot's index in the swarm (`user<first + index>`).
    index: usize,
    conn: Option<Connection>,
    /// A login for this bot is under way.
    logging_in: bool,
    mask: u8,
    seed: u64,
    hold_index: u64,
    hold_start: Instant,
    hold_from: Option<[f32; 3]>,
    last_tick: u64,
    last_update: Option<Instant>,
    /// When the current session's login answered, until its first state update.
    awaiting_first_update: Option<Instant>,
    last_publish: Instant,
    intervals: Vec<u64>,
    /// Logins' times to their first update, µs, since the last publish.
    first_updates: Vec<u64>,
    ticks_missed: u64,
    own_seen: bool,
    in_view: usize,
    /// Staleness samples since the last publish: (distance from the bot, age).
    staleness: Vec<(f32, Duration)>,
    /// When the bot last sampled the staleness of what it holds.
    last_staleness: Instant,
}

impl Player {
    fn new(index: usize) -> Self {
        let now = Instant::now();
        Player {
            index,
            conn: None,
            logging_in: true,
            mask: 0,
            seed: (index as u64 + 1).wrapping_mul(0x9e37_79b9_7f4a_7c15),
            hold_index: 0,
            hold_start: now,
            hold_from: None,
            last_tick: 0,
            last_update: None,
            awaiting_first_update: None,
            last_publish: now,
            intervals: Vec::with_capacity(16),
            first_updates: Vec::new(),
            ticks_missed: 0,
            own_seen: false,
            in_view: 0,
            staleness: Vec::new(),
            last_staleness: now,
        }
    }
}

/// Logs bot `index` in, retrying refusals that may pass later (waiting the server's hint,
/// at most 5 s), through the swarm's semaphore of logins in flight.
async fn login_retrying(
    ctx: Arc<Ctx>,
    index: usize,
    stop: watch::Receiver<bool>,
) -> Result<(LoginAccepted, Option<MapData>), ClientError> {
    let credentials = Credentials::test_user(ctx.config.first + index);
    let mut attempt = 0;
    loop {
        let result = {
            let _permit = ctx.logins.acquire().await.map_err(|_| ClientError::Timeout("swarm stopped"))?;
            ctx.shared.login_attempts.fetch_add(1, Ordering::Relaxed);
            login(&ctx.config.client, &credentials).await
        };
        attempt += 1;
        match result {
            Ok(answer) => return Ok(answer),
            Err(e) if e.is_retryable() && attempt < ctx.config.login_attempts && !*stop.borrow() => {
                let wait = match &e {
                    ClientError::Refused { retry_after_ms, .. } if *retry_after_ms > 0 => {
                        Duration::from_millis(u64::from(*retry_after_ms).min(5000))
                    }
                    _ => Duration::from_millis(200 * u64::from(attempt.min(10))),
                };
                tokio::time::sleep(wait).await;
            }
            Err(e) => return Err(e),
        }
    }
}

/// Logs bot `index` (at `at` in its group) in on a task of its own, after `delay`.
fn spawn_login(
    logins: &mut JoinSet<LoginDone>,
    ctx: &Arc<Ctx>,
    (at, index): (usize, usize),
    delay: Duration,
    stop: &watch::Receiver<bool>,
) {
    let (ctx, stop) = (ctx.clone(), stop.clone());
    logins.spawn(async move {
        tokio::time::sleep(delay).await;
        (at, login_retrying(ctx, index, stop).await)
    });
}

/// A group of bots on one socket; see the module docs.
pub(super) struct Group {
    pub(super) ctx: Arc<Ctx>,
    /// The bots' indices in the swarm.
    pub(super) members: Vec<usize>,
}

impl Group {
    /// Runs the group until the swarm stops; then every bot says goodbye.
    pub(super) async fn run(self, stop: watch::Receiver<bool>) {
        let ctx = self.ctx;
        let mut players: Vec<Player> = self.members.iter().map(|&i| Player::new(i)).collect();
        let mut logins: JoinSet<LoginDone> = JoinSet::new();
        for (at, p) in players.iter().enumerate() {
            // Bot i of n starts at i/n of the spread.
            let delay = ctx.config.login_spread.mul_f64(p.index as f64 / ctx.config.count.max(1) as f64);
            spawn_login(&mut logins, &ctx, (at, p.index), delay, &stop);
        }
        let mut socket: Option<Arc<UdpSocket>> = None;
        let mut by_session: foldhash::HashMap<u64, usize> = foldhash::HashMap::default();
        let period = Duration::from_secs_f32(1.0 / ctx.config.rate_hz.max(0.1));
        let mut ticker = tokio::time::interval(period);
        ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut buf = vec![0u8; MAX_DATAGRAM + 64];
        // One wait for the stop, kept across the loop: made afresh in every `select!`, it
        // registered and dropped a waiter per wake-up.
        let mut stop_signal = stop.clone();
        let stopped = stop_signal.changed();
        tokio::pin!(stopped);
        loop {
            let readable = async {
                match &socket {
                    Some(s) => s.readable().await,
                    None => std::future::pending().await,
                }
            };
            tokio::select! {
                _ = &mut stopped => break,
                Some(done) = logins.join_next(), if !logins.is_empty() => {
                    let Ok((at, answer)) = done else { continue };
                    let p = &mut players[at];
                    if let Err(e) = logged_in(&ctx, p, at, answer, &mut socket, &mut by_session, self.members.len()).await {
                        let again = if p.conn.is_some() { "reconnect: " } else { "" };
                        if p.conn.is_none() {
                            ctx.shared.logins_failed.fetch_add(1, Ordering::Relaxed);
                        }
                        if let Some(c) = p.conn.take() {
                            by_session.remove(&c.session_id());
                        }
                        ctx.state(p.index).error = Some(format!("user{}: {again}{e}", ctx.config.first + p.index));
                    }
                }
                _ = ticker.tick() => {
                    let now = Instant::now();
                    for (at, p) in players.iter_mut().enumerate().filter(|(_, p)| !p.logging_in) {
                        if on_tick(&ctx, p, now).await {
                            spawn_login(&mut logins, &ctx, (at, p.index), Duration::ZERO, &stop);
                        }
                    }
                }
                r = readable => {
                    if r.is_err() {
                        continue;
                    }
                    let Some(s) = &socket else { continue };
                    for _ in 0..MAX_READS {
                        match s.try_recv(&mut buf) {
                            Ok(n) => on_datagram(&ctx, &mut players, &by_session, &mut buf[..n]),
                            Err(e) if e.kind() == ErrorKind::WouldBlock => break,
                            // An ICMP error of an earlier send (the server's port closed):
                            // it concerns no datagram; read on.
                            Err(_) => {}
                        }
                    }
                }
            }
        }
        for p in &mut players {
            if let Some(conn) = &mut p.conn {
                let _ = conn.disconnect().await;
                publish(&ctx, p);
            }
            ctx.state(p.index).connected = false;
        }
    }
}

/// Starts or resumes bot `p`'s session (at `at` in the group) after a login's `answer`,
/// on the group's socket (made at the first login, made anew if the server's UDP port
/// moved).
async fn logged_in(
    ctx: &Ctx,
    p: &mut Player,
    at: usize,
    answer: Result<(LoginAccepted, Option<MapData>), ClientError>,
    socket: &mut Option<Arc<UdpSocket>>,
    by_session: &mut foldhash::HashMap<u64, usize>,
    members: usize,
) -> Result<(), ClientError> {
    p.logging_in = false;
    let (accepted, map) = answer?;
    let client = &ctx.config.client;
    let wanted = std::net::SocketAddr::new(client.login_addr.ip(), accepted.udp_port);
    if socket.as_ref().is_none_or(|s| s.peer_addr().ok() != Some(wanted)) {
        *socket = Some(Arc::new(server_socket(client, accepted.udp_port, recv_buffer(members)).await?));
    }
    let socket = socket.clone().expect("made above");
    match &mut p.conn {
        Some(conn) => {
            by_session.remove(&conn.session_id());
            conn.resume(accepted, map, socket).await?;
        }
        None => {
            let credentials = Credentials::test_user(ctx.config.first + p.index);
            p.conn = Some(Connection::from_login(client.clone(), credentials, accepted, map, socket).await?);
        }
    }
    let conn = p.conn.as_ref().expect("set above");
    by_session.insert(conn.session_id(), at);
    ctx.shared.logins_ok.fetch_add(1, Ordering::Relaxed);
    ctx.state(p.index).connected = true;
    p.awaiting_first_update = Some(Instant::now());
    p.hold_from = None;
    Ok(())
}

/// A bot's tick: judge the hold that ended and pick the next, send the action, publish
/// every 250 ms. Returns whether the bot's session is over (the server ended it, or it
/// went silent) and it must log in again.
async fn on_tick(ctx: &Ctx, p: &mut Player, now: Instant) -> bool {
    let Some(conn) = p.conn.as_mut() else { return false };
    if now.duration_since(p.hold_start) >= HOLD {
        ctx.check_move(p.index, p.mask, p.hold_from, conn.own_position(), p.hold_index, conn.dilation_permille());
        p.hold_index += 1;
        p.seed = p.seed.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
        p.mask = match ctx.config.behaviour {
            Behaviour::Idle => 0,
            Behaviour::Circle => [ActionMask::FORWARD, ActionMask::RIGHT, ActionMask::BACK, ActionMask::LEFT]
                [(p.hold_index % 4) as usize],
            Behaviour::Shuttle => [ActionMask::RIGHT, ActionMask::LEFT][(p.hold_index / SHUTTLE_HOLDS % 2) as usize],
            Behaviour::Random => [0, ActionMask::FORWARD, ActionMask::BACK, ActionMask::RIGHT, ActionMask::LEFT]
                [((p.seed >> 33) % 5) as usize],
        };
        p.hold_start = now;
        p.hold_from = conn.own_position();
    }
    // Resends what the session still waits for, probes a silent server; the session is
    // over only on evidence (a Disconnect, or silence through the probes).
    if let Err(e) = conn.on_timer(now).await {
        tracing::debug!(bot = p.index, error = %e, "send failed");
    }
    if let Some(end) = conn.ended() {
        let mut state = ctx.state(p.index);
        state.connected = false;
        match end {
            SessionEnd::Disconnected(DisconnectReason::Kicked) => state.kicked += 1,
            SessionEnd::Disconnected(DisconnectReason::Banned) => state.banned += 1,
            _ => {}
        }
        drop(state);
        p.logging_in = true;
        return true;
    }
    if let Err(e) = conn.send_action(p.mask).await {
        tracing::debug!(bot = p.index, error = %e, "send failed");
    }
    if now.duration_since(p.last_publish) >= Duration::from_millis(250) {
        p.last_publish = now;
        let mirror = conn.mirror_mut();
        mirror.mark_stale(now);
        // A walking bot meets thousands of objects: keep only recent ones.
        mirror.forget_older_than(FORGET_AFTER, now);
        p.in_view = mirror.fresh();
        if now.duration_since(p.last_staleness) >= STALENESS_EVERY {
            p.last_staleness = now;
            held_staleness(conn, ctx.config.aoi_size / 2.0, &mut p.staleness);
        }
        publish(ctx, p);
    }
    false
}

/// Hands one datagram from the group's socket to the bot whose session it names.
fn on_datagram(ctx: &Ctx, players: &mut [Player], by_session: &foldhash::HashMap<u64, usize>, datagram: &mut [u8]) {
    let at = peek_header(datagram, Direction::ServerToClient).ok().and_then(|h| by_session.get(&h.session_id));
    let Some(p) = at.and_then(|&at| players.get_mut(at)) else {
        // Not for a live session of this group (one that ended, or garbage).
        ctx.shared.stray_datagrams.fetch_add(1, Ordering::Relaxed);
        return;
    };
    let Some(conn) = p.conn.as_mut() else { return };
    let now = Instant::now();
    // Only updates need the bot's attention; the connection itself keeps what tells it
    // the session lives (every authentic datagram).
    let Event::Update { tick, .. } = conn.handle_datagram(datagram, now) else { return };
    if let Some(login) = p.awaiting_first_update.take() {
        p.first_updates.push(micros(now.duration_since(login)));
    }
    if tick > p.last_tick {
        if let Some(prev) = p.last_update {
            p.intervals.push(micros(now.duration_since(prev)));
            p.ticks_missed += tick - p.last_tick - 1;
        }
        p.last_tick = tick;
        p.last_update = Some(now);
    }
    p.own_seen = p.own_seen || conn.own_position().is_some();
}

/// Appends the staleness of every fresh object `conn` holds within `half` (per axis) of
/// its own object: the age of its newest state against the newest update (the own
/// object's tick: it is in every update), at the server's tick rate.
fn held_staleness(conn: &Connection, half: f32, out: &mut Vec<(f32, Duration)>) {
    let mirror = conn.mirror();
    let Some(own) = mirror.get(conn.entity_id()) else { return };
    let rate = mirror.clock().rate();
    for (id, o) in mirror.iter() {
        let d: [f32; 3] = std::array::from_fn(|i| o.position[i] - own.position[i]);
        if id == conn.entity_id() || o.stale || d.iter().any(|c| c.abs() > half) {
            continue;
        }
        let ticks = own.tick.saturating_sub(o.tick);
        let distance = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        out.push((distance, Duration::from_secs_f64(ticks as f64 / rate)));
    }
}

/// A duration in µs within the swarm's histograms' bounds.
fn micros(d: Duration) -> u64 {
    d.as_micros().clamp(1, 60_000_000) as u64
}

/// Publishes a bot's numbers: counters and view into its state, the intervals measured
/// since the last publish into the swarm's histogram.
fn publish(ctx: &Ctx, p: &mut Player) {
    {
        let mut s = ctx.state(p.index);
        if let Some(conn) = &p.conn {
            s.stats = conn.stats();
        }
        s.in_view = p.in_view;
        s.ticks_missed = p.ticks_missed;
        s.own_seen = p.own_seen;
    }
    if !p.staleness.is_empty() {
        let mut quality = ctx.shared.quality.lock().unwrap_or_else(|e| e.into_inner());
        for &(distance, age) in &p.staleness {
            quality.record_staleness(distance, age);
        }
        drop(quality);
        p.staleness.clear();
    }
    for (samples, hist) in
        [(&mut p.intervals, &ctx.shared.intervals), (&mut p.first_updates, &ctx.shared.first_updates)]
    {
        if !samples.is_empty() {
            let mut hist = hist.lock().unwrap_or_else(|e| e.into_inner());
            for &us in samples.iter() {
                let _ = hist.record(us);
            }
            samples.clear();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn receive_buffers_grow_with_the_group_within_bounds() {
        assert_eq!(recv_buffer(1), MIN_RECV_BUFFER);
        assert_eq!(recv_buffer(64), 1 << 20);
        assert_eq!(recv_buffer(10_000), 8 << 20);
    }
}
