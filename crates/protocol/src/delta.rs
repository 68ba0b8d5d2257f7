//! Delta state updates: each record carries an object relative to a state of it the
//! client acknowledged (its *baseline*), or absolute when there is none.
//!
//! # Body layout (all little-endian)
//!
//! ```text
//! offset  size  field
//!      0     8  server tick (u64)
//!      8     2  time dilation in 1/1000 (u16)
//!     10    12  origin x, y, z (i32 each, 1/64 unit), normally the AOI centre
//!     22     2  record count (u16)
//!     24     …  records, ids strictly increasing
//! ```
//!
//! # Records
//!
//! A form byte, the id as an unsigned LEB128 varint of the *gap* (the first record's id
//! itself, each later one `id - previous id - 1`), then the form's payload:
//!
//! | form (bits 0–1) | bits 2–7 | payload | meaning |
//! | --- | --- | --- | --- |
//! | 0 `Delta` | back (1–63) | 3 × i8 | baseline + (dx, dy, dz), 1/64 unit |
//! | 1 `Same` | back (1–63) | none | the baseline's position, unchanged |
//! | 2 `Near` | bits 2–3 shape kind, 4–7 zero | 3 × i16 | origin + offset |
//! | 3 `Far` | bits 2–3 shape kind, 4–7 zero | 3 × i32 | absolute position |
//!
//! The baseline of a `Delta` or `Same` record is the state of the same object that the
//! client received in the update of tick `tick - back`; its shape kind carries over. A
//! client that does not hold that state skips the record (its state is only delayed,
//! never corrupted: [`Baselines`]). A varint is at most 10 bytes and has exactly one
//! encoding (no trailing zero groups); as in version 1, a body ends with its last record.
//!
//! [`DeltaRecord::choose`] picks the smallest form that carries the position exactly:
//! `Same` (1 byte and the id), `Delta` for moves up to ±127/64 units per axis (4 bytes and
//! the id), `Near` (7) within ±512 units of the origin, `Far` (13) anywhere.

use std::collections::VecDeque;

use crate::batch::DatagramBatch;
use crate::error::DecodeError;
use crate::header::{HEADER_LEN, MAX_BODY, MAX_DATAGRAM, PROTOCOL_VERSION, PacketKind, TAG_LEN};
use crate::quant::QuantPos;
use crate::update::{ShapeKind, StateRecord, UpdateHeader, read_header_fields, write_header_fields};
use crate::wire::Reader;

/// Length of a delta update's own header, at the start of its body.
pub const DELTA_HEADER_LEN: usize = 24;

/// The oldest baseline a record may name, in ticks before its update's tick. A client
/// keeps every state it received for this many ticks behind the newest tick it saw.
pub const MAX_BACK: u64 = 63;

/// Most bytes one record can take: the form byte, a 10-byte varint and 12 bytes of
/// `Far` position.
pub const MAX_RECORD_LEN: usize = 1 + 10 + 12;

const DELTA: u8 = 0;
const SAME: u8 = 1;
const NEAR: u8 = 2;
const FAR: u8 = 3;

/// A state the client holds and acknowledged, which a record may be relative to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Baseline {
    /// The tick of the update that carried it.
    pub tick: u64,
    /// The position it carried.
    pub pos: QuantPos,
}

/// How a record carries its object.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum RecordState {
    /// The baseline `back` ticks ago moved by `d` (1/64 unit per axis).
    Delta {
        /// Ticks between the baseline and this update (1..=[`MAX_BACK`]).
        back: u8,
        /// Position minus the baseline's.
        d: [i8; 3],
    },
    /// The baseline `back` ticks ago, unchanged.
    Same {
        /// Ticks between the baseline and this update (1..=[`MAX_BACK`]).
        back: u8,
    },
    /// An absolute state (written `Near` or `Far` depending on the origin).
    Absolute {
        /// The object's shape.
        kind: ShapeKind,
        /// Its position.
        pos: QuantPos,
    },
}

/// One object in a delta update.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct DeltaRecord {
    /// The object's id.
    pub id: u64,
    /// Its state.
    pub state: RecordState,
}

