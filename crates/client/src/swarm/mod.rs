//! A swarm of bots: many [`Connection`](crate::Connection)s on one tokio runtime, each playing
//! `user<i>` / `password<i>`, in groups that share a UDP socket and a task
//! ([`SwarmConfig::bots_per_socket`]; one bot a group by default: a socket and a task a
//! bot, as real players have; `group.rs` says why larger groups cost less).
//!
//! # How it works
//!
//! Bots log in through a semaphore (`login_concurrency` at once: the server hashes each
//! password), retrying refusals that may pass later. Each bot then sends its action at
//! `rate_hz`, reads every datagram into its mirror, records the interval between
//! consecutive ticks' updates in a histogram, and checks that its own object moves as
//! commanded: a direction is held for [`HOLD`], and at the end of the hold the bot's
//! horizontal displacement must point the commanded way (idle bots must stay put). A bot
//! whose session ends (server restart, time-out, replaced) logs in again. Every second
//! each bot measures the staleness of the states it holds of the objects around it
//! (near and over its AOI cube), against the newest update it got.

mod group;

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use hdrhistogram::Histogram;
use myriad_protocol::ActionMask;
use tokio::sync::{Semaphore, watch};
use tokio::task::JoinSet;

use crate::connection::ClientConfig;
use crate::quality::{Percentiles, Quality};
use crate::stats::ClientStats;

/// How long a bot holds one direction before checking its movement.
pub const HOLD: Duration = Duration::from_millis(1500);

/// A bot's mirror forgets objects it has not heard of for this long.
pub const FORGET_AFTER: Duration = Duration::from_secs(10);

/// What bots do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Behaviour {
    /// A random direction (or none) per hold.
    Random,
    /// The four directions in turn: a square walk.
    Circle,
    /// Stand still (still sending empty actions, which keep the session alive).
    Idle,
    /// Back and forth along x: right for [`SHUTTLE_HOLDS`] holds, then left as long
    /// (30 s each way, 150 units at the default speed): walks across zone boundaries.
    Shuttle,
}

/// Holds a shuttling bot walks one way before turning.
pub const SHUTTLE_HOLDS: u64 = 20;

impl std::str::FromStr for Behaviour {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "random" => Ok(Self::Random),
            "circle" => Ok(Self::Circle),
            "idle" => Ok(Self::Idle),
            "shuttle" => Ok(Self::Shuttle),
            other => Err(format!("unknown behaviour {other:?} (random, circle, idle, shuttle)")),
        }
    }
}

/// Settings of a swarm.
#[derive(Debug, Clone)]
pub struct SwarmConfig {
    /// How to reach the server.
    pub client: ClientConfig,
    /// Number of bots.
    pub count: usize,
    /// Index of the first bot's account (`user<first>`).
    pub first: usize,
    /// Actions per second per bot.
    pub rate_hz: f32,
    /// What bots do.
    pub behaviour: Behaviour,
    /// Logins in flight at once.
    pub login_concurrency: usize,
    /// Login attempts per bot before giving up (refusals that may pass later: busy, rate
    /// limited, server full, unavailable; each waits the server's hint, at most 5 s). A
    /// server protects its tick by verifying few passwords at once, so a burst of
    /// logins takes a while: bots keep trying, as players would.
    pub login_attempts: u32,
    /// A bot whose session stays silent this long, its keep-alive probes unanswered,
    /// logs in again: every bot's [`ClientConfig::silence_timeout`] (the swarm sets it).
    pub silence_reconnect: Duration,
    /// Bots that share one UDP socket and one task (at least 1). The server tells their
    /// sessions apart by id; the group's task reads every datagram queued on the socket
    /// at one wake-up and hands each to its bot, which costs a machine far less than a
    /// task and a socket a bot when the swarm shares it with the server.
    pub bots_per_socket: usize,
    /// The bots' first logins are spread evenly over this long (zero: all at once,
    /// through the semaphore), as players arrive over time rather than in one burst.
    pub login_spread: Duration,
    /// Edge of the server's area-of-interest cube (world units; the server's default is
    /// 100): the objects a bot holds within it around its own object are the ones whose
    /// staleness it measures ([`SwarmSnapshot::staleness_near_ms`]).
    pub aoi_size: f32,
}

