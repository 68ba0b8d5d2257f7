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
//! **Ground nudges.** Most moving objects walk on the terrain (four in five nudges at
//! scenario 2's density): their x and z follow the physics' step on the ground (the
//! velocity kept by drag and friction plus the held direction's push: `integrate` with
//! the object's action, standing), and the floor clamps their height to the terrain's
//! under their new x and z, which a steady prediction misses by the slope's change and
//! gravity's pull. The ground prediction runs that step for x and z, then takes y as the
//! floor (the terrain's height plus the object's half height, not below the world's
//! lower bound) at the new x and z, once their changes are applied: an object walking
//! on the terrain without a contact costs its three changes of zero. It reads what both
//! sides hold: the object's action (a view carries each change of it, `acts`), its half
//! height (a whole record's), and the world's terrain and bounds ([`GroundWorld`]),
//! which a zone uses only for a gateway whose subscription names the same
//! [`ground_fingerprint`].
//!
//! Encoding, one nudge after another, ids strictly ascending: a varint of the id's
//! difference from the previous nudge's id (from 0 for the first), shifted left by
//! three, whose bit 2 says that every change is zero (the prediction is exact: half the
//! nudges at scenario 2's density once they may be on the ground) and whose two low bits
//! say what the change is from (0: the base, 1: the steady prediction, 2: the airborne
//! one, 3: the ground one); then, unless bit 2 is set, the three coordinates' zigzagged
//! bit changes as varints, not all zero. Varints must be minimal (one encoding per
//! message): `unsigned-varint` refuses the others.

use myriad_core::{Aabb, EntityId, Terrain, Vec3};
use myriad_physics::TickConstants;
use myriad_physics::integrate::{floor_at, integrate};
use unsigned_varint::{decode, encode};

use super::WireError;

/// The most bytes a compact nudge takes: a 5-byte id delta and three 3-byte coordinates.
pub const NUDGE_MAX_LEN: usize = 5 + 3 * 3;

/// The smallest encoded nudge (a one-byte id word, no changes).
const NUDGE_MIN_LEN: usize = 1;

/// The id word's bit saying that every change is zero (none follow).
const EXACT: u64 = 1 << 2;

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
    /// The ground prediction: the physics' step on the ground for x and z, the floor
    /// under them for y (see the module docs).
    Ground,
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
            Prediction::Ground => 3,
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

/// The world a ground prediction reads: its terrain and bounds (the floor under an
/// object). A zone predicts on the ground only for a gateway whose world has the same
/// [`ground_fingerprint`].
#[derive(Clone, Copy, Debug)]
pub struct GroundWorld<'a> {
    /// The terrain.
    pub terrain: &'a Terrain,
    /// The world's bounds (an object's floor is never below the lower one).
    pub bounds: &'a Aabb,
}

impl GroundWorld<'_> {
    /// What a subscription names so that a zone knows the gateway computes the same
    /// floors: a hash of the terrain's content and of the bounds; never 0 (which names
    /// none).
    pub fn fingerprint(&self) -> u64 {
        ground_fingerprint(self.terrain, self.bounds)
    }

    /// The floor at (`x`, `z`) of an object `half_y` half high: the physics' own.
    fn floor(&self, half_y: f32, x: f32, z: f32) -> f32 {
        floor_at(self.terrain, self.bounds, half_y, x, z)
    }

    /// Height `y` at (`x`, `z`) after the physics' limits: below the world's top, on or
    /// above the floor.
    fn settle(&self, half_y: f32, x: f32, y: f32, z: f32) -> f32 {
        let top = self.bounds.max.y - half_y;
        let y = if y > top { top } else { y };
        let floor = self.floor(half_y, x, z);
        if y < floor { floor } else { y }
    }
}

/// A world's ground fingerprint, kept: hashed again only when its terrain (by the
/// terrain's stamp: a terrain never changes once made) or its bounds change, as hashing
/// a terrain is a pass over its samples.
#[derive(Clone, Copy, Debug, Default)]
pub struct FingerprintCache(Option<((u64, [u32; 6]), u64)>);