impl DeltaRecord {
    /// The smallest record carrying object `id` (shape `kind`) at `pos` in the update of
    /// `tick`, relative to `baseline` if there is one within [`MAX_BACK`] ticks.
    pub fn choose(id: u64, kind: ShapeKind, pos: QuantPos, tick: u64, baseline: Option<Baseline>) -> Self {
        let relative = baseline.and_then(|b| {
            let back = tick.checked_sub(b.tick).filter(|back| (1..=MAX_BACK).contains(back))? as u8;
            if b.pos == pos {
                return Some(RecordState::Same { back });
            }
            let d = |a: i32, b: i32| i8::try_from(i64::from(a) - i64::from(b)).ok();
            Some(RecordState::Delta { back, d: [d(pos.x, b.pos.x)?, d(pos.y, b.pos.y)?, d(pos.z, b.pos.z)?] })
        });
        Self { id, state: relative.unwrap_or(RecordState::Absolute { kind, pos }) }
    }

    /// Bytes this record takes after a record of id `previous` (`None`: first in its
    /// datagram), against `origin`. `previous` must be below `self.id`.
    pub fn encoded_len(&self, previous: Option<u64>, origin: QuantPos) -> usize {
        1 + varint_len(gap(previous, self.id))
            + match self.state {
                RecordState::Delta { .. } => 3,
                RecordState::Same { .. } => 0,
                RecordState::Absolute { pos, .. } => {
                    if pos.offset_from(origin).is_some() {
                        6
                    } else {
                        12
                    }
                }
            }
    }

    /// Writes the record after one of id `previous` at the start of `out`; returns the
    /// bytes written, or `None` (writing nothing) if `out` is too short.
    fn write(&self, previous: Option<u64>, origin: QuantPos, out: &mut [u8]) -> Option<usize> {
        let len = self.encoded_len(previous, origin);
        let out = out.get_mut(..len)?;
        let form = match self.state {
            RecordState::Delta { back, .. } => DELTA | back << 2,
            RecordState::Same { back } => SAME | back << 2,
            RecordState::Absolute { kind, pos } if pos.offset_from(origin).is_some() => NEAR | (kind as u8) << 2,
            RecordState::Absolute { kind, .. } => FAR | (kind as u8) << 2,
        };
        out[0] = form;
        let at = 1 + write_varint(gap(previous, self.id), &mut out[1..]);
        let payload = &mut out[at..];
        match self.state {
            RecordState::Delta { d, .. } => payload.copy_from_slice(&d.map(|v| v as u8)),
            RecordState::Same { .. } => {}
            RecordState::Absolute { pos, .. } => match pos.offset_from(origin) {
                Some(o) => {
                    for (chunk, v) in payload.chunks_exact_mut(2).zip(o) {
                        chunk.copy_from_slice(&v.to_le_bytes());
                    }
                }
                None => {
                    for (chunk, v) in payload.chunks_exact_mut(4).zip([pos.x, pos.y, pos.z]) {
                        chunk.copy_from_slice(&v.to_le_bytes());
                    }
                }
            },
        }
        Some(len)
    }

    fn read(r: &mut Reader<'_>, previous: Option<u64>, origin: QuantPos) -> Result<Self, DecodeError> {
        let form = r.u8()?;
        let gap = r.varint()?;
        let id = match previous {
            None => gap,
            Some(p) => p.checked_add(1).and_then(|n| n.checked_add(gap)).ok_or(DecodeError::IdOverflow)?,
        };
        let back = form >> 2;
        let state = match form & 3 {
            DELTA | SAME if !(1..=MAX_BACK as u8).contains(&back) => return Err(DecodeError::BadBack(back)),
            DELTA => RecordState::Delta { back, d: [r.u8()? as i8, r.u8()? as i8, r.u8()? as i8] },
            SAME => RecordState::Same { back },
            _ if form >> 4 != 0 => return Err(DecodeError::ReservedBits(u32::from(form))),
            code => {
                let kind = ShapeKind::from_code(back & 3).ok_or(DecodeError::BadShapeKind(back & 3))?;
                let pos = if code == NEAR {
                    QuantPos::add_offset(origin, [r.i16()?, r.i16()?, r.i16()?])
                } else {
                    QuantPos::new(r.i32()?, r.i32()?, r.i32()?)
                };
                RecordState::Absolute { kind, pos }
            }
        };
        Ok(Self { id, state })
    }
}

