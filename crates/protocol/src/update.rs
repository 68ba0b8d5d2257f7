//! State updates: the server's per-tick positions of the objects a player can see.
//!
//! # Body layout (all little-endian)
//!
//! ```text
//! offset  size  field
//!      0     8  server tick (u64); a client ignores a record older than what it has
//!      8     2  time dilation in 1/1000 (u16; 1000 = real time)
//!     10    12  origin x, y, z (i32 each, 1/64 unit), normally the AOI centre
//!     22     8  id base (u64), the smallest object id in this datagram
//!     30     2  record count (u16)
//!     32     …  records
//! ```
//!
//! # Records
//!
//! *Compact*, 10 bytes, used whenever it can represent the object exactly:
//!
//! ```text
//!  0  4  word (u32): bits 0..=1 shape kind (0 sphere, 1 box, 2 capsule),
//!                    bits 2..=31 id - id base (must be < 2^30)
//!  4  6  dx, dy, dz (i16 each, 1/64 unit), position - origin (±512 units)
//! ```
//!
//! *Extended*, 24 bytes, the escape for an id more than 2^30 above the base or a
//! position more than 512 units from the origin:
//!
//! ```text
//!  0  4  word (u32): bits 0..=1 = 3 (escape), bits 2..=3 shape kind, bits 4..=31 zero
//!  4  8  object id (u64), absolute
//! 12 12  x, y, z (i32 each, 1/64 unit), absolute
//! ```
//!
//! So ids of any size and positions anywhere in the ±33.5 million unit fixed-point range
//! are carried exactly (no clamping); only their cost grows. A 1200-byte datagram holds
//! up to [`MAX_COMPACT_RECORDS`] (113) compact records.

use crate::batch::DatagramBatch;
use crate::error::{DecodeError, EncodeError};
use crate::header::{HEADER_LEN, MAX_BODY, MAX_DATAGRAM, PROTOCOL_VERSION, PacketKind, TAG_LEN};
use crate::quant::QuantPos;
use crate::wire::Reader;

/// Length of the state update's own header, at the start of its body.
pub const UPDATE_HEADER_LEN: usize = 32;
/// Length of a compact record.
pub const COMPACT_RECORD_LEN: usize = 10;
/// Length of an extended (escape) record.
pub const EXTENDED_RECORD_LEN: usize = 24;
/// Compact records carry `id - id_base` in 30 bits.
pub const ID_WINDOW: u64 = 1 << 30;
/// Most compact records one datagram holds.
pub const MAX_COMPACT_RECORDS: usize = (MAX_BODY - UPDATE_HEADER_LEN) / COMPACT_RECORD_LEN;

const ESCAPE: u32 = 3;

/// The three shapes a dynamic object can have.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
#[repr(u8)]
pub enum ShapeKind {
    /// A sphere.
    #[default]
    Sphere = 0,
    /// An axis-aligned box.
    Box = 1,
    /// A vertical capsule.
    Capsule = 2,
}

impl ShapeKind {
    /// Parses the two-bit kind code; 3 is not a kind.
    pub const fn from_code(code: u8) -> Option<Self> {
        match code {
            0 => Some(Self::Sphere),
            1 => Some(Self::Box),
            2 => Some(Self::Capsule),
            _ => None,
        }
    }
}

/// One object's state in an update.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct StateRecord {
    /// The object's id.
    pub id: u64,
    /// Its shape.
    pub kind: ShapeKind,
    /// Its position, quantized.
    pub pos: QuantPos,
}

/// The fields shared by every datagram of one player's update in one tick.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct UpdateHeader {
    /// The server tick the positions belong to.
    pub tick: u64,
    /// Time dilation in 1/1000 (1000 = real time).
    pub dilation_permille: u16,
    /// The point record positions are relative to (the player's AOI centre).
    pub origin: QuantPos,
}

