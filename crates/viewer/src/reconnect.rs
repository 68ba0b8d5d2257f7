//! When the viewer's session ends, what it says and when it logs in again: the
//! [`Backoff`] schedule (1 s doubling to 30 s, with jitter so that many viewers of a
//! restarted server do not all knock at once), the [`Link`] state the status line shows,
//! and which ends are worth a new login at all ([`end_reason`]).
//!
//! Kept free of I/O and clocks (every function takes `now`) so the schedule is tested
//! without sleeping.

use std::time::{Duration, Instant};

use myriad_client::{ClientError, SessionEnd};
use myriad_protocol::DisconnectReason;
use myriad_protocol::login::RefusalReason;

/// The first wait before logging in again.
pub const FIRST_DELAY: Duration = Duration::from_secs(1);

/// The longest wait between two login attempts.
pub const MAX_DELAY: Duration = Duration::from_secs(30);

/// Each delay is scaled by a factor drawn uniformly from `1 ± JITTER`.
pub const JITTER: f64 = 0.1;

/// The delays between login attempts: [`FIRST_DELAY`], doubling up to [`MAX_DELAY`],
/// each scaled by a random factor within `1 ± JITTER`. One `Backoff` serves one outage:
/// a session that logged in again starts the next outage with a fresh one.
#[derive(Debug, Clone)]
pub struct Backoff {
    nominal: Duration,
    rng: fastrand::Rng,
}

impl Backoff {
    /// A schedule whose jitter comes from `seed` (the viewer seeds it from the clock; a
    /// test picks one).
    pub fn new(seed: u64) -> Self {
        Backoff { nominal: FIRST_DELAY, rng: fastrand::Rng::with_seed(seed) }
    }

    /// The delay before the next attempt (and the schedule moves on).
    pub fn next_delay(&mut self) -> Duration {
        let nominal = self.nominal;
        self.nominal = (nominal * 2).min(MAX_DELAY);
        let factor = 1.0 + JITTER * (2.0 * self.rng.f64() - 1.0);
        nominal.mul_f64(factor)
    }
}

/// The state of the viewer's link to the server, as the status line shows it.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub enum Link {
    /// A login is in flight (`attempt` 0 is the first login of the run).
    #[default]
    LoggingIn,
    /// The session is up.
    Connected,
    /// The session ended for `reason`; the next login starts at `at`.
    Reconnecting {
        /// Why the session ended, or why the last login failed.
        reason: String,
        /// When the next attempt starts.
        at: Instant,
    },
    /// The session ended and the viewer does not try again (the account logged in
    /// elsewhere, a ban, a wrong password): restart the viewer.
    Disconnected {
        /// Why.
        reason: String,
    },
}

impl Link {
    /// The status-line text at `now`: `connected`, `logging in`, `disconnected: REASON |
    /// reconnecting in N s`, or `disconnected: REASON | not reconnecting`.
    pub fn status(&self, now: Instant) -> String {
        match self {
            Link::LoggingIn => "logging in".into(),
            Link::Connected => "connected".into(),
            Link::Reconnecting { reason, at } => {
                // Rounded up: "in 0 s" would read as "now" while there is still a wait.
                let secs = at.saturating_duration_since(now).as_secs_f64().ceil();
                format!("disconnected: {reason} | reconnecting in {secs:.0} s")
            }
            Link::Disconnected { reason } => format!("disconnected: {reason} | not reconnecting"),
        }
    }

    /// Whether the session is up.
    pub fn is_connected(&self) -> bool {
        *self == Link::Connected
    }
}

/// Why a session ended, in words, and whether logging in again may help: not when the
/// account logged in elsewhere (the two would replace each other in turn) or is banned.
pub fn end_reason(end: SessionEnd, silence_timeout: Duration) -> (String, bool) {
    use DisconnectReason::*;
    match end {
        SessionEnd::Silent => (format!("no answer from the server for {} s", silence_timeout.as_secs()), true),
        SessionEnd::Disconnected(reason) => {
            let text = match reason {
                Shutdown => "the server shut down",
                Timeout => "the server timed the session out",
                Kicked => "removed by an operator",
                Replaced => "the account logged in elsewhere",
                ServerFull => "the server is full",
                ProtocolViolation => "the server saw a protocol violation",
                Banned => "the account is banned",
            };
            (text.into(), !matches!(reason, Replaced | Banned))
        }
    }
}

