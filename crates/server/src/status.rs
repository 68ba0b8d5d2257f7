//! What the tick loop shares with the rest of the process: stop flags, counters and a
//! once-per-second status summary (the demo's live line, the stage log).

use std::sync::Mutex;

use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, AtomicUsize};
use std::time::{Duration, Instant};

use crate::stages::{StageTimes, TickWork};

/// State shared between the tick thread, the login service and the handle.
#[derive(Debug, Default)]
pub struct ServerShared {
    /// Set to stop the tick loop.
    pub stop: AtomicBool,
    /// Set with `stop` to stop without the final persistence (simulated crash).
    pub crash: AtomicBool,
    /// Current tick.
    pub tick: AtomicU64,
    /// Players logged in.
    pub players: AtomicUsize,
    /// Current time dilation in thousandths.
    pub dilation_permille: AtomicU32,
    /// Extra busy time per tick in microseconds (load tests).
    pub artificial_load_us: AtomicU32,
    /// The last one-second summary.
    pub status: Mutex<ServerStatus>,
    /// What the abuse defences did.
    pub defence: DefenceCounters,
}

/// Counters of the abuse defences since start (also in the metrics; kept here so tests
/// and tools in the same process can read them without a metrics endpoint).
#[derive(Debug, Default)]
pub struct DefenceCounters {
    /// Datagrams that reached their session's opener (window, then tag check): at most
    /// this many tag checks were paid.
    pub tag_checks: AtomicU64,
    /// Datagrams dropped over a session's receive budget, before any cryptography.
    pub over_budget: AtomicU64,
    /// Logins refused because the hashing queue was full or its deadline passed.
    pub logins_busy: AtomicU64,
    /// Logins refused by the failed-login limits (without checking the password).
    pub logins_rate_limited: AtomicU64,
    /// Logins for unknown users refused without hashing.
    pub unknown_users_refused: AtomicU64,
    /// Login connections closed at once (per-address or global cap).
    pub connections_refused: AtomicU64,
    /// Login connections closed at the handshake-and-request deadline.
    pub handshake_timeouts: AtomicU64,
    /// Malformed login requests.
    pub bad_requests: AtomicU64,
}

/// A snapshot of [`DefenceCounters`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DefenceStats {
    /// See [`DefenceCounters::tag_checks`].
    pub tag_checks: u64,
    /// See [`DefenceCounters::over_budget`].
    pub over_budget: u64,
    /// See [`DefenceCounters::logins_busy`].
    pub logins_busy: u64,
    /// See [`DefenceCounters::logins_rate_limited`].
    pub logins_rate_limited: u64,
    /// See [`DefenceCounters::unknown_users_refused`].
    pub unknown_users_refused: u64,
    /// See [`DefenceCounters::connections_refused`].
    pub connections_refused: u64,
    /// See [`DefenceCounters::handshake_timeouts`].
    pub handshake_timeouts: u64,
    /// See [`DefenceCounters::bad_requests`].
    pub bad_requests: u64,
}

impl DefenceCounters {
    /// The counters now.
    pub fn snapshot(&self) -> DefenceStats {
        let r = |c: &AtomicU64| c.load(std::sync::atomic::Ordering::Relaxed);
        DefenceStats {
            tag_checks: r(&self.tag_checks),
            over_budget: r(&self.over_budget),
            logins_busy: r(&self.logins_busy),
            logins_rate_limited: r(&self.logins_rate_limited),
            unknown_users_refused: r(&self.unknown_users_refused),
            connections_refused: r(&self.connections_refused),
            handshake_timeouts: r(&self.handshake_timeouts),
            bad_requests: r(&self.bad_requests),
        }
    }
}

/// Adds one to a defence counter.
pub(crate) fn bump(counter: &AtomicU64) {
    counter.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
}

/// One second of the server, averaged.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ServerStatus {
    /// Tick at the end of the window.
    pub tick: u64,
    /// Players logged in.
    pub players: usize,
    /// Dynamic objects in the world.
    pub objects: usize,
    /// Ticks run in the window, per second.
    pub ticks_per_s: f64,
    /// Mean milliseconds per stage.
    pub stages: StageTimes,
    /// Mean work time of a tick in milliseconds.
    pub tick_ms: f64,
    /// Slowest tick of the window in milliseconds.
    pub max_tick_ms: f64,
    /// Time dilation in thousandths.
    pub dilation_permille: u16,
    /// Bytes sent per second.
    pub bytes_per_s: f64,
    /// Datagrams sent per second.
    pub datagrams_per_s: f64,
    /// State records sent per second.
    pub records_per_s: f64,
}

impl ServerStatus {
    /// One log line with every stage's mean time.
    pub fn stage_line(&self) -> String {
        let stages: Vec<String> = self.stages.iter().map(|(stage, v)| format!("{}={v:.2}", stage.name())).collect();
        format!(
            "tick {} | {:.1} ticks/s | tick {:.2} ms (max {:.2}) | {} | players {} objects {} | {:.0} kB/s | dilation {}",
            self.tick,
            self.ticks_per_s,
            self.tick_ms,
            self.max_tick_ms,
            stages.join(" "),
            self.players,
            self.objects,
            self.bytes_per_s / 1000.0,
            self.dilation_permille
        )
    }
}

/// Accumulates ticks until a summary is taken.
#[derive(Debug)]
pub(crate) struct StatusWindow {
    start: Instant,
    ticks: u64,
    stages: StageTimes,
    tick_ms: f64,
    max_tick_ms: f64,
    bytes: u64,
    datagrams: u64,
    records: u64,
}

impl Default for StatusWindow {
    fn default() -> Self {
        Self {
            start: Instant::now(),
            ticks: 0,
            stages: StageTimes::default(),
            tick_ms: 0.0,
            max_tick_ms: 0.0,
            bytes: 0,
            datagrams: 0,
            records: 0,
        }
    }
}

impl StatusWindow {
    pub(crate) fn add(&mut self, work: &TickWork, tick_ms: f64) {
        self.ticks += 1;
        self.stages += &work.stages;
        self.tick_ms += tick_ms;
        self.max_tick_ms = self.max_tick_ms.max(tick_ms);
        self.bytes += work.bytes;
        self.datagrams += work.datagrams;
        self.records += work.records as u64;
    }

    pub(crate) fn elapsed(&self) -> Duration {
        self.start.elapsed()
    }

    /// The summary of the window; starts a new one.
    pub(crate) fn finish(&mut self, tick: u64, players: usize, objects: usize, dilation_permille: u16) -> ServerStatus {
        let secs = self.start.elapsed().as_secs_f64().max(1e-9);
        let n = self.ticks.max(1) as f64;
        let status = ServerStatus {
            tick,
            players,
            objects,
            ticks_per_s: self.ticks as f64 / secs,
            stages: self.stages.divided_by(n),
            tick_ms: self.tick_ms / n,
            max_tick_ms: self.max_tick_ms,
            dilation_permille,
            bytes_per_s: self.bytes as f64 / secs,
            datagrams_per_s: self.datagrams as f64 / secs,
            records_per_s: self.records as f64 / secs,
        };
        *self = StatusWindow::default();
        status
    }
}