impl FingerprintCache {
    /// `world`'s fingerprint.
    pub fn of(&mut self, world: GroundWorld<'_>) -> u64 {
        let [a, b] = [world.bounds.min, world.bounds.max].map(|v| v.to_array().map(f32::to_bits));
        let which = (world.terrain.stamp(), [a[0], a[1], a[2], b[0], b[1], b[2]]);
        match self.0 {
            Some((w, f)) if w == which => f,
            _ => {
                let f = world.fingerprint();
                self.0 = Some((which, f));
                f
            }
        }
    }
}

/// [`GroundWorld::fingerprint`] of `terrain` and `bounds`.
pub fn ground_fingerprint(terrain: &Terrain, bounds: &Aabb) -> u64 {
    let mut h = xxhash_rust::xxh3::Xxh3::new();
    h.update(&terrain.content_hash().to_le_bytes());
    for c in [bounds.min, bounds.max].iter().flat_map(|v| v.to_array()) {
        h.update(&c.to_bits().to_le_bytes());
    }
    h.digest().max(1)
}

/// What a ground prediction reads of one object besides its positions: the world, the
/// action it held in the step (the one its state has after it) and its half height.
#[derive(Clone, Copy, Debug)]
pub struct Ground<'a> {
    /// The world.
    pub world: GroundWorld<'a>,
    /// The object's action.
    pub action: u8,
    /// The object's half height.
    pub half_y: f32,
}

