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
//! **Predicted nudges.** An object that walks steadily changes its bits by about the same
//! each tick, so a nudge can carry the change against a prediction instead: the bits at
//! the base plus the change from the tick before the base to the base (both sides hold
//! both ticks' positions, and the arithmetic is on integers, so the result is exact). A
//! walker at constant speed then costs a byte an axis where its plain change takes two
//! or three. The zone predicts only along a chain of views (the base is the tick before
//! the view's, and the tick before the base is the base of the view before: a tick the
//! gateway took) and only for objects the gateway held at that tick
//! (`crate::views`), and takes whichever form is shorter.
//!
//! **Airborne nudges.** An object in the air moves as the physics' Verlet step says:
//! its velocity kept by the air's drag, less gravity's pull a tick (`integrate` with no
//! action, not standing). A steady prediction misses that by the pull, about 2,850 ulps
//! of the height at heights in [32, 64): two bytes for y in three nudges of four at
//! scenario 2's density (`docs/zones.md`, "Packed views"). The airborne prediction runs
//! that step, with the default physics constants (a fixed part of this format, whatever
//! the world's), on both sides from the same two positions, in `f32` operations that
//! give the same bits everywhere; an object in free flight then costs a byte an axis,
//! its change exactly zero. Only finite positions are predicted this way.
//!
//! Encoding, one nudge after another, ids strictly ascending: a varint of the id's
//! difference from the previous nudge's id (from 0 for the first), shifted left by two,
//! whose low bits say what the change is from (0: the base, 1: the steady prediction,
//! 2: the airborne one; 3 is refused); then the three coordinates' zigzagged bit changes
//! as varints. Varints must be minimal (one encoding per message): `unsigned-varint`
//! refuses the others.

use myriad_core::{EntityId, Vec3};
use myriad_physics::TickConstants;
use myriad_physics::integrate::integrate;
use unsigned_varint::{decode, encode};

use super::WireError;

/// The most bytes a compact nudge takes: a 5-byte id delta and three 3-byte coordinates.
pub const NUDGE_MAX_LEN: usize = 5 + 3 * 3;

/// The smallest encoded nudge (a one-byte id delta, three one-byte coordinates).
const NUDGE_MIN_LEN: usize = 4;

/// A zigzagged change below this takes at most three varint bytes.
const COMPACT_LIMIT: u32 = 1 << 21;

/// What a nudge's change is from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Prediction {
    /// The position at the base tick.
    Off,
    /// The steady prediction: the bits at the base plus their change from the tick
    /// before (`2 × base − before`, on the bits).
    Steady,
    /// The airborne prediction: the physics' step in the air from the tick before and
    /// the base (see the module docs).
    Airborne,
}

impl Prediction {
    /// Whether it needs the position at the tick before the base.
    pub fn needs_before(self) -> bool {
        self != Prediction::Off
    }

    fn code(self) -> u64 {
        match self {
            Prediction::Off => 0,
            Prediction::Steady => 1,
            Prediction::Airborne => 2,
        }
    }
}

/// An object's new position as the wrapping change of each coordinate's `f32` bits since
/// the view's base tick, or since a prediction from the base and the tick before it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Nudge {
    /// The object.
    pub id: EntityId,
    /// What `bits` are the change from.
    pub prediction: Prediction,
    /// Per axis: the new coordinate's bits minus (wrapping) those at the base tick, or
    /// those predicted.
    pub bits: [i32; 3],
}

/// Each coordinate's bits.
fn bits(v: Vec3) -> [u32; 3] {
    [v.x, v.y, v.z].map(f32::to_bits)
}

/// The steady prediction from the tick before the base (`before`) and the base (`base`):
/// each coordinate's bits at the base plus their change from `before` (wrapping).
fn predict(before: Vec3, base: Vec3) -> [u32; 3] {
    let (a, b) = (bits(before), bits(base));
    [0, 1, 2].map(|i| b[i].wrapping_add(b[i].wrapping_sub(a[i])))
}

/// The airborne prediction: the physics' step of an object in the air with no action,
/// from `before` and `base`, with the default constants; `None` unless both are finite
/// (a NaN's bits after arithmetic are not the same on every machine).
fn predict_airborne(before: Vec3, base: Vec3) -> Option<[u32; 3]> {
    if !(before.is_finite() && base.is_finite()) {
        return None;
    }
    let (mut pos, mut prev) = (base, before);
    integrate(&mut pos, &mut prev, 0, false, &TickConstants::default());
    Some(bits(pos))
}

impl Nudge {
    /// The nudge that takes `from` to `to` exactly.
    pub fn between(id: EntityId, from: Vec3, to: Vec3) -> Nudge {
        Nudge::change(id, Prediction::Off, bits(from), to)
    }