/// What a failed login attempt means for the next one.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LoginFailure {
    /// Why, in words (never the password: [`ClientError`] does not carry it).
    pub reason: String,
    /// Whether another attempt may succeed: what [`ClientError::is_retryable`] says, and
    /// also a server that is shutting down (a restart is the case this module is for).
    pub retry: bool,
    /// The least wait the server asked for (a rate limit's hint), zero if none.
    pub at_least: Duration,
}

/// Reads a failed login attempt.
pub fn login_failure(e: &ClientError) -> LoginFailure {
    let (retry, at_least) = match e {
        ClientError::Refused { reason: RefusalReason::ShuttingDown, retry_after_ms } => {
            (true, Duration::from_millis(u64::from(*retry_after_ms)))
        }
        ClientError::Refused { retry_after_ms, .. } => {
            (e.is_retryable(), Duration::from_millis(u64::from(*retry_after_ms)))
        }
        _ => (e.is_retryable(), Duration::ZERO),
    };
    LoginFailure { reason: format!("login failed: {e}"), retry, at_least }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn delays_double_from_one_second_to_thirty_within_the_jitter() {
        let nominal = [1.0, 2.0, 4.0, 8.0, 16.0, 30.0, 30.0, 30.0];
        for seed in 0..50 {
            let mut b = Backoff::new(seed);
            for n in nominal {
                let d = b.next_delay().as_secs_f64();
                assert!((n * (1.0 - JITTER)..=n * (1.0 + JITTER)).contains(&d), "seed {seed}: {d} s for {n} s");
            }
        }
    }

    #[test]
    fn jitter_spreads_viewers_apart() {
        let firsts: std::collections::HashSet<Duration> = (0..20).map(|s| Backoff::new(s).next_delay()).collect();
        assert!(firsts.len() > 15, "{firsts:?}");
        assert_eq!(Backoff::new(7).next_delay(), Backoff::new(7).next_delay(), "seeded");
    }

    #[test]
    fn status_line_texts() {
        let now = Instant::now();
        assert_eq!(Link::default().status(now), "logging in");
        assert_eq!(Link::Connected.status(now), "connected");
        let r = Link::Reconnecting { reason: "the server shut down".into(), at: now + Duration::from_millis(3_200) };
        assert_eq!(r.status(now), "disconnected: the server shut down | reconnecting in 4 s");
        assert_eq!(r.status(now + Duration::from_secs(5)), "disconnected: the server shut down | reconnecting in 0 s");
        let d = Link::Disconnected { reason: "the account is banned".into() };
        assert_eq!(d.status(now), "disconnected: the account is banned | not reconnecting");
    }

    #[test]
    fn only_some_ends_are_retried() {
        let t = Duration::from_secs(5);
        assert_eq!(end_reason(SessionEnd::Silent, t), ("no answer from the server for 5 s".into(), true));
        for reason in DisconnectReason::ALL {
            let (_, retry) = end_reason(SessionEnd::Disconnected(reason), t);
            let expected = !matches!(reason, DisconnectReason::Replaced | DisconnectReason::Banned);
            assert_eq!(retry, expected, "{reason:?}");
        }
        let refused = |reason, retry_after_ms| ClientError::Refused { reason, retry_after_ms };
        assert!(!login_failure(&refused(RefusalReason::WrongCredentials, 0)).retry);
        assert!(!login_failure(&refused(RefusalReason::Banned, 0)).retry);
        assert!(login_failure(&refused(RefusalReason::ShuttingDown, 0)).retry, "a restart refuses while stopping");
        let limited = login_failure(&refused(RefusalReason::RateLimited, 2_500));
        assert!(limited.retry && limited.at_least == Duration::from_millis(2_500));
        assert!(login_failure(&ClientError::Timeout("login")).retry);
    }
}
