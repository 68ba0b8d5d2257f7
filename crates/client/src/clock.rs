//! The client's estimate of the server's tick at a local instant, from the ticks of the
//! state updates and the instants they arrived.
//!
//! # Method
//!
//! Count local time in ticks at the server's wall-clock tick rate (the nominal rate the
//! login names times the announced time dilation: a dilated server ticks more slowly).
//! An update of tick `T` arriving at local instant `a` says that the server's clock at
//! `a` read at least `T`: it was built at `T` and travelled for some delay `d ≥ 0`, so
//! `T = θ(a) − d` where `θ(a)` is the server's tick at `a`. The least-delayed updates
//! bound `θ` best, so the estimate is the *upper envelope* of the observations:
//!
//! - between observations it advances at the rate, slowed by [`ServerClock::SINK`]
//!   (2 %), so that it sinks slowly towards the observations when it ran ahead of them
//!   (a path whose delay grew, a server a little slower than its announced rate);
//! - an observation above the estimate raises it at once (a datagram cannot arrive
//!   before it was sent, so a higher observation is always closer to the truth);
//! - an observation below it (a late or jittered datagram) changes nothing: the
//!   estimate never jumps backwards;
//! - an observation more than [`ServerClock::RESYNC`] below it (the server restarted or
//!   stalled) starts the estimate afresh from that observation: the only backward step.
//!
//! The estimate thus follows the server's clock less the smallest recent delay, and the
//! render time ([`crate::WorldMirror::render_tick`]) is this estimate less the render
//! delay. A rate change (new dilation) re-anchors the estimate where it stands, so it
//! stays continuous.

use std::time::{Duration, Instant};

/// The estimate of the server's tick at local instants; see the module docs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ServerClock {
    /// Server ticks per local second.
    rate: f64,
    /// The estimate at one instant: `(local instant, server tick)`; none before the first
    /// observation.
    anchor: Option<(Instant, f64)>,
}

/// Signed seconds from `from` to `to`.
fn seconds_between(from: Instant, to: Instant) -> f64 {
    match to.checked_duration_since(from) {
        Some(d) => d.as_secs_f64(),
        None => -from.duration_since(to).as_secs_f64(),
    }
}

impl ServerClock {
    /// How much slower than the rate the estimate advances between observations (it is
    /// pulled up again by every observation above it).
    pub const SINK: f64 = 0.02;
    /// An observation this far below the estimate resets it (a restarted or stalled
    /// server).
    pub const RESYNC: Duration = Duration::from_secs(1);

    /// A clock without observations for a server ticking `rate` times a second.
    pub fn new(rate: f64) -> Self {
        Self { rate: rate.max(f64::MIN_POSITIVE), anchor: None }
    }

    /// Server ticks per local second.
    pub fn rate(&self) -> f64 {
        self.rate
    }

    /// Whether an update was observed since the last reset.
    pub fn is_synced(&self) -> bool {
        self.anchor.is_some()
    }

    /// The estimated server tick at `now` (fractional); none before the first
    /// observation.
    pub fn tick_at(&self, now: Instant) -> Option<f64> {
        let (at, tick) = self.anchor?;
        Some(tick + seconds_between(at, now) * self.rate * (1.0 - Self::SINK))
    }

    /// Takes the update of server tick `tick` that arrived at `now`.
    pub fn observe(&mut self, tick: u64, now: Instant) {
        let observed = tick as f64;
        let take = match self.tick_at(now) {
            None => true,
            Some(estimate) => observed > estimate || estimate - observed > Self::RESYNC.as_secs_f64() * self.rate,
        };
        // Otherwise the estimate stands (it is linear from its anchor): a late datagram
        // moves nothing.
        if take {
            self.anchor = Some((now, observed));
        }
    }

    /// A new rate (ticks per local second, e.g. after a dilation change): the estimate
    /// continues from where it stands at `now`.
    pub fn set_rate(&mut self, rate: f64, now: Instant) {
        let rate = rate.max(f64::MIN_POSITIVE);
        if rate == self.rate {
            return;
        }
        if let Some(tick) = self.tick_at(now) {
            self.anchor = Some((now, tick));
        }
        self.rate = rate;
    }

