//! The fabric's message format: what zones (and later gateways) say to each other.
//!
//! Every message is a fixed header, a body of fixed-size records and an HMAC-SHA256 tag
//! over both with the cluster's key. The tag is checked before anything else is read, so
//! a message from outside the cluster (or a corrupted one) is never parsed, let alone
//! applied. Replays and reordering are caught above this layer, by the receiver's inbox
//! (`crate::zone`), from the header's run id and tick. Byte layout: `docs/zones.md`.
//!
//! ```
//! use myriad_zone::wire::{Border, ClusterKey, Message, decode, encode_border};
//! use myriad_zone::ZoneId;
//! let key = ClusterKey::new(b"a key of at least sixteen bytes!").unwrap();
//! let m = Border { run: 7, tick: 3, from: ZoneId(0), to: ZoneId(1), part: 0, parts: 1, objects: vec![] };
//! let bytes = encode_border(&key, &m).unwrap();
//! assert_eq!(decode(&key, &bytes).unwrap(), Message::Border(m));
//! assert!(decode(&key, &bytes[..bytes.len() - 1]).is_err());
//! ```

use myriad_core::world::flags;
use myriad_core::{EntityId, ObjectKind, ObjectState, ShapeKind, Vec3};
use ring::hmac;

use crate::layout::ZoneId;
use crate::rebalance::{CutMove, Cuts};

mod cuts;
pub use cuts::Load;
use cuts::{cut_block, read_cuts};

mod interest;
pub use interest::{
    ACT_LEN, KIND_SUBSCRIPTION, KIND_VIEW, KIND_VIEW_PACKED, MAX_CELLS, MAX_PACKED_VIEW_BODY, MAX_RESYNCS, MOVE_LEN,
    Subscription, VIEW_FIXED, View, cell_bytes, encode_subscription, encode_view,
};
mod nudge;
pub use nudge::{FingerprintCache, Ground, GroundWorld, NUDGE_MAX_LEN, Nudge, Prediction, ground_fingerprint};

/// First two bytes of every message.
pub const MAGIC: [u8; 2] = *b"MZ";
/// The format's version; a message of another version is refused. (2: heartbeats carry
/// the zone's load, starts and checkpoints the cuts, and cut moves exist; 3: views carry
/// nudges; 4: views travel packed; 5: ground nudges, views carry acts, subscriptions the
/// ground fingerprint.)
pub const VERSION: u8 = 5;
/// Bytes before the body.
pub const HEADER_LEN: usize = 32;
/// Bytes of one object record.
pub const RECORD_LEN: usize = 48;
/// Bytes of the tag.
pub const TAG_LEN: usize = 32;
/// Message kind: a zone's border state for a neighbour.
pub const KIND_BORDER: u8 = 1;
/// Message kind: a zone's objects at a tick (a checkpoint, or a run's result).
pub const KIND_CHECKPOINT: u8 = 2;
/// Message kind: a zone's heartbeat.
pub const KIND_HEARTBEAT: u8 = 3;
/// Message kind: the supervisor's halt (a new epoch follows).
pub const KIND_HALT: u8 = 4;
/// Message kind: the supervisor's start of an epoch from a checkpoint.
pub const KIND_START: u8 = 5;
/// Message kind: a zone's owned objects after a step, to every gateway.
pub const KIND_STATES: u8 = 6;
/// Message kind: a gateway's players' intents (join, action, leave), to every zone.
pub const KIND_INTENTS: u8 = 7;
/// Message kind: a gateway's claim of an account's session, to every gateway.
pub const KIND_CLAIM: u8 = 8;
/// Message kind: the supervisor's move of the cuts, to every zone.
pub const KIND_CUT_MOVE: u8 = 9;
/// Bytes of a heartbeat's body: the zone's [`Load`].
pub const LOAD_LEN: usize = 24;
/// Bit of a record's flag byte that hands the object to the receiver.
const YOURS: u8 = 1 << 7;