/// The ground prediction before the limits: the physics' step without contacts from
/// `before` and `base`, with the object's action, standing if the terrain held it at the
/// base (as the physics' flag says: within the ground tolerance of its floor), and
/// without vertical velocity if the floor clamped it there (exactly on its floor; the
/// limits then drop that velocity); `None` unless both are finite.
fn predict_ground(before: Vec3, base: Vec3, g: &Ground) -> Option<Vec3> {
    if !(before.is_finite() && base.is_finite()) {
        return None;
    }
    let k = TickConstants::default();
    let floor = g.world.floor(g.half_y, base.x, base.z);
    let standing = base.y <= floor + k.ground_tolerance;
    let prev_y = if base.y == floor { base.y } else { before.y };
    let (mut pos, mut prev) = (base, Vec3::new(before.x, prev_y, before.z));
    integrate(&mut pos, &mut prev, g.action, standing, &k);
    Some(pos)
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

    /// The ground nudge that does the same, or `None` where positions are not finite.
    pub fn ground(id: EntityId, before: Vec3, from: Vec3, to: Vec3, g: &Ground) -> Option<Nudge> {
        let p = predict_ground(before, from, g)?;
        if !to.is_finite() {
            return None;
        }
        let y = g.world.settle(g.half_y, to.x, p.y, to.z);
        Some(Nudge::change(id, Prediction::Ground, bits(Vec3::new(p.x, y, p.z)), to))
    }

    /// The shortest of the plain nudge and, given the tick before, the predicted ones
    /// (the ground one only with `ground`; the earliest of them when equal).
    pub fn shortest(id: EntityId, before: Option<Vec3>, from: Vec3, to: Vec3, ground: Option<&Ground>) -> Nudge {
        let plain = Nudge::between(id, from, to);
        let Some(before) = before else { return plain };
        let mut best = Nudge::shorter(plain, Nudge::predicted(id, before, from, to));
        // No change at all is the least a nudge takes: no other form can be shorter (and
        // the physics' steps cost more than the others).
        let least = |n: &Nudge| n.bits == [0; 3];
        if least(&best) {
            return best;
        }
        if let Some(air) = Nudge::airborne(id, before, from, to) {
            best = Nudge::shorter(best, air);
        }
        match ground.filter(|_| !least(&best)).and_then(|g| Nudge::ground(id, before, from, to, g)) {
            Some(on_ground) => Nudge::shorter(best, on_ground),
            None => best,
        }
    }

    fn change(id: EntityId, prediction: Prediction, from: [u32; 3], to: Vec3) -> Nudge {
        let to = bits(to);
        Nudge { id, prediction, bits: [0, 1, 2].map(|i| to[i].wrapping_sub(from[i]) as i32) }
    }

    /// The position it gives from the base tick's `from` (and, if it is predicted, the
    /// tick before's `before`; `None` then: no position; nor for an airborne or ground
    /// prediction from positions that are not finite, nor for a ground one without
    /// `ground` or whose x or z comes out not finite).
    pub fn apply(&self, before: Option<Vec3>, from: Vec3, ground: Option<&Ground>) -> Option<Vec3> {
        let at = |start: u32, i: usize| f32::from_bits(start.wrapping_add(self.bits[i] as u32));
        let start = match (self.prediction, before) {
            (Prediction::Off, _) => bits(from),
            (Prediction::Steady, Some(before)) => predict(before, from),
            (Prediction::Airborne, Some(before)) => predict_airborne(before, from)?,
            (Prediction::Ground, Some(before)) => {
                let g = ground?;
                let p = predict_ground(before, from, g)?;
                let (x, z) = (at(p.x.to_bits(), 0), at(p.z.to_bits(), 2));
                // The floor under a coordinate that is not finite is not the same bits
                // on every machine: no zone sends such a nudge.
                if !(x.is_finite() && z.is_finite()) {
                    return None;
                }
                let y = g.world.settle(g.half_y, x, p.y, z);
                return Some(Vec3::new(x, at(y.to_bits(), 1), z));
            }
            (_, None) => return None,
        };
        Some(Vec3::new(at(start[0], 0), at(start[1], 1), at(start[2], 2)))
    }

    /// The bytes it takes on the wire (its id's delta from `prev`'s).
    fn len(&self, prev: u32) -> usize {
        let changes = match self.bits {
            [0, 0, 0] => 0,
            bits => bits.iter().map(|&c| varint_len(u64::from(zigzag(c)))).sum::<usize>(),
        };
        varint_len(id_word(self, prev)) + changes
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

/// The first varint of a nudge: its id's delta from `prev`, whether its changes are all
/// zero, and what its change is from.
fn id_word(n: &Nudge, prev: u32) -> u64 {
    let exact = if n.bits == [0; 3] { EXACT } else { 0 };
    u64::from(n.id.0 - prev) << 3 | exact | n.prediction.code()
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
        if n.bits != [0; 3] {
            for &c in &n.bits {
                b.extend_from_slice(encode::u64(u64::from(zigzag(c)), &mut buf));
            }
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
            _ => Prediction::Ground,
        };
        let delta = u32::try_from(word >> 3).map_err(|_| WireError::Field("view ids"))?;
        let id = match prev {
            None => delta,
            Some(_) if delta == 0 => return Err(WireError::Field("view ids")),
            Some(p) => p.checked_add(delta).ok_or(WireError::Field("view ids"))?,
        };
        let mut bits = [0i32; 3];
        let mut r = r;
        if word & EXACT == 0 {
            for c in &mut bits {
                let (u, r2) = decode::u32(r).map_err(bad)?;
                *c = unzigzag(u);
                r = r2;
            }
            // Three zero changes have their own, shorter encoding.
            if bits == [0; 3] {
                return Err(WireError::Field("view nudges"));
            }
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
    use myriad_core::Action;

    #[test]
    fn a_nudge_is_exact_both_ways_whatever_the_values() {
        let cases = [
            (Vec3::new(500.0, 12.5, 3.0), Vec3::new(500.1, 12.49, 2.95)),
            (Vec3::new(-0.0, 1e-30, -7.0), Vec3::new(0.0, -1e-30, 7.0)),
            (Vec3::new(f32::MAX, f32::MIN_POSITIVE, 1.0), Vec3::new(-f32::MAX, 0.0, 1.0)),
        ];
        for (a, b) in cases {
            let n = Nudge::between(EntityId(3), a, b);
            assert_eq!(n.apply(None, a, None).map(bits), Some(bits(b)));
            // Predicted from any two earlier positions, as exact.
            for before in [a, b, Vec3::new(-3.0, f32::MAX, 0.5)] {
                let p = Nudge::predicted(EntityId(3), before, a, b);
                assert_eq!(p.apply(Some(before), a, None).map(bits), Some(bits(b)));
                assert_eq!(p.apply(None, a, None), None, "a prediction needs the tick before");
                if before.is_finite() && a.is_finite() {
                    let air = Nudge::airborne(EntityId(3), before, a, b).expect("finite");
                    assert_eq!(air.apply(Some(before), a, None).map(bits), Some(bits(b)));
                    assert_eq!(air.apply(None, a, None), None, "a prediction needs the tick before");
                    let (terrain, bounds) = hills();
                    let g =
                        Ground { world: GroundWorld { terrain: &terrain, bounds: &bounds }, action: 5, half_y: 0.9 };
                    if let Some(on) = Nudge::ground(EntityId(3), before, a, b, &g) {
                        assert_eq!(on.apply(Some(before), a, Some(&g)).map(bits), Some(bits(b)));
                        assert_eq!(on.apply(Some(before), a, None), None, "a ground prediction needs the world");
                        assert_eq!(on.apply(None, a, Some(&g)), None, "a prediction needs the tick before");
                    }
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
    fn a_fall_predicted_airborne_takes_one_byte() {
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
            assert_eq!(air.len(0), 1, "its id word alone");
            let best = Nudge::shortest(EntityId(9), Some(before), from, to, None);
            assert_eq!(best.prediction, Prediction::Airborne);
            assert!(Nudge::predicted(EntityId(9), before, from, to).len(0) > 4, "the steady one misses gravity");
        }
        // On the ground (no change), the plain nudge is as short and comes first.
        let still = Vec3::new(1.0, 2.0, 3.0);
        assert_eq!(Nudge::shortest(EntityId(9), Some(still), still, still, None).prediction, Prediction::Off);
        assert_eq!(Nudge::shortest(EntityId(9), None, still, still, None).prediction, Prediction::Off);
        // Not from positions that are not finite.
        let nan = Vec3::new(f32::NAN, 0.0, 0.0);
        assert_eq!(Nudge::airborne(EntityId(9), nan, still, still), None);
        let forged = Nudge { id: EntityId(9), prediction: Prediction::Airborne, bits: [0; 3] };
        assert_eq!(forged.apply(Some(still), nan, None), None);
    }

    /// A hilly terrain over a world 200 units wide.
    fn hills() -> (Terrain, Aabb) {
        use myriad_core::terrain::TerrainPlacement;
        let at = TerrainPlacement { origin_x: 0.0, origin_z: 0.0, extent_x: 200.0, extent_z: 200.0, base_y: 0.0 };
        let bounds = Aabb::new(Vec3::new(0.0, 0.0, 0.0), Vec3::new(200.0, 100.0, 200.0));
        (Terrain::generate(11, 65, 65, 30.0, at).unwrap(), bounds)
    }

    #[test]
    fn a_walk_on_the_hills_predicted_on_the_ground_takes_one_byte() {
        // The physics' own steps of an object walking on the terrain (forward and right,
        // then standing still), over slopes that change its height every tick.
        let k = TickConstants::default();
        let (terrain, bounds) = hills();
        let world = GroundWorld { terrain: &terrain, bounds: &bounds };
        let half = Vec3::new(0.4, 0.9, 0.4);
        let start = Vec3::new(60.0, terrain.height_at(60.0, 70.0) + half.y, 70.0);
        let (mut pos, mut prev, mut on_terrain) = (start, start, true);
        let mut path = vec![(pos, 0u8)];
        for tick in 0..90 {
            let action = if tick < 60 { Action::FORWARD | Action::RIGHT } else { 0 };
            integrate(&mut pos, &mut prev, action, on_terrain, &k);
            let flags = myriad_physics::integrate::enforce_limits(&mut pos, &mut prev, half, &bounds, &terrain, &k);
            on_terrain = flags != 0;
            path.push((pos, action));
        }
        let (mut ground, mut steady, mut chosen) = (0, 0, 0);
        for w in path.windows(3).skip(1) {
            let ((before, _), (from, _), (to, action)) = (w[0], w[1], w[2]);
            let g = Ground { world, action, half_y: half.y };
            let on = Nudge::ground(EntityId(9), before, from, to, &g).unwrap();
            assert_eq!(on.apply(Some(before), from, Some(&g)).map(bits), Some(bits(to)));
            // The floor clamps the height every tick: the prediction is exact, and the
            // shortest form is the id word alone (the ground's, unless a form before it
            // is as short: standing still, the plain one; in the air, the airborne one).
            let steady_len = Nudge::predicted(EntityId(9), before, from, to).len(0);
            if on.bits == [0; 3] {
                ground += 1;
                let best = Nudge::shortest(EntityId(9), Some(before), from, to, Some(&g));
                assert_eq!(best.len(0), 1);
                chosen += usize::from(best.prediction == Prediction::Ground);
            }
            steady += usize::from(steady_len == 1);
        }
        assert_eq!(ground, 88, "every step predicted exactly on the ground");
        assert!(chosen >= 40, "the ground's form taken {chosen} times of 88");
        assert!(steady < 30, "the steady prediction misses the slopes: {steady} of 88");
        // Without the world the ground form is never chosen.
        let ((before, _), (from, _), (to, _)) = (path[10], path[11], path[12]);
        assert_ne!(Nudge::shortest(EntityId(9), Some(before), from, to, None).prediction, Prediction::Ground);
        // A forged ground nudge that moves x past the finite numbers gives no position.
        let g = Ground { world, action: 0, half_y: half.y };
        let forged = Nudge {
            id: EntityId(9),
            prediction: Prediction::Ground,
            bits: [0x7f80_0000 - 60f32.to_bits() as i32, 0, 0],
        };
        assert_eq!(forged.apply(Some(from), from, Some(&g)), None);
        // The fingerprint names the terrain's content and the bounds, never 0.
        let (again, _) = hills();
        assert_eq!(world.fingerprint(), ground_fingerprint(&again, &bounds));
        let wider = Aabb::new(bounds.min, bounds.max + Vec3::X);
        assert_ne!(world.fingerprint(), ground_fingerprint(&terrain, &wider));
        assert_ne!(world.fingerprint(), 0);
    }

    #[test]
    fn nudges_round_trip_at_their_computed_length_and_refuse_bad_bytes() {
        let list = vec![
            Nudge { id: EntityId(0), prediction: Prediction::Off, bits: [0, -1, 1] },
            Nudge { id: EntityId(200), prediction: Prediction::Steady, bits: [3277, -(1 << 20), (1 << 20) - 1] },
            Nudge { id: EntityId(201), prediction: Prediction::Ground, bits: [0, 0, -64] },
            Nudge { id: EntityId(202), prediction: Prediction::Ground, bits: [0, 0, 0] },
            Nudge { id: EntityId(u32::MAX), prediction: Prediction::Airborne, bits: [i32::MIN, i32::MAX, 64] },
        ];
        let mut b = Vec::new();
        put_nudges(&mut b, &list);
        assert_eq!(b.len(), nudges_len(&list));
        // The exact one (id 202) is its id word alone.
        assert_eq!(b.len(), 4 + (2 + 2 + 3 + 3) + (1 + 1 + 1 + 1) + 1 + (5 + 5 + 5 + 2));
        assert_eq!(nudges(&b, 5).unwrap(), list);
        assert!(nudges(&b, 4).is_err(), "bytes left over");
        assert!(nudges(&b[..b.len() - 1], 5).is_err(), "truncated");
        assert!(nudges(&b, 1_000).is_err(), "a count the bytes cannot hold");
        // The same id twice (a zero delta after the first).
        assert_eq!(nudges(&[5, 5], 2), Err(WireError::Field("view ids")));
        // A non-minimal varint (0 written in two bytes).
        assert!(nudges(&[0x80, 0x00, 0, 0, 0], 1).is_err());
        // The fourth kind of change: the ground's; exact, its id word alone.
        assert_eq!(
            nudges(&[3, 2, 0, 0], 1).unwrap()[0],
            Nudge { id: EntityId(0), prediction: Prediction::Ground, bits: [1, 0, 0] }
        );
        assert_eq!(
            nudges(&[7], 1).unwrap()[0],
            Nudge { id: EntityId(0), prediction: Prediction::Ground, bits: [0; 3] }
        );
        // Three zero changes written out: a second encoding of the exact one.
        assert_eq!(nudges(&[3, 0, 0, 0], 1), Err(WireError::Field("view nudges")));
        // Ids past u32::MAX.
        let mut over = Vec::new();
        put_nudges(&mut over, &list[4..]);
        over.extend_from_slice(&[2, 0, 0, 0]);
        assert_eq!(nudges(&over, 2), Err(WireError::Field("view ids")));
    }
}
