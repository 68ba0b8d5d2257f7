//! Delta state updates: each record carries an object relative to a state of it the
//! client acknowledged (its *baseline*), or absolute when there is none, bit-packed
//! (`docs/protocol.md`, section 5.3).
//!
//! # Body layout
//!
//! ```text
//! offset  size  field (little-endian)
//!      0     8  server tick (u64)
//!      8     2  time dilation in 1/1000 (u16)
//!     10    12  origin x, y, z (i32 each, 1/64 unit), normally the AOI centre
//!     22     2  record count (u16)
//!     24     …  records, a bit stream ([`crate::bits`]) padded with zeros to a byte
//! ```
//!
//! The bit stream opens with the datagram's *usual back* (6 bits) and the order `k` of
//! its id codes (6 bits). Each record is its id as an exp-Golomb code of order `k` (the
//! first record's id whole, each later one `id - previous id - 1`), a form, and the
//! form's payload:
//!
//! | form bits | form | payload |
//! | --- | --- | --- |
//! | `1` | `Delta` / `Predicted` | back; `0`, or `1` and prior; class (2); 3 × delta |
//! | `0 1` | `Near` | kind (2); class (2); 3 × offset from the origin |
//! | `0 0 1` | `Same` | back |
//! | `0 0 0` | `Far` | kind (2); 3 × 32-bit position |
//!
//! A back (and a prior) is `1` for the usual back (the prior: equal to the back), or `0`
//! and 6 bits. Deltas take [`DELTA_WIDTHS`]`[class]` bits an axis, offsets
//! [`NEAR_WIDTHS`]`[class]`, two's complement. A `Predicted` record's delta is from the
//! baseline extrapolated along its move since the *prior* state, `prior` ticks before the
//! baseline ([`predict`]).
//!
//! [`DeltaRecord::choose`] picks the smallest form that carries the position exactly;
//! [`pack_deltas`] chooses each update's usual back and code order.

use crate::batch::DatagramBatch;
use crate::bits::{BitReader, BitWriter, exp_golomb_bits, signed_bits};
use crate::error::DecodeError;
use crate::header::{HEADER_LEN, MAX_BODY, MAX_DATAGRAM, PROTOCOL_VERSION, PacketKind, TAG_LEN};
use crate::quant::QuantPos;
use crate::update::{ShapeKind, UpdateHeader, read_header_fields, write_header_fields};
use crate::wire::Reader;

pub use crate::baselines::{Baselines, ResolveError, predict};

/// Length of a delta update's own header, at the start of its body.
pub const DELTA_HEADER_LEN: usize = 24;

/// The oldest state a record may name, in ticks before its update's tick: a baseline's
/// back, or a prediction's back plus prior. A client keeps every state it received for
/// this many ticks behind the newest tick it saw.
pub const MAX_BACK: u64 = 63;

/// Bits an axis of a delta takes, by its 2-bit class.
pub const DELTA_WIDTHS: [u32; 4] = [3, 5, 7, 10];

/// Bits an axis of a `Near` offset takes, by its 2-bit class.
pub const NEAR_WIDTHS: [u32; 4] = [10, 12, 13, 16];

/// Bits opening each datagram's records: its usual back and its id code order.
pub const STREAM_PARAMS_BITS: u32 = 12;