    /// The steadily predicted nudge that takes the object from `before` (its position at
    /// the tick before the base) and `from` (at the base) to `to` exactly.
    pub fn predicted(id: EntityId, before: Vec3, from: Vec3, to: Vec3) -> Nudge {
        Nudge::change(id, Prediction::Steady, predict(before, from), to)
    }

    /// The airborne nudge that does the same, or `None` where positions are not finite.
    pub fn airborne(id: EntityId, before: Vec3, from: Vec3, to: Vec3) -> Option<Nudge> {
        Some(Nudge::change(id, Prediction::Airborne, predict_airborne(before, from)?, to))
    }

    /// The shortest of the plain nudge and, given the tick before, the two predicted ones
    /// (the earlier of these when equal).
    pub fn shortest(id: EntityId, before: Option<Vec3>, from: Vec3, to: Vec3) -> Nudge {
        let plain = Nudge::between(id, from, to);
        let Some(before) = before else { return plain };
        let best = Nudge::shorter(plain, Nudge::predicted(id, before, from, to));
        // A byte an axis is the least a nudge takes: no third form can be shorter (and
        // the physics' step costs more than the others).
        if best.bits.iter().all(|&c| varint_len(u64::from(zigzag(c))) == 1) {
            return best;
        }
        match Nudge::airborne(id, before, from, to) {
            Some(air) => Nudge::shorter(best, air),
            None => best,
        }
    }

    fn change(id: EntityId, prediction: Prediction, from: [u32; 3], to: Vec3) -> Nudge {
        let to = bits(to);
        Nudge { id, prediction, bits: [0, 1, 2].map(|i| to[i].wrapping_sub(from[i]) as i32) }
    }

    /// The position it gives from the base tick's `from` (and, if it is predicted, the
    /// tick before's `before`; `None` then: no position; nor for an airborne prediction
    /// from positions that are not finite).
    pub fn apply(&self, before: Option<Vec3>, from: Vec3) -> Option<Vec3> {
        let start = match (self.prediction, before) {
            (Prediction::Off, _) => bits(from),
            (Prediction::Steady, Some(before)) => predict(before, from),
            (Prediction::Airborne, Some(before)) => predict_airborne(before, from)?,
            (_, None) => return None,
        };
        let a = |i: usize| f32::from_bits(start[i].wrapping_add(self.bits[i] as u32));
        Some(Vec3::new(a(0), a(1), a(2)))
    }

    /// The bytes it takes on the wire (its id's delta from `prev`'s).
    fn len(&self, prev: u32) -> usize {
        varint_len(id_word(self, prev)) + self.bits.iter().map(|&c| varint_len(u64::from(zigzag(c)))).sum::<usize>()
    }