impl SwarmConfig {
    /// `count` random-walking bots at 30 Hz.
    pub fn new(client: ClientConfig, count: usize) -> Self {
        Self {
            client,
            count,
            first: 0,
            rate_hz: 30.0,
            behaviour: Behaviour::Random,
            login_concurrency: 32,
            login_attempts: 200,
            silence_reconnect: Duration::from_secs(5),
            bots_per_socket: 1,
            login_spread: Duration::ZERO,
            aoi_size: 100.0,
        }
    }
}

/// One bot's live numbers.
#[derive(Debug, Clone, Default)]
struct BotState {
    stats: ClientStats,
    connected: bool,
    in_view: usize,
    moves_ok: u64,
    moves_wrong: u64,
    /// Server ticks whose update never came (a newer tick's came first).
    ticks_missed: u64,
    own_seen: bool,
    error: Option<String>,
    /// Sessions the server ended with Kicked (an operator).
    kicked: u64,
    /// Sessions the server ended with Banned (an operator banned the account).
    banned: u64,
}

#[derive(Debug)]
struct Shared {
    logins_ok: AtomicU64,
    logins_failed: AtomicU64,
    login_attempts: AtomicU64,
    bots: Vec<Mutex<BotState>>,
    /// Datagrams on a shared socket for no live session of its group (one that ended,
    /// or garbage), counted with the rejected ones.
    stray_datagrams: AtomicU64,
    /// Every bot's intervals between consecutive ticks' updates, in µs: one histogram
    /// for the swarm, which each bot adds its recent intervals to when it publishes (a
    /// histogram a bot was 20 KiB, 50 MiB for 2,500 bots, touched on every datagram).
    intervals: Mutex<Histogram<u64>>,
    /// Every session's time from its login's answer to its first state update, in µs
    /// (the handshake's cost: a lost Ready shows here).
    first_updates: Mutex<Histogram<u64>>,
    /// Every bot's staleness samples (`group.rs`: `held_staleness`), added when it
    /// publishes.
    quality: Mutex<Quality>,
}

/// An empty histogram of intervals: 1 µs to 1 min, 2 significant digits.
fn interval_histogram() -> Histogram<u64> {
    Histogram::new_with_bounds(1, 60_000_000, 2).expect("valid histogram bounds")
}

/// The swarm's totals at one moment.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SwarmSnapshot {
    /// When it was taken, seconds since the swarm started.
    pub elapsed_s: f64,
    /// Bots configured.
    pub bots: usize,
    /// Successful logins (reconnects included).
    pub logins_ok: u64,
    /// Bots that gave up logging in.
    pub logins_failed: u64,
    /// Bots with a live session.
    pub connected: usize,
    /// Sum of every bot's counters.
    pub totals: ClientStats,
    /// Mean objects in view per connected bot.
    pub mean_in_view: f64,
    /// Bots that have seen their own object in an update.
    pub own_object_seen: usize,
    /// Holds whose movement matched the command.
    pub moves_ok: u64,
    /// Holds whose movement did not (blocked by an obstacle, or a bug).
    pub moves_wrong: u64,
    /// Median interval between consecutive ticks' updates, ms.
    pub interval_p50_ms: f64,
    /// 99th percentile of that interval, ms.
    pub interval_p99_ms: f64,
    /// The longest such interval, ms.
    pub interval_max_ms: f64,
    /// Sessions that got their first state update.
    pub first_updates: u64,
    /// 99th percentile of the time from a login's answer to the session's first state
    /// update, ms.
    pub first_update_p99_ms: f64,
    /// The longest such time, ms.
    pub first_update_max_ms: f64,
    /// Age of the newest state a bot holds of each object within [`crate::quality::NEAR`]
    /// of it, against the newest update it got (what a bot can know without the
    /// server's truth; `myriad bench` measures against the truth), ms, sampled every
    /// second over the run. Objects not heard of for the stale time (1 s) are left out.
    pub staleness_near_ms: Percentiles,
    /// The same over every object held within the AOI cube ([`SwarmConfig::aoi_size`])
    /// around the bot (one that just left it counts until it is stale).
    pub staleness_all_ms: Percentiles,
    /// Server ticks whose update a bot never got (a newer tick's came first), over all
    /// bots: a gap in the updates longer than one tick.
    pub ticks_missed: u64,
    /// Share of server datagrams lost.
    pub loss: f64,
    /// One failure message, if any bot failed.
    pub first_error: Option<String>,
    /// Sessions an operator ended with a kick (the bot logs in again).
    pub kicked: u64,
    /// Sessions an operator ended with a ban (the bot's logins are then refused).
    pub banned: u64,
}