/// Most bytes one record can take: a 129-bit id code, a `Far` form (3 bits), its kind
/// and position (98 bits).
pub const MAX_RECORD_LEN: usize = (129 + 3 + 98usize).div_ceil(8);

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
        /// Position minus the baseline's, within the widest [`DELTA_WIDTHS`] class.
        d: [i16; 3],
    },
    /// The baseline `back` ticks ago, extrapolated along its move from the state
    /// `prior` ticks before it ([`predict`]), then moved by `d`.
    Predicted {
        /// Ticks between the baseline and this update (1..=[`MAX_BACK`]).
        back: u8,
        /// Ticks between the prior state and the baseline (`back + prior` ≤
        /// [`MAX_BACK`]).
        prior: u8,
        /// Position minus the prediction, within the widest [`DELTA_WIDTHS`] class.
        d: [i16; 3],
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

/// The narrowest class of `widths` holding every axis of `v`.
fn class_of(widths: &[u32; 4], v: [i64; 3]) -> Option<u8> {
    let need = v.iter().map(|&a| signed_bits(a)).max().unwrap_or(1);
    widths.iter().position(|&w| w >= need).map(|c| c as u8)
}

/// The delta of `pos` from `from`, if the widest class holds it.
fn delta_to(pos: QuantPos, from: [i64; 3]) -> Option<[i16; 3]> {
    let d = [i64::from(pos.x) - from[0], i64::from(pos.y) - from[1], i64::from(pos.z) - from[2]];
    class_of(&DELTA_WIDTHS, d)?;
    Some(d.map(|a| a as i16))
}

fn widened(p: QuantPos) -> [i64; 3] {
    [p.x.into(), p.y.into(), p.z.into()]
}

/// Whether `back` can be named (1..=[`MAX_BACK`]).
fn valid_back(back: u8) -> bool {
    (1..=MAX_BACK as u8).contains(&back)
}

impl DeltaRecord {
    /// The smallest record carrying object `id` (shape `kind`) at `pos` in the update of
    /// `tick`, relative to `baseline` if there is one within [`MAX_BACK`] ticks, and
    /// predicted from `prior` (the acknowledged state before the baseline) if that is
    /// smaller still.
    pub fn choose(
        id: u64,
        kind: ShapeKind,
        pos: QuantPos,
        tick: u64,
        baseline: Option<Baseline>,
        prior: Option<Baseline>,
    ) -> Self {
        let relative = baseline.and_then(|b| {
            let back = tick.checked_sub(b.tick).filter(|back| (1..=MAX_BACK).contains(back))? as u8;
            if b.pos == pos {
                return Some(RecordState::Same { back });
            }
            let plain = delta_to(pos, widened(b.pos)).map(|d| RecordState::Delta { back, d });
            let predicted = prior.and_then(|p| {
                let prior = b.tick.checked_sub(p.tick).filter(|&n| n >= 1 && u64::from(back) + n <= MAX_BACK)? as u8;
                let d = delta_to(pos, predict(b.pos, p.pos, back, prior))?;
                Some(RecordState::Predicted { back, prior, d })
            });
            let bits = |s: &RecordState| Self { id, state: *s }.bits(QuantPos::default(), 0);
            match (plain, predicted) {
                (Some(a), Some(b)) => Some(if bits(&b) < bits(&a) { b } else { a }),
                (a, b) => a.or(b),
            }
        });
        Self { id, state: relative.unwrap_or(RecordState::Absolute { kind, pos }) }
    }

    /// Bits this record takes besides its id code, against `origin`, in a datagram
    /// whose usual back is `usual` (0 for none); `None` for a record no datagram can
    /// carry (a back, prior or delta out of range).
    pub fn bits(&self, origin: QuantPos, usual: u8) -> Option<u32> {
        let back_bits = |back: u8| if back == usual { 1 } else { 7 };
        match self.state {
            RecordState::Same { back } if valid_back(back) => Some(3 + back_bits(back)),
            RecordState::Delta { back, d } if valid_back(back) => {
                let class = class_of(&DELTA_WIDTHS, d.map(i64::from))?;
                Some(1 + back_bits(back) + 1 + 2 + 3 * DELTA_WIDTHS[usize::from(class)])
            }
            RecordState::Predicted { back, prior, d }
                if valid_back(back) && prior >= 1 && u64::from(back) + u64::from(prior) <= MAX_BACK =>
            {
                let class = class_of(&DELTA_WIDTHS, d.map(i64::from))?;
                let prior_bits = if prior == back { 1 } else { 7 };
                Some(1 + back_bits(back) + 1 + prior_bits + 2 + 3 * DELTA_WIDTHS[usize::from(class)])
            }
            RecordState::Absolute { pos, .. } => Some(match near_class(pos, origin) {
                Some(class) => 2 + 2 + 2 + 3 * NEAR_WIDTHS[usize::from(class)],
                None => 3 + 2 + 96,
            }),
            _ => None,
        }
    }

    fn write(&self, w: &mut BitWriter<'_>, previous: Option<u64>, params: StreamParams, origin: QuantPos) {
        w.put_exp_golomb(gap(previous, self.id), params.k);
        let put_back = |w: &mut BitWriter<'_>, back: u8| {
            if back == params.usual {
                w.put(1, 1);
            } else {
                w.put(0, 1);
                w.put(u64::from(back), 6);
            }
        };
        let put_delta = |w: &mut BitWriter<'_>, d: [i16; 3]| {
            let class = class_of(&DELTA_WIDTHS, d.map(i64::from)).unwrap_or(3);
            w.put(u64::from(class), 2);
            for a in d {
                w.put_signed(a.into(), DELTA_WIDTHS[usize::from(class)]);
            }
        };
        match self.state {
            RecordState::Delta { back, d } => {
                w.put(1, 1);
                put_back(w, back);
                w.put(0, 1);
                put_delta(w, d);
            }
            RecordState::Predicted { back, prior, d } => {
                w.put(1, 1);
                put_back(w, back);
                w.put(1, 1);
                if prior == back {
                    w.put(1, 1);
                } else {
                    w.put(0, 1);
                    w.put(u64::from(prior), 6);
                }
                put_delta(w, d);
            }
            RecordState::Same { back } => {
                w.put(0b100, 3);
                put_back(w, back);
            }
            RecordState::Absolute { kind, pos } => match near_class(pos, origin) {
                Some(class) => {
                    w.put(0b10, 2);
                    w.put(kind as u64, 2);
                    w.put(u64::from(class), 2);
                    let o = widened(origin);
                    for v in [i64::from(pos.x) - o[0], i64::from(pos.y) - o[1], i64::from(pos.z) - o[2]] {
                        w.put_signed(v, NEAR_WIDTHS[usize::from(class)]);
                    }
                }
                None => {
                    w.put(0b000, 3);
                    w.put(kind as u64, 2);
                    for v in [pos.x, pos.y, pos.z] {
                        w.put(u64::from(v as u32), 32);
                    }
                }
            },
        }
    }

    fn read(
        r: &mut BitReader<'_>,
        previous: Option<u64>,
        params: StreamParams,
        origin: QuantPos,
    ) -> Result<Self, DecodeError> {
        let gap = r.get_exp_golomb(params.k)?;
        let id = match previous {
            None => gap,
            Some(p) => p.checked_add(1).and_then(|n| n.checked_add(gap)).ok_or(DecodeError::IdOverflow)?,
        };
        let get_back = |r: &mut BitReader<'_>| -> Result<u8, DecodeError> {
            let back = if r.bit()? { params.usual } else { r.get(6)? as u8 };
            if valid_back(back) { Ok(back) } else { Err(DecodeError::BadBack(back)) }
        };
        let get_delta = |r: &mut BitReader<'_>| -> Result<[i16; 3], DecodeError> {
            let width = DELTA_WIDTHS[r.get(2)? as usize];
            Ok([r.get_signed(width)? as i16, r.get_signed(width)? as i16, r.get_signed(width)? as i16])
        };
        let get_kind = |r: &mut BitReader<'_>| -> Result<ShapeKind, DecodeError> {
            let code = r.get(2)? as u8;
            ShapeKind::from_code(code).ok_or(DecodeError::BadShapeKind(code))
        };
        let state = if r.bit()? {
            let back = get_back(r)?;
            if r.bit()? {
                let prior = if r.bit()? { back } else { r.get(6)? as u8 };
                if prior == 0 || u64::from(back) + u64::from(prior) > MAX_BACK {
                    return Err(DecodeError::BadPrior { back, prior });
                }
                RecordState::Predicted { back, prior, d: get_delta(r)? }
            } else {
                RecordState::Delta { back, d: get_delta(r)? }
            }
        } else if r.bit()? {
            let kind = get_kind(r)?;
            let width = NEAR_WIDTHS[r.get(2)? as usize];
            // Offsets are at most 16 bits wide: an `i16` holds them.
            let o = [r.get_signed(width)? as i16, r.get_signed(width)? as i16, r.get_signed(width)? as i16];
            RecordState::Absolute { kind, pos: QuantPos::add_offset(origin, o) }
        } else if r.bit()? {
            RecordState::Same { back: get_back(r)? }
        } else {
            let kind = get_kind(r)?;
            let v = [r.get(32)? as u32 as i32, r.get(32)? as u32 as i32, r.get(32)? as u32 as i32];
            RecordState::Absolute { kind, pos: QuantPos::new(v[0], v[1], v[2]) }
        };
        Ok(Self { id, state })
    }
}