    /// Whichever of `a` and `b` takes fewer bytes (`a` when equal).
    pub fn shorter(a: Nudge, b: Nudge) -> Nudge {
        if b.len(0) < a.len(0) { b } else { a }
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

/// The first varint of a nudge: its id's delta from `prev`, and what its change is from.
fn id_word(n: &Nudge, prev: u32) -> u64 {
    u64::from(n.id.0 - prev) << 2 | n.prediction.code()
}

/// The bytes of `v` as a LEB128 varint.
fn varint_len(v: u64) -> usize {
    (64 - v.leading_zeros()).max(1).div_ceil(7) as usize
}

/// Appends `nudges` (ids strictly ascending, checked by the caller).
pub(super) fn put_nudges(b: &mut Vec<u8>, nudges: &[Nudge]) {
    let mut prev = 0u32;
    for n in nudges {
        let mut buf = encode::u64_buffer();
        b.extend_from_slice(encode::u64(id_word(n, prev), &mut buf));
        prev = n.id.0;
        for &c in &n.bits {
            b.extend_from_slice(encode::u64(u64::from(zigzag(c)), &mut buf));
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
        let (word, r) = decode::u64(rest).map_err(bad)?;
        let prediction = match word & 3 {
            0 => Prediction::Off,
            1 => Prediction::Steady,
            2 => Prediction::Airborne,
            _ => return Err(WireError::Field("view nudges")),
        };
        let delta = u32::try_from(word >> 2).map_err(|_| WireError::Field("view ids"))?;
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
        out.push(Nudge { id: EntityId(id), prediction, bits });
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
    let mut prev = 0u32;
    nudges
        .iter()
        .map(|n| {
            let len = n.len(prev);
            prev = n.id.0;
            len
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
            assert_eq!(n.apply(None, a).map(bits), Some(bits(b)));
            // Predicted from any two earlier positions, as exact.
            for before in [a, b, Vec3::new(-3.0, f32::MAX, 0.5)] {
                let p = Nudge::predicted(EntityId(3), before, a, b);
                assert_eq!(p.apply(Some(before), a).map(bits), Some(bits(b)));
                assert_eq!(p.apply(None, a), None, "a prediction needs the tick before");
                if before.is_finite() && a.is_finite() {
                    let air = Nudge::airborne(EntityId(3), before, a, b).expect("finite");
                    assert_eq!(air.apply(Some(before), a).map(bits), Some(bits(b)));
                    assert_eq!(air.apply(None, a), None, "a prediction needs the tick before");
                }
            }
        }
        // A short walk is compact; a jump across the map or through zero is not.
        assert!(Nudge::between(EntityId(1), cases[0].0, cases[0].1).compact());
        assert!(!Nudge::between(EntityId(1), cases[1].0, cases[1].1).compact());
        assert!(!Nudge::between(EntityId(1), Vec3::splat(10.0), Vec3::splat(900.0)).compact());
    }

    #[test]
    fn a_steady_walk_predicted_takes_a_byte_an_axis() {
        // A walk of 0.1 units a tick near 500 (3,277 ulps), slowing a little.
        let (before, from, to) =
            (Vec3::new(499.8, 12.5, 3.0), Vec3::new(499.9, 12.5, 2.95), Vec3::new(499.99995, 12.5, 2.900001));
        let plain = Nudge::between(EntityId(9), from, to);
        let predicted = Nudge::predicted(EntityId(9), before, from, to);
        assert_eq!((plain.len(0), predicted.len(0)), (1 + 2 + 1 + 3, 1 + 1 + 1 + 1));
        assert_eq!(Nudge::shorter(plain, predicted), predicted);
        assert_eq!(Nudge::shorter(plain, plain), plain);
    }

    #[test]
    fn a_fall_predicted_airborne_takes_a_byte_an_axis() {
        // Thrown up and across at 40 units, then falling: the physics' own steps.
        let k = TickConstants::default();
        let (mut pos, mut prev) = (Vec3::new(300.0, 40.0, 7.0), Vec3::new(299.9, 39.8, 7.05));
        let mut path = vec![prev, pos];
        for _ in 0..40 {
            integrate(&mut pos, &mut prev, 0, false, &k);
            path.push(pos);
        }
        for w in path.windows(3) {
            let (before, from, to) = (w[0], w[1], w[2]);
            let air = Nudge::airborne(EntityId(9), before, from, to).unwrap();
            assert_eq!(air.bits, [0; 3], "free flight is the prediction exactly");
            assert_eq!(air.len(0), 4);
            let best = Nudge::shortest(EntityId(9), Some(before), from, to);
            assert_eq!(best.prediction, Prediction::Airborne);
            assert!(Nudge::predicted(EntityId(9), before, from, to).len(0) > 4, "the steady one misses gravity");
        }
        // On the ground (no change), the plain nudge is as short and comes first.
        let still = Vec3::new(1.0, 2.0, 3.0);
        assert_eq!(Nudge::shortest(EntityId(9), Some(still), still, still).prediction, Prediction::Off);
        assert_eq!(Nudge::shortest(EntityId(9), None, still, still).prediction, Prediction::Off);
        // Not from positions that are not finite.
        let nan = Vec3::new(f32::NAN, 0.0, 0.0);
        assert_eq!(Nudge::airborne(EntityId(9), nan, still, still), None);
        let forged = Nudge { id: EntityId(9), prediction: Prediction::Airborne, bits: [0; 3] };
        assert_eq!(forged.apply(Some(still), nan), None);
    }

    #[test]
    fn nudges_round_trip_at_their_computed_length_and_refuse_bad_bytes() {
        let list = vec![
            Nudge { id: EntityId(0), prediction: Prediction::Off, bits: [0, -1, 1] },
            Nudge { id: EntityId(200), prediction: Prediction::Steady, bits: [3277, -(1 << 20), (1 << 20) - 1] },
            Nudge { id: EntityId(u32::MAX), prediction: Prediction::Airborne, bits: [i32::MIN, i32::MAX, 64] },
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
        // The fourth kind of change, which does not exist.
        assert_eq!(nudges(&[3, 0, 0, 0], 1), Err(WireError::Field("view nudges")));
        // Ids past u32::MAX.
        let mut over = Vec::new();
        put_nudges(&mut over, &list[2..]);
        over.extend_from_slice(&[2, 0, 0, 0]);
        assert_eq!(nudges(&over, 2), Err(WireError::Field("view ids")));
    }
}
