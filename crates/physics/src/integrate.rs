//! Forces, Verlet integration, world limits and the terrain floor; and the NPCs' random
//! walk.
//!
//! All of it is per object and independent, so it parallelises trivially; the arithmetic
//! is written out in a fixed order that the CUDA kernels repeat.

use crate::consts::TickConstants;
use myriad_core::rng::hash3;
use myriad_core::world::flags;
use myriad_core::{Aabb, Action, EntityId, Terrain, Vec3};

/// `1/√2` rounded to `f32`: the per-axis share of a diagonal move.
const DIAGONAL: f32 = std::f32::consts::FRAC_1_SQRT_2;

/// The nine moves an NPC picks from (none and eight directions).
const NPC_MOVES: [u8; 9] = [
    0,
    Action::FORWARD,
    Action::BACK,
    Action::RIGHT,
    Action::LEFT,
    Action::FORWARD | Action::RIGHT,
    Action::FORWARD | Action::LEFT,
    Action::BACK | Action::RIGHT,
    Action::BACK | Action::LEFT,
];

/// Salt of the per-NPC phase draw, so that NPCs do not all turn on the same tick.
const PHASE_SALT: u64 = u64::MAX;

/// When NPCs turn at a given tick: each NPC has a phase in `[0, period)` (a draw of
/// (seed, id)), and turns at the ticks where `(tick + phase) % period == 0`, i.e. when
/// its phase equals [`NpcTurn::phase`]. Computing that phase once per tick keeps the
/// 64-bit division out of the per-object loop (and out of the GPU kernel).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct NpcTurn {
    /// The tick.
    pub tick: u64,
    /// The period in ticks.
    pub period: u32,
    /// NPCs whose phase equals this value turn at `tick`.
    pub phase: u32,
}

impl NpcTurn {
    /// The turn for `tick` with a period of `period` ticks (at least 1).
    pub fn at(tick: u64, period: u32) -> NpcTurn {
        let period = period.max(1);
        let r = (tick % period as u64) as u32;
        NpcTurn { tick, period, phase: (period - r) % period }
    }

    /// The action an NPC holds after this tick's turn, given the one it held: unchanged
    /// unless it is this NPC's turn, then a counter-based draw of (seed, id, tick).
    #[inline]
    pub fn action(&self, seed: u64, id: EntityId, current: u8) -> u8 {
        // Lemire's multiply-shift maps 32 random bits to [0, period) without division.
        let phase = (((hash3(seed, id.0 as u64, PHASE_SALT) >> 32) * self.period as u64) >> 32) as u32;
        if phase != self.phase {
            return current;
        }
        let r = hash3(seed, id.0 as u64, self.tick);
        let mv = NPC_MOVES[(((r >> 32) * 9) >> 32) as usize];
        // One turn in 16 includes a jump.
        let jump = if r & 15 == 0 { Action::JUMP } else { 0 };
        mv | jump
    }
}

/// Gravity, drag, friction and the held action, then the Verlet step: `prev` becomes the
/// old position and `pos` the new one. `standing` says whether the object stands on the
/// terrain or on something.
#[inline]
pub fn integrate(pos: &mut Vec3, prev: &mut Vec3, action: u8, standing: bool, k: &TickConstants) {
    let v = *pos - *prev;
    let mut vx = v.x * k.air_keep;
    let mut vy = v.y * k.air_keep;
    let mut vz = v.z * k.air_keep;
    if standing {
        vx *= k.ground_keep;
        vz *= k.ground_keep;
        let mut dx = 0.0f32;
        let mut dz = 0.0f32;
        if action & Action::RIGHT != 0 {
            dx += 1.0;
        }
        if action & Action::LEFT != 0 {
            dx -= 1.0;
        }
        if action & Action::FORWARD != 0 {
            dz += 1.0;
        }
        if action & Action::BACK != 0 {
            dz -= 1.0;
        }
        if dx != 0.0 && dz != 0.0 {
            dx *= DIAGONAL;
            dz *= DIAGONAL;
        }
        vx += dx * k.move_accel;
        vz += dz * k.move_accel;
        if action & Action::JUMP != 0 {
            vy = k.jump_velocity;
        }
    }
    vy -= k.gravity_dt2;
    let old = *pos;
    *pos = Vec3::new(old.x + vx, old.y + vy, old.z + vz);
    *prev = old;
}

/// The lowest height the centre of an object `half_y` half high may have at (`x`, `z`):
/// on the terrain, not below the world's lower bound. What [`enforce_limits`] clamps to,
/// and what a zone's ground nudges predict with (`myriad_zone::wire::Nudge`).
#[inline]
pub fn floor_at(terrain: &Terrain, bounds: &Aabb, half_y: f32, x: f32, z: f32) -> f32 {
    (terrain.height_at(x, z) + half_y).max(bounds.min.y + half_y)
}

