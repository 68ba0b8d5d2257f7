//! The structs the replica kernels share with the host (`kernels/replica.cuh`), field
//! for field; `layout_matches_the_c_side` checks their sizes against the C compiler's.
//! The fields are those of the C structs, documented there (and in the Rust replica
//! they mirror), so they carry no docs of their own here.
#![allow(missing_docs)]

use bytemuck::{Pod, Zeroable};

/// `RPos`: a quantized position.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct RPos {
    pub x: i32,
    pub y: i32,
    pub z: i32,
}

/// `RTrack`: what the server knows of one object in a player's view.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, Pod, Zeroable)]
pub struct RTrack {
    pub id: u64,
    pub acked_tick: u64,
    pub sent_tick: u64,
    pub acked: RPos,
    pub sent: RPos,
    pub priority: f32,
    pub slot: u32,
    pub prior_back: u8,
    pub sent_moved: u8,
    pub prior_offset: [i16; 3],
}

/// `RConfig`: the replication configuration and the most datagrams a player.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, Pod, Zeroable)]
pub struct RConfig {
    pub resend_ticks: u64,
    pub budget: f32,
    pub near_units: f32,
    pub near_bound: f32,
    pub far_bound: f32,
    pub far_units: f32,
    pub refresh: f32,
    pub max_wait: f32,
    pub max_datagrams: u32,
}

/// `RRecord`: a record; `v` is the delta or the absolute position.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct RRecord {
    pub id: u64,
    pub form: u8,
    pub kind: u8,
    pub back: u8,
    pub prior: u8,
    pub v: [i32; 3],
}

/// `RCand`: an object in view.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, Pod, Zeroable)]
pub struct RCand {
    pub id: u64,
    pub slot: u32,
    pub kind: u32,
    pub pos: RPos,
    pub distance: f32,
}

/// `RObj` (`kernels/replica.cu`, device only): an object as a build reads it, gathered
/// once a build into one 32-byte sector (its position quantized and as is, its id and
/// shape).
#[repr(C, align(16))]
#[derive(Debug, Clone, Copy, Default, Pod, Zeroable)]
pub struct RObj {
    pub q: RPos,
    pub p: [f32; 3],
    pub id: u32,
    pub kind: u32,
}

const _: () = assert!(size_of::<RObj>() == 32);

/// `RFlight`: a datagram in flight.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, Pod, Zeroable)]
pub struct RFlight {
    pub sequence: u64,
    pub tick: u64,
    pub start: u32,
    pub len: u32,
}

/// `RState`: a state a flight carried.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, Pod, Zeroable)]
pub struct RState {
    pub id: u64,
    pub slot: u32,
    pub pos: RPos,
}

/// `RMoved`: an object matched by id.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, Pod, Zeroable)]
pub struct RMoved {
    pub id: u64,
    pub from: u32,
    pub to: u32,
}

/// `RDue`: an object due.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, Pod, Zeroable)]
pub struct RDue {
    pub hi: u64,
    pub id: u64,
    pub track: u32,
    pub cand: u32,
    pub starving: u32,
    pub eager: u32,
}

/// `RChosen`: a record chosen and where it came from.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, Pod, Zeroable)]
pub struct RChosen {
    pub rec: RRecord,
    pub track: u32,
    pub cand: u32,
}

/// `RHome`: what persists of a player besides its tracks.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, Pod, Zeroable)]
pub struct RHome {
    pub own: RTrack,
    pub credit: f32,
    pub has_own: u32,
    pub nflights: u32,
    pub track_off: u32,
    pub track_len: u32,
    pub has_own_now: u32,
    pub own_now_id: u64,
    pub own_now: RPos,
    pub pad: u32,
    /// One past the tick of the newest flight the player acknowledged (0: none yet).
    pub heard: u64,
}

/// `RPlayer`: one player's inputs of a build.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, Pod, Zeroable)]
pub struct RPlayer {
    pub ack_newest: u64,
    pub ack_bits: u64,
    pub centre: [f32; 3],
    pub home: u32,
    pub reset: u32,
    pub own_slot: u32,
    pub has_acks: u32,
    pub pad: u32,
}

/// `RInfo`: one player's outputs of a build besides its records.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, Pod, Zeroable)]
pub struct RInfo {
    pub own_record: RRecord,
    pub has_own_record: u32,
    pub datagrams: u32,
    pub count: u32,
    pub in_view: u32,
    pub out_of_order: u32,
    pub deferred: u32,
    pub starving: u32,
    pub unsorted: u32,
}

/// `RCommit`: what the host's packing and sealing did.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, Pod, Zeroable)]
pub struct RCommit {
    pub first: u64,
    pub spent: f32,
    pub ok: u32,
    pub packed: u32,
    pub datagrams: u32,
}

/// `RKey`: an index sorted by id.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, Pod, Zeroable)]
pub struct RKey {
    pub id: u64,
    pub index: u32,
    pub pad: u32,
}

/// `RPacked`: what packing one player's records did (`kernels/pack.cuh`).
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, Pod, Zeroable)]
pub struct RPacked {
    pub packed: u32,
    pub relative: u32,
    pub datagrams: u32,
    pub pad: u32,
}

/// Sizes in the order of `myriad_replica_sizes` (`src/replica/host.c`).
#[cfg(test)]
pub(crate) const SIZES: [usize; 15] = [
    size_of::<RTrack>(),
    size_of::<RConfig>(),
    size_of::<RRecord>(),
    size_of::<RCand>(),
    size_of::<RFlight>(),
    size_of::<RState>(),
    size_of::<RMoved>(),
    size_of::<RDue>(),
    size_of::<RChosen>(),
    size_of::<RHome>(),
    size_of::<RPlayer>(),
    size_of::<RInfo>(),
    size_of::<RCommit>(),
    size_of::<RKey>(),
    size_of::<RPacked>(),
];