/// Why bytes from the fabric are not a message.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum WireError {
    /// Shorter than a header and a tag.
    #[error("truncated: {0} bytes")]
    Truncated(usize),
    /// Not a Myriad fabric message.
    #[error("bad magic")]
    Magic,
    /// Another version of the format.
    #[error("version {0}, expected {VERSION}")]
    Version(u8),
    /// The tag does not match: not from the cluster, or altered.
    #[error("bad tag")]
    Tag,
    /// An unknown message kind.
    #[error("unknown kind {0}")]
    Kind(u8),
    /// The body's length disagrees with the header's count.
    #[error("body of {actual} bytes for {count} records")]
    Length {
        /// Records the header announces.
        count: u32,
        /// Bytes the body has.
        actual: usize,
    },
    /// Part numbers out of range.
    #[error("part {part} of {parts}")]
    Part {
        /// This part.
        part: u16,
        /// Parts in all.
        parts: u16,
    },
    /// A record is not a valid object state.
    #[error("record {index}: {reason}")]
    Record {
        /// Its index in the message.
        index: usize,
        /// What is wrong.
        reason: String,
    },
    /// Header fields that must be zero for this kind are not, or a heartbeat's state is
    /// unknown.
    #[error("field {0} out of range for this kind")]
    Field(&'static str),
    /// A key shorter than 16 bytes.
    #[error("a cluster key needs at least 16 bytes")]
    WeakKey,
    /// A subscription's grid has no cells or more than [`MAX_CELLS`].
    #[error("a subscription of {0} cells (at most {MAX_CELLS})")]
    Cells(u64),
}

impl WireError {
    /// A short stable name, for metrics labels.
    pub fn label(&self) -> &'static str {
        match self {
            WireError::Truncated(_) => "truncated",
            WireError::Magic => "magic",
            WireError::Version(_) => "version",
            WireError::Tag => "tag",
            WireError::Kind(_) => "kind",
            WireError::Length { .. } => "length",
            WireError::Part { .. } => "part",
            WireError::Record { .. } => "record",
            WireError::Field(_) => "field",
            WireError::WeakKey => "key",
            WireError::Cells(_) => "cells",
        }
    }
}

/// The secret every process of a cluster shares; it signs and checks every message.
#[derive(Clone)]
pub struct ClusterKey(hmac::Key);

impl ClusterKey {
    /// A key from secret bytes (at least 16).
    pub fn new(secret: &[u8]) -> Result<ClusterKey, WireError> {
        if secret.len() < 16 {
            return Err(WireError::WeakKey);
        }
        Ok(ClusterKey(hmac::Key::new(hmac::HMAC_SHA256, secret)))
    }

    /// The first 8 bytes of HMAC-SHA256(`bytes`) under this key, as a number: a digest
    /// nobody outside the cluster can compute or aim at.
    pub fn digest64(&self, bytes: &[u8]) -> u64 {
        let tag = hmac::sign(&self.0, bytes);
        u64::from_le_bytes(tag.as_ref()[..8].try_into().expect("32 bytes"))
    }

    /// A fresh random key, for a cluster that lives in one process.
    pub fn random() -> ClusterKey {
        ClusterKey::new(random_secret().as_bytes()).expect("48 bytes")
    }
}

/// A fresh random secret for [`ClusterKey::new`]: 48 hexadecimal characters (192 bits),
/// printable so that it can travel in an environment variable.
pub fn random_secret() -> String {
    let mut secret = [0u8; 24];
    ring::rand::SecureRandom::fill(&ring::rand::SystemRandom::new(), &mut secret)
        .expect("the system's random source works");
    secret.iter().map(|b| format!("{b:02x}")).collect()
}

impl std::fmt::Debug for ClusterKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ClusterKey(..)")
    }
}

/// One object of a [`Border`] message: its state, and whether the message hands it to
/// the receiver (a hand-off: the receiver owns it from this tick on; otherwise it is a
/// ghost the receiver only sees). On the wire, `yours` is the top bit of the flag byte.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BorderRecord {
    /// The object's state.
    pub state: ObjectState,
    /// Whether the receiver now owns it.
    pub yours: bool,
}

impl BorderRecord {
    /// A record that hands nothing (a ghost, or any record of a message that never
    /// hands objects: states, checkpoints, intents).
    pub fn seen(state: ObjectState) -> BorderRecord {
        BorderRecord { state, yours: false }
    }
}

