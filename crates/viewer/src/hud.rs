//! The on-screen status line and the measurements behind it.

use std::time::{Duration, Instant};

use myriad_client::ClientStats;

/// What the status line shows.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct HudInfo {
    /// Newest server tick received.
    pub tick: u64,
    /// Dynamic objects drawn (not stale, inside the far plane, the player included).
    pub in_view: usize,
    /// Keep-alive round trip, if one has been measured (see [`PingTracker`]).
    pub ping: Option<Duration>,
    /// Bytes per second received (authenticated datagrams, over the last second).
    pub bytes_per_s: f64,
    /// Time dilation in thousandths (1000 = real time).
    pub dilation_permille: u16,
    /// Frames per second drawn.
    pub fps: f64,
}

/// The status line: `tick 1234 | in view 87 | ping 12 ms | 41.3 kB/s | 60 fps`, with
/// the time dilation added when the server runs slower than real time.
pub fn hud_line(h: &HudInfo) -> String {
    let ping = match h.ping {
        Some(p) => format!("{} ms", p.as_millis()),
        None => "–".to_string(),
    };
    let mut line = format!(
        "tick {} | in view {} | ping {} | {:.1} kB/s | {:.0} fps",
        h.tick,
        h.in_view,
        ping,
        h.bytes_per_s / 1000.0,
        h.fps
    );
    if h.dilation_permille != 0 && h.dilation_permille < 1000 {
        line.push_str(&format!(" | dilation {:.2}", f64::from(h.dilation_permille) / 1000.0));
    }
    line
}

/// Measures the round trip of keep-alives: the server answers each one with its own
/// keep-alive, queued until its next send stage, so the figure is the network round trip
/// plus up to one tick. One probe is outstanding at a time; a lost one is given up after
/// `timeout`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PingTracker {
    every: Duration,
    timeout: Duration,
    outstanding: Option<Instant>,
    last_sent: Option<Instant>,
    last: Option<Duration>,
}

impl PingTracker {
    /// A probe every `every`, abandoned after `timeout`.
    pub fn new(every: Duration, timeout: Duration) -> Self {
        PingTracker { every, timeout, outstanding: None, last_sent: None, last: None }
    }

    /// Whether a probe should be sent now.
    pub fn due(&self, now: Instant) -> bool {
        match (self.outstanding, self.last_sent) {
            (Some(sent), _) => now.saturating_duration_since(sent) >= self.timeout,
            (None, Some(sent)) => now.saturating_duration_since(sent) >= self.every,
            (None, None) => true,
        }
    }

    /// A probe left now.
    pub fn sent(&mut self, now: Instant) {
        self.outstanding = Some(now);
        self.last_sent = Some(now);
    }

    /// A keep-alive arrived; returns the round trip if it answers a probe.
    pub fn echoed(&mut self, now: Instant) -> Option<Duration> {
        let sent = self.outstanding.take()?;
        let rtt = now.saturating_duration_since(sent);
        self.last = Some(rtt);
        Some(rtt)
    }

    /// The last round trip measured.
    pub fn last(&self) -> Option<Duration> {
        self.last
    }
}

/// Bytes per second over windows of at least `window`, from cumulative [`ClientStats`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RateMeter {
    window: Duration,
    since: Option<(Instant, ClientStats)>,
    bytes_per_s: f64,
}

impl RateMeter {
    /// A meter averaging over `window`.
    pub fn new(window: Duration) -> Self {
        RateMeter { window, since: None, bytes_per_s: 0.0 }
    }

    /// Feeds the counters at `now`; the rate changes once a window has passed.
    pub fn update(&mut self, stats: ClientStats, now: Instant) -> f64 {
        match self.since {
            None => self.since = Some((now, stats)),
            Some((t0, s0)) => {
                let dt = now.saturating_duration_since(t0);
                if dt >= self.window {
                    self.bytes_per_s = stats.rates_since(&s0, dt.as_secs_f64()).bytes_per_s;
                    self.since = Some((now, stats));
                }
            }
        }
        self.bytes_per_s
    }