/// Keeps an object with half extents `half` inside `bounds` and on or above the terrain.
/// A clamped axis loses its velocity (`prev` is set to `pos` on that axis). Returns the
/// object's new [`flags::ON_TERRAIN`] bit.
#[inline]
pub fn enforce_limits(
    pos: &mut Vec3,
    prev: &mut Vec3,
    half: Vec3,
    bounds: &Aabb,
    terrain: &Terrain,
    k: &TickConstants,
) -> u8 {
    let lo = bounds.min + half;
    let hi = bounds.max - half;
    if pos.x < lo.x {
        pos.x = lo.x;
        prev.x = pos.x;
    } else if pos.x > hi.x {
        pos.x = hi.x;
        prev.x = pos.x;
    }
    if pos.z < lo.z {
        pos.z = lo.z;
        prev.z = pos.z;
    } else if pos.z > hi.z {
        pos.z = hi.z;
        prev.z = pos.z;
    }
    if pos.y > hi.y {
        pos.y = hi.y;
        prev.y = pos.y;
    }
    let floor = floor_at(terrain, bounds, half.y, pos.x, pos.z);
    if pos.y < floor {
        pos.y = floor;
        prev.y = pos.y;
    }
    if pos.y <= floor + k.ground_tolerance { flags::ON_TERRAIN } else { 0 }
}

#[cfg(test)]
mod tests {
    use super::*;
    use myriad_core::terrain::TerrainPlacement;

    fn flat() -> (Aabb, Terrain) {
        let bounds = Aabb::new(Vec3::new(-50.0, 0.0, -50.0), Vec3::new(50.0, 100.0, 50.0));
        let t = Terrain::flat(TerrainPlacement {
            origin_x: -50.0,
            origin_z: -50.0,
            extent_x: 100.0,
            extent_z: 100.0,
            base_y: 0.0,
        });
        (bounds, t)
    }

    #[test]
    fn walking_reaches_the_configured_speed_and_stops_with_friction() {
        let k = TickConstants::default();
        let (bounds, terrain) = flat();
        let half = Vec3::splat(0.5);
        let (mut pos, mut prev) = (Vec3::new(0.0, 0.5, 0.0), Vec3::new(0.0, 0.5, 0.0));
        for _ in 0..300 {
            integrate(&mut pos, &mut prev, Action::FORWARD, true, &k);
            enforce_limits(&mut pos, &mut prev, half, &bounds, &terrain, &k);
        }
        let speed = (pos.z - prev.z) * 30.0; // units per second at 30 Hz
        assert!((speed - 5.0).abs() < 0.05, "speed {speed}");
        assert_eq!(pos.y, 0.5);
        for _ in 0..300 {
            integrate(&mut pos, &mut prev, 0, true, &k);
            enforce_limits(&mut pos, &mut prev, half, &bounds, &terrain, &k);
        }
        assert!((pos - prev).length() < 1e-6);
    }

    #[test]
    fn jump_rises_and_lands() {
        let k = TickConstants::default();
        let (bounds, terrain) = flat();
        let half = Vec3::splat(0.5);
        let (mut pos, mut prev) = (Vec3::new(0.0, 0.5, 0.0), Vec3::new(0.0, 0.5, 0.0));
        integrate(&mut pos, &mut prev, Action::JUMP, true, &k);
        let on = enforce_limits(&mut pos, &mut prev, half, &bounds, &terrain, &k);
        assert!(pos.y > 0.55 && on == 0, "the jump leaves the ground at once");
        let mut top = pos.y;
        for _ in 0..60 {
            integrate(&mut pos, &mut prev, 0, false, &k);
            enforce_limits(&mut pos, &mut prev, half, &bounds, &terrain, &k);
            top = top.max(pos.y);
        }
        // v²/2g = 25 / 19.62 ≈ 1.27 above the start.
        assert!((top - 0.5 - 1.27).abs() < 0.15, "apex {top}");
        assert_eq!(pos.y, 0.5);
    }

    #[test]
    fn limits_clamp_and_kill_velocity() {
        let k = TickConstants::default();
        let (bounds, terrain) = flat();
        let half = Vec3::splat(1.0);
        let mut pos = Vec3::new(60.0, -5.0, -70.0);
        let mut prev = Vec3::new(55.0, -4.0, -60.0);
        let f = enforce_limits(&mut pos, &mut prev, half, &bounds, &terrain, &k);
        assert_eq!(pos, Vec3::new(49.0, 1.0, -49.0));
        assert_eq!(prev, pos);
        assert_eq!(f, flags::ON_TERRAIN);
    }

    #[test]
    fn npc_actions_change_on_their_phase_only() {
        for id in (0..50).map(EntityId) {
            let mut turns = Vec::new();
            let mut a = 0xff; // an impossible action: every turn shows as a change
            for tick in 0..600 {
                let b = NpcTurn::at(tick, 60).action(9, id, a);
                if b != a {
                    turns.push(tick);
                }
                a = b;
            }
            let first = turns[0];
            assert!(first < 60, "{id:?} first turns at {first}");
            for t in &turns {
                assert_eq!((t - first) % 60, 0, "{id:?} turned off its phase at {t}");
            }
        }
        let turn = NpcTurn::at(123, 60);
        assert_eq!(turn.action(9, EntityId(3), 0), turn.action(9, EntityId(3), 0));
        assert_eq!(NpcTurn::at(0, 60).phase, 0);
        assert_eq!(NpcTurn::at(1, 60).phase, 59);
        assert_eq!(NpcTurn::at(5, 1).phase, 0);
    }
}