/// One part of a zone's border state for one neighbour at one tick: the objects the
/// neighbour must see (ghosts) and those it now owns (hand-offs, `yours`).
#[derive(Clone, Debug, PartialEq)]
pub struct Border {
    /// The run (a cluster's epoch): messages of another run are refused.
    pub run: u64,
    /// The tick whose step these states start.
    pub tick: u64,
    /// The sender.
    pub from: ZoneId,
    /// The receiver.
    pub to: ZoneId,
    /// This part's index.
    pub part: u16,
    /// How many parts the sender sends this tick (at least 1, even with no objects).
    pub parts: u16,
    /// The objects, each with whether it is handed to the receiver.
    pub objects: Vec<BorderRecord>,
}

/// What a gateway asks of the zones for its players.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
#[repr(u16)]
pub enum IntentKind {
    /// A player's object enters the world: the zone whose region holds it adopts it.
    Join = 0,
    /// A player's newest action: whichever zone owns the object applies it.
    Action = 1,
    /// A player's object leaves the world: whichever zone owns it removes it.
    Leave = 2,
}

/// One message of intents of one kind, from one gateway, at one of its ticks. The
/// records are whole object states; a zone takes all of a join's, only the id and
/// action of an action's, only the id of a leave's.
#[derive(Clone, Debug, PartialEq)]
pub struct Intents {
    /// The gateway's incarnation (its start time in ms): a restarted gateway's intents
    /// supersede its earlier ones.
    pub incarnation: u64,
    /// The gateway's tick when it sent them (ordering within an incarnation).
    pub tick: u64,
    /// The gateway.
    pub gateway: u16,
    /// What they ask.
    pub kind: IntentKind,
    /// The players' objects.
    pub objects: Vec<ObjectState>,
}

/// What a zone process is doing, as its heartbeat says.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum ZoneState {
    /// Waiting for the supervisor's start.
    Waiting = 0,
    /// Stepping.
    Running = 1,
    /// A neighbour did not answer in time; waiting for a rollback.
    Stalled = 2,
    /// Reached the last tick of the run; its result is stored.
    Done = 3,
}

/// Every message of the fabric.
#[derive(Clone, Debug, PartialEq)]
pub enum Message {
    /// Zone to neighbour, every tick.
    Border(Border),
    /// A zone's advanced objects at `tick` (all the world's objects it stepped last), by
    /// id: checkpoints and results, kept in the checkpoint store.
    Checkpoint {
        /// The epoch that wrote it.
        run: u64,
        /// The world's tick.
        tick: u64,
        /// The zone.
        zone: ZoneId,
        /// The cuts the zone stepped the objects to `tick` with (the layout under which
        /// every zone's checkpoint of `tick` together is the world).
        cuts: Cuts,
        /// The objects.
        objects: Vec<ObjectState>,
    },
    /// Zone to supervisor, a few times a second.
    Heartbeat {
        /// The epoch the zone is in.
        run: u64,
        /// The tick it is at.
        tick: u64,
        /// The zone.
        zone: ZoneId,
        /// What it is doing.
        state: ZoneState,
        /// Its load and the cuts it follows.
        load: Load,
    },
    /// Supervisor to zones: stop stepping; epoch `run` will start.
    Halt {
        /// The coming epoch.
        run: u64,
    },
    /// Supervisor to zones: start epoch `run` from the checkpoint at `tick` (0 with no
    /// checkpoint: the generated world) with `cuts` (those every zone's checkpoint of
    /// `tick` holds).
    Start {
        /// The epoch.
        run: u64,
        /// The checkpoint's tick.
        tick: u64,
        /// The cuts the zones start with.
        cuts: Cuts,
    },
    /// Supervisor to zones: from tick `cut.apply_at` on, the cuts are `cut`'s
    /// ([`crate::rebalance::live`]).
    CutMove {
        /// The epoch it belongs to.
        run: u64,
        /// The move.
        cut: CutMove,
    },
    /// Zone to gateways, every tick: part of the objects the zone owns after the step
    /// that ended at `tick` (a [`Border`] whose `to` is [`ALL`] and with no hand-off).
    States(Border),
    /// Gateway to zones.
    Intents(Intents),
    /// Gateway to zones, every gateway tick: what its players can see.
    Subscription(Subscription),
    /// Zone to one gateway, every tick: what changed in its subscription.
    View(View),
    /// Gateway to gateways: a session of the account whose name hashes to `account`
    /// was admitted at `gateway` at `time_ms` (wall clock, ms since the Unix epoch).
    Claim {
        /// When.
        time_ms: u64,
        /// The account: [`crate::claims::account_hash`] of its name.
        account: u64,
        /// The gateway.
        gateway: u16,
    },
}

