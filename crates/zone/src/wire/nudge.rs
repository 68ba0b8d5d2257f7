//! Compact moves for a zone's view (`docs/zones.md`, "States by interest"): an object's
//! new position as the change of each coordinate's bits since the view's base tick,
//! whose state the gateway holds.
//!
//! Why bits and not a quantised offset: a gateway's world must hold the zones' positions
//! exactly (its players' records are built from them, and must be those of one process),
//! and an `f32`'s bits, read as an integer, change by about `d / ulp` when the value moves
//! by `d`; at a coordinate of 500 (an ulp of 2⁻¹⁵) a walk of 0.1 units is 3,277. The
//! wrapping difference of the bits is exact and always reversible, whatever the two
//! values; zigzag and LEB128 varints make small changes a byte or two. A nudge is used
//! only when each coordinate takes at most three bytes ([`Nudge::compact`]): then the
//! whole nudge (id delta included) is at most [`NUDGE_MAX_LEN`] bytes, under a 16-byte
//! move's.
//!
//! Encoding, one nudge after another, ids strictly ascending: the id as a varint of its
//! difference from the previous nudge's id (from 0 for the first), then the three
//! coordinates' zigzagged bit changes as varints. Varints must be minimal (one encoding
//! per message): `unsigned-varint` refuses the others.

use myriad_core::{EntityId, Vec3};
use unsigned_varint::{decode, encode};

use super::WireError;

/// The most bytes a compact nudge takes: a 5-byte id delta and three 3-byte coordinates.
pub const NUDGE_MAX_LEN: usize = 5 + 3 * 3;

/// The smallest encoded nudge (a one-byte id delta, three one-byte coordinates).
const NUDGE_MIN_LEN: usize = 4;

/// A zigzagged change below this takes at most three varint bytes.
const COMPACT_LIMIT: u32 = 1 << 21;

/// An object's new position as the wrapping change of each coordinate's `f32` bits since
/// the view's base tick.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Nudge {
    /// The object.
    pub id: EntityId,
    /// Per axis: the new coordinate's bits minus (wrapping) those at the base tick.
    pub bits: [i32; 3],
}

impl Nudge {
    /// The nudge that takes `from` to `to` exactly.
    pub fn between(id: EntityId, from: Vec3, to: Vec3) -> Nudge {
        let d = |a: f32, b: f32| b.to_bits().wrapping_sub(a.to_bits()) as i32;
        Nudge { id, bits: [d(from.x, to.x), d(from.y, to.y), d(from.z, to.z)] }
    }

    /// The position it gives from the base tick's `from`.
    pub fn apply(&self, from: Vec3) -> Vec3 {
        let a = |c: f32, d: i32| f32::from_bits(c.to_bits().wrapping_add(d as u32));
        Vec3::new(a(from.x, self.bits[0]), a(from.y, self.bits[1]), a(from.z, self.bits[2]))
    }

    /// Whether every coordinate takes at most three bytes (so the nudge is smaller than
    /// a move): the zone sends the others as moves.
    pub fn compact(&self) -> bool {
        self.bits.iter().all(|&b| zigzag(b) < COMPACT_LIMIT)
    }
}

fn zigzag(v: i32) -> u32 {
    ((v << 1) ^ (v >> 31)) as u32
}

fn unzigzag(u: u32) -> i32 {
    ((u >> 1) as i32) ^ -((u & 1) as i32)
}

/// Appends `nudges` (ids strictly ascending, checked by the caller).
pub(super) fn put_nudges(b: &mut Vec<u8>, nudges: &[Nudge]) {
    let mut prev = 0u32;
    for n in nudges {
        let mut buf = encode::u32_buffer();
        b.extend_from_slice(encode::u32(n.id.0 - prev, &mut buf));
        prev = n.id.0;
        for &c in &n.bits {
            b.extend_from_slice(encode::u32(zigzag(c), &mut buf));
        }
    }
}

