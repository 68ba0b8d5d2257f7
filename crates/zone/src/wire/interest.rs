//! The messages of states by interest (`docs/zones.md`, "States by interest"): a
//! gateway's [`Subscription`] (the cells its players can see, and the last zones' tick it
//! has whole), to every zone, and a zone's [`View`] for one gateway (what changed in
//! those cells since that tick, and what left them).
//!
//! Both share the fabric's header and tag; their bodies are their own (not 48-byte
//! records only), so their lengths are checked here, after the tag, like every other
//! field: every body has exactly one encoding.
//!
//! **Packed views.** A view's body of 512 bytes or more travels compressed (zstd, kind
//! [`KIND_VIEW_PACKED`]) whenever that makes it smaller: its nudges are mostly small
//! integers in a few bytes each, and its whole records carry positions near one
//! another, which a general compressor shortens by about a fifth (`docs/zones.md`, "Packed views"). The tag covers
//! the packed bytes, so nothing is unpacked before the sender is known; the plain body
//! inside has the one encoding above, and a packed view that unpacks to anything else,
//! or to more than its stated length, is refused.

use myriad_core::{Action, EntityId, ObjectState, Vec3};

use super::nudge::{Nudge, nudges, nudges_len, put_nudges};
use super::{ALL, ClusterKey, HEADER_LEN, Head, RECORD_LEN, WireError, header, plain, record, sign};
use crate::layout::ZoneId;

/// Message kind: a gateway's subscription, to every zone.
pub const KIND_SUBSCRIPTION: u8 = 10;
/// Message kind: a zone's view for one gateway.
pub const KIND_VIEW: u8 = 11;
/// Message kind: a zone's view for one gateway, its body packed: the plain body's length
/// (4 bytes) and the plain body compressed as one zstd frame.
pub const KIND_VIEW_PACKED: u8 = 12;
/// The longest plain body a packed view may state (the fabric's messages are far
/// smaller; this bounds what an authenticated but faulty sender can make a gateway
/// allocate).
pub const MAX_PACKED_VIEW_BODY: usize = 64 << 20;
/// zstd's level for views: its fastest, which already takes most of what higher levels
/// do on these bodies (level 3 packed 0.7 % more, measured) at a fraction of the time.
const VIEW_PACK_LEVEL: i32 = 1;
/// Bodies shorter than this travel plain: a zstd frame's own bytes take most of what it
/// could save there, and the time is better spent elsewhere.
const VIEW_PACK_MIN: usize = 512;
/// Most cells a subscription's grid may have (a 32 KiB bit set).
pub const MAX_CELLS: u64 = 1 << 18;
/// Bytes of a subscription's body before its cells.
const SUBSCRIPTION_FIXED: usize = 32;
/// Bytes of a view's body before its records: base, counts of gone ids, moves, nudges
/// and acts, and the nudges' bytes.
pub const VIEW_FIXED: usize = 28;
/// Bytes of a move: id and position.
pub const MOVE_LEN: usize = 16;
/// Bytes of an act: id and action.
pub const ACT_LEN: usize = 5;
/// A subscription's `resyncs` stay below this (they share a word with a flag).
pub const MAX_RESYNCS: u32 = 1 << 31;
/// A view's base when it is whole (the gateway drops what it had of the zone).
const WHOLE: u64 = u64::MAX;

/// What a gateway's players can see, as cells of a grid over the world, and how far it
/// has followed the zones. Sent to every zone every gateway tick.
#[derive(Clone, Debug, PartialEq)]
pub struct Subscription {
    /// The gateway's incarnation (its start time in ms): a restarted gateway is a new
    /// subscriber, which gets whole views.
    pub incarnation: u64,
    /// The gateway.
    pub gateway: u16,
    /// Grows by one whenever the cells change (a zone refuses an older one).
    pub version: u64,
    /// The zones' run and the last tick of it whose views this gateway has taken whole,
    /// from every zone: a zone sends what changed since then. `None`: nothing yet.
    pub confirmed: Option<(u64, u64)>,
    /// How many times the gateway found a zone's chain of views broken (a view it needed
    /// was lost), below 2^31: each new value asks every zone for its next view relative
    /// to `confirmed` (`crate::views`, "Bases").
    pub resyncs: u32,
    /// The grid's cell side, in world units (the grid starts at the world's lower x and
    /// z bounds).
    pub cell: f32,
    /// The grid's columns (along x).
    pub cols: u16,
    /// The grid's rows (along z).
    pub rows: u16,
    /// One bit per cell, row-major (cell `row × cols + col` is bit `i % 8` of byte
    /// `i / 8`); the bits past the last cell are zero.
    pub cells: Vec<u8>,
    /// The fingerprint of the gateway's terrain and bounds
    /// ([`crate::wire::ground_fingerprint`]; 0: none): a zone whose world has the same
    /// predicts its nudges on the ground.
    pub ground: u64,
}