/// The `to` field of messages for every zone.
pub const ALL: ZoneId = ZoneId(u16::MAX);

#[derive(Clone, Copy)]
struct Head {
    kind: u8,
    run: u64,
    tick: u64,
    from: ZoneId,
    to: ZoneId,
    aux: [u16; 2],
}

/// The header of `h` with `count`, in a buffer with room for `body` more bytes and the
/// tag.
fn header(h: &Head, count: u32, body: usize) -> Vec<u8> {
    let mut b = Vec::with_capacity(HEADER_LEN + body + TAG_LEN);
    b.extend_from_slice(&MAGIC);
    b.push(VERSION);
    b.push(h.kind);
    b.extend_from_slice(&h.run.to_le_bytes());
    b.extend_from_slice(&h.tick.to_le_bytes());
    b.extend_from_slice(&h.from.0.to_le_bytes());
    b.extend_from_slice(&h.to.0.to_le_bytes());
    b.extend_from_slice(&h.aux[0].to_le_bytes());
    b.extend_from_slice(&h.aux[1].to_le_bytes());
    b.extend_from_slice(&count.to_le_bytes());
    b
}

fn encode_with(
    key: &ClusterKey,
    h: Head,
    records: impl ExactSizeIterator<Item = BorderRecord>,
) -> Result<Vec<u8>, WireError> {
    encode_with_prefix(key, h, &[], records)
}

/// A message whose body opens with `prefix` (a kind's fixed fields or cuts) before the
/// records.
fn encode_with_prefix(
    key: &ClusterKey,
    h: Head,
    prefix: &[u8],
    records: impl ExactSizeIterator<Item = BorderRecord>,
) -> Result<Vec<u8>, WireError> {
    let count = u32::try_from(records.len()).map_err(|_| WireError::Length { count: u32::MAX, actual: 0 })?;
    let mut b = header(&h, count, prefix.len() + records.len() * RECORD_LEN);
    b.extend_from_slice(prefix);
    for r in records {
        put_record(&mut b, r);
    }
    Ok(sign(key, &b))
}

/// Appends one record ([`RECORD_LEN`] bytes; the layout is in `docs/zones.md`).
pub(crate) fn put_record(b: &mut Vec<u8>, BorderRecord { state: o, yours }: BorderRecord) {
    b.extend_from_slice(&o.id.0.to_le_bytes());
    b.push(o.kind as u8);
    b.push(o.shape as u8);
    b.push(o.action);
    b.push(o.flags | if yours { YOURS } else { 0 });
    for v in [o.half.x, o.half.y, o.half.z, o.radius, o.pos.x, o.pos.y, o.pos.z, o.prev.x, o.prev.y, o.prev.z] {
        b.extend_from_slice(&v.to_le_bytes());
    }
}

/// Checks the tag of a signed blob that is not a fabric message (an intent log) and
/// returns what it signs.
pub(crate) fn verified<'a>(key: &ClusterKey, b: &'a [u8]) -> Result<&'a [u8], WireError> {
    if b.len() < TAG_LEN {
        return Err(WireError::Truncated(b.len()));
    }
    let (signed, tag) = b.split_at(b.len() - TAG_LEN);
    hmac::verify(&key.0, signed, tag).map_err(|_| WireError::Tag)?;
    Ok(signed)
}

/// Encodes and signs a border message.
pub fn encode_border(key: &ClusterKey, m: &Border) -> Result<Vec<u8>, WireError> {
    if m.parts == 0 || m.part >= m.parts {
        return Err(WireError::Part { part: m.part, parts: m.parts });
    }
    let h = Head { kind: KIND_BORDER, run: m.run, tick: m.tick, from: m.from, to: m.to, aux: [m.part, m.parts] };
    encode_with(key, h, m.objects.iter().copied())
}