    /// Forgets every observation (a new session: the server's ticks may start over).
    pub fn reset(&mut self) {
        self.anchor = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use myriad_core::rng::Stream;

    const RATE: f64 = 30.0;

    fn at(t0: Instant, seconds: f64) -> Instant {
        t0 + Duration::from_secs_f64(seconds)
    }

    #[test]
    fn without_jitter_the_estimate_is_the_tick_just_received() {
        let t0 = Instant::now();
        let mut c = ServerClock::new(RATE);
        assert_eq!(c.tick_at(t0), None);
        for tick in 100..200u64 {
            c.observe(tick, at(t0, (tick - 100) as f64 / RATE));
        }
        let last = at(t0, 99.0 / RATE);
        assert!((c.tick_at(last).unwrap() - 199.0).abs() < 1e-6);
        // Half a tick later, about half a tick on (the sink slows it by 2 %).
        let half = c.tick_at(at(t0, 99.5 / RATE)).unwrap();
        assert!((half - 199.49).abs() < 1e-6, "{half}");
    }

    #[test]
    fn under_jitter_it_follows_the_least_delayed_updates_and_never_goes_back() {
        // Delays of 20 to 60 ms, arrivals out of order: the estimate tracks the server's
        // tick less the smallest delay (20 ms = 0.6 ticks), within the sink's slack, and
        // each reading is at least the one before it.
        let t0 = Instant::now();
        let mut c = ServerClock::new(RATE);
        let mut rng = Stream::new(7, 1);
        let mut arrivals: Vec<(f64, u64)> =
            (0..600u64).map(|tick| (tick as f64 / RATE + 0.020 + 0.040 * f64::from(rng.unit()), tick)).collect();
        arrivals.sort_by(|a, b| a.0.total_cmp(&b.0));
        let mut previous = f64::NEG_INFINITY;
        let (mut behind_sum, mut samples) = (0.0, 0.0);
        for &(when, tick) in &arrivals {
            c.observe(tick, at(t0, when));
            let now = c.tick_at(at(t0, when)).unwrap();
            assert!(now >= previous, "went back from {previous} to {now} at tick {tick}");
            previous = now;
            if tick > 60 {
                // Never ahead of the server less the smallest delay, never further behind
                // than the newest observation.
                let behind = when * RATE - now;
                assert!((0.6 - 1e-6..=1.8 + 1e-6).contains(&behind), "{behind} ticks behind at tick {tick}");
                behind_sum += behind;
                samples += 1.0;
            }
        }
        // The delays average 1.2 ticks; the envelope sits near the smallest (0.6).
        let mean = behind_sum / samples;
        assert!(mean < 0.9, "{mean} ticks behind on average");
    }

    #[test]
    fn a_late_datagram_does_not_move_it_and_a_restart_resets_it() {
        let t0 = Instant::now();
        let mut c = ServerClock::new(RATE);
        c.observe(1000, t0);
        let t = at(t0, 0.1);
        let before = c.tick_at(t).unwrap();
        c.observe(990, t);
        assert_eq!(c.tick_at(t).unwrap(), before, "a late tick changes nothing");
        // Two seconds' worth of ticks below: the server started over.
        c.observe(5, t);
        assert_eq!(c.tick_at(t).unwrap(), 5.0);
    }

    #[test]
    fn a_rate_change_keeps_the_estimate_continuous() {
        let t0 = Instant::now();
        let mut c = ServerClock::new(RATE);
        c.observe(300, t0);
        let t = at(t0, 1.0);
        let before = c.tick_at(t).unwrap();
        c.set_rate(15.0, t);
        assert_eq!(c.tick_at(t).unwrap(), before);
        let later = c.tick_at(at(t0, 2.0)).unwrap();
        assert!((later - before - 15.0 * 0.98).abs() < 1e-9, "{later}");
    }
}