/// One part of what a zone sends one gateway after a step: its owned objects in the
/// gateway's cells (and the gateway's own players, wherever they are) whose state the
/// gateway lacks, and the ids of those it must drop.
#[derive(Clone, Debug, PartialEq)]
pub struct View {
    /// The zones' run.
    pub run: u64,
    /// The zone's tick after the step.
    pub tick: u64,
    /// The zone.
    pub zone: ZoneId,
    /// The gateway.
    pub gateway: u16,
    /// This part's index.
    pub part: u16,
    /// Parts of this zone's view of this tick (at least 1, even when empty).
    pub parts: u16,
    /// `None`: the whole view (the gateway replaces what it had of this zone); `Some(c)`:
    /// the changes since tick `c`, which the gateway has whole.
    pub base: Option<u64>,
    /// Whole states, ids ascending: objects that entered the view, and the gateway's
    /// own players.
    pub objects: Vec<ObjectState>,
    /// New positions of objects the gateway already holds (ids ascending): all that
    /// changes of an object a gateway shows, in a third of a whole record. None in a
    /// whole view.
    pub moves: Vec<(EntityId, Vec3)>,
    /// New positions of objects the gateway already holds, as the change of their bits
    /// since their state at `base` (ids ascending, none also among `moves`): the same as
    /// a move, in 1 to [`crate::wire::NUDGE_MAX_LEN`] bytes. None in a whole view.
    pub nudges: Vec<Nudge>,
    /// Objects of this zone the gateway must drop (they left its cells, or the zone),
    /// ids ascending; none in a whole view.
    pub gone: Vec<EntityId>,
    /// The new actions of objects the gateway holds (ids ascending), which ground nudges
    /// read: the gateway applies them before the tick's moves and nudges. None in a
    /// whole view.
    pub acts: Vec<(EntityId, u8)>,
}

/// Bytes of the bit set of `cols × rows` cells.
pub fn cell_bytes(cols: u16, rows: u16) -> usize {
    (usize::from(cols) * usize::from(rows)).div_ceil(8)
}

/// Encodes and signs a subscription.
pub fn encode_subscription(key: &ClusterKey, s: &Subscription) -> Result<Vec<u8>, WireError> {
    let n = u64::from(s.cols) * u64::from(s.rows);
    if n == 0 || n > MAX_CELLS {
        return Err(WireError::Cells(n));
    }
    if s.cells.len() != cell_bytes(s.cols, s.rows)
        || s.resyncs >= MAX_RESYNCS
        || !tail_clear(&s.cells, n)
        || s.gateway == ALL.0
        || !(s.cell.is_finite() && s.cell > 0.0)
    {
        return Err(WireError::Field("subscription"));
    }
    let len = SUBSCRIPTION_FIXED + s.cells.len();
    let h = Head {
        kind: KIND_SUBSCRIPTION,
        run: s.incarnation,
        tick: s.version,
        from: ZoneId(s.gateway),
        to: ALL,
        aux: [s.cols, s.rows],
    };
    let mut b = header(&h, len as u32, len);
    let (run, tick) = s.confirmed.unwrap_or((0, 0));
    // The confirmation's flag and the resyncs share a word: bit 0 and the rest.
    b.extend_from_slice(&(s.resyncs << 1 | u32::from(s.confirmed.is_some())).to_le_bytes());
    b.extend_from_slice(&s.cell.to_le_bytes());
    b.extend_from_slice(&run.to_le_bytes());
    b.extend_from_slice(&tick.to_le_bytes());
    b.extend_from_slice(&s.ground.to_le_bytes());
    b.extend_from_slice(&s.cells);
    Ok(sign(key, &b))
}