/// Encodes and signs a checkpoint of `objects`, stepped to `tick` with `cuts`.
pub fn encode_checkpoint(
    key: &ClusterKey,
    run: u64,
    tick: u64,
    zone: ZoneId,
    cuts: &Cuts,
    objects: &[ObjectState],
) -> Result<Vec<u8>, WireError> {
    let (counts, prefix) = cut_block(cuts)?;
    let h = Head { kind: KIND_CHECKPOINT, run, tick, from: zone, to: zone, aux: counts };
    encode_with_prefix(key, h, &prefix, objects.iter().copied().map(BorderRecord::seen))
}

/// Encodes and signs the supervisor's cut move for epoch `run`.
pub fn encode_cut_move(key: &ClusterKey, run: u64, m: &CutMove) -> Result<Vec<u8>, WireError> {
    let (counts, cuts) = cut_block(&(m.xs.clone(), m.zs.clone()))?;
    let mut prefix = m.decided_at.to_le_bytes().to_vec();
    prefix.extend_from_slice(&cuts);
    let h = Head { kind: KIND_CUT_MOVE, run, tick: m.apply_at, from: ALL, to: ALL, aux: counts };
    encode_with_prefix(key, h, &prefix, std::iter::empty())
}

/// Encodes and signs a zone's states for the gateways (`m.to` must be [`ALL`], and no
/// object handed to anyone).
pub fn encode_states(key: &ClusterKey, m: &Border) -> Result<Vec<u8>, WireError> {
    if m.parts == 0 || m.part >= m.parts {
        return Err(WireError::Part { part: m.part, parts: m.parts });
    }
    if m.to != ALL || m.objects.iter().any(|r| r.yours) {
        return Err(WireError::Field("states header"));
    }
    let h = Head { kind: KIND_STATES, run: m.run, tick: m.tick, from: m.from, to: ALL, aux: [m.part, m.parts] };
    encode_with(key, h, m.objects.iter().copied())
}

/// Encodes and signs a gateway's intents.
pub fn encode_intents(key: &ClusterKey, m: &Intents) -> Result<Vec<u8>, WireError> {
    let h = Head {
        kind: KIND_INTENTS,
        run: m.incarnation,
        tick: m.tick,
        from: ZoneId(m.gateway),
        to: ALL,
        aux: [m.kind as u16, 0],
    };
    encode_with(key, h, m.objects.iter().copied().map(BorderRecord::seen))
}

/// Encodes and signs a message without objects (heartbeat, halt, start, claim, cut move).
pub fn encode_control(key: &ClusterKey, m: &Message) -> Result<Vec<u8>, WireError> {
    let (h, prefix) = match m {
        &Message::Heartbeat { run, tick, zone, state, load } => {
            (Head { kind: KIND_HEARTBEAT, run, tick, from: zone, to: ALL, aux: [state as u16, 0] }, load.to_bytes())
        }
        &Message::Halt { run } => (Head { kind: KIND_HALT, run, tick: 0, from: ALL, to: ALL, aux: [0, 0] }, vec![]),
        Message::Start { run, tick, cuts } => {
            let (counts, b) = cut_block(cuts)?;
            (Head { kind: KIND_START, run: *run, tick: *tick, from: ALL, to: ALL, aux: counts }, b)
        }
        &Message::Claim { time_ms, account, gateway } => {
            let h = Head { kind: KIND_CLAIM, run: time_ms, tick: account, from: ZoneId(gateway), to: ALL, aux: [0, 0] };
            (h, vec![])
        }
        Message::CutMove { run, cut } => return encode_cut_move(key, *run, cut),
        Message::Border(_)
        | Message::Checkpoint { .. }
        | Message::States(_)
        | Message::Intents(_)
        | Message::Subscription(_)
        | Message::View(_) => {
            return Err(WireError::Field("kind"));
        }
    };
    encode_with_prefix(key, h, &prefix, std::iter::empty())
}

/// Appends the tag of `signed` (header and body) under `key`: a message the cluster
/// would accept as authentic, whatever it holds (fuzzing reaches the parser this way).
pub fn sign(key: &ClusterKey, signed: &[u8]) -> Vec<u8> {
    let mut b = signed.to_vec();
    b.extend_from_slice(hmac::sign(&key.0, signed).as_ref());
    b
}