/// Bytes `rec` takes when encoded against `id_base` and `origin`:
/// [`COMPACT_RECORD_LEN`] or [`EXTENDED_RECORD_LEN`].
#[inline]
pub fn record_len(rec: &StateRecord, id_base: u64, origin: QuantPos) -> usize {
    if compact_parts(rec, id_base, origin).is_some() { COMPACT_RECORD_LEN } else { EXTENDED_RECORD_LEN }
}

#[inline]
fn compact_parts(rec: &StateRecord, id_base: u64, origin: QuantPos) -> Option<(u32, [i16; 3])> {
    let delta = rec.id.checked_sub(id_base).filter(|&d| d < ID_WINDOW)?;
    let offset = rec.pos.offset_from(origin)?;
    Some((((delta as u32) << 2) | rec.kind as u32, offset))
}

/// Writes `rec` at the start of `out` and returns the bytes written, or `None`
/// (writing nothing) if `out` is too short for it.
#[inline]
fn write_record(rec: &StateRecord, id_base: u64, origin: QuantPos, out: &mut [u8]) -> Option<usize> {
    match compact_parts(rec, id_base, origin) {
        Some((word, d)) => {
            let out = out.get_mut(..COMPACT_RECORD_LEN)?;
            out[0..4].copy_from_slice(&word.to_le_bytes());
            out[4..6].copy_from_slice(&d[0].to_le_bytes());
            out[6..8].copy_from_slice(&d[1].to_le_bytes());
            out[8..10].copy_from_slice(&d[2].to_le_bytes());
            Some(COMPACT_RECORD_LEN)
        }
        None => {
            let out = out.get_mut(..EXTENDED_RECORD_LEN)?;
            let word = ESCAPE | ((rec.kind as u32) << 2);
            out[0..4].copy_from_slice(&word.to_le_bytes());
            out[4..12].copy_from_slice(&rec.id.to_le_bytes());
            out[12..16].copy_from_slice(&rec.pos.x.to_le_bytes());
            out[16..20].copy_from_slice(&rec.pos.y.to_le_bytes());
            out[20..24].copy_from_slice(&rec.pos.z.to_le_bytes());
            Some(EXTENDED_RECORD_LEN)
        }
    }
}

/// Writes the 22 bytes both update forms start with: tick, dilation, origin.
pub(crate) fn write_header_fields(h: &UpdateHeader, out: &mut [u8]) {
    out[0..8].copy_from_slice(&h.tick.to_le_bytes());
    out[8..10].copy_from_slice(&h.dilation_permille.to_le_bytes());
    out[10..14].copy_from_slice(&h.origin.x.to_le_bytes());
    out[14..18].copy_from_slice(&h.origin.y.to_le_bytes());
    out[18..22].copy_from_slice(&h.origin.z.to_le_bytes());
}

/// Reads what [`write_header_fields`] wrote.
pub(crate) fn read_header_fields(r: &mut Reader<'_>) -> Result<UpdateHeader, DecodeError> {
    Ok(UpdateHeader {
        tick: r.u64()?,
        dilation_permille: r.u16()?,
        origin: QuantPos::new(r.i32()?, r.i32()?, r.i32()?),
    })
}

fn write_update_header(h: &UpdateHeader, id_base: u64, count: u16, out: &mut [u8]) {
    write_header_fields(h, out);
    out[22..30].copy_from_slice(&id_base.to_le_bytes());
    out[30..32].copy_from_slice(&count.to_le_bytes());
}

fn read_record(r: &mut Reader<'_>, id_base: u64, origin: QuantPos) -> Result<StateRecord, DecodeError> {
    let word = r.u32()?;
    if word & 3 != ESCAPE {
        let kind = ShapeKind::from_code((word & 3) as u8).ok_or(DecodeError::BadShapeKind(3))?;
        let id = id_base.checked_add(u64::from(word >> 2)).ok_or(DecodeError::IdOverflow)?;
        let d = [r.i16()?, r.i16()?, r.i16()?];
        Ok(StateRecord { id, kind, pos: QuantPos::add_offset(origin, d) })
    } else {
        if word >> 4 != 0 {
            return Err(DecodeError::ReservedBits(word));
        }
        let code = ((word >> 2) & 3) as u8;
        let kind = ShapeKind::from_code(code).ok_or(DecodeError::BadShapeKind(code))?;
        let id = r.u64()?;
        let pos = QuantPos::new(r.i32()?, r.i32()?, r.i32()?);
        Ok(StateRecord { id, kind, pos })
    }
}