/// Reads exactly `count` nudges from all of `bytes`: ids strictly ascending, varints
/// minimal, nothing left over.
pub(super) fn nudges(bytes: &[u8], count: u32) -> Result<Vec<Nudge>, WireError> {
    let bad = |_| WireError::Field("view nudges");
    // A forged count must not make the decoder allocate what the bytes cannot hold.
    if count as usize > bytes.len() / NUDGE_MIN_LEN {
        return Err(WireError::Field("view nudges"));
    }
    let mut out = Vec::with_capacity(count as usize);
    let mut rest = bytes;
    let mut prev: Option<u32> = None;
    for _ in 0..count {
        let (delta, r) = decode::u32(rest).map_err(bad)?;
        let id = match prev {
            None => delta,
            Some(_) if delta == 0 => return Err(WireError::Field("view ids")),
            Some(p) => p.checked_add(delta).ok_or(WireError::Field("view ids"))?,
        };
        let mut bits = [0i32; 3];
        let mut r = r;
        for c in &mut bits {
            let (u, r2) = decode::u32(r).map_err(bad)?;
            *c = unzigzag(u);
            r = r2;
        }
        out.push(Nudge { id: EntityId(id), bits });
        prev = Some(id);
        rest = r;
    }
    if !rest.is_empty() {
        return Err(WireError::Field("view nudges"));
    }
    Ok(out)
}

/// The bytes `nudges` take.
pub(super) fn nudges_len(nudges: &[Nudge]) -> usize {
    let len = |v: u32| (32 - v.leading_zeros()).max(1).div_ceil(7) as usize;
    let mut prev = 0u32;
    nudges
        .iter()
        .map(|n| {
            let id = len(n.id.0 - prev);
            prev = n.id.0;
            id + n.bits.iter().map(|&c| len(zigzag(c))).sum::<usize>()
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_nudge_is_exact_both_ways_whatever_the_values() {
        let cases = [
            (Vec3::new(500.0, 12.5, 3.0), Vec3::new(500.1, 12.49, 2.95)),
            (Vec3::new(-0.0, 1e-30, -7.0), Vec3::new(0.0, -1e-30, 7.0)),
            (Vec3::new(f32::MAX, f32::MIN_POSITIVE, 1.0), Vec3::new(-f32::MAX, 0.0, 1.0)),
        ];
        for (a, b) in cases {
            let n = Nudge::between(EntityId(3), a, b);
            let got = n.apply(a);
            assert_eq!([got.x, got.y, got.z].map(f32::to_bits), [b.x, b.y, b.z].map(f32::to_bits));
        }
        // A short walk is compact; a jump across the map or through zero is not.
        assert!(Nudge::between(EntityId(1), cases[0].0, cases[0].1).compact());
        assert!(!Nudge::between(EntityId(1), cases[1].0, cases[1].1).compact());
        assert!(!Nudge::between(EntityId(1), Vec3::splat(10.0), Vec3::splat(900.0)).compact());
    }

    #[test]
    fn nudges_round_trip_at_their_computed_length_and_refuse_bad_bytes() {
        let list = vec![
            Nudge { id: EntityId(0), bits: [0, -1, 1] },
            Nudge { id: EntityId(200), bits: [3277, -(1 << 20), (1 << 20) - 1] },
            Nudge { id: EntityId(u32::MAX), bits: [i32::MIN, i32::MAX, 64] },
        ];
        let mut b = Vec::new();
        put_nudges(&mut b, &list);
        assert_eq!(b.len(), nudges_len(&list));
        assert_eq!(b.len(), 4 + (2 + 2 + 3 + 3) + (5 + 5 + 5 + 2));
        assert_eq!(nudges(&b, 3).unwrap(), list);
        assert!(nudges(&b, 2).is_err(), "bytes left over");
        assert!(nudges(&b[..b.len() - 1], 3).is_err(), "truncated");
        assert!(nudges(&b, 1_000).is_err(), "a count the bytes cannot hold");
        // The same id twice (a zero delta after the first).
        assert_eq!(nudges(&[1, 0, 0, 0, 0, 0, 0, 0], 2), Err(WireError::Field("view ids")));
        // A non-minimal varint (0 written in two bytes).
        assert!(nudges(&[0x80, 0x00, 0, 0, 0], 1).is_err());
        // Ids past u32::MAX.
        let mut over = Vec::new();
        put_nudges(&mut over, &list[2..]);
        over.extend_from_slice(&[1, 0, 0, 0]);
        assert_eq!(nudges(&over, 2), Err(WireError::Field("view ids")));
    }
}
