//! Configuration and per-tick inputs.

use myriad_protocol::MAX_COMPACT_RECORDS;

/// How much each player may receive per tick, and how it is shared.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InterestConfig {
    /// Most `StateUpdate` datagrams per player per tick (at least 1; 0 is read as 1).
    /// Each holds up to 113 compact records, so 2 datagrams at 20 Hz are about
    /// 48 kB/s per player.
    pub max_datagrams: usize,
    /// Share of an over-budget update given to the nearest objects, the rest going to
    /// the stalest ones. Clamped so that at least one record rotates; NaN is read as 0.5.
    pub near_share: f32,
}

impl Default for InterestConfig {
    fn default() -> Self {
        Self { max_datagrams: 2, near_share: 0.5 }
    }
}

impl InterestConfig {
    /// Compact records of other objects one player can receive per tick: every datagram
    /// carries the player's own object first, then up to `MAX_COMPACT_RECORDS - 1`
    /// others.
    pub fn capacity(&self) -> usize {
        self.max_datagrams.max(1) * (MAX_COMPACT_RECORDS - 1)
    }

    /// `K`: records given to the nearest objects when over budget (own object excluded).
    pub fn near_slots(&self) -> usize {
        let share = if self.near_share.is_nan() { 0.5 } else { self.near_share.clamp(0.0, 1.0) };
        let available = self.capacity();
        ((available as f32 * share) as usize).min(available - 1)
    }

    /// `R`: records given to the stalest objects when over budget.
    pub fn rotation_slots(&self) -> usize {
        self.capacity() - self.near_slots()
    }

    /// The refresh bound in ticks for a view of `objects_in_view` objects (own object
    /// excluded): every object that stays in view is sent at least once in every this
    /// many consecutive ticks. 1 when everything fits. Assumes compact records.
    pub fn refresh_bound(&self, objects_in_view: usize) -> u64 {
        if objects_in_view <= self.capacity() { 1 } else { objects_in_view.div_ceil(self.rotation_slots()) as u64 }
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
    fn slots_and_bound() {
        let c = InterestConfig::default();
        assert_eq!(c.capacity(), 224);
        assert_eq!(c.near_slots(), 112);
        assert_eq!(c.rotation_slots(), 112);
        assert_eq!(c.refresh_bound(224), 1);
        assert_eq!(c.refresh_bound(300), 3);
        let greedy = InterestConfig { max_datagrams: 0, near_share: 7.0 };
        assert_eq!(greedy.capacity(), 112);
        assert_eq!(greedy.rotation_slots(), 1);
        let nan = InterestConfig { max_datagrams: 1, near_share: f32::NAN };
        assert_eq!(nan.near_slots(), 56);
    }
}
