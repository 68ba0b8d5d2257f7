//! Interest management for Myriad: which object states each player gets this tick.
//!
//! No I/O and no physics here. The physics backend answers one area-of-interest (AOI)
//! query per player as a CSR list ([`AoiLists`]: `offsets` and `objects`, slot indices
//! into the world's arrays); the server owns one [`Subscriber`] per player (its own
//! object, AOI centre, sealer and [`Replica`]); [`InterestManager::build`] turns both
//! into sealed `StateUpdate` datagrams of protocol version 3, one batch per subscriber,
//! in parallel over players with rayon.
//!
//! # How it works
//!
//! For each subscriber, in parallel:
//!
//! 1. Gather the player's own object and every valid object of its AOI list
//!    (out-of-range slots are skipped and counted), quantized, with its distance from
//!    the AOI centre.
//! 2. The subscriber's [`Replica`] ([`replica`]'s module docs) applies the client's
//!    acknowledgements ([`Subscriber::acknowledge`]), raises each object's priority by
//!    its distance and whether the client holds its current state, takes the objects due
//!    into the player's byte budget (near ones first; one that waited too long even over
//!    it), and writes them as delta records against the states the client acknowledged.
//!    The own object is in **every** datagram, so each one alone tells the player where
//!    it is.
//! 3. Seal every datagram with the subscriber's [`Sealer`](myriad_protocol::Sealer); what
//!    each carried stays in flight until the client acknowledges it.
//!
//! # Bounds
//!
//! A changing object is sent within its refresh bound (3 ticks within 30 units, growing
//! to 24 at 60), an unchanged one is confirmed every 24 ticks, and no object waits more
//! than `max_wait_ticks` (30) while the datagram ceiling allows
//! ([`ReplicationConfig`]); `replica_tests.rs` pins them with a client that loses
//! datagrams and acknowledgements.
//!
//! # Performance note
//!
//! Scratch buffers live in a thread-local per rayon worker and the output batches and
//! replicas in the subscribers, so a warm tick allocates nothing. Each object in view
//! costs a step of a merge (its track, in the view's slot order) and a priority update;
//! only the objects due are ranked, a slice of the order at a time.

mod config;
mod manager;
pub mod replica;
mod source;

pub use config::{InterestConfig, TickInfo};
pub use manager::{InterestError, InterestManager, Subscriber, SubscriberReport, TickReport};
pub use replica::{Packing, Replica, ReplicaReport, ReplicaScratch, ReplicationConfig};
pub use source::{AoiLists, ObjectSource, SoaObjects};
