//! Configuration and per-tick inputs.

use crate::replica::ReplicationConfig;

/// How much each player may receive per tick, and how urgently each object is sent.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InterestConfig {
    /// Most `StateUpdate` datagrams per player per tick (at least 1; 0 is read as 1):
    /// the ceiling even objects sent over the byte budget (starving ones) stay under.
    pub max_datagrams: usize,
    /// The byte budget and the refresh bounds ([`ReplicationConfig`]).
    pub replication: ReplicationConfig,
}

impl Default for InterestConfig {
    fn default() -> Self {
        Self { max_datagrams: 2, replication: ReplicationConfig::default() }
    }
}

impl InterestConfig {
    /// At most `max_datagrams` datagrams a tick, `send_budget_kbps` kilobits per second
    /// at `tick_rate_hz` ticks per second, the other bounds at their defaults.
    /// (a rate below 1 is read as 1).
    pub fn with_budget(max_datagrams: usize, send_budget_kbps: f64, tick_rate_hz: f64) -> Self {
        let replication = ReplicationConfig {
            budget_bytes_per_tick: (send_budget_kbps * 1000.0 / 8.0 / tick_rate_hz.max(1.0)) as f32,
            ..ReplicationConfig::default()
        };
        Self { max_datagrams, replication }
    }
}

/// What is shared by every update of one tick.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct TickInfo {
    /// The server tick the positions belong to.
    pub tick: u64,
    /// Time dilation in 1/1000 (1000 = real time).
    pub dilation_permille: u16,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn budget_in_kilobits_per_second_becomes_bytes_per_tick() {
        let c = InterestConfig::with_budget(3, 64.0, 30.0);
        assert_eq!(c.max_datagrams, 3);
        assert!((c.replication.budget_bytes_per_tick - 8000.0 / 30.0).abs() < 1e-3);
        // A tick rate of 0 (or NaN) is read as 1 rather than dividing by it.
        assert_eq!(InterestConfig::with_budget(1, 8.0, 0.0).replication.budget_bytes_per_tick, 1000.0);
        assert_eq!(InterestConfig::with_budget(1, 8.0, f64::NAN).replication.budget_bytes_per_tick, 1000.0);
    }
}
