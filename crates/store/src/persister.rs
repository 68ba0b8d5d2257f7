//! Write-behind persistence of player positions; see [`Persister`] for how it works.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use tokio::sync::{mpsc, oneshot};
use tokio::time::Instant;

use crate::error::{Result, StoreError};
use crate::model::PlayerState;
use crate::store::Store;

/// Settings of a [`Persister`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PersisterConfig {
    /// Time between periodic writes. At most this much progress is lost on a crash.
    pub interval: Duration,
    /// Most rows per transaction.
    pub batch_size: usize,
    /// Most distinct (user, map) states held in memory, queued or in flight.
    pub max_pending: usize,
    /// First retry delay after a failed write.
    pub retry_min: Duration,
    /// Longest retry delay (the backoff doubles up to this).
    pub retry_max: Duration,
}

impl Default for PersisterConfig {
    fn default() -> Self {
        PersisterConfig {
            interval: Duration::from_millis(500),
            batch_size: 1000,
            max_pending: 100_000,
            retry_min: Duration::from_millis(100),
            retry_max: Duration::from_secs(10),
        }
    }
}

/// Why [`Persister::submit`] did not queue a snapshot.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SubmitError {
    /// The queue already holds [`PersisterConfig::max_pending`] players and this one is
    /// not among them (counted in [`PersisterStats::dropped_overflow`]).
    #[error("persistence queue full")]
    Full,
    /// The state has a non-finite position or invalid shape.
    #[error("invalid player state: {0}")]
    Invalid(String),
    /// The persister was shut down.
    #[error("persister shut down")]
    Closed,
}

/// A snapshot of the persister's counters, for metrics.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct PersisterStats {
    /// Snapshots accepted by `submit`.
    pub submitted: u64,
    /// Accepted snapshots that replaced a queued one of the same player (never written).
    pub coalesced: u64,
    /// Rows written to the database.
    pub rows_written: u64,
    /// Transactions committed.
    pub batches_written: u64,
    /// Failed write attempts (each is retried).
    pub failures: u64,
    /// Rows the database refused for good (not for unavailability) and that were dropped.
    pub rejected_rows: u64,
    /// Snapshots dropped because the queue was full.
    pub dropped_overflow: u64,
    /// States waiting to be written right now, in flight included.
    pub queued: u64,
}

/// Report of a successful [`Persister::flush`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct FlushReport {
    /// Rows written by this flush.
    pub rows_written: u64,
}

#[derive(Default)]
struct Pending {
    /// Ordered by (user, map) so that each batch covers a contiguous key range: the
    /// database then updates neighbouring index pages instead of scattered ones.
    entries: BTreeMap<(i64, i64), PlayerState>,
    in_flight: usize,
    closed: bool,
}

#[derive(Default)]
struct Counters {
    submitted: AtomicU64,
    coalesced: AtomicU64,
    rows_written: AtomicU64,
    batches_written: AtomicU64,
    failures: AtomicU64,
    rejected_rows: AtomicU64,
    dropped_overflow: AtomicU64,
}