/// Whether the bits past the last of `n` cells are zero (one encoding per set).
fn tail_clear(cells: &[u8], n: u64) -> bool {
    let used = (n % 8) as u32;
    used == 0 || cells.last().is_none_or(|b| b >> used == 0)
}

/// Encodes and signs one part of a view.
pub fn encode_view(key: &ClusterKey, v: &View) -> Result<Vec<u8>, WireError> {
    if v.parts == 0 || v.part >= v.parts {
        return Err(WireError::Part { part: v.part, parts: v.parts });
    }
    let whole_with_changes =
        v.base.is_none() && !(v.gone.is_empty() && v.moves.is_empty() && v.nudges.is_empty() && v.acts.is_empty());
    if v.gateway == ALL.0 || v.zone == ALL || whole_with_changes || v.base == Some(WHOLE) {
        return Err(WireError::Field("view"));
    }
    let ascending = |ids: &mut dyn Iterator<Item = EntityId>| {
        let ids: Vec<EntityId> = ids.collect();
        ids.windows(2).all(|w| w[0] < w[1])
    };
    if !ascending(&mut v.objects.iter().map(|o| o.id))
        || !ascending(&mut v.moves.iter().map(|m| m.0))
        || !ascending(&mut v.gone.iter().copied())
        || !ascending(&mut v.nudges.iter().map(|n| n.id))
        || !ascending(&mut v.acts.iter().map(|a| a.0))
        || overlap(&v.moves, &v.nudges)
    {
        return Err(WireError::Field("view ids"));
    }
    if v.moves.iter().any(|(_, p)| !p.is_finite()) {
        return Err(WireError::Field("view moves"));
    }
    if v.acts.iter().any(|&(_, a)| Action::from_bits(a).is_none()) {
        return Err(WireError::Field("view acts"));
    }
    let count = u32::try_from(v.objects.len()).map_err(|_| WireError::Field("view records"))?;
    let gone = u32::try_from(v.gone.len()).map_err(|_| WireError::Field("view gone"))?;
    let moves = u32::try_from(v.moves.len()).map_err(|_| WireError::Field("view moves"))?;
    let nudges = u32::try_from(v.nudges.len()).map_err(|_| WireError::Field("view nudges"))?;
    let acts = u32::try_from(v.acts.len()).map_err(|_| WireError::Field("view acts"))?;
    let nudge_bytes = nudges_len(&v.nudges);
    let nudge_len = u32::try_from(nudge_bytes).map_err(|_| WireError::Field("view nudges"))?;
    let h =
        Head { kind: KIND_VIEW, run: v.run, tick: v.tick, from: v.zone, to: ZoneId(v.gateway), aux: [v.part, v.parts] };
    let body = VIEW_FIXED
        + v.objects.len() * RECORD_LEN
        + v.moves.len() * MOVE_LEN
        + v.gone.len() * 4
        + v.acts.len() * ACT_LEN
        + nudge_bytes;
    let mut b = header(&h, count, body);
    b.extend_from_slice(&v.base.unwrap_or(WHOLE).to_le_bytes());
    b.extend_from_slice(&gone.to_le_bytes());
    b.extend_from_slice(&moves.to_le_bytes());
    b.extend_from_slice(&nudges.to_le_bytes());
    b.extend_from_slice(&nudge_len.to_le_bytes());
    b.extend_from_slice(&acts.to_le_bytes());
    for o in &v.objects {
        super::put_record(&mut b, super::BorderRecord::seen(*o));
    }
    for (id, p) in &v.moves {
        b.extend_from_slice(&id.0.to_le_bytes());
        for c in [p.x, p.y, p.z] {
            b.extend_from_slice(&c.to_le_bytes());
        }
    }
    for id in &v.gone {
        b.extend_from_slice(&id.0.to_le_bytes());
    }
    for (id, action) in &v.acts {
        b.extend_from_slice(&id.0.to_le_bytes());
        b.push(*action);
    }
    put_nudges(&mut b, &v.nudges);
    Ok(sign(key, &pack_view(h, count, b)))
}

