//! The client half of protocol version 3's replication: resolving each opened update
//! and acknowledging it.

use crate::ack::{AckField, AckTracker};
use crate::delta::{Baselines, DeltaRecord, DeltaUpdate};
use crate::update::StateRecord;

/// What a client keeps to follow a server's updates: the [`Baselines`] that resolve
/// relative records and the [`AckTracker`] of the datagrams to acknowledge.
///
/// A datagram is acknowledged only when every record in it resolved. The server takes
/// an acknowledged datagram's states as held and writes later records relative to them
/// (`docs/protocol.md`, sections 4.1 and 5.5), so acknowledging one with a skipped
/// record would let it name a state this client lacks. The one rule, in one place, for
/// every client: the library's connection, the bench's bots and the test harnesses.
///
/// ```
/// use myriad_protocol::{DeltaRecord, QuantPos, RecordState, ShapeKind, UpdateReceiver};
///
/// let mut receiver = UpdateReceiver::default();
/// let mut states = Vec::new();
/// // Tick 10, datagram 1: an absolute record resolves, so the datagram is acknowledged.
/// let far = DeltaRecord { id: 7, state: RecordState::Absolute { kind: ShapeKind::Box, pos: QuantPos::new(64, 0, 0) } };
/// assert_eq!(receiver.receive(1, 10, [far], &mut states), 0);
/// assert_eq!(receiver.acks().map(|a| a.newest()), Some(1));
/// // Tick 12, datagram 2: a delta against tick 11, which this client never got.
/// let delta = DeltaRecord { id: 7, state: RecordState::Delta { back: 1, d: [1, 0, 0] } };
/// assert_eq!(receiver.receive(2, 12, [delta], &mut states), 1);
/// assert_eq!(receiver.acks().map(|a| a.newest()), Some(1), "not acknowledged");
/// // Tick 13, datagram 3: a delta against tick 10, which it holds.
/// let delta = DeltaRecord { id: 7, state: RecordState::Delta { back: 3, d: [1, 0, 0] } };
/// assert_eq!(receiver.receive(3, 13, [delta], &mut states), 0);
/// assert_eq!(states.last().map(|s| s.pos), Some(QuantPos::new(65, 0, 0)));
/// assert!(receiver.acks().is_some_and(|a| a.contains(3) && a.contains(1) && !a.contains(2)));
/// ```
#[derive(Debug, Clone, Default)]
pub struct UpdateReceiver {
    baselines: Baselines,
    acks: AckTracker,
}

impl UpdateReceiver {
    /// Resolves the records of the update of tick `tick` that came in the datagram
    /// numbered `sequence`, appending their states to `out` in the update's order, and
    /// returns how many could not be resolved; the datagram is acknowledged only when
    /// none.
    pub fn receive(
        &mut self,
        sequence: u64,
        tick: u64,
        records: impl IntoIterator<Item = DeltaRecord>,
        out: &mut Vec<StateRecord>,
    ) -> usize {
        let unresolved = self.baselines.resolve_records(tick, records, out);
        if unresolved == 0 {
            self.acks.record(sequence);
        }
        unresolved
    }

    /// [`Self::receive`] for a decoded update.
    pub fn receive_update(&mut self, sequence: u64, update: &DeltaUpdate, out: &mut Vec<StateRecord>) -> usize {
        self.receive(sequence, update.header.tick, update.records.iter().copied(), out)
    }

    /// What to acknowledge now, in the next action or keep-alive (`None` until a
    /// datagram resolved whole).
    pub fn acks(&self) -> Option<AckField> {
        self.acks.field()
    }
}