/// An owned state update, as decoded by [`crate::ServerMessage::decode_body`].
#[derive(Debug, Clone, PartialEq, Eq, Hash, Default)]
pub struct StateUpdate {
    /// Tick, dilation and origin.
    pub header: UpdateHeader,
    /// The records, in packet order.
    pub records: Vec<StateRecord>,
}

impl StateUpdate {
    /// Appends the body to `out`; fails, appending nothing, if it does not fit one
    /// datagram (use [`pack_updates`] to split large updates).
    pub fn encode_body(&self, out: &mut Vec<u8>) -> Result<(), EncodeError> {
        let id_base = self.records.iter().map(|r| r.id).min().unwrap_or(0);
        let origin = self.header.origin;
        let len = UPDATE_HEADER_LEN + self.records.iter().map(|r| record_len(r, id_base, origin)).sum::<usize>();
        if len > MAX_BODY {
            return Err(EncodeError::TooLarge { len, max: MAX_BODY });
        }
        let start = out.len();
        out.resize(start + len, 0);
        let body = &mut out[start..];
        // len <= MAX_BODY bounds the count far below u16::MAX.
        write_update_header(&self.header, id_base, self.records.len() as u16, body);
        let mut pos = UPDATE_HEADER_LEN;
        for rec in &self.records {
            // The length was computed above, so every record fits.
            pos += write_record(rec, id_base, origin, &mut body[pos..]).unwrap_or(0);
        }
        Ok(())
    }

    /// Decodes a body.
    pub fn decode_body(body: &[u8]) -> Result<Self, DecodeError> {
        let view = StateUpdateView::parse(body)?;
        Ok(Self { header: view.header(), records: view.records().collect() })
    }
}

/// A validated, borrowed state update body: decoding without allocating.
#[derive(Debug, Clone, Copy)]
pub struct StateUpdateView<'a> {
    header: UpdateHeader,
    id_base: u64,
    count: u16,
    records: &'a [u8],
}

impl<'a> StateUpdateView<'a> {
    /// Checks the whole body (header, every record, exact length) and returns a view
    /// whose [`records`](Self::records) cannot fail.
    pub fn parse(body: &'a [u8]) -> Result<Self, DecodeError> {
        let mut r = Reader::new(body);
        let header = read_header_fields(&mut r)?;
        let id_base = r.u64()?;
        let count = r.u16()?;
        // Cheap bound before the loop: every record takes at least the compact length.
        if usize::from(count) * COMPACT_RECORD_LEN > r.remaining() {
            return Err(DecodeError::RecordCount { count });
        }
        let records = &body[UPDATE_HEADER_LEN..];
        for _ in 0..count {
            read_record(&mut r, id_base, header.origin)?;
        }
        r.finish()?;
        Ok(Self { header, id_base, count, records })
    }

    /// Tick, dilation and origin.
    pub fn header(&self) -> UpdateHeader {
        self.header
    }

    /// The id base compact records are relative to.
    pub fn id_base(&self) -> u64 {
        self.id_base
    }

    /// Number of records.
    pub fn len(&self) -> usize {
        usize::from(self.count)
    }

    /// Whether the update holds no record.
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// The records, in packet order.
    pub fn records(&self) -> impl Iterator<Item = StateRecord> + 'a {
        let mut r = Reader::new(self.records);
        let (id_base, origin) = (self.id_base, self.header.origin);
        // `parse` already decoded every record successfully, so `ok()` never stops early.
        (0..self.count).map_while(move |_| read_record(&mut r, id_base, origin).ok())
    }
}

