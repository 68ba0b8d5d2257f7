//! The moving crowd: a scenario whose load walks across the map, so that a world split
//! into zones needs boundaries that follow it (docs/zones.md, rebalancing).
//!
//! A background world (a [`ScenarioSpec`]: statics, NPCs wandering at random) and a crowd
//! of users gathered around one point, each holding a move toward +x — now straight,
//! now a little to either side, sometimes with a jump, so that the crowd flows around
//! obstacles instead of piling up behind them. The moves are an [`ActionScript`]: no
//! physics of its own, the same world and the same script from the same seed on every
//! machine.

use glam::Vec3;

use crate::action::Action;
use crate::error::CoreError;
use crate::rng::{Stream, hash3};
use crate::scenario::ScenarioSpec;
use crate::script::{ActionScript, ScriptedAction};
use crate::shape::Shape;
use crate::world::{EntityId, ObjectKind, World};

/// Stream of the crowd's placement (the scenario's own streams are 1 to 3).
const PLACEMENT: u64 = 16;
/// Salt of the crowd's moves.
const MOVES: u64 = 17;

/// The moves a crowd member picks from, each with a +x part: straight right three times
/// out of five, diagonally right the rest.
const CROWD_MOVES: [u8; 5] =
    [Action::RIGHT, Action::RIGHT, Action::RIGHT, Action::RIGHT | Action::FORWARD, Action::RIGHT | Action::BACK];

/// A crowd walking toward +x through a background world (see the module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct MovingCrowd {
    /// The world around the crowd: its map, statics and NPCs (its users, if any, stand
    /// still).
    pub base: ScenarioSpec,
    /// Users in the crowd.
    pub crowd: u32,
    /// Where the crowd starts: its centre as shares (0..1) of the map along x and z.
    pub start: (f32, f32),
    /// Standard deviation of a member's distance from the centre, per axis, in units.
    pub spread: f32,
}

impl MovingCrowd {
    /// The scenario `moving-crowd`: a 512-unit map of low hills with 1,500 NPCs and 750
    /// static objects, and 3,000 users starting around (20 %, 30 %) of the map. Walking
    /// about 5 units a second, the crowd reaches the middle of the map (the cut of 2 or
    /// 4 zones) after about 800 ticks.
    pub fn new(seed: u64) -> MovingCrowd {
        let mut base = ScenarioSpec::custom(seed).counts(1_500, 0, 750).map_size(512.0, 257);
        base.name = "moving-crowd".into();
        base.max_height = 24.0;
        MovingCrowd { base, crowd: 3_000, start: (0.2, 0.3), spread: 512.0 / 24.0 }
    }

    /// The world: the base's, then the crowd (ids after the base's objects).
    pub fn build(&self) -> Result<World, CoreError> {
        let mut world = self.base.build()?;
        self.spawn(&mut world)?;
        Ok(world)
    }

    /// Adds the crowd to `world` (built from [`MovingCrowd::base`]); returns the
    /// members' ids.
    pub fn spawn(&self, world: &mut World) -> Result<Vec<EntityId>, CoreError> {
        let b = &self.base;
        let unit = |v: f32| (0.0..=1.0).contains(&v);
        let valid = self.spread.is_finite() && self.spread > 0.0 && unit(self.start.0) && unit(self.start.1);
        if !valid {
            return Err(CoreError::invalid("moving crowd", format!("start {:?}, spread {}", self.start, self.spread)));
        }
        let mut rng = Stream::new(b.seed, PLACEMENT);
        let (cx, cz) = (b.origin.x + b.world_size * self.start.0, b.origin.z + b.world_size * self.start.1);
        let margin = 2.0;
        let (lo_x, hi_x) = (b.origin.x + margin, b.origin.x + b.world_size - margin);
        let (lo_z, hi_z) = (b.origin.z + margin, b.origin.z + b.world_size - margin);
        let mut ids = Vec::with_capacity(self.crowd as usize);
        for i in 0..self.crowd {
            let s = rng.range(0.8, 1.2);
            let shape = match i % 3 {
                0 => Shape::Sphere { radius: 0.5 * s },
                1 => Shape::Box { half: Vec3::splat(0.5 * s) },
                _ => Shape::Capsule { radius: 0.35 * s, half_height: 0.55 * s },
            };
            let x = (cx + rng.normalish() * self.spread).clamp(lo_x, hi_x);
            let z = (cz + rng.normalish() * self.spread).clamp(lo_z, hi_z);
            let y = world.terrain.height_at(x, z) + shape.half_extents().y + 0.01;
            ids.push(world.dynamics.spawn(shape, Vec3::new(x, y, z), ObjectKind::User)?);
        }
        Ok(ids)
    }