/// The id field's value: the id itself first, then the gap less one.
fn gap(previous: Option<u64>, id: u64) -> u64 {
    previous.map_or(id, |p| id.wrapping_sub(p).wrapping_sub(1))
}

/// Bytes of the LEB128 encoding of `v`.
fn varint_len(v: u64) -> usize {
    (64 - (v | 1).leading_zeros() as usize).div_ceil(7)
}

/// Writes `v` as LEB128 at the start of `out` (which must hold [`varint_len`] bytes).
fn write_varint(mut v: u64, out: &mut [u8]) -> usize {
    let mut i = 0;
    loop {
        let byte = (v & 0x7f) as u8;
        v >>= 7;
        if v == 0 {
            out[i] = byte;
            return i + 1;
        }
        out[i] = byte | 0x80;
        i += 1;
    }
}

fn write_delta_header(h: &UpdateHeader, count: u16, out: &mut [u8]) {
    write_header_fields(h, out);
    out[22..24].copy_from_slice(&count.to_le_bytes());
}

/// An owned delta update, as decoded by [`DeltaUpdate::decode_body`].
#[derive(Debug, Clone, PartialEq, Eq, Hash, Default)]
pub struct DeltaUpdate {
    /// Tick, dilation and origin.
    pub header: UpdateHeader,
    /// The records, ids strictly increasing.
    pub records: Vec<DeltaRecord>,
}

impl DeltaUpdate {
    /// Appends the body to `out`; fails, appending nothing, if it does not fit one
    /// datagram or the ids are not strictly increasing.
    pub fn encode_body(&self, out: &mut Vec<u8>) -> Result<(), crate::EncodeError> {
        if self.records.windows(2).any(|w| w[0].id >= w[1].id) {
            return Err(crate::EncodeError::Unordered);
        }
        let origin = self.header.origin;
        let mut previous = None;
        let mut len = DELTA_HEADER_LEN;
        for r in &self.records {
            len += r.encoded_len(previous, origin);
            previous = Some(r.id);
        }
        if len > MAX_BODY {
            return Err(crate::EncodeError::TooLarge { len, max: MAX_BODY });
        }
        let start = out.len();
        out.resize(start + len, 0);
        let body = &mut out[start..];
        write_delta_header(&self.header, self.records.len() as u16, body);
        let (mut at, mut previous) = (DELTA_HEADER_LEN, None);
        for r in &self.records {
            at += r.write(previous, origin, &mut body[at..]).unwrap_or(0);
            previous = Some(r.id);
        }
        Ok(())
    }

    /// Decodes a body.
    pub fn decode_body(body: &[u8]) -> Result<Self, DecodeError> {
        let view = DeltaUpdateView::parse(body)?;
        Ok(Self { header: view.header(), records: view.records().collect() })
    }
}

/// A validated, borrowed delta update body.
#[derive(Debug, Clone, Copy)]
pub struct DeltaUpdateView<'a> {
    header: UpdateHeader,
    count: u16,
    records: &'a [u8],
}

impl<'a> DeltaUpdateView<'a> {
    /// Checks the whole body (header, every record, exact length) and returns a view
    /// whose [`records`](Self::records) cannot fail.
    pub fn parse(body: &'a [u8]) -> Result<Self, DecodeError> {
        let mut r = Reader::new(body);
        let header = read_header_fields(&mut r)?;
        let count = r.u16()?;
        // Cheap bound before the loop: every record takes at least two bytes.
        if usize::from(count) * 2 > r.remaining() {
            return Err(DecodeError::RecordCount { count });
        }
        let mut previous = None;
        for _ in 0..count {
            previous = Some(DeltaRecord::read(&mut r, previous, header.origin)?.id);
        }
        r.finish()?;
        Ok(Self { header, count, records: &body[DELTA_HEADER_LEN..] })
    }

    /// Tick, dilation and origin.
    pub fn header(&self) -> UpdateHeader {
        self.header
    }

    /// Number of records.
    pub fn len(&self) -> usize {
        usize::from(self.count)
    }