/// Packs `records`, in order, into as few `StateUpdate` datagrams as possible, at most
/// `max_datagrams`, and appends them to `out` as unsealed frames (header space with the
/// version and kind set, body, zeroed tag space) ready for
/// [`Sealer::seal_batch`](crate::Sealer::seal_batch). Returns how many records (a
/// prefix of `records`) were packed; the caller decides what to do with the rest.
///
/// All datagrams share `header`; each has its own id base, the smallest id among the
/// records it carries.
/// Datagrams are filled greedily in order, so with compact records each holds
/// [`MAX_COMPACT_RECORDS`]. No allocation happens beyond growing `out`, which a caller
/// reuses from tick to tick.
pub fn pack_updates(
    header: &UpdateHeader,
    records: &[StateRecord],
    max_datagrams: usize,
    out: &mut DatagramBatch,
) -> usize {
    pack_updates_pinned(header, None, records, max_datagrams, out)
}

/// Like [`pack_updates`], with `pinned` (a player's own object) written first in
/// **every** datagram, so each datagram alone tells the player where it is: a lost
/// datagram never leaves it without its own position. Returns how many of `records` (a
/// prefix) were packed; `pinned` is not counted. With a pinned record, every datagram
/// holds it even when `records` is empty (one datagram then).
pub fn pack_updates_pinned(
    header: &UpdateHeader,
    pinned: Option<&StateRecord>,
    records: &[StateRecord],
    max_datagrams: usize,
    out: &mut DatagramBatch,
) -> usize {
    if pinned.is_none() && records.is_empty() {
        return 0;
    }
    let origin = header.origin;
    let room = MAX_BODY - UPDATE_HEADER_LEN;
    let mut packed = 0;
    let mut datagrams = 0;
    // With a pinned record, the first datagram is made even if `records` is empty.
    while (packed < records.len() || (pinned.is_some() && datagrams == 0)) && datagrams < max_datagrams {
        // Which records go in decides the id base, and the base decides their sizes:
        // fit first, then write against the smallest id actually sent.
        let (take, id_base) = fit(pinned, &records[packed..], origin, room);
        let buf = begin_update_frame(out);
        let body_start = HEADER_LEN;
        let mut pos = body_start + UPDATE_HEADER_LEN;
        let limit = HEADER_LEN + MAX_BODY;
        let mut count = 0u16;
        for rec in pinned.into_iter().chain(&records[packed..packed + take]) {
            // `fit` measured these against this base: each one fits.
            if let Some(len) = write_record(rec, id_base, origin, &mut buf[pos..limit]) {
                pos += len;
                count += 1;
            }
        }
        packed += take;
        write_update_header(header, id_base, count, &mut buf[body_start..]);
        // The tag space after `pos` is still zero from `begin`.
        out.finish(pos + TAG_LEN);
        datagrams += 1;
        if take == 0 {
            // Only the pinned record went in: nothing left, or (impossible, any record
            // fits beside it) a record that fits nowhere. Never loop on it.
            break;
        }
    }
    packed
}

/// Starts a zeroed `StateUpdate` frame in `out` with its version and kind set.
fn begin_update_frame(out: &mut DatagramBatch) -> &mut [u8] {
    let buf = out.begin(MAX_DATAGRAM);
    buf[0] = PROTOCOL_VERSION;
    buf[1] = PacketKind::StateUpdate as u8;
    buf
}

