//! What a client repeats because UDP may lose it, and when it gives a session up: the
//! timers of docs/protocol.md §7a, kept I/O-free so that they are tested without sockets
//! or sleeps. [`Connection`](crate::Connection) owns one per session and sends what
//! `Liveness::due` asks for.
//!
//! - **Ready** is resent after [`READY_FIRST_RETRY`], then at doubling gaps up to
//!   [`READY_MAX_RETRY`], until the session's first ServerInfo or state update arrives:
//!   one lost Ready must not cost a login.
//! - **Silence**: once nothing authentic was heard for a probe gap (the silence timeout
//!   over [`SILENCE_PROBES`] + 1), a KeepAlive probe goes out, one a gap; the session is
//!   declared silent only when the timeout has passed **and** [`SILENCE_PROBES`] probes
//!   went unanswered, the last a whole gap ago. A lost datagram or two never ends it.

use std::time::{Duration, Instant};

/// The first gap before Ready is sent again.
pub const READY_FIRST_RETRY: Duration = Duration::from_millis(100);

/// The longest gap between two Readies (the gaps double up to it: 100, 200, 400, 800,
/// 1600 ms, then 1600 ms until the session answers or is declared silent).
pub const READY_MAX_RETRY: Duration = Duration::from_millis(1600);

/// Unanswered keep-alive probes before a silent session is given up.
pub const SILENCE_PROBES: u32 = 3;

/// Copies of a Disconnect a client sends (each sealed afresh: the replay window would
/// drop a copy of the same datagram). The server sends as many.
pub const DISCONNECT_COPIES: usize = 3;

/// What is due now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Due {
    /// Send Ready again.
    Ready,
    /// Send a KeepAlive probe.
    Probe,
}

/// One session's retransmission and silence timers; see the module docs.
#[derive(Debug, Clone)]
pub(crate) struct Liveness {
    /// The gap between probes: the silence timeout over `SILENCE_PROBES + 1`.
    probe_gap: Duration,
    silence_timeout: Duration,
    /// When Ready is due again and the gap after that resend; `None` once the session
    /// answered.
    ready: Option<(Instant, Duration)>,
    last_heard: Instant,
    /// Probes sent since `last_heard`, and when the last went out.
    probes: u32,
    last_probe: Option<Instant>,
    silent: bool,
}

impl Liveness {
    /// The timers of a session whose first Ready went out at `now`.
    pub(crate) fn start(now: Instant, silence_timeout: Duration) -> Self {
        Liveness {
            probe_gap: silence_timeout / (SILENCE_PROBES + 1),
            silence_timeout,
            ready: Some((now + READY_FIRST_RETRY, (READY_FIRST_RETRY * 2).min(READY_MAX_RETRY))),
            last_heard: now,
            probes: 0,
            last_probe: None,
            silent: false,
        }
    }

    /// An authentic datagram of the session arrived at `now`; `started` when it shows the
    /// server took the Ready (ServerInfo or a state update).
    pub(crate) fn heard(&mut self, now: Instant, started: bool) {
        self.last_heard = self.last_heard.max(now);
        self.probes = 0;
        self.last_probe = None;
        if started {
            self.ready = None;
        }
    }

    /// Whether the session has been declared silent.
    pub(crate) fn silent(&self) -> bool {
        self.silent
    }

    /// The next thing to send at `now`, if any (call until `None`); declares the session
    /// silent when the module docs' rule says so.
    pub(crate) fn due(&mut self, now: Instant) -> Option<Due> {
        if self.silent {
            return None;
        }
        if let Some((at, gap)) = self.ready
            && now >= at
        {
            self.ready = Some((now + gap, (gap * 2).min(READY_MAX_RETRY)));
            return Some(Due::Ready);
        }
        let quiet = now.saturating_duration_since(self.last_heard);
        let since_probe = self.last_probe.map_or(quiet, |t| now.saturating_duration_since(t));
        if since_probe < self.probe_gap || quiet < self.probe_gap {
            return None;
        }
        if self.probes < SILENCE_PROBES {
            self.probes += 1;
            self.last_probe = Some(now);
            return Some(Due::Probe);
        }
        if quiet >= self.silence_timeout {
            self.silent = true;
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(n: u64) -> Duration {
        Duration::from_millis(n)
    }

    /// Everything due at each of `times` (ms after `t0`).
    fn run(l: &mut Liveness, t0: Instant, times: impl IntoIterator<Item = u64>) -> Vec<(u64, Due)> {
        let mut out = Vec::new();
        for t in times {
            while let Some(d) = l.due(t0 + ms(t)) {
                out.push((t, d));
            }
        }
        out
    }

    #[test]
    fn ready_is_resent_with_doubling_gaps_until_the_session_starts() {
        let t0 = Instant::now();
        let mut l = Liveness::start(t0, Duration::from_secs(60));
        let readies: Vec<u64> =
            run(&mut l, t0, (0..=6_000).step_by(10)).into_iter().filter(|d| d.1 == Due::Ready).map(|d| d.0).collect();
        assert_eq!(readies, [100, 300, 700, 1500, 3100, 4700]);
        l.heard(t0 + ms(6_000), true);
        assert!(run(&mut l, t0, (6_010..=9_000).step_by(10)).iter().all(|d| d.1 != Due::Ready));
    }

    #[test]
    fn a_keepalive_answer_does_not_stop_the_ready_resends() {
        let t0 = Instant::now();
        let mut l = Liveness::start(t0, Duration::from_secs(60));
        l.heard(t0 + ms(50), false);
        assert_eq!(run(&mut l, t0, [100]), [(100, Due::Ready)]);
    }

    #[test]
    fn silence_is_declared_only_after_the_probes_went_unanswered() {
        let t0 = Instant::now();
        let mut l = Liveness::start(t0, ms(4_000));
        l.heard(t0, true);
        let probes = run(&mut l, t0, (0..=3_990).step_by(10));
        assert_eq!(probes, [(1_000, Due::Probe), (2_000, Due::Probe), (3_000, Due::Probe)]);
        assert!(!l.silent(), "not before the timeout");
        assert!(run(&mut l, t0, [4_000]).is_empty());
        assert!(l.silent());
    }

    #[test]
    fn an_answer_to_a_probe_keeps_the_session() {
        let t0 = Instant::now();
        let mut l = Liveness::start(t0, ms(4_000));
        l.heard(t0, true);
        run(&mut l, t0, (0..=2_500).step_by(10));
        l.heard(t0 + ms(2_500), false);
        run(&mut l, t0, (2_510..=6_000).step_by(10));
        assert!(!l.silent(), "heard at 2.5 s: quiet for 3.5 s only");
        run(&mut l, t0, (6_010..=6_500).step_by(10));
        assert!(l.silent());
    }

    #[test]
    fn a_caller_that_was_late_still_waits_for_its_probes() {
        // Called for the first time long after the timeout: the probes are sent one a
        // gap, not all at once followed by a verdict.
        let t0 = Instant::now();
        let mut l = Liveness::start(t0, ms(4_000));
        l.heard(t0, true);
        assert_eq!(run(&mut l, t0, [10_000]), [(10_000, Due::Probe)]);
        assert!(!l.silent());
        run(&mut l, t0, [11_000, 12_000]);
        assert!(!l.silent(), "the third probe went out at 12 s");
        run(&mut l, t0, [13_000]);
        assert!(l.silent());
    }
}