/// Encodes and signs any message (the inverse of [`decode`]).
pub fn encode(key: &ClusterKey, m: &Message) -> Result<Vec<u8>, WireError> {
    match m {
        Message::Border(b) => encode_border(key, b),
        Message::Checkpoint { run, tick, zone, cuts, objects } => {
            encode_checkpoint(key, *run, *tick, *zone, cuts, objects)
        }
        Message::States(b) => encode_states(key, b),
        Message::Intents(i) => encode_intents(key, i),
        Message::Subscription(s) => encode_subscription(key, s),
        Message::View(v) => encode_view(key, v),
        _ => encode_control(key, m),
    }
}

fn u16_at(b: &[u8], at: usize) -> u16 {
    u16::from_le_bytes([b[at], b[at + 1]])
}
fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().expect("4 bytes"))
}
fn u64_at(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(b[at..at + 8].try_into().expect("8 bytes"))
}
fn f32_at(b: &[u8], at: usize) -> f32 {
    f32::from_le_bytes(b[at..at + 4].try_into().expect("4 bytes"))
}

/// Decodes and checks one record ([`RECORD_LEN`] bytes), the `index`-th of its message.
pub(crate) fn record(index: usize, r: &[u8]) -> Result<BorderRecord, WireError> {
    let bad = |reason: String| WireError::Record { index, reason };
    let kind = match r[4] {
        0 => ObjectKind::Npc,
        1 => ObjectKind::User,
        k => return Err(bad(format!("object kind {k}"))),
    };
    let shape = ShapeKind::from_u8(r[5]).ok_or_else(|| bad(format!("shape {}", r[5])))?;
    let f = |i: usize| f32_at(r, 8 + 4 * i);
    let o = ObjectState {
        id: EntityId(u32_at(r, 0)),
        kind,
        shape,
        action: r[6],
        flags: r[7] & !YOURS,
        half: Vec3::new(f(0), f(1), f(2)),
        radius: f(3),
        pos: Vec3::new(f(4), f(5), f(6)),
        prev: Vec3::new(f(7), f(8), f(9)),
    };
    o.validate().map_err(|e| bad(e.to_string()))?;
    debug_assert_eq!(o.flags & !(flags::ON_TERRAIN | flags::SUPPORTED), 0);
    Ok(BorderRecord { state: o, yours: r[7] & YOURS != 0 })
}

/// Records that hand nothing to anyone: the hand-off bit must be clear, so that a
/// message has one encoding (found by fuzzing, for checkpoints).
fn plain(records: impl Iterator<Item = Result<BorderRecord, WireError>>) -> Result<Vec<ObjectState>, WireError> {
    records
        .enumerate()
        .map(|(index, r)| match r {
            Ok(BorderRecord { yours: true, .. }) => {
                Err(WireError::Record { index, reason: "hand-off bit where nothing is handed".into() })
            }
            Ok(BorderRecord { state, yours: false }) => Ok(state),
            Err(e) => Err(e),
        })
        .collect()
}

