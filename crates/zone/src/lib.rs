//! One world on many servers: zones with ghosts and hand-offs over a message fabric,
//! ending in the same state hash as one process.
//!
//! - [`layout`]: where zones are (a grid whose cuts are data), who sees what, who
//!   neighbours whom.
//! - [`zone`]: one zone's tick: send border states, gather the neighbours', step owned
//!   objects with ghosts, keep the owned results.
//! - [`wire`]: the fabric's messages: versioned, length-checked, signed (HMAC-SHA256).
//! - [`fabric`]: the [`Fabric`] trait and the in-process [`MemoryFabric`]; [`nats`]: the
//!   [`NatsFabric`] between processes; [`fabric_auth`]: who may publish what on it (the
//!   NATS users of a cluster's roles) and the credentials a process presents.
//! - [`gateway`]: a gateway's world, mirrored from the zones ([`ZonesBackend`]), and
//!   [`intents`]: the players' joins, actions and leaves as a zone keeps them.
//! - [`local`]: K zones on threads, reassembled ([`run_zoned`]).
//! - [`resident`]: a zone's world kept from tick to tick, changed where it changed.
//! - [`replay`]: each zone's log of the intents it took, and the replay of a live run
//!   from a checkpoint with them.
//! - [`rebalance`]: boundaries that follow the load: when and where cuts move, and
//!   how every zone switches at one announced tick.
//! - [`subscription`] and [`views`]: states by interest: the cells a gateway subscribes
//!   to, and the view of them each zone sends it.
//! - [`stats`]: per-zone counters and their Prometheus form.
//!
//! Design, subjects, message layouts and measurements: `docs/zones.md`.

pub mod checkpoint;
pub mod claims;
pub mod error;
pub mod fabric;
pub mod fabric_auth;
pub mod gateway;
mod gateway_cuts;
mod gateway_view;
pub mod intents;
pub mod layout;
pub mod local;
pub mod nats;
pub mod process;
pub mod rebalance;
pub mod replay;
pub mod resident;
pub mod stats;
pub mod subscription;
pub mod supervisor;
#[cfg(test)]
mod test_objects;
pub mod views;
pub mod wire;
pub mod zone;

pub use error::ZoneError;
pub use fabric::{Fabric, GatewayLink, MemoryFabric, MemoryGatewayLink};
pub use gateway::{GatewayConfig, ZonesBackend};
pub use layout::{Rect, ZoneId, ZoneLayout};
pub use local::{RunOptions, ZonedRun, pair_reach, run_zoned};
pub use nats::NatsFabric;
pub use rebalance::{CutMove, RebalanceOptions};
pub use stats::ZoneStats;
pub use wire::{ClusterKey, WireError};
pub use zone::{TickEnd, Zone, ZoneConfig};
