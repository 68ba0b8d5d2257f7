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
    /// Longest time a submitted snapshot waits before the writer picks it up when nobody
    /// calls [`Persister::checkpoint`]. A caller that checkpoints on its own clock (the
    /// server's tick does) gets its states written right after each checkpoint, so its
    /// loss bound is its own interval plus one write, whatever this is.
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
    /// Snapshots refused by `submit_many` because the state was invalid (non-finite
    /// position, bad shape).
    pub dropped_invalid: u64,
    /// Snapshots still queued when [`Persister::shutdown`] gave up (lost).
    pub lost_at_shutdown: u64,
    /// Whether the last write attempt succeeded (true before the first attempt).
    pub healthy: bool,
    /// States waiting to be written right now, in flight included.
    pub queued: u64,
}

impl PersisterStats {
    /// Every snapshot dropped so far, whatever the reason: refused by the database for
    /// good, queue full, invalid, or still queued when shutdown gave up.
    pub fn dropped_total(&self) -> u64 {
        self.rejected_rows + self.dropped_overflow + self.dropped_invalid + self.lost_at_shutdown
    }
}

/// Report of a successful [`Persister::flush`] (or of a [`Persister::shutdown`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct FlushReport {
    /// Rows written by this flush.
    pub rows_written: u64,
}

/// Why a [`Persister::shutdown`] left positions unwritten.
#[derive(Debug, thiserror::Error)]
#[error("{lost} player positions were not saved before the {deadline:?} deadline: {cause}")]
pub struct ShutdownLoss {
    /// Rows written before giving up.
    pub rows_written: u64,
    /// Snapshots still queued (lost).
    pub lost: u64,
    /// The deadline that ran out.
    pub deadline: Duration,
    /// The last error (or the deadline itself when the attempt was cut short).
    pub cause: StoreError,
}

/// How the database looks to the writer; logged once per change.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Health {
    Up,
    /// The database answered with an error (connection refused, read-only file, ...).
    Refused,
    /// The database did not answer in time (pool timeout, a write cut by a deadline).
    Stalled,
}

impl Health {
    fn of(error: &StoreError) -> Health {
        match error {
            StoreError::Unavailable(sqlx::Error::PoolTimedOut) => Health::Stalled,
            StoreError::Unavailable(sqlx::Error::Io(e)) if e.kind() == std::io::ErrorKind::TimedOut => Health::Stalled,
            StoreError::Internal(m) if m.contains("timed out") => Health::Stalled,
            _ => Health::Refused,
        }
    }
    fn word(self) -> &'static str {
        match self {
            Health::Up => "up",
            Health::Refused => "refused",
            Health::Stalled => "stalled",
        }
    }
}

#[derive(Default)]
struct Pending {
    /// Ordered by (user, map) so that each batch covers a contiguous key range: the
    /// database then updates neighbouring index pages instead of scattered ones.
    entries: BTreeMap<(i64, i64), PlayerState>,
    in_flight: usize,
    closed: bool,
    /// The writer's view of the database, and since when it has been down.
    health: Option<(Health, std::time::Instant)>,
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
    dropped_invalid: AtomicU64,
    lost_at_shutdown: AtomicU64,
}

struct Shared {
    config: PersisterConfig,
    pending: Mutex<Pending>,
    counters: Counters,
    /// Wakes the writer right after a [`Persister::checkpoint`].
    wake: tokio::sync::Notify,
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
    Shutdown(Instant, oneshot::Sender<(u64, Result<()>)>),
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
        let shared = Arc::new(Shared {
            config,
            pending: Mutex::new(Pending::default()),
            counters: Counters::default(),
            wake: tokio::sync::Notify::new(),
        });
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
                Shared::bump(&self.shared.counters.dropped_invalid, 1);
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