struct Shared {
    config: PersisterConfig,
    pending: Mutex<Pending>,
    counters: Counters,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, Pending> {
        // A panic while holding this lock cannot leave the map inconsistent (every
        // critical section is a handful of map operations), so poisoning is ignored.
        self.pending.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn bump(counter: &AtomicU64, n: u64) {
        counter.fetch_add(n, Ordering::Relaxed);
    }
}

enum Command {
    Flush(oneshot::Sender<Result<FlushReport>>),
    Shutdown(Duration, oneshot::Sender<Result<FlushReport>>),
}

/// Write-behind queue of player states: the tick thread submits, a task writes.
///
/// # How it works
/// The server's tick thread calls [`Persister::submit`] (or [`Persister::submit_many`])
/// with position snapshots. The call only takes a mutex around an in-memory map keyed by
/// (user, map) and replaces that player's entry, so it never waits on the database and
/// coalesces for free: only the newest state of each player is ever written.
/// The writer task holds that mutex only to move at most `batch_size` entries out (tens
/// of microseconds), never across a database call.
///
/// A tokio task drains the map every [`PersisterConfig::interval`] (and on
/// [`Persister::flush`]) in batches of [`PersisterConfig::batch_size`] rows, each batch
/// one transaction through [`Store::save_player_states`]. Entries are moved out of the
/// map while their batch is in flight; if the write fails they are put back unless a
/// newer snapshot of the same player arrived meanwhile.
///
/// When the database is unreachable ([`StoreError::Unavailable`]) the world keeps
/// running: snapshots keep coalescing in memory, the failure is counted, and the task
/// retries with exponential backoff ([`PersisterConfig::retry_min`] doubling up to
/// [`PersisterConfig::retry_max`]) until a write succeeds. Memory stays bounded by
/// [`PersisterConfig::max_pending`] distinct players: beyond it, snapshots of players not
/// already queued are dropped and counted in [`PersisterStats::dropped_overflow`]
/// (queued players keep being updated to their newest state).
///
/// A batch rejected for another reason (say, a player whose user row was deleted) is
/// retried row by row, and rows the database refuses are dropped and counted in
/// [`PersisterStats::rejected_rows`], so one bad row cannot block everybody's saves.
///
/// Cloning gives another handle to the same queue and task. When every handle is
/// dropped the task makes one last attempt to write what is queued and exits; call
/// [`Persister::shutdown`] to wait for the final write.
#[derive(Clone)]
pub struct Persister {
    shared: Arc<Shared>,
    commands: mpsc::Sender<Command>,
}

impl std::fmt::Debug for Persister {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Persister").field("config", &self.shared.config).field("stats", &self.stats()).finish()
    }
}

impl Persister {
    /// Starts the writer task on the current tokio runtime. Fails with
    /// [`StoreError::Internal`] outside a runtime and [`StoreError::InvalidInput`] for a
    /// zero batch size or queue bound.
    pub fn start(store: Store, config: PersisterConfig) -> Result<Persister> {
        if config.batch_size == 0 || config.max_pending == 0 {
            return Err(StoreError::InvalidInput("persister batch_size and max_pending must be > 0".into()));
        }
        let runtime = tokio::runtime::Handle::try_current()
            .map_err(|_| StoreError::Internal("Persister::start needs a tokio runtime".into()))?;
        let shared =
            Arc::new(Shared { config, pending: Mutex::new(Pending::default()), counters: Counters::default() });
        let (commands, receiver) = mpsc::channel(16);
        let writer = Writer { store, shared: shared.clone() };
        runtime.spawn(writer.run(receiver));
        Ok(Persister { shared, commands })
    }

    /// Queues a snapshot, replacing any queued one of the same player on the same map.
    /// Never blocks on the database; safe to call from a non-async thread.
    pub fn submit(&self, state: PlayerState) -> Result<(), SubmitError> {
        state.validate().map_err(|e| SubmitError::Invalid(e.to_string()))?;
        let mut pending = self.shared.lock();
        self.insert(&mut pending, state)
    }