/// The narrowest `Near` class holding `pos - origin`, if any does.
fn near_class(pos: QuantPos, origin: QuantPos) -> Option<u8> {
    let o = widened(origin);
    class_of(&NEAR_WIDTHS, [i64::from(pos.x) - o[0], i64::from(pos.y) - o[1], i64::from(pos.z) - o[2]])
}

/// The id field's value: the id itself first, then the gap less one.
fn gap(previous: Option<u64>, id: u64) -> u64 {
    previous.map_or(id, |p| id.wrapping_sub(p).wrapping_sub(1))
}

/// What opens a datagram's bit stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct StreamParams {
    /// The back a record's `1` back bit names (0: none; such a record is malformed).
    usual: u8,
    /// Order of the id codes (0..=63).
    k: u32,
}

impl StreamParams {
    fn write(self, w: &mut BitWriter<'_>) {
        w.put(u64::from(self.usual), 6);
        w.put(u64::from(self.k), 6);
    }

    fn read(r: &mut BitReader<'_>) -> Result<Self, DecodeError> {
        Ok(Self { usual: r.get(6)? as u8, k: r.get(6)? as u32 })
    }

    /// The parameters that make `records` (ids increasing) small: the most common back
    /// among them, and the code order that suits their id gaps (from a histogram of the
    /// gaps' lengths, so it costs a pass over the records, not one per order).
    fn for_records<'r>(records: impl Iterator<Item = &'r DeltaRecord>) -> Self {
        let (mut backs, mut lengths) = ([0u32; 64], [0u32; 65]);
        let mut previous = None;
        for r in records {
            let g = gap(previous, r.id);
            previous = Some(r.id);
            lengths[(64 - g.leading_zeros()) as usize] += 1;
            if let RecordState::Delta { back, .. } | RecordState::Predicted { back, .. } | RecordState::Same { back } =
                r.state
            {
                backs[usize::from(back & 63)] += 1;
            }
        }
        let usual = (1..64).max_by_key(|&b| (backs[b], std::cmp::Reverse(b))).filter(|&b| backs[b] > 0).unwrap_or(0);
        // A gap of length `len` (2^(len-1) ≤ g < 2^len) costs about what its smallest
        // value does; no order above the longest length can be cheaper.
        let longest = (0..=64u32).rev().find(|&len| lengths[len as usize] > 0).unwrap_or(0);
        let cost = |k: u32| -> u64 {
            (0..=longest)
                .filter(|&len| lengths[len as usize] > 0)
                .map(|len| {
                    let g = if len == 0 { 0 } else { 1u64 << (len - 1) };
                    u64::from(lengths[len as usize]) * u64::from(exp_golomb_bits(g, k))
                })
                .sum()
        };
        let k = (0..=longest.min(63)).min_by_key(|&k| (cost(k), k)).unwrap_or(0);
        Self { usual: usual as u8, k }
    }
}