    /// The crowd's moves for ticks `0..ticks`: every member (`ids`, from
    /// [`MovingCrowd::spawn`]) starts within the first 5 ticks and picks a new move
    /// every 20 to 59 ticks, one in eight with a jump; all from the seed.
    pub fn script(&self, ids: &[EntityId], ticks: u64) -> ActionScript {
        let seed = self.base.seed ^ MOVES.rotate_left(32);
        let mut entries = Vec::new();
        for (n, &entity) in ids.iter().enumerate() {
            let mut tick = hash3(seed, n as u64, 0) % 5;
            let mut turn = 1u64;
            while tick < ticks {
                let h = hash3(seed, n as u64, turn);
                let mv = CROWD_MOVES[(((h >> 32) * CROWD_MOVES.len() as u64) >> 32) as usize];
                let jump = if h & 7 == 0 { Action::JUMP } else { 0 };
                entries.push(ScriptedAction { tick, entity, action: Action::from_bits_truncate(mv | jump) });
                tick += 20 + (h >> 8) % 40;
                turn += 1;
            }
        }
        ActionScript::new(entries)
    }

    /// The world and its script for a run of `ticks` ticks.
    pub fn build_with_script(&self, ticks: u64) -> Result<(World, ActionScript), CoreError> {
        let mut world = self.base.build()?;
        let ids = self.spawn(&mut world)?;
        Ok((world, self.script(&ids, ticks)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small() -> MovingCrowd {
        let mut c = MovingCrowd::new(3);
        c.base = c.base.counts(100, 0, 20).map_size(96.0, 33);
        c.crowd = 200;
        c.spread = 4.0;
        c
    }

    #[test]
    fn same_seed_same_crowd_and_every_move_goes_right() {
        let c = small();
        let (a, sa) = c.build_with_script(300).unwrap();
        let (b, sb) = c.build_with_script(300).unwrap();
        assert_eq!(a.state_hash(), b.state_hash());
        assert_eq!(sa, sb);
        assert_eq!(a.dynamics.len(), 300);
        let users = a.dynamics.kinds().iter().filter(|k| **k == ObjectKind::User).count();
        assert_eq!(users, 200);
        // Every member moves from its first 5 ticks on, always with a +x part.
        assert_eq!(sa.entities().len(), 200);
        assert!(sa.entries().iter().all(|e| e.action.has(Action::RIGHT) && e.tick < 300));
        assert!(sa.entries().iter().filter(|e| e.tick < 5).count() == 200);
        // The crowd is gathered: its mean x is near 20 % of the map.
        let xs: Vec<f32> = a.dynamics.positions()[100..].iter().map(|p| p.x).collect();
        let mean = xs.iter().sum::<f32>() / xs.len() as f32;
        assert!((mean - 0.2 * 96.0).abs() < 2.0, "{mean}");
        let other = MovingCrowd { base: ScenarioSpec { seed: 4, ..c.base.clone() }, ..c.clone() };
        assert_ne!(other.build().unwrap().state_hash(), a.state_hash());
        assert!(MovingCrowd { spread: 0.0, ..c.clone() }.build().is_err());
        assert!(MovingCrowd { start: (1.5, 0.0), ..c }.build().is_err());
    }
}