    /// Queues `states` (as [`Persister::submit_many`]) and has the writer write them now.
    ///
    /// This is how the loss bound holds by construction: the caller's clock alone decides
    /// when states are taken, and each checkpoint is committed right away (one write
    /// later), so a crash loses at most the caller's interval plus one write. With a
    /// separate writer timer the two clocks drift apart and the bound doubles.
    pub fn checkpoint<'a>(&self, states: impl IntoIterator<Item = &'a PlayerState>) -> Result<usize, SubmitError> {
        let accepted = self.submit_many(states)?;
        self.shared.wake.notify_one();
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
    /// until it succeeds or `timeout` elapses, and stops the task. The deadline is hard:
    /// a write still waiting on the database when it passes is abandoned. When states are
    /// left unwritten the answer says how many ([`ShutdownLoss`]), and they are counted
    /// in [`PersisterStats::lost_at_shutdown`].
    pub async fn shutdown(&self, timeout: Duration) -> Result<FlushReport, ShutdownLoss> {
        // The deadline runs from this call, even if the writer is still inside a write
        // that waits on a stalled database when the command is sent.
        let deadline = after(timeout);
        self.shared.lock().closed = true;
        let loss = |cause| {
            let lost = self.stats().queued;
            Shared::bump(&self.shared.counters.lost_at_shutdown, lost);
            ShutdownLoss { rows_written: 0, lost, deadline: timeout, cause }
        };
        let (reply, answer) = oneshot::channel();
        let asked = async {
            self.commands.send(Command::Shutdown(deadline, reply)).await.map_err(|_| "persister already shut down")?;
            answer.await.map_err(|_| "persister task is gone")
        };
        let (written, result) = match tokio::time::timeout_at(deadline, asked).await {
            Ok(Ok(r)) => r,
            Ok(Err(why)) => return Err(loss(StoreError::Internal(why.into()))),
            Err(_) => {
                return Err(loss(StoreError::Internal(
                    "the writer was still waiting on the database at the deadline (timed out)".into(),
                )));
            }
        };
        match result {
            Ok(()) => Ok(FlushReport { rows_written: written }),
            Err(cause) => {
                let lost = self.stats().queued;
                Shared::bump(&self.shared.counters.lost_at_shutdown, lost);
                Err(ShutdownLoss { rows_written: written, lost, deadline: timeout, cause })
            }
        }
    }

    /// Current counters.
    pub fn stats(&self) -> PersisterStats {
        let (queued, healthy) = {
            let p = self.shared.lock();
            ((p.entries.len() + p.in_flight) as u64, p.health)
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
            dropped_invalid: get(&c.dropped_invalid),
            lost_at_shutdown: get(&c.lost_at_shutdown),
            healthy: healthy.is_none_or(|(h, _)| h == Health::Up),
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
        // While a retry is scheduled, checkpoints do not trigger extra attempts: the
        // backoff decides, so a dead database is not hammered twice a second.
        let mut backing_off = false;
        loop {
            let scheduled = tokio::select! {
                _ = self.shared.wake.notified(), if !backing_off => true,
                _ = tokio::time::sleep_until(next_write) => true,
                command = commands.recv() => match command {
                    Some(Command::Flush(reply)) => {
                        let result = self.write_all().await;
                        self.note(result.as_ref().err());
                        if result.is_ok() {
                            retry_delay = config.retry_min;
                            backing_off = false;
                        }
                        // The caller may have given up waiting; nothing to do then.
                        let _ = reply.send(result);
                        false
                    }
                    Some(Command::Shutdown(deadline, reply)) => {
                        self.shared.lock().closed = true;
                        let _ = reply.send(self.drain_until(deadline).await);
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
            };
            if !scheduled {
                continue;
            }
            let result = self.write_all().await;
            self.note(result.as_ref().err());
            match result {
                Ok(_) => {
                    retry_delay = config.retry_min;
                    next_write = after(config.interval);
                    backing_off = false;
                }
                Err(e) => {
                    tracing::debug!(error = %e, retry_in = ?retry_delay, "saving player states failed");
                    next_write = after(retry_delay);
                    retry_delay = retry_delay.saturating_mul(2).min(config.retry_max);
                    backing_off = true;
                }
            }
        }
    }

    /// Records the outcome of a write attempt and logs once per change of the database's
    /// state: down (naming refused or stalled, with the cause), back up (with how long it
    /// was down), or a change of the failure's kind.
    fn note(&self, error: Option<&StoreError>) {
        let now = match error {
            None => Health::Up,
            Some(e) => Health::of(e),
        };
        let (before, queued) = {
            let mut p = self.shared.lock();
            let before = p.health;
            let since = match before {
                Some((h, since)) if h != Health::Up && now != Health::Up => since,
                _ => std::time::Instant::now(),
            };
            p.health = Some((now, since));
            (before, p.entries.len() + p.in_flight)
        };
        let was = before.map_or(Health::Up, |(h, _)| h);
        if was == now {
            return;
        }
        let dropped = {
            let c = &self.shared.counters;
            c.rejected_rows.load(Ordering::Relaxed) + c.dropped_overflow.load(Ordering::Relaxed)
        };
        match (was, error) {
            (Health::Up, Some(e)) => tracing::error!(
                state = now.word(),
                error = %e,
                queued,
                "database writes failing ({}): player positions are kept in memory (newest per player) and retried",
                now.word()
            ),
            (_, Some(e)) => tracing::error!(
                state = now.word(),
                error = %e,
                queued,
                "database writes still failing, now {}",
                now.word()
            ),
            (_, None) => tracing::info!(
                down_for = ?before.map(|(_, since)| since.elapsed()).unwrap_or_default(),
                dropped_so_far = dropped,
                "database writes back up"
            ),
        }
    }

    /// Retries `write_all` with backoff until it succeeds or the deadline passes; the
    /// deadline also cuts short an attempt still waiting on the database. Answers the rows
    /// written meanwhile and the outcome.
    async fn drain_until(&self, deadline: Instant) -> (u64, Result<()>) {
        let rows_before = self.shared.counters.rows_written.load(Ordering::Relaxed);
        let written = || self.shared.counters.rows_written.load(Ordering::Relaxed) - rows_before;
        let mut delay = self.shared.config.retry_min;
        loop {
            match tokio::time::timeout_at(deadline, self.write_all()).await {
                Ok(Ok(_)) => {
                    self.note(None);
                    return (written(), Ok(()));
                }
                Ok(Err(e)) => {
                    self.note(Some(&e));
                    if after(delay) >= deadline {
                        return (written(), Err(e));
                    }
                    tokio::time::sleep(delay).await;
                    delay = delay.saturating_mul(2).min(self.shared.config.retry_max);
                }
                Err(_) => {
                    let e = StoreError::Internal("the last write was still waiting on the database (timed out)".into());
                    self.note(Some(&e));
                    return (written(), Err(e));
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
                tracing::debug!(error = %e, rows = states.len(), "batch refused; saving row by row");
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
        let mut refused = 0u64;
        let mut first_refusal = None;
        let report = |refused: u64, first: Option<(StoreError, i64)>| {
            if let Some((e, user)) = first {
                // One line per batch, not one per row: the count and the first cause.
                tracing::warn!(error = %e, first_user = user, refused, "player states refused by the database; dropped");
            }
        };
        for (handled, state) in states.iter().enumerate() {
            match self.store.save_player_states(std::slice::from_ref(state)).await {
                Ok(n) => {
                    written += n;
                    Shared::bump(&counters.batches_written, 1);
                }
                Err(e) if e.is_transient() => {
                    report(refused, first_refusal);
                    return Outcome { written, handled, error: Some(e) };
                }
                Err(e) => {
                    Shared::bump(&counters.rejected_rows, 1);
                    refused += 1;
                    first_refusal.get_or_insert((e, state.user_id.0));
                }
            }
        }
        report(refused, first_refusal);
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