fn write_delta_header(h: &UpdateHeader, count: u16, out: &mut [u8]) {
    write_header_fields(h, out);
    out[22..24].copy_from_slice(&count.to_le_bytes());
}

/// Bits of `records` (ids increasing) written after a record of id `previous`.
fn stream_bits<'r>(
    records: impl Iterator<Item = &'r DeltaRecord>,
    mut previous: Option<u64>,
    params: StreamParams,
    origin: QuantPos,
) -> Option<usize> {
    let mut bits = 0usize;
    for r in records {
        bits += (exp_golomb_bits(gap(previous, r.id), params.k) + r.bits(origin, params.usual)?) as usize;
        previous = Some(r.id);
    }
    Some(bits)
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
    /// datagram, the ids are not strictly increasing, or a record cannot be carried.
    pub fn encode_body(&self, out: &mut Vec<u8>) -> Result<(), crate::EncodeError> {
        if self.records.windows(2).any(|w| w[0].id >= w[1].id) {
            return Err(crate::EncodeError::Unordered);
        }
        let origin = self.header.origin;
        let params = StreamParams::for_records(self.records.iter());
        let len = self.body_len_with(params).ok_or(crate::EncodeError::OutOfRange)?;
        if len > MAX_BODY {
            return Err(crate::EncodeError::TooLarge { len, max: MAX_BODY });
        }
        let start = out.len();
        out.resize(start + len, 0);
        let body = &mut out[start..];
        write_delta_header(&self.header, self.records.len() as u16, body);
        let mut w = BitWriter::new(&mut body[DELTA_HEADER_LEN..]);
        params.write(&mut w);
        let mut previous = None;
        for r in &self.records {
            r.write(&mut w, previous, params, origin);
            previous = Some(r.id);
        }
        w.finish();
        Ok(())
    }

    /// Bytes [`Self::encode_body`] writes (ids assumed increasing), limit aside; `None`
    /// if a record cannot be carried.
    pub fn body_len(&self) -> Option<usize> {
        self.body_len_with(StreamParams::for_records(self.records.iter()))
    }

    fn body_len_with(&self, params: StreamParams) -> Option<usize> {
        let bits = stream_bits(self.records.iter(), None, params, self.header.origin)?;
        Some(DELTA_HEADER_LEN + (STREAM_PARAMS_BITS as usize + bits).div_ceil(8))
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
    /// Checks the whole body (header, every record, exact length and zero padding) and
    /// returns a view whose [`records`](Self::records) cannot fail.
    pub fn parse(body: &'a [u8]) -> Result<Self, DecodeError> {
        let mut r = Reader::new(body);
        let header = read_header_fields(&mut r)?;
        let count = r.u16()?;
        let stream = &body[DELTA_HEADER_LEN..];
        // Cheap bound before the loop: every record takes at least five bits.
        if usize::from(count) * 5 > (stream.len() * 8).saturating_sub(STREAM_PARAMS_BITS as usize) {
            return Err(DecodeError::RecordCount { count });
        }
        let mut bits = BitReader::new(stream);
        let params = StreamParams::read(&mut bits)?;
        let mut previous = None;
        for _ in 0..count {
            previous = Some(DeltaRecord::read(&mut bits, previous, params, header.origin)?.id);
        }
        bits.finish()?;
        Ok(Self { header, count, records: stream })
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
        let mut r = BitReader::new(self.records);
        let origin = self.header.origin;
        // `parse` decoded every record successfully, so `ok()` never stops early.
        let params = StreamParams::read(&mut r).ok();
        let mut previous = None;
        (0..self.count).map_while(move |_| {
            let rec = DeltaRecord::read(&mut r, previous, params?, origin).ok()?;
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
/// when `records` is empty. Packing stops at a record no datagram can carry
/// ([`DeltaRecord::bits`] is `None`); [`DeltaRecord::choose`] makes none.
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
    // The parameters suit the records and the pinned one at its place among them.
    let split = pinned.map_or(records.len(), |p| records.partition_point(|r| r.id < p.id));
    let params = StreamParams::for_records(records[..split].iter().chain(pinned).chain(&records[split..]));
    // Inserting the pinned record only shortens its neighbour's gap (a code no longer
    // for a smaller value), so its size as a first record is all the room it needs.
    let pinned_bits = match pinned.map(|p| stream_bits(std::iter::once(p), None, params, origin)) {
        Some(None) => return 0,
        Some(Some(bits)) => bits,
        None => 0,
    };
    let room = (MAX_BODY - DELTA_HEADER_LEN) * 8 - STREAM_PARAMS_BITS as usize - pinned_bits;
    let (mut packed, mut datagrams) = (0, 0);
    while (packed < records.len() || (pinned.is_some() && datagrams == 0)) && datagrams < max_datagrams {
        let (mut used, mut previous, mut end) = (0, None, packed);
        while let Some(r) = records.get(end) {
            let Some(bits) = stream_bits(std::iter::once(r), previous, params, origin) else { break };
            if used + bits > room {
                break;
            }
            used += bits;
            previous = Some(r.id);
            end += 1;
        }
        // Every byte up to the datagram's end is written here or by the sealer (the
        // bit writer overwrites what it reaches), so no stale byte can be sent.
        let buf = out.begin(MAX_DATAGRAM);
        buf[0] = PROTOCOL_VERSION;
        buf[1] = PacketKind::StateUpdate as u8;
        let mut pinned_left = pinned;
        let mut count = 0u16;
        let mut w = BitWriter::new(&mut buf[HEADER_LEN + DELTA_HEADER_LEN..HEADER_LEN + MAX_BODY]);
        params.write(&mut w);
        let mut previous = None;
        for r in &records[packed..end] {
            if let Some(p) = pinned_left.filter(|p| p.id < r.id) {
                p.write(&mut w, previous, params, origin);
                previous = Some(p.id);
                count += 1;
                pinned_left = None;
            }
            r.write(&mut w, previous, params, origin);
            previous = Some(r.id);
            count += 1;
        }
        if let Some(p) = pinned_left {
            p.write(&mut w, previous, params, origin);
            count += 1;
        }
        let at = HEADER_LEN + DELTA_HEADER_LEN + w.finish();
        write_delta_header(header, count, &mut buf[HEADER_LEN..]);
        out.finish(at + TAG_LEN);
        ends.push(end);
        datagrams += 1;
        if end == packed {
            // Nothing but the pinned record went in (or the next record cannot be
            // carried): never loop on it.
            break;
        }
        packed = end;
    }
    packed
}

/// A delta update body of a length no datagram has: shorter than its header or longer
/// than [`MAX_BODY`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("a delta update body of {0} bytes (a body holds {DELTA_HEADER_LEN} to {MAX_BODY})")]
pub struct BodyLengthError(pub usize);

/// Appends to `out` a state update datagram (unsealed, ready for
/// [`Sealer::seal_batch`](crate::Sealer::seal_batch)) around `body`, a delta update body
/// as [`pack_deltas`] writes it: the frame for bodies packed elsewhere by the same rules
/// (the CUDA backend packs on the device). Only the length is checked: the body's
/// maker answers for its contents.
pub fn frame_delta_body(body: &[u8], out: &mut DatagramBatch) -> Result<(), BodyLengthError> {
    if !(DELTA_HEADER_LEN..=MAX_BODY).contains(&body.len()) {
        return Err(BodyLengthError(body.len()));
    }
    let buf = out.begin(HEADER_LEN + body.len() + TAG_LEN);
    buf[0] = PROTOCOL_VERSION;
    buf[1] = PacketKind::StateUpdate as u8;
    buf[HEADER_LEN..HEADER_LEN + body.len()].copy_from_slice(body);
    out.finish(HEADER_LEN + body.len() + TAG_LEN);
    Ok(())
}

#[cfg(test)]
#[path = "delta_tests.rs"]
mod tests;
