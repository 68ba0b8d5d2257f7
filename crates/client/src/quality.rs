//! What a player actually gets of the objects around it: how old the states it holds
//! are (*staleness*) and how far what it draws is from the truth (*error*), each
//! separately for the objects near it ([`NEAR`]) and for its whole area of interest.
//!
//! The measurement's owner decides the samples: `myriad bench` compares sampled bots'
//! mirrors with the server's world in the same process (staleness and error);
//! `myriad bots`, without the truth, measures the staleness of the states a bot holds
//! against the newest update it got. [`Quality`] only collects and summarises them
//! (HDR histograms: 3 significant digits, constant memory however many samples).

use std::time::Duration;

use hdrhistogram::Histogram;

/// Objects within this distance of the player (world units) count as near.
pub const NEAR: f32 = 30.0;

/// Staleness is kept in µs up to 10 minutes.
const MAX_STALENESS_US: u64 = 600_000_000;
/// Error is kept in thousandths of a unit up to 100,000 units.
const MAX_ERROR_MILLI: u64 = 100_000_000;

fn histogram(max: u64) -> Histogram<u64> {
    Histogram::new_with_bounds(1, max, 3).expect("valid histogram bounds")
}

/// Percentiles of one measure.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Percentiles {
    /// Samples taken.
    pub samples: u64,
    /// Median.
    pub p50: f64,
    /// 99th percentile.
    pub p99: f64,
    /// Largest sample.
    pub max: f64,
}

impl Percentiles {
    fn of(h: &Histogram<u64>, unit: f64) -> Self {
        if h.is_empty() {
            return Self::default();
        }
        Self {
            samples: h.len(),
            p50: h.value_at_quantile(0.5) as f64 / unit,
            p99: h.value_at_quantile(0.99) as f64 / unit,
            max: h.max() as f64 / unit,
        }
    }
}

/// One measure kept twice: for near objects and for every object of the AOI.
#[derive(Debug, Clone)]
struct Split {
    near: Histogram<u64>,
    all: Histogram<u64>,
    max: u64,
}

impl Split {
    fn new(max: u64) -> Self {
        Self { near: histogram(max), all: histogram(max), max }
    }

    fn record(&mut self, distance: f32, value: u64) {
        let value = value.min(self.max);
        // Within the bounds by the clamp: recording cannot fail.
        let _ = self.all.record(value);
        if distance <= NEAR {
            let _ = self.near.record(value);
        }
    }

    fn add(&mut self, other: &Split) {
        // Same bounds on both sides: adding cannot fail.
        let _ = self.near.add(&other.near);
        let _ = self.all.add(&other.all);
    }
}

/// Collected staleness and error samples; see the module docs.
#[derive(Debug, Clone)]
pub struct Quality {
    staleness: Split,
    error: Split,
    missing_near: u64,
    missing_all: u64,
}

impl Default for Quality {
    fn default() -> Self {
        Self::new()
    }
}

/// The summary of a [`Quality`].
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct QualitySummary {
    /// Age of the newest state held of each near object, ms.
    pub staleness_near_ms: Percentiles,
    /// Age of the newest state held of each object of the AOI, ms.
    pub staleness_all_ms: Percentiles,
    /// Distance between the drawn and the true position of near objects, units.
    pub error_near: Percentiles,
    /// Distance between the drawn and the true position of every object of the AOI,
    /// units.
    pub error_all: Percentiles,
    /// Near objects of which the player held no state at all when sampled.
    pub missing_near: u64,
    /// Objects of the AOI of which the player held no state at all when sampled.
    pub missing_all: u64,
}

impl Quality {
    /// No samples yet.
    pub fn new() -> Self {
        Self {
            staleness: Split::new(MAX_STALENESS_US),
            error: Split::new(MAX_ERROR_MILLI),
            missing_near: 0,
            missing_all: 0,
        }
    }

    /// An object `distance` units from the player whose newest state held is `age` old.
    pub fn record_staleness(&mut self, distance: f32, age: Duration) {
        self.staleness.record(distance, u64::try_from(age.as_micros()).unwrap_or(u64::MAX));
    }

    /// An object `distance` units from the player of which it holds no state.
    pub fn record_missing(&mut self, distance: f32) {
        self.missing_all += 1;
        self.missing_near += u64::from(distance <= NEAR);
    }

    /// An object `distance` units from the player drawn `error` units from where it is.
    pub fn record_error(&mut self, distance: f32, error: f32) {
        self.error.record(distance, (f64::from(error.max(0.0)) * 1000.0).round() as u64);
    }

    /// Adds another collection's samples.
    pub fn add(&mut self, other: &Quality) {
        self.staleness.add(&other.staleness);
        self.error.add(&other.error);
        self.missing_near += other.missing_near;
        self.missing_all += other.missing_all;
    }

    /// Percentiles of everything recorded.
    pub fn summary(&self) -> QualitySummary {
        QualitySummary {
            staleness_near_ms: Percentiles::of(&self.staleness.near, 1000.0),
            staleness_all_ms: Percentiles::of(&self.staleness.all, 1000.0),
            error_near: Percentiles::of(&self.error.near, 1000.0),
            error_all: Percentiles::of(&self.error.all, 1000.0),
            missing_near: self.missing_near,
            missing_all: self.missing_all,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn near_samples_count_in_both_and_far_ones_only_in_all() {
        let mut q = Quality::new();
        for ms in 1..=100u64 {
            q.record_staleness(10.0, Duration::from_millis(ms));
        }
        q.record_staleness(31.0, Duration::from_secs(2));
        q.record_error(NEAR, 0.25);
        q.record_error(50.0, 4.0);
        q.record_missing(5.0);
        q.record_missing(45.0);
        let s = q.summary();
        assert_eq!(s.staleness_near_ms.samples, 100);
        assert_eq!(s.staleness_all_ms.samples, 101);
        assert!((s.staleness_near_ms.p50 - 50.0).abs() < 0.1, "{s:?}");
        assert!((s.staleness_near_ms.max - 100.0).abs() < 0.1, "{s:?}");
        assert!((s.staleness_all_ms.max - 2000.0).abs() < 2.0, "{s:?}");
        assert_eq!((s.error_near.samples, s.error_all.samples), (1, 2));
        assert!((s.error_near.p99 - 0.25).abs() < 1e-3 && (s.error_all.max - 4.0).abs() < 1e-2, "{s:?}");
        assert_eq!((s.missing_near, s.missing_all), (1, 2));
        let mut total = Quality::new();
        total.add(&q);
        total.add(&q);
        assert_eq!(total.summary().staleness_all_ms.samples, 202);
        assert_eq!(total.summary().missing_all, 4);
    }
}