    /// Whether the update holds no record.
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// The records, ids strictly increasing.
    pub fn records(&self) -> impl Iterator<Item = DeltaRecord> + 'a {
        let mut r = Reader::new(self.records);
        let origin = self.header.origin;
        let mut previous = None;
        // `parse` decoded every record successfully, so `ok()` never stops early.
        (0..self.count).map_while(move |_| {
            let rec = DeltaRecord::read(&mut r, previous, origin).ok()?;
            previous = Some(rec.id);
            Some(rec)
        })
    }
}

/// Packs `records` (ids strictly increasing), in order, into at most `max_datagrams`
/// delta update frames appended to `out` (unsealed, ready for
/// [`Sealer::seal_batch`](crate::Sealer::seal_batch)), with `pinned` (the player's own
/// object, whose id is not among `records`) in **every** datagram at its place in id
/// order. Returns how many of `records` (a prefix) were packed, and leaves in `ends`
/// where each datagram's share of them ends (datagram `i` holds `records[ends[i - 1]..
/// ends[i]]`, from 0 for the first). With a pinned record, one datagram is made even
/// when `records` is empty.
pub fn pack_deltas(
    header: &UpdateHeader,
    pinned: Option<&DeltaRecord>,
    records: &[DeltaRecord],
    max_datagrams: usize,
    out: &mut DatagramBatch,
    ends: &mut Vec<usize>,
) -> usize {
    ends.clear();
    let origin = header.origin;
    // Inserting the pinned record only shortens its neighbour's gap, so its size as a
    // first record is all the room it needs.
    let room = MAX_BODY - DELTA_HEADER_LEN - pinned.map_or(0, |p| p.encoded_len(None, origin));
    let (mut packed, mut datagrams) = (0, 0);
    while (packed < records.len() || (pinned.is_some() && datagrams == 0)) && datagrams < max_datagrams {
        let (mut used, mut previous, mut end) = (0, None, packed);
        while let Some(r) = records.get(end) {
            let len = r.encoded_len(previous, origin);
            if used + len > room {
                break;
            }
            used += len;
            previous = Some(r.id);
            end += 1;
        }
        let buf = out.begin(MAX_DATAGRAM);
        buf[0] = PROTOCOL_VERSION;
        buf[1] = PacketKind::StateUpdate as u8;
        let mut pinned_left = pinned;
        let (mut at, mut previous, mut count) = (HEADER_LEN + DELTA_HEADER_LEN, None, 0u16);
        let limit = HEADER_LEN + MAX_BODY;
        for r in &records[packed..end] {
            if let Some(p) = pinned_left.filter(|p| p.id < r.id) {
                at += p.write(previous, origin, &mut buf[at..limit]).unwrap_or(0);
                previous = Some(p.id);
                count += 1;
                pinned_left = None;
            }
            at += r.write(previous, origin, &mut buf[at..limit]).unwrap_or(0);
            previous = Some(r.id);
            count += 1;
        }
        if let Some(p) = pinned_left {
            at += p.write(previous, origin, &mut buf[at..limit]).unwrap_or(0);
            count += 1;
        }
        write_delta_header(header, count, &mut buf[HEADER_LEN..]);
        out.finish(at + TAG_LEN);
        ends.push(end);
        datagrams += 1;
        if end == packed {
            // Nothing but the pinned record went in; never loop on a record that fits
            // nowhere (none exists: any record fits an empty datagram).
            packed = end;
            break;
        }
        packed = end;
    }
    packed
}

/// Why a record could not be applied.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum ResolveError {
    /// The record is relative to a state the client does not hold (it came too late, or
    /// the client restarted); the object's state is kept as it was.
    #[error("no state of object {id} at tick {tick} to apply a delta to")]
    MissingBaseline {
        /// The object.
        id: u64,
        /// The baseline's tick (0 for a record naming a tick before 0).
        tick: u64,
    },
}

/// What a client keeps to resolve delta records: every state it received of each object
/// in the last [`MAX_BACK`] ticks before the newest tick it saw.
#[derive(Debug, Clone, Default)]
pub struct Baselines {
    objects: foldhash::HashMap<u64, History>,
    newest: u64,
    pruned_at: u64,
}

#[derive(Debug, Clone)]
struct History {
    kind: ShapeKind,
    /// `(tick, position)`, ticks increasing.
    states: VecDeque<(u64, QuantPos)>,
}