    /// Queues many snapshots under one lock; returns how many were accepted. Invalid
    /// states and overflow are skipped (overflow is counted).
    pub fn submit_many<'a>(&self, states: impl IntoIterator<Item = &'a PlayerState>) -> Result<usize, SubmitError> {
        let mut pending = self.shared.lock();
        let mut accepted = 0;
        for state in states {
            if state.validate().is_err() {
                continue;
            }
            match self.insert(&mut pending, *state) {
                Ok(()) => accepted += 1,
                Err(SubmitError::Closed) => return Err(SubmitError::Closed),
                Err(_) => {}
            }
        }
        Ok(accepted)
    }

    fn insert(&self, pending: &mut Pending, state: PlayerState) -> Result<(), SubmitError> {
        if pending.closed {
            return Err(SubmitError::Closed);
        }
        let counters = &self.shared.counters;
        let key = (state.user_id.0, state.map_id.0);
        if let Some(entry) = pending.entries.get_mut(&key) {
            *entry = state;
            Shared::bump(&counters.coalesced, 1);
        } else if pending.entries.len() + pending.in_flight >= self.shared.config.max_pending {
            Shared::bump(&counters.dropped_overflow, 1);
            return Err(SubmitError::Full);
        } else {
            pending.entries.insert(key, state);
        }
        Shared::bump(&counters.submitted, 1);
        Ok(())
    }

    /// Writes everything queued now and waits for it (for logout and shutdown). One
    /// attempt, no backoff: while the database is down this fails with
    /// [`StoreError::Unavailable`] and the states stay queued for the background retries.
    pub async fn flush(&self) -> Result<FlushReport> {
        let (reply, answer) = oneshot::channel();
        self.commands
            .send(Command::Flush(reply))
            .await
            .map_err(|_| StoreError::Internal("persister task is gone".into()))?;
        answer.await.map_err(|_| StoreError::Internal("persister task is gone".into()))?
    }

    /// Stops accepting snapshots, then keeps trying (with backoff) to write what is queued
    /// until it succeeds or `timeout` elapses, and stops the task. Returns the error of the
    /// last attempt when states are left unwritten (see [`PersisterStats::queued`]).
    pub async fn shutdown(&self, timeout: Duration) -> Result<FlushReport> {
        let (reply, answer) = oneshot::channel();
        self.commands
            .send(Command::Shutdown(timeout, reply))
            .await
            .map_err(|_| StoreError::Internal("persister already shut down".into()))?;
        answer.await.map_err(|_| StoreError::Internal("persister task is gone".into()))?
    }

    /// Current counters.
    pub fn stats(&self) -> PersisterStats {
        let queued = {
            let p = self.shared.lock();
            (p.entries.len() + p.in_flight) as u64
        };
        let c = &self.shared.counters;
        let get = |a: &AtomicU64| a.load(Ordering::Relaxed);
        PersisterStats {
            submitted: get(&c.submitted),
            coalesced: get(&c.coalesced),
            rows_written: get(&c.rows_written),
            batches_written: get(&c.batches_written),
            failures: get(&c.failures),
            rejected_rows: get(&c.rejected_rows),
            dropped_overflow: get(&c.dropped_overflow),
            queued,
        }
    }
}

/// `now + d`, saturating at a year from now instead of overflowing on absurd settings.
fn after(d: Duration) -> Instant {
    const FAR: Duration = Duration::from_secs(365 * 24 * 3600);
    let now = Instant::now();
    now.checked_add(d.min(FAR)).unwrap_or(now)
}

/// The background task.
struct Writer {
    store: Store,
    shared: Arc<Shared>,
}

impl Writer {
    async fn run(self, mut commands: mpsc::Receiver<Command>) {
        let config = self.shared.config;
        let mut retry_delay = config.retry_min;
        let mut next_write = after(config.interval);
        loop {
            tokio::select! {
                _ = tokio::time::sleep_until(next_write) => {
                    match self.write_all().await {
                        Ok(_) => {
                            retry_delay = config.retry_min;
                            next_write = after(config.interval);
                        }
                        Err(e) => {
                            tracing::warn!(error = %e, retry_in = ?retry_delay, "saving player states failed");
                            next_write = after(retry_delay);
                            retry_delay = retry_delay.saturating_mul(2).min(config.retry_max);
                        }
                    }
                }
                command = commands.recv() => match command {
                    Some(Command::Flush(reply)) => {
                        let result = self.write_all().await;
                        if result.is_ok() {
                            retry_delay = config.retry_min;
                        }
                        // The caller may have given up waiting; nothing to do then.
                        let _ = reply.send(result);
                    }
                    Some(Command::Shutdown(timeout, reply)) => {
                        self.shared.lock().closed = true;
                        let _ = reply.send(self.drain_until(after(timeout)).await);
                        return;
                    }
                    None => {
                        // Every handle is gone: one last attempt, nobody to report to.
                        self.shared.lock().closed = true;
                        if let Err(e) = self.write_all().await {
                            tracing::error!(error = %e, "player states lost at persister drop");
                        }
                        return;
                    }
                }
            }
        }
    }