/// How many of `records` (a prefix) fit in `room` bytes of records after `pinned`, and
/// the id base they are written against: the smallest id among `pinned` and them. A
/// record with a smaller id lowers the base, which can turn earlier compact records into
/// extended ones; the sizes are then recomputed, and the record waits for the next
/// datagram if the prefix no longer fits.
fn fit(pinned: Option<&StateRecord>, records: &[StateRecord], origin: QuantPos, room: usize) -> (usize, u64) {
    let Some(first) = pinned.or(records.first()) else { return (0, 0) };
    let mut base = first.id;
    let size = |recs: &[StateRecord], base: u64| -> usize {
        pinned.map_or(0, |p| record_len(p, base, origin))
            + recs.iter().map(|r| record_len(r, base, origin)).sum::<usize>()
    };
    let mut used = pinned.map_or(0, |p| record_len(p, base, origin));
    let mut take = 0;
    for (i, rec) in records.iter().enumerate() {
        if rec.id < base {
            let lower = size(&records[..=i], rec.id);
            if lower > room {
                break;
            }
            base = rec.id;
            used = lower;
        } else {
            let len = record_len(rec, base, origin);
            if used + len > room {
                break;
            }
            used += len;
        }
        take = i + 1;
    }
    (take, base)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rec(id: u64, kind: ShapeKind, p: (i32, i32, i32)) -> StateRecord {
        StateRecord { id, kind, pos: QuantPos::new(p.0, p.1, p.2) }
    }

    #[test]
    fn capacity_is_113_compact_records() {
        assert_eq!(MAX_COMPACT_RECORDS, 113);
        let h = UpdateHeader::default();
        let recs: Vec<_> = (0..113 * 3 + 1).map(|i| rec(i, ShapeKind::Box, (i as i32, 0, 0))).collect();
        let mut b = DatagramBatch::new();
        assert_eq!(pack_updates(&h, &recs, 10, &mut b), recs.len());
        assert_eq!(b.len(), 4);
        assert_eq!(b.get(0).map(<[u8]>::len), Some(HEADER_LEN + UPDATE_HEADER_LEN + 1130 + TAG_LEN));
        let mut b = DatagramBatch::new();
        assert_eq!(pack_updates(&h, &recs, 2, &mut b), 226);
        assert_eq!(b.len(), 2);
    }

    #[test]
    fn escapes_for_far_positions_and_large_ids() {
        let origin = QuantPos::new(100, 100, 100);
        let base = 1u64 << 40;
        assert_eq!(record_len(&rec(base, ShapeKind::Sphere, (100, 100, 100)), base, origin), 10);
        assert_eq!(record_len(&rec(base + ID_WINDOW - 1, ShapeKind::Sphere, (100, 100, 100)), base, origin), 10);
        assert_eq!(record_len(&rec(base + ID_WINDOW, ShapeKind::Sphere, (100, 100, 100)), base, origin), 24);
        assert_eq!(record_len(&rec(base, ShapeKind::Sphere, (100 + 32768, 100, 100)), base, origin), 24);
        let u = StateUpdate {
            header: UpdateHeader { tick: 9, dilation_permille: 1000, origin },
            records: vec![
                rec(u64::MAX, ShapeKind::Capsule, (i32::MIN, i32::MAX, 0)),
                rec(5, ShapeKind::Box, (100 - 32768, 100 + 32767, 100)),
            ],
        };
        let mut body = Vec::new();
        u.encode_body(&mut body).unwrap();
        assert_eq!(body.len(), UPDATE_HEADER_LEN + 24 + 10);
        assert_eq!(StateUpdate::decode_body(&body), Ok(u));
    }

    #[test]
    fn decoder_rejects_bad_records() {
        let u = StateUpdate {
            header: UpdateHeader::default(),
            records: vec![rec(1, ShapeKind::Box, (0, 0, 0)), rec(2, ShapeKind::Sphere, (1, 2, 3))],
        };
        let mut body = Vec::new();
        u.encode_body(&mut body).unwrap();
        let mut bad = body.clone();
        bad[UPDATE_HEADER_LEN] |= 3; // compact word turned into an escape
        assert!(StateUpdate::decode_body(&bad).is_err());
        let mut bad = body.clone();
        bad[30] = 3; // count says 3
        assert_eq!(StateUpdate::decode_body(&bad), Err(DecodeError::RecordCount { count: 3 }));
        let mut bad = body.clone();
        bad[30] = 1; // count says 1: the second record is left over
        assert_eq!(StateUpdate::decode_body(&bad), Err(DecodeError::TrailingBytes { extra: 10 }));
        let mut bad = body.clone();
        bad[22..30].copy_from_slice(&u64::MAX.to_le_bytes()); // id base + delta overflows
        assert_eq!(StateUpdate::decode_body(&bad), Err(DecodeError::IdOverflow));
        let mut bad = body.clone();
        bad.push(0);
        assert_eq!(StateUpdate::decode_body(&bad), Err(DecodeError::TrailingBytes { extra: 1 }));
    }

    #[test]
    fn pinned_record_is_in_every_datagram() {
        let h = UpdateHeader::default();
        let own = rec(500, ShapeKind::Capsule, (0, 0, 0));
        let recs: Vec<_> = (0..300).map(|i| rec(i, ShapeKind::Box, (i as i32, 0, 0))).collect();
        let mut b = DatagramBatch::new();
        // 112 others beside the pinned record in each datagram.
        assert_eq!(pack_updates_pinned(&h, Some(&own), &recs, 2, &mut b), 224);
        assert_eq!(b.len(), 2);
        for d in b.iter() {
            let view = StateUpdateView::parse(&d[HEADER_LEN..d.len() - TAG_LEN]).unwrap();
            let got: Vec<_> = view.records().collect();
            assert_eq!(got[0], own);
            assert_eq!(got.len(), MAX_COMPACT_RECORDS);
        }
        let mut b = DatagramBatch::new();
        assert_eq!(pack_updates_pinned(&h, Some(&own), &[], 2, &mut b), 0);
        assert_eq!(b.len(), 1, "the pinned record alone still makes a datagram");
        let mut b = DatagramBatch::new();
        assert_eq!(pack_updates_pinned(&h, None, &[], 2, &mut b), 0);
        assert!(b.is_empty());
    }

    // Issue 14: the id base was the smallest id of every record offered, computed before
    // the records were cut to fit, so a datagram could carry a base no record of it had.
    #[test]
    fn each_datagram_is_based_on_the_smallest_id_it_actually_carries() {
        let h = UpdateHeader::default();
        let own = rec(5_000, ShapeKind::Capsule, (0, 0, 0));
        // Ids 10,000.. first; the one small id comes last and does not fit in two
        // datagrams.
        let mut recs: Vec<_> = (0..300).map(|i| rec(10_000 + i, ShapeKind::Box, (i as i32, 0, 0))).collect();
        recs.push(rec(3, ShapeKind::Sphere, (0, 0, 0)));
        let mut b = DatagramBatch::new();
        assert_eq!(pack_updates_pinned(&h, Some(&own), &recs, 2, &mut b), 224);
        for d in b.iter() {
            let view = StateUpdateView::parse(&d[HEADER_LEN..d.len() - TAG_LEN]).unwrap();
            let smallest = view.records().map(|r| r.id).min().unwrap();
            assert_eq!(view.id_base(), smallest);
            assert_eq!(smallest, 5_000, "the pinned record is the smallest here");
        }
        // Without a pinned record, each datagram gets its own base; a small id that
        // would turn the records before it into extended ones waits for the next one.
        let mut recs: Vec<_> = (0..113).map(|i| rec((1 << 31) + i, ShapeKind::Box, (i as i32, 0, 0))).collect();
        recs.push(rec(1, ShapeKind::Sphere, (0, 0, 0)));
        let mut b = DatagramBatch::new();
        assert_eq!(pack_updates(&h, &recs, 3, &mut b), 114);
        let mut all = Vec::new();
        for d in b.iter() {
            let view = StateUpdateView::parse(&d[HEADER_LEN..d.len() - TAG_LEN]).unwrap();
            let ids: Vec<_> = view.records().map(|r| r.id).collect();
            assert_eq!(view.id_base(), *ids.iter().min().unwrap());
            all.extend(view.records());
        }
        assert_eq!(all, recs, "every record arrives exactly");
        assert_eq!(b.len(), 2);
    }
}