/// `plain` (a view's header and body), or, when that is smaller, the packed view of the
/// same body.
fn pack_view(h: Head, count: u32, plain: Vec<u8>) -> Vec<u8> {
    let body = &plain[HEADER_LEN..];
    // Past the bound a decoder takes, the plain view goes (no fabric carries one).
    if !(VIEW_PACK_MIN..=MAX_PACKED_VIEW_BODY).contains(&body.len()) {
        return plain;
    }
    // Compression into memory cannot fail for a body this size; if it ever did, the
    // plain view still says everything.
    let Ok(packed) = zstd::bulk::compress(body, VIEW_PACK_LEVEL) else { return plain };
    if 4 + packed.len() >= body.len() {
        return plain;
    }
    let mut b = header(&Head { kind: KIND_VIEW_PACKED, ..h }, count, 4 + packed.len());
    b.extend_from_slice(&(body.len() as u32).to_le_bytes());
    b.extend_from_slice(&packed);
    b
}

/// Whether an object is both moved and nudged (both lists ids ascending).
fn overlap(moves: &[(EntityId, Vec3)], nudges: &[Nudge]) -> bool {
    let (mut i, mut j) = (0, 0);
    while i < moves.len() && j < nudges.len() {
        match moves[i].0.cmp(&nudges[j].id) {
            std::cmp::Ordering::Less => i += 1,
            std::cmp::Ordering::Greater => j += 1,
            std::cmp::Ordering::Equal => return true,
        }
    }
    false
}

/// The header's fields, as [`super::decode`] reads them.
pub(super) struct Fields {
    pub run: u64,
    pub tick: u64,
    pub from: ZoneId,
    pub to: ZoneId,
    pub aux0: u16,
    pub aux1: u16,
    pub count: u32,
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().expect("4 bytes"))
}
fn u64_at(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(b[at..at + 8].try_into().expect("8 bytes"))
}

/// Decodes an authenticated subscription's body.
pub(super) fn decode_subscription(f: &Fields, body: &[u8]) -> Result<Subscription, WireError> {
    let (cols, rows) = (f.aux0, f.aux1);
    let n = u64::from(cols) * u64::from(rows);
    if n == 0 || n > MAX_CELLS {
        return Err(WireError::Cells(n));
    }
    let len = SUBSCRIPTION_FIXED + cell_bytes(cols, rows);
    if body.len() != len || f.count as usize != len {
        return Err(WireError::Length { count: f.count, actual: body.len() });
    }
    if f.to != ALL || f.from == ALL {
        return Err(WireError::Field("subscription header"));
    }
    let word = u32_at(body, 0);
    let confirmed = match word & 1 {
        0 if u64_at(body, 8) == 0 && u64_at(body, 16) == 0 => None,
        1 => Some((u64_at(body, 8), u64_at(body, 16))),
        _ => return Err(WireError::Field("subscription confirmation")),
    };
    let resyncs = word >> 1;
    let cell = f32::from_le_bytes(body[4..8].try_into().expect("4 bytes"));
    if !(cell.is_finite() && cell > 0.0) {
        return Err(WireError::Field("subscription cell"));
    }
    let ground = u64_at(body, 24);
    let cells = body[SUBSCRIPTION_FIXED..].to_vec();
    if !tail_clear(&cells, n) {
        return Err(WireError::Field("subscription cells"));
    }
    Ok(Subscription {
        incarnation: f.run,
        gateway: f.from.0,
        version: f.tick,
        confirmed,
        resyncs,
        cell,
        cols,
        rows,
        cells,
        ground,
    })
}