    /// Retries `write_all` with backoff until it succeeds or the deadline passes.
    async fn drain_until(&self, deadline: Instant) -> Result<FlushReport> {
        let mut delay = self.shared.config.retry_min;
        let mut total = 0;
        loop {
            match self.write_all().await {
                Ok(report) => {
                    total += report.rows_written;
                    return Ok(FlushReport { rows_written: total });
                }
                Err(e) if after(delay) >= deadline => return Err(e),
                Err(_) => {
                    tokio::time::sleep(delay).await;
                    delay = delay.saturating_mul(2).min(self.shared.config.retry_max);
                }
            }
        }
    }

    /// Writes what is queued when called, batch by batch. Stops at the first
    /// unavailability error. Snapshots submitted meanwhile wait for the next round, so a
    /// busy tick thread cannot keep this loop going forever.
    async fn write_all(&self) -> Result<FlushReport> {
        let mut budget = self.shared.lock().entries.len();
        let mut written = 0u64;
        while budget > 0 {
            let batch = self.take_batch(budget);
            if batch.is_empty() {
                break;
            }
            budget -= batch.len();
            written += self.write_batch(batch).await?;
        }
        Ok(FlushReport { rows_written: written })
    }

    /// Moves up to `min(limit, batch_size)` entries from the queue to "in flight".
    fn take_batch(&self, limit: usize) -> Vec<((i64, i64), PlayerState)> {
        let mut pending = self.shared.lock();
        let n = limit.min(self.shared.config.batch_size);
        let batch: Vec<_> = std::iter::from_fn(|| pending.entries.pop_first()).take(n).collect();
        pending.in_flight += batch.len();
        batch
    }

    /// Writes one batch; on failure puts back the entries not yet handled, unless a newer
    /// snapshot of the same player was submitted meanwhile.
    async fn write_batch(&self, batch: Vec<((i64, i64), PlayerState)>) -> Result<u64> {
        let counters = &self.shared.counters;
        let states: Vec<PlayerState> = batch.iter().map(|(_, s)| *s).collect();
        let outcome = match self.store.save_player_states(&states).await {
            Ok(n) => {
                Shared::bump(&counters.batches_written, 1);
                Outcome { written: n, handled: states.len(), error: None }
            }
            Err(e) if e.is_transient() => Outcome { written: 0, handled: 0, error: Some(e) },
            Err(e) => {
                Shared::bump(&counters.failures, 1);
                tracing::warn!(error = %e, rows = states.len(), "batch refused; saving row by row");
                self.write_rows_individually(&states).await
            }
        };
        let mut pending = self.shared.lock();
        pending.in_flight -= batch.len();
        Shared::bump(&counters.rows_written, outcome.written);
        match outcome.error {
            None => Ok(outcome.written),
            Some(e) => {
                Shared::bump(&counters.failures, 1);
                for (key, state) in batch.into_iter().skip(outcome.handled) {
                    // A newer snapshot submitted while this batch was in flight wins.
                    pending.entries.entry(key).or_insert(state);
                }
                Err(e)
            }
        }
    }

    /// Fallback for a batch the database refused: each row in its own statement, rows
    /// refused for good are dropped and counted. Stops at an unavailability error.
    async fn write_rows_individually(&self, states: &[PlayerState]) -> Outcome {
        let counters = &self.shared.counters;
        let mut written = 0;
        for (handled, state) in states.iter().enumerate() {
            match self.store.save_player_states(std::slice::from_ref(state)).await {
                Ok(n) => {
                    written += n;
                    Shared::bump(&counters.batches_written, 1);
                }
                Err(e) if e.is_transient() => return Outcome { written, handled, error: Some(e) },
                Err(e) => {
                    Shared::bump(&counters.rejected_rows, 1);
                    tracing::warn!(
                        error = %e,
                        user = state.user_id.0,
                        map = state.map_id.0,
                        "player state refused by the database; dropped"
                    );
                }
            }
        }
        Outcome { written, handled: states.len(), error: None }
    }
}

/// What became of one batch.
struct Outcome {
    /// Rows written.
    written: u64,
    /// How many leading rows of the batch were dealt with (written or dropped); the rest
    /// go back to the queue when `error` is set.
    handled: usize,
    /// The unavailability error that stopped the batch, if any.
    error: Option<StoreError>,
}
