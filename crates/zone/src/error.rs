//! Errors of the zone layer.

use myriad_core::{CoreError, EntityId};
use myriad_physics::PhysicsError;

use crate::layout::ZoneId;
use crate::wire::WireError;

/// Why a zone could not go on. A bad message from the fabric is *not* one of these: it is
/// rejected and counted ([`crate::ZoneStats::rejected`]) and the zone keeps waiting for a
/// good one.
#[derive(Debug, thiserror::Error)]
pub enum ZoneError {
    /// The zones' geometry is unusable.
    #[error("zone layout: {0}")]
    Layout(String),
    /// The message fabric failed (connection lost, publish refused).
    #[error("fabric: {0}")]
    Fabric(String),
    /// A neighbour's border state did not arrive in time: it died or stalls.
    #[error("zone {zone:?} waited longer than {waited_ms} ms at tick {tick} for {missing:?}")]
    Stalled {
        /// The zone that waited.
        zone: ZoneId,
        /// The tick it waited at.
        tick: u64,
        /// How long.
        waited_ms: u64,
        /// The neighbours it still lacked.
        missing: Vec<ZoneId>,
    },
    /// An object moved farther in one tick than the layout allows, so a zone that needs
    /// it may not be a neighbour of its owner.
    #[error("object {id:?} moved to {to:?}, which zone {from:?} does not exchange with (raise the max step)")]
    TooFar {
        /// The object.
        id: EntityId,
        /// Its owner.
        from: ZoneId,
        /// The zone it reached.
        to: ZoneId,
    },
    /// Two zones claimed the same object at one tick.
    #[error("object {0:?} arrived twice at tick {1}")]
    Duplicate(EntityId, u64),
    /// The coordinator of a rebalancing run stopped answering (another zone failed; the
    /// run reports that zone's error).
    #[error("the rebalancing coordinator stopped")]
    CoordinatorGone,
    /// A checkpoint could not be stored or read.
    #[error("checkpoint: {0}")]
    Checkpoint(String),
    /// An intent log could not be read, or a replay could not follow it.
    #[error("replay: {0}")]
    Replay(String),
    /// A message could not be encoded (too many objects for one part).
    #[error("encoding: {0}")]
    Encode(#[from] WireError),
    /// The physics step failed.
    #[error(transparent)]
    Physics(#[from] PhysicsError),
    /// A world could not be assembled.
    #[error(transparent)]
    Core(#[from] CoreError),
}
