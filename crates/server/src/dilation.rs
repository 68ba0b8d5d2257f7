//! Time dilation (EVE Online's scheme): when ticks overrun their budget, the world slows
//! down in small steps instead of falling behind, and speeds up again when load drops.
//!
//! # How it works
//!
//! The tick loop reports how long each tick's work took. The controller keeps an
//! exponential average of it and, every [`DilationController::EVALUATE_EVERY`] ticks,
//! compares it with the current tick period: above 95 % of the period it lowers the
//! factor by one step (5 %, never below the configured floor), below 70 % it raises it
//! by one step (never above real time). The loop then runs ticks every
//! `nominal period / factor` real seconds, each tick still simulating one nominal
//! period, so simulated time runs at `factor` × real time. Keeping the simulated step
//! unchanged (`TickConstants::new(config, 1.0)`) means a dilated world follows exactly
//! the same trajectories, only later: physics stability and determinism do not depend on
//! load. Clients learn the factor from every state update (`dilation_permille`).

use std::time::Duration;

/// The dilation state machine.
#[derive(Debug, Clone)]
pub struct DilationController {
    nominal: Duration,
    enabled: bool,
    min: f64,
    factor: f64,
    average_work_s: f64,
    ticks: u32,
}

impl DilationController {
    /// Ticks between two decisions (so one slow tick does not move the factor).
    pub const EVALUATE_EVERY: u32 = 10;
    /// Change of the factor per decision.
    pub const STEP: f64 = 0.05;

    /// A controller for ticks of `nominal` length that never goes below `min_permille`.
    pub fn new(nominal: Duration, enabled: bool, min_permille: u16) -> Self {
        Self {
            nominal,
            enabled,
            min: f64::from(min_permille.clamp(1, 1000)) / 1000.0,
            factor: 1.0,
            average_work_s: 0.0,
            ticks: 0,
        }
    }

    /// Records one tick's work time; returns true when the factor changed.
    pub fn record(&mut self, work: Duration) -> bool {
        let w = work.as_secs_f64();
        self.average_work_s =
            if self.ticks == 0 && self.average_work_s == 0.0 { w } else { 0.8 * self.average_work_s + 0.2 * w };
        self.ticks += 1;
        if !self.enabled || !self.ticks.is_multiple_of(Self::EVALUATE_EVERY) {
            return false;
        }
        let period = self.period().as_secs_f64();
        let before = self.factor;
        if self.average_work_s > 0.95 * period {
            self.factor = (self.factor - Self::STEP).max(self.min);
        } else if self.average_work_s < 0.7 * period {
            self.factor = (self.factor + Self::STEP).min(1.0);
        }
        (self.factor - before).abs() > f64::EPSILON
    }

    /// Simulated seconds per real second (1 = real time).
    pub fn factor(&self) -> f64 {
        self.factor
    }

    /// The factor in thousandths, as the protocol carries it.
    pub fn permille(&self) -> u16 {
        (self.factor * 1000.0).round().clamp(1.0, 1000.0) as u16
    }

    /// Real time between tick starts at the current factor.
    pub fn period(&self) -> Duration {
        self.nominal.div_f64(self.factor)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn engages_under_load_and_recovers() {
        let period = Duration::from_millis(33);
        let mut c = DilationController::new(period, true, 200);
        for _ in 0..100 {
            c.record(Duration::from_millis(10));
        }
        assert_eq!(c.permille(), 1000, "light load keeps real time");
        // Work of 66 ms per tick needs a factor of about 0.5.
        for _ in 0..400 {
            c.record(Duration::from_millis(66));
        }
        assert!((400..=550).contains(&c.permille()), "factor {}", c.permille());
        assert!(c.period() > Duration::from_millis(60));
        for _ in 0..400 {
            c.record(Duration::from_millis(5));
        }
        assert_eq!(c.permille(), 1000, "recovers when load drops");
    }

    #[test]
    fn respects_floor_and_disable() {
        let mut c = DilationController::new(Duration::from_millis(10), true, 300);
        for _ in 0..1000 {
            c.record(Duration::from_secs(1));
        }
        assert_eq!(c.permille(), 300);
        let mut off = DilationController::new(Duration::from_millis(10), false, 300);
        for _ in 0..1000 {
            off.record(Duration::from_secs(1));
        }
        assert_eq!(off.permille(), 1000);
    }
}
