//! What the tick loop shares with the rest of the process: stop flags, counters and a
//! once-per-second status summary (the demo's live line, the stage log).

use std::sync::Mutex;

use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, AtomicUsize};
use std::time::{Duration, Instant};

use crate::stages::StageTimes;
use crate::tick::TickWork;

/// State shared between the tick thread, the login service and the handle.
#[derive(Debug, Default)]
pub struct Shared {
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
