//! Admission to the password-hashing pool ([`HashGate`]); see the [module docs](super).

use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

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

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;
    use std::time::Instant;

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
