//! Interest management for Myriad: which object states each player gets this tick.
//!
//! No I/O and no physics here. The physics backend answers one area-of-interest (AOI)
//! query per player as a CSR list ([`AoiLists`]: `offsets` and `objects`, slot indices
//! into the world's arrays); the server owns one [`Subscriber`] per player (its own
//! object, AOI centre, sealer and rotation state); [`InterestManager::build`] turns
//! both into sealed `StateUpdate` datagrams, one batch per subscriber, in parallel over
//! players with rayon.
//!
//! [`replica`] is protocol version 2's server half (deltas against acknowledged states,
//! a priority accumulator, a byte budget), measured beside this one by `myriad bench
//! --shadow-budget-kbps` and not yet what the server sends.
//!
//! # How it works
//!
//! For each subscriber, in parallel:
//!
//! 1. Gather the player's own object and every valid object of its AOI list (duplicate
//!    and out-of-range slots are skipped), quantize positions relative to the AOI
//!    centre.
//! 2. If everything fits `max_datagrams` whatever order it is packed in, pack it all
//!    (in the list's order). The own object leads **every**
//!    datagram, so each one alone tells the player where it is (a lost datagram never
//!    leaves it without its own position); the budget for other objects is
//!    `max_datagrams × 112` compact records.
//! 3. Otherwise the update is *over budget*: send the own object, then the `K` nearest
//!    objects (`K` = `near_share` of the budget), then the `R` stalest of the rest
//!    (*staleness*: the tick an object was last sent, or entered the view). The
//!    staleness keys persist in the subscriber from one tick to the next (a player who
//!    missed a tick starts afresh). Both orders are total: nearest by (distance², id),
//!    stalest by (key, id); the nearest group is packed first, then the stalest, each
//!    sorted, so when extended records take more room what is cut is the least urgent,
//!    and the payload is a function of the world, the tick and the history alone.
//!    `myriad-cuda`'s device selection applies the same rule, packs and seals on the
//!    device under sequence numbers leased from each subscriber's sealer;
//!    [`InterestManager::adopt_sealed`] takes its datagrams: the bytes are the same.
//! 4. Seal every datagram with the subscriber's [`Sealer`](myriad_protocol::Sealer).
//!
//! # Refresh bound
//!
//! With `N` objects in view (own excluded) and `R` rotation records per tick (the
//! budget for others minus `K`), every object that stays in view is sent at least once in
//! every `ceil(N / R)` consecutive ticks, and an object entering the view is sent
//! within `ceil(N / R)` ticks. Why: serving the stalest first is earliest-deadline-first;
//! the objects ahead of a waiting object are all in view (at most `N - 1`), every tick
//! it waits removes `R` of them (they are sent, and come back behind it), and newcomers
//! and re-sent objects queue behind it. [`InterestConfig::refresh_bound`] computes the
//! bound, assuming compact 10-byte records (objects within ±512 units of the centre
//! and ids within 2^30 of each other; extended records take 2.4 slots each).
//!
//! # Performance note
//!
//! Scratch buffers live in a thread-local per rayon worker and the output batches in
//! the subscribers, so a warm tick allocates nothing. The common case (everything
//! fits) is one pass to gather and one to pack; over-budget players add a hash-table
//! lookup per object (staleness keys) and two partial selections.

mod config;
mod manager;
pub mod replica;
mod source;
mod stale;

pub use config::{InterestConfig, TickInfo};
pub use manager::{InterestError, InterestManager, Packed, Subscriber, SubscriberReport, TickReport};
pub use replica::{Replica, ReplicaReport, ReplicaScratch, ReplicationConfig};
pub use source::{AoiLists, ObjectSource, SoaObjects};