/// A running swarm.
pub struct Swarm {
    shared: Arc<Shared>,
    stop: watch::Sender<bool>,
    tasks: JoinSet<()>,
    started: Instant,
}

impl std::fmt::Debug for Swarm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Swarm").field("bots", &self.shared.bots.len()).finish()
    }
}

impl Swarm {
    /// Starts every bot on the current tokio runtime.
    pub fn start(mut config: SwarmConfig) -> Swarm {
        config.client.silence_timeout = config.silence_reconnect;
        let shared = Arc::new(Shared {
            logins_ok: AtomicU64::new(0),
            logins_failed: AtomicU64::new(0),
            login_attempts: AtomicU64::new(0),
            bots: (0..config.count).map(|_| Mutex::new(BotState::default())).collect(),
            stray_datagrams: AtomicU64::new(0),
            intervals: Mutex::new(interval_histogram()),
            first_updates: Mutex::new(interval_histogram()),
            quality: Mutex::new(Quality::new()),
        });
        let (stop, stop_rx) = watch::channel(false);
        let logins = Arc::new(Semaphore::new(config.login_concurrency.max(1)));
        let per_socket = config.bots_per_socket.max(1);
        let bots = config.count;
        let ctx = Arc::new(Ctx { config: Arc::new(config), shared: shared.clone(), logins });
        let mut tasks = JoinSet::new();
        for first in (0..bots).step_by(per_socket) {
            let members = (first..(first + per_socket).min(bots)).collect();
            tasks.spawn(group::Group { ctx: ctx.clone(), members }.run(stop_rx.clone()));
        }
        Swarm { shared, stop, tasks, started: Instant::now() }
    }

    /// Logins attempted so far (for a progress bar).
    pub fn login_attempts(&self) -> u64 {
        self.shared.login_attempts.load(Ordering::Relaxed)
    }