    /// The last rate.
    pub fn bytes_per_s(&self) -> f64 {
        self.bytes_per_s
    }
}

/// Frame times: a running frames-per-second figure for the HUD and every frame's
/// duration for the summary `--frames` prints.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FrameTimes {
    /// Every frame time recorded, in milliseconds.
    pub samples_ms: Vec<f64>,
    fps: f64,
}

impl FrameTimes {
    /// Records one frame of `ms` milliseconds.
    pub fn record(&mut self, ms: f64) {
        self.samples_ms.push(ms);
        // An exponential average over roughly the last 30 frames.
        let inst = if ms > 0.0 { 1000.0 / ms } else { 0.0 };
        self.fps = if self.samples_ms.len() == 1 { inst } else { self.fps + (inst - self.fps) / 30.0 };
    }

    /// Smoothed frames per second.
    pub fn fps(&self) -> f64 {
        self.fps
    }

    /// `(mean, median, 95th percentile)` of the frame times in milliseconds, skipping the
    /// first `skip` frames (shader compilation, first uploads).
    pub fn summary(&self, skip: usize) -> Option<(f64, f64, f64)> {
        let mut v: Vec<f64> = self.samples_ms.iter().skip(skip).copied().collect();
        if v.is_empty() {
            return None;
        }
        v.sort_by(f64::total_cmp);
        let mean = v.iter().sum::<f64>() / v.len() as f64;
        let pct = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
        Some((mean, pct(0.5), pct(0.95)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn line_shows_every_field() {
        let h = HudInfo {
            tick: 1234,
            in_view: 87,
            ping: Some(Duration::from_micros(12_600)),
            bytes_per_s: 41_280.0,
            dilation_permille: 1000,
            fps: 59.6,
        };
        assert_eq!(hud_line(&h), "tick 1234 | in view 87 | ping 12 ms | 41.3 kB/s | 60 fps");
        let slow = HudInfo { ping: None, dilation_permille: 500, ..h };
        assert_eq!(hud_line(&slow), "tick 1234 | in view 87 | ping – | 41.3 kB/s | 60 fps | dilation 0.50");
    }

    #[test]
    fn ping_measures_one_probe_at_a_time() {
        let t = Instant::now();
        let ms = Duration::from_millis;
        let mut p = PingTracker::new(ms(1000), ms(3000));
        assert!(p.due(t));
        p.sent(t);
        assert!(!p.due(t + ms(500)));
        assert_eq!(p.echoed(t + ms(40)), Some(ms(40)));
        assert_eq!(p.echoed(t + ms(60)), None, "an unsolicited keep-alive is not a round trip");
        assert_eq!(p.last(), Some(ms(40)));
        assert!(!p.due(t + ms(900)));
        assert!(p.due(t + ms(1000)));
        // A lost probe is retried after the timeout.
        p.sent(t + ms(1000));
        assert!(!p.due(t + ms(3500)));
        assert!(p.due(t + ms(4000)));
    }

    #[test]
    fn bandwidth_over_a_window() {
        let t = Instant::now();
        let mut m = RateMeter::new(Duration::from_secs(1));
        let s = |bytes| ClientStats { bytes, ..Default::default() };
        assert_eq!(m.update(s(1000), t), 0.0);
        assert_eq!(m.update(s(5000), t + Duration::from_millis(500)), 0.0, "window not over yet");
        assert_eq!(m.update(s(21_000), t + Duration::from_secs(2)), 10_000.0);
        assert_eq!(m.bytes_per_s(), 10_000.0);
    }

    #[test]
    fn frame_time_summary() {
        let mut f = FrameTimes::default();
        for ms in [100.0, 10.0, 20.0, 30.0, 40.0] {
            f.record(ms);
        }
        assert_eq!(f.summary(1), Some((25.0, 30.0, 40.0)));
        assert_eq!(f.summary(9), None);
        assert!(f.fps() > 15.0 && f.fps() < 15.5, "{}", f.fps());
    }
}