/// Decodes an authenticated packed view's body: unpacks it within its stated length,
/// then decodes the plain body.
pub(super) fn decode_packed_view(f: &Fields, body: &[u8]) -> Result<View, WireError> {
    if body.len() < 4 {
        return Err(WireError::Length { count: f.count, actual: body.len() });
    }
    let stated = u32_at(body, 0) as usize;
    if !(VIEW_FIXED..=MAX_PACKED_VIEW_BODY).contains(&stated) {
        return Err(WireError::Field("packed view length"));
    }
    // `decompress` fails when the frame unpacks to more than `stated` bytes.
    let plain = zstd::bulk::decompress(&body[4..], stated).map_err(|_| WireError::Field("packed view"))?;
    if plain.len() != stated {
        return Err(WireError::Field("packed view length"));
    }
    decode_view(f, &plain)
}

/// Decodes an authenticated view's body.
pub(super) fn decode_view(f: &Fields, body: &[u8]) -> Result<View, WireError> {
    if f.aux1 == 0 || f.aux0 >= f.aux1 {
        return Err(WireError::Part { part: f.aux0, parts: f.aux1 });
    }
    if f.to == ALL || f.from == ALL {
        return Err(WireError::Field("view header"));
    }
    if body.len() < VIEW_FIXED {
        return Err(WireError::Length { count: f.count, actual: body.len() });
    }
    let base = u64_at(body, 0);
    let (gone, moves, nudge_count, nudge_bytes, acts) =
        (u32_at(body, 8), u32_at(body, 12), u32_at(body, 16), u32_at(body, 20), u32_at(body, 24));
    let expected = VIEW_FIXED as u64
        + u64::from(f.count) * RECORD_LEN as u64
        + u64::from(moves) * MOVE_LEN as u64
        + u64::from(gone) * 4
        + u64::from(acts) * ACT_LEN as u64
        + u64::from(nudge_bytes);
    if body.len() as u64 != expected {
        return Err(WireError::Length { count: f.count, actual: body.len() });
    }
    if base == WHOLE && (gone != 0 || moves != 0 || nudge_count != 0 || acts != 0) {
        return Err(WireError::Field("view body"));
    }
    let records_end = VIEW_FIXED + f.count as usize * RECORD_LEN;
    let moves_end = records_end + moves as usize * MOVE_LEN;
    let objects = plain(body[VIEW_FIXED..records_end].chunks_exact(RECORD_LEN).enumerate().map(|(i, r)| record(i, r)))?;
    let f32_at = |b: &[u8], at: usize| f32::from_le_bytes(b[at..at + 4].try_into().expect("4 bytes"));
    let moves: Vec<(EntityId, Vec3)> = body[records_end..moves_end]
        .chunks_exact(MOVE_LEN)
        .map(|m| (EntityId(u32_at(m, 0)), Vec3::new(f32_at(m, 4), f32_at(m, 8), f32_at(m, 12))))
        .collect();
    let gone_end = moves_end + gone as usize * 4;
    let gone: Vec<EntityId> = body[moves_end..gone_end]
        .chunks_exact(4)
        .map(|b| EntityId(u32::from_le_bytes(b.try_into().expect("4"))))
        .collect();
    let acts_end = gone_end + acts as usize * ACT_LEN;
    let acts: Vec<(EntityId, u8)> =
        body[gone_end..acts_end].chunks_exact(ACT_LEN).map(|a| (EntityId(u32_at(a, 0)), a[4])).collect();
    if acts.iter().any(|&(_, a)| Action::from_bits(a).is_none()) {
        return Err(WireError::Field("view acts"));
    }
    let nudges = nudges(&body[acts_end..], nudge_count)?;
    if objects.windows(2).any(|w| w[0].id >= w[1].id)
        || moves.windows(2).any(|w| w[0].0 >= w[1].0)
        || gone.windows(2).any(|w| w[0] >= w[1])
        || acts.windows(2).any(|w| w[0].0 >= w[1].0)
        || overlap(&moves, &nudges)
    {
        return Err(WireError::Field("view ids"));
    }
    if moves.iter().any(|(_, p)| !p.is_finite()) {
        return Err(WireError::Field("view moves"));
    }
    Ok(View {
        run: f.run,
        tick: f.tick,
        zone: f.from,
        gateway: f.to.0,
        part: f.aux0,
        parts: f.aux1,
        base: (base != WHOLE).then_some(base),
        objects,
        moves,
        nudges,
        gone,
        acts,
    })
}
