//! The stages of a server tick, by a typed enum, their times, and what one tick did
//! ([`TickWork`]: the times and the tick's counts, which the tick loop, the status
//! window and the tick benchmark all read).
//!
//! A server tick runs the physics backend's seven stages ([`Stage`]) between its own:
//! `receive` (draining and opening client datagrams, before the step), `packets` (the
//! AOI query, interest management, packing and sealing) and `send`. Reports list them
//! in [`TickStage::ALL`]'s order: the physics stages first (the reference's Table 2
//! columns), then `packets`, `send`, `receive`.

use std::ops::{AddAssign, Index, IndexMut};

use myriad_physics::{Stage, StepReport};
use serde::{Deserialize, Serialize};

/// One stage of a server tick.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum TickStage {
    /// A stage of the physics step.
    Physics(Stage),
    /// AOI query, interest management, packing and sealing (and, where these overlap
    /// the sending, everything of the two but [`TickStage::Send`]).
    Packets,
    /// Sending the sealed datagrams: the control replies, plus the mean over the
    /// transport's lanes of each lane's time in the transport (the lanes send at once).
    Send,
    /// Receiving and opening client datagrams, session expiry.
    Receive,
}

impl TickStage {
    /// Every stage, in report order.
    pub const ALL: [TickStage; 10] = [
        TickStage::Physics(Stage::Upload),
        TickStage::Physics(Stage::BuildDynamicBvh),
        TickStage::Physics(Stage::BroadStatic),
        TickStage::Physics(Stage::BroadDynamic),
        TickStage::Physics(Stage::NarrowStatic),
        TickStage::Physics(Stage::NarrowDynamic),
        TickStage::Physics(Stage::Forces),
        TickStage::Packets,
        TickStage::Send,
        TickStage::Receive,
    ];

    /// The name reports and metrics use (`upload`, …, `packets`, `send`, `receive`).
    pub const fn name(self) -> &'static str {
        match self {
            TickStage::Physics(s) => s.name(),
            TickStage::Packets => "packets",
            TickStage::Send => "send",
            TickStage::Receive => "receive",
        }
    }

    /// Position in [`TickStage::ALL`].
    pub const fn index(self) -> usize {
        match self {
            TickStage::Physics(s) => s as usize,
            TickStage::Packets => Stage::ALL.len(),
            TickStage::Send => Stage::ALL.len() + 1,
            TickStage::Receive => Stage::ALL.len() + 2,
        }
    }
}

/// The names of [`TickStage::ALL`], in order.
pub const STAGES: [&str; 10] = {
    let mut names = [""; 10];
    let mut i = 0;
    while i < names.len() {
        names[i] = TickStage::ALL[i].name();
        i += 1;
    }
    names
};

/// Milliseconds per stage of one tick (or a sum or mean of ticks), indexed by
/// [`TickStage`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StageTimes([f64; 10]);

impl StageTimes {
    /// Every stage with its time, in report order.
    pub fn iter(&self) -> impl Iterator<Item = (TickStage, f64)> + '_ {
        TickStage::ALL.into_iter().zip(self.0.iter().copied())
    }

    /// The sum of every stage: the tick's measured work.
    pub fn total(&self) -> f64 {
        self.0.iter().sum()
    }

    /// Copies the physics step's stage times in.
    pub fn set_physics(&mut self, report: &StepReport) {
        for stage in Stage::ALL {
            self[TickStage::Physics(stage)] = report.ms(stage);
        }
    }

    /// Each stage divided by `n` (a mean from a sum).
    pub fn divided_by(mut self, n: f64) -> StageTimes {
        for v in &mut self.0 {
            *v /= n;
        }
        self
    }
}

impl Index<TickStage> for StageTimes {
    type Output = f64;
    fn index(&self, stage: TickStage) -> &f64 {
        &self.0[stage.index()]
    }
}

impl IndexMut<TickStage> for StageTimes {
    fn index_mut(&mut self, stage: TickStage) -> &mut f64 {
        &mut self.0[stage.index()]
    }
}

impl AddAssign<&StageTimes> for StageTimes {
    fn add_assign(&mut self, other: &StageTimes) {
        for (a, b) in self.0.iter_mut().zip(other.0) {
            *a += b;
        }
    }
}

/// What one tick did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct TickWork {
    /// Milliseconds per stage.
    pub stages: StageTimes,
    /// The part of `packets` spent in the backend's AOI query, in ms
    /// ([`crate::outbound::OutboundReport::aoi_ms`]).
    pub aoi_ms: f64,
    /// Bytes sent (control replies and updates).
    pub bytes: u64,
    /// Datagrams sent.
    pub datagrams: u64,
    /// State records packed.
    pub records: usize,
    /// Of those, records relative to a state the player acknowledged (`Delta`, `Same`).
    pub relative: usize,
    /// Datagrams received from clients (before authentication).
    pub received: u64,
    /// Actions applied to the world.
    pub actions: u64,
    /// Received datagrams that reached their session's opener (window, then tag check).
    pub tag_checks: u64,
    /// Received datagrams dropped over their session's receive budget, before any
    /// cryptography.
    pub over_budget: u64,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn all_is_in_index_order_with_unique_names() {
        for (i, s) in TickStage::ALL.iter().enumerate() {
            assert_eq!(s.index(), i);
            assert_eq!(STAGES[i], s.name());
        }
        let mut names = STAGES.to_vec();
        names.sort_unstable();
        names.dedup();
        assert_eq!(names.len(), STAGES.len());
    }

    #[test]
    fn physics_times_land_on_their_stages() {
        let mut report = StepReport::default();
        report.stage_ms[Stage::Forces as usize] = 2.0;
        let mut t = StageTimes::default();
        t[TickStage::Packets] = 1.5;
        t.set_physics(&report);
        assert_eq!(t[TickStage::Physics(Stage::Forces)], 2.0);
        assert_eq!(t.total(), 3.5);
        let mut sum = t;
        sum += &t;
        assert_eq!(sum.divided_by(2.0), t);
    }
}