/// Checks the tag, then decodes a message. Nothing of an unauthenticated message is
/// parsed beyond the magic and version.
pub fn decode(key: &ClusterKey, b: &[u8]) -> Result<Message, WireError> {
    if b.len() < HEADER_LEN + TAG_LEN {
        return Err(WireError::Truncated(b.len()));
    }
    if b[..2] != MAGIC {
        return Err(WireError::Magic);
    }
    if b[2] != VERSION {
        return Err(WireError::Version(b[2]));
    }
    let (signed, tag) = b.split_at(b.len() - TAG_LEN);
    hmac::verify(&key.0, signed, tag).map_err(|_| WireError::Tag)?;
    let (run, tick) = (u64_at(signed, 4), u64_at(signed, 12));
    let (from, to) = (ZoneId(u16_at(signed, 20)), ZoneId(u16_at(signed, 22)));
    let (aux0, aux1, count) = (u16_at(signed, 24), u16_at(signed, 26), u32_at(signed, 28));
    // Bytes before the records: a kind's fixed fields, or the cuts the header counts.
    let cut_bytes = 4 * (aux0 as u64 + aux1 as u64);
    let prefix = match signed[3] {
        KIND_HEARTBEAT => LOAD_LEN as u64,
        KIND_CHECKPOINT | KIND_START => cut_bytes,
        KIND_CUT_MOVE => 8 + cut_bytes,
        _ => 0,
    };
    let body = &signed[HEADER_LEN..];
    // The kinds of states by interest have bodies of their own.
    if let k @ (KIND_SUBSCRIPTION | KIND_VIEW | KIND_VIEW_PACKED) = signed[3] {
        let f = interest::Fields { run, tick, from, to, aux0, aux1, count };
        return match k {
            KIND_SUBSCRIPTION => interest::decode_subscription(&f, body).map(Message::Subscription),
            KIND_VIEW => interest::decode_view(&f, body).map(Message::View),
            _ => interest::decode_packed_view(&f, body).map(Message::View),
        };
    }
    if body.len() as u64 != prefix + count as u64 * RECORD_LEN as u64 {
        return Err(WireError::Length { count, actual: body.len() });
    }
    let (fixed, body) = body.split_at(prefix as usize);
    let records = || body.chunks_exact(RECORD_LEN).enumerate().map(|(i, r)| record(i, r));
    let none = |ok: bool, field| if ok { Ok(()) } else { Err(WireError::Field(field)) };
    match signed[3] {
        KIND_BORDER => {
            if aux1 == 0 || aux0 >= aux1 {
                return Err(WireError::Part { part: aux0, parts: aux1 });
            }
            let objects = records().collect::<Result<Vec<_>, _>>()?;
            Ok(Message::Border(Border { run, tick, from, to, part: aux0, parts: aux1, objects }))
        }
        KIND_CHECKPOINT => {
            none(from == to, "checkpoint header")?;
            let cuts = read_cuts(fixed, [aux0, aux1])?;
            let objects = plain(records())?;
            Ok(Message::Checkpoint { run, tick, zone: from, cuts, objects })
        }
        KIND_STATES => {
            if aux1 == 0 || aux0 >= aux1 {
                return Err(WireError::Part { part: aux0, parts: aux1 });
            }
            none(to == ALL && from != ALL, "states header")?;
            let objects = plain(records())?.into_iter().map(BorderRecord::seen).collect();
            Ok(Message::States(Border { run, tick, from, to, part: aux0, parts: aux1, objects }))
        }
        KIND_INTENTS => {
            none(to == ALL && aux1 == 0, "intents header")?;
            let kind = match aux0 {
                0 => IntentKind::Join,
                1 => IntentKind::Action,
                2 => IntentKind::Leave,
                _ => return Err(WireError::Field("intent kind")),
            };
            let objects = plain(records())?;
            Ok(Message::Intents(Intents { incarnation: run, tick, gateway: from.0, kind, objects }))
        }
        KIND_HEARTBEAT => {
            none(count == 0 && aux1 == 0 && to == ALL, "heartbeat header")?;
            let load = Load::from_bytes(fixed);
            let state = match aux0 {
                0 => ZoneState::Waiting,
                1 => ZoneState::Running,
                2 => ZoneState::Stalled,
                3 => ZoneState::Done,
                _ => return Err(WireError::Field("state")),
            };
            Ok(Message::Heartbeat { run, tick, zone: from, state, load })
        }
        KIND_HALT => {
            none(count == 0 && aux0 == 0 && aux1 == 0 && tick == 0 && from == ALL && to == ALL, "halt header")?;
            Ok(Message::Halt { run })
        }
        KIND_CLAIM => {
            none(count == 0 && aux0 == 0 && aux1 == 0 && to == ALL, "claim header")?;
            Ok(Message::Claim { time_ms: run, account: tick, gateway: from.0 })
        }
        KIND_START => {
            none(count == 0 && from == ALL && to == ALL, "start header")?;
            Ok(Message::Start { run, tick, cuts: read_cuts(fixed, [aux0, aux1])? })
        }
        KIND_CUT_MOVE => {
            none(count == 0 && from == ALL && to == ALL, "cut move header")?;
            let (xs, zs) = read_cuts(&fixed[8..], [aux0, aux1])?;
            let cut = CutMove { decided_at: u64_at(fixed, 0), apply_at: tick, xs, zs };
            Ok(Message::CutMove { run, cut })
        }
        k => Err(WireError::Kind(k)),
    }
}

#[cfg(test)]
mod tests;