impl History {
    /// The state of `tick`. Searched from the newest: a record's baseline is the newest
    /// state the client acknowledged, nearly always one of the last few kept.
    fn at(&self, tick: u64) -> Option<QuantPos> {
        self.states.iter().rev().take_while(|s| s.0 >= tick).find(|s| s.0 == tick).map(|s| s.1)
    }
}

impl Baselines {
    /// Resolves `record` of the update of tick `tick` into the object's state, and keeps
    /// that state as a baseline for later records.
    pub fn resolve(&mut self, tick: u64, record: &DeltaRecord) -> Result<StateRecord, ResolveError> {
        let id = record.id;
        let (kind, pos) = match record.state {
            RecordState::Absolute { kind, pos } => (kind, pos),
            RecordState::Delta { back, .. } | RecordState::Same { back } => {
                // A record naming a tick before 0 has no baseline: it must not fall back
                // on tick 0's state (only a broken server sends one).
                let at = tick.checked_sub(u64::from(back));
                let base = at.zip(self.objects.get(&id)).and_then(|(at, h)| Some((h.kind, h.at(at)?)));
                let Some((kind, base)) = base else {
                    return Err(ResolveError::MissingBaseline { id, tick: at.unwrap_or(0) });
                };
                match record.state {
                    RecordState::Delta { d, .. } => (kind, add(base, d)),
                    _ => (kind, base),
                }
            }
        };
        self.remember(tick, StateRecord { id, kind, pos });
        Ok(StateRecord { id, kind, pos })
    }

    /// Resolves every record of `update` into `out` (appended, in the update's order) and
    /// returns how many could not be: a client acknowledges the datagram only when none
    /// failed, so the server never takes a state the client lacks for a baseline.
    pub fn resolve_update(&mut self, update: &DeltaUpdate, out: &mut Vec<StateRecord>) -> usize {
        self.resolve_records(update.header.tick, update.records.iter().copied(), out)
    }

    /// [`Self::resolve_update`] for the records of the update of tick `tick` as they come
    /// (a [`DeltaUpdateView`]'s, without collecting them first).
    pub fn resolve_records(
        &mut self,
        tick: u64,
        records: impl IntoIterator<Item = DeltaRecord>,
        out: &mut Vec<StateRecord>,
    ) -> usize {
        let mut unresolved = 0;
        for r in records {
            match self.resolve(tick, &r) {
                Ok(state) => out.push(state),
                Err(_) => unresolved += 1,
            }
        }
        unresolved
    }

    /// Keeps `state` of tick `tick`.
    fn remember(&mut self, tick: u64, state: StateRecord) {
        self.newest = self.newest.max(tick);
        let floor = self.newest.saturating_sub(MAX_BACK);
        let h = self.objects.entry(state.id).or_insert_with(|| History { kind: state.kind, states: VecDeque::new() });
        h.kind = state.kind;
        // Where it goes, from the newest: updates mostly come in order.
        match h.states.iter().rposition(|s| s.0 <= tick) {
            Some(i) if h.states[i].0 == tick => h.states[i].1 = state.pos,
            Some(i) => h.states.insert(i + 1, (tick, state.pos)),
            None => h.states.push_front((tick, state.pos)),
        }
        while h.states.front().is_some_and(|s| s.0 < floor) {
            h.states.pop_front();
        }
        // Now and then, forget objects with nothing left in the window. (Saturating: a
        // tick near `u64::MAX`, which only a broken server sends, must not overflow.)
        if self.newest >= self.pruned_at.saturating_add(MAX_BACK) {
            self.pruned_at = self.newest;
            self.objects.retain(|_, h| {
                while h.states.front().is_some_and(|s| s.0 < floor) {
                    h.states.pop_front();
                }
                !h.states.is_empty()
            });
        }
    }
}

fn add(p: QuantPos, d: [i8; 3]) -> QuantPos {
    QuantPos::new(
        p.x.saturating_add(i32::from(d[0])),
        p.y.saturating_add(i32::from(d[1])),
        p.z.saturating_add(i32::from(d[2])),
    )
}

#[cfg(test)]
#[path = "delta_tests.rs"]
mod tests;