    /// Totals now.
    pub fn snapshot(&self) -> SwarmSnapshot {
        let mut s = SwarmSnapshot {
            elapsed_s: self.started.elapsed().as_secs_f64(),
            bots: self.shared.bots.len(),
            logins_ok: self.shared.logins_ok.load(Ordering::Relaxed),
            logins_failed: self.shared.logins_failed.load(Ordering::Relaxed),
            ..SwarmSnapshot::default()
        };
        let mut in_view = 0usize;
        for bot in &self.shared.bots {
            let b = bot.lock().unwrap_or_else(|p| p.into_inner());
            let t = &mut s.totals;
            let c = &b.stats;
            t.datagrams += c.datagrams;
            t.bytes += c.bytes;
            t.updates += c.updates;
            t.records += c.records;
            t.rejected += c.rejected;
            t.decode_errors += c.decode_errors;
            t.unresolved += c.unresolved;
            t.last_tick = t.last_tick.max(c.last_tick);
            t.lost += c.lost;
            t.sent += c.sent;
            t.reconnects += c.reconnects;
            t.resent += c.resent;
            if b.connected {
                s.connected += 1;
                in_view += b.in_view;
            }
            s.own_object_seen += usize::from(b.own_seen);
            s.moves_ok += b.moves_ok;
            s.moves_wrong += b.moves_wrong;
            s.ticks_missed += b.ticks_missed;
            s.kicked += b.kicked;
            s.banned += b.banned;
            if s.first_error.is_none() {
                s.first_error.clone_from(&b.error);
            }
        }
        s.mean_in_view = if s.connected > 0 { in_view as f64 / s.connected as f64 } else { 0.0 };
        let hist = self.shared.intervals.lock().unwrap_or_else(|p| p.into_inner());
        if !hist.is_empty() {
            s.interval_p50_ms = hist.value_at_quantile(0.5) as f64 / 1000.0;
            s.interval_p99_ms = hist.value_at_quantile(0.99) as f64 / 1000.0;
            s.interval_max_ms = hist.max() as f64 / 1000.0;
        }
        drop(hist);
        let hist = self.shared.first_updates.lock().unwrap_or_else(|p| p.into_inner());
        if !hist.is_empty() {
            s.first_updates = hist.len();
            s.first_update_p99_ms = hist.value_at_quantile(0.99) as f64 / 1000.0;
            s.first_update_max_ms = hist.max() as f64 / 1000.0;
        }
        drop(hist);
        let quality = self.shared.quality.lock().unwrap_or_else(|p| p.into_inner()).summary();
        s.staleness_near_ms = quality.staleness_near_ms;
        s.staleness_all_ms = quality.staleness_all_ms;
        s.totals.rejected += self.shared.stray_datagrams.load(Ordering::Relaxed);
        s.loss = s.totals.loss();
        s
    }

    /// Stops every bot (each sends Disconnect) and returns the final totals.
    pub async fn stop(mut self) -> SwarmSnapshot {
        let _ = self.stop.send(true);
        while self.tasks.join_next().await.is_some() {}
        self.snapshot()
    }
}

/// What every group of the swarm shares: the settings, the bots' states, the logins'
/// semaphore.
struct Ctx {
    config: Arc<SwarmConfig>,
    shared: Arc<Shared>,
    logins: Arc<Semaphore>,
}

/// The unit direction (x, z) a mask commands.
fn direction(mask: u8) -> (f32, f32) {
    let mut d = (0.0, 0.0);
    if mask & ActionMask::FORWARD != 0 {
        d.1 += 1.0;
    }
    if mask & ActionMask::BACK != 0 {
        d.1 -= 1.0;
    }
    if mask & ActionMask::RIGHT != 0 {
        d.0 += 1.0;
    }
    if mask & ActionMask::LEFT != 0 {
        d.0 -= 1.0;
    }
    d
}

impl Ctx {
    fn state(&self, index: usize) -> std::sync::MutexGuard<'_, BotState> {
        self.shared.bots[index].lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Judges one finished hold: did the own object move the commanded way?
    fn check_move(
        &self,
        index: usize,
        mask: u8,
        from: Option<[f32; 3]>,
        to: Option<[f32; 3]>,
        hold_index: u64,
        dilation: u16,
    ) {
        // The first hold starts before the first update arrives: nothing to compare.
        let (Some(a), Some(b)) = (from, to) else { return };
        if hold_index == 0 {
            return;
        }
        let (dx, dz) = (b[0] - a[0], b[2] - a[2]);
        let (ux, uz) = direction(mask);
        let ok = if ux == 0.0 && uz == 0.0 {
            // Standing still: only pushes by others may move it a little.
            (dx * dx + dz * dz).sqrt() < 1.0
        } else {
            // A dilated world moves slower in real time: scale the expected distance.
            dx * ux + dz * uz > 0.25 * f32::from(dilation) / 1000.0
        };
        let mut s = self.state(index);
        if ok {
            s.moves_ok += 1;
        } else {
            s.moves_wrong += 1;
        }
    }
}

/// Tells whether a bot result should count as a movement failure.
pub fn movement_ok_share(s: &SwarmSnapshot) -> f64 {
    let n = s.moves_ok + s.moves_wrong;
    if n == 0 { 0.0 } else { s.moves_ok as f64 / n as f64 }
}
