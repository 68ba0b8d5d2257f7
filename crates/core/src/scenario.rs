//! Seeded world generation: the reference's three scenarios (docs/design.md, scenarios),
//! scenario 4 (scenario 3 scaled to 50,000 players) and custom ones.
//!
//! A scenario fixes counts, world size, seed and placement; [`ScenarioSpec::build`] turns
//! it into a [`World`]. Every draw comes from [`crate::rng::Stream`]s of the seed, one
//! stream per purpose, so the same spec gives the same world on every machine.
//!
//! Counts follow the reference exactly: `n` dynamic objects are `n - 2⌊n/3⌋` spheres,
//! `⌊n/3⌋` boxes and `⌊n/3⌋` capsules (6,000 → 2,000 each; 260,000 → 86,668 + 86,666 +
//! 86,666), users spread evenly among them; `m` static objects are trees, crates and rocks
//! in equal thirds (the remainder going to trees), a tree being a capsule trunk and two
//! crown boxes, a crate one box, a rock two boxes — 5 boxes and 1 capsule per triple.

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::aabb::Aabb;
use crate::error::CoreError;
use crate::rng::Stream;
use crate::shape::Shape;
use crate::terrain::{Terrain, TerrainPlacement};
use crate::world::{ObjectKind, StaticKind, World};

/// How dynamic objects are spread over the map.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Placement {
    /// Uniformly over the whole map (the reference's placement).
    Uniform,
    /// Most objects crowd a few hot spots (the trade-hub case): `fraction` of them are
    /// spread around `hotspots` centres with a standard deviation of `spread` units, the
    /// rest uniformly.
    Clustered {
        /// Number of hot spots.
        hotspots: u32,
        /// Share of objects placed in hot spots (0..=1).
        fraction: f32,
        /// Standard deviation of the distance from a hot spot's centre, in units.
        spread: f32,
    },
}

/// Everything that determines a generated world.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ScenarioSpec {
    /// A label for reports (`1`, `2`, `3`, `custom`, `clustered`).
    pub name: String,
    /// Static objects (trees, crates, rocks).
    pub static_objects: u32,
    /// Dynamic objects, users included.
    pub dynamic: u32,
    /// How many dynamic objects are users (the rest are NPCs).
    pub users: u32,
    /// Length of the map along x and z.
    pub world_size: f32,
    /// The world's minimum corner (bounds need not start at 0).
    pub origin: Vec3,
    /// Heightmap samples per side.
    pub terrain_samples: u32,
    /// Height of the highest terrain sample above the floor.
    pub max_height: f32,
    /// The seed of everything.
    pub seed: u64,
    /// Placement of dynamic objects.
    pub placement: Placement,
}

/// Stream numbers: one per purpose (see [`Stream`]).
mod streams {
    pub const STATIC: u64 = 1;
    pub const DYNAMIC: u64 = 2;
    pub const HOTSPOT: u64 = 3;
}

/// The numbered scenarios [`ScenarioSpec::reference`] makes.
pub const NUMBERED_SCENARIOS: std::ops::RangeInclusive<u8> = 1..=4;

/// Scenario 4's map: scenario 3's 1,024 units grown by √5 (its five times the objects at
/// scenario 3's density), rounded to a whole unit.
pub const SCENARIO_4_WORLD_SIZE: f32 = 2_290.0;

/// Scenario 4's heightmap samples per side: scenario 3's spacing of one unit.
pub const SCENARIO_4_TERRAIN_SAMPLES: u32 = 2_291;

impl ScenarioSpec {
    /// A numbered scenario ([`NUMBERED_SCENARIOS`]): the reference's scenario 1, 2 or 3
    /// (docs/design.md, scenarios) on a 1024-unit map, or scenario 4, scenario 3 scaled to
    /// 50,000 players: five times its counts (1,300,000 dynamic objects, 50,000 of them
    /// users, and 500,000 static) on a map [`SCENARIO_4_WORLD_SIZE`] long, so the objects
    /// per unit² stay scenario 3's, with [`SCENARIO_4_TERRAIN_SAMPLES`] heightmap samples
    /// a side, so the samples keep scenario 3's one-unit spacing.
    pub fn reference(n: u8, seed: u64) -> Result<ScenarioSpec, CoreError> {
        let (static_objects, dynamic, users) = match n {
            1 => (3_000, 6_000, 1_000),
            2 => (15_000, 55_000, 5_000),
            3 => (99_999, 260_000, 10_000),
            4 => (500_000, 1_300_000, 50_000),
            _ => {
                return Err(CoreError::invalid("scenario", format!("{n}: the scenarios are 1, 2, 3 and 4")));
            }
        };
        let spec = ScenarioSpec { name: n.to_string(), static_objects, dynamic, users, ..ScenarioSpec::custom(seed) };
        Ok(if n == 4 { spec.map_size(SCENARIO_4_WORLD_SIZE, SCENARIO_4_TERRAIN_SAMPLES) } else { spec })
    }

    /// A custom scenario with the defaults of scenario 1; change the fields as needed.
    pub fn custom(seed: u64) -> ScenarioSpec {
        ScenarioSpec {
            name: "custom".into(),
            static_objects: 3_000,
            dynamic: 6_000,
            users: 1_000,
            world_size: 1024.0,
            origin: Vec3::ZERO,
            terrain_samples: 1025,
            max_height: 128.0,
            seed,
            placement: Placement::Uniform,
        }
    }

    /// These counts: `dynamic` objects, of which `users` are users, and `static_objects`
    /// static objects. With [`ScenarioSpec::map_size`], the one-expression test world of
    /// tests and benches: `ScenarioSpec::custom(seed).counts(300, 0, 30).map_size(96.0, 33)`.
    pub fn counts(self, dynamic: u32, users: u32, static_objects: u32) -> ScenarioSpec {
        ScenarioSpec { dynamic, users, static_objects, ..self }
    }

    /// A map `world_size` long along x and z, with `terrain_samples` heightmap samples per
    /// side.
    pub fn map_size(self, world_size: f32, terrain_samples: u32) -> ScenarioSpec {
        ScenarioSpec { world_size, terrain_samples, ..self }
    }

    /// Scenario 2's counts with most dynamic objects crowding eight hot spots.
    pub fn clustered(seed: u64) -> ScenarioSpec {
        ScenarioSpec {
            name: "clustered".into(),
            static_objects: 15_000,
            dynamic: 55_000,
            users: 5_000,
            placement: Placement::Clustered { hotspots: 8, fraction: 0.8, spread: 16.0 },
            ..ScenarioSpec::custom(seed)
        }
    }

    /// The world bounds this spec generates.
    pub fn bounds(&self) -> Aabb {
        let top = self.max_height + 64.0;
        Aabb::new(self.origin, self.origin + Vec3::new(self.world_size, top, self.world_size))
    }

    /// Number of spheres, boxes and capsules among the dynamic objects.
    pub fn dynamic_shapes(&self) -> [u32; 3] {
        let third = self.dynamic / 3;
        [self.dynamic - 2 * third, third, third]
    }

    /// Number of trees, crates and rocks.
    pub fn static_kinds(&self) -> [u32; 3] {
        let third = self.static_objects / 3;
        [self.static_objects - 2 * third, third, third]
    }

    fn validate(&self) -> Result<(), CoreError> {
        if !(self.world_size.is_finite() && self.world_size >= 16.0) {
            return Err(CoreError::invalid("world size", format!("{} (at least 16)", self.world_size)));
        }
        if !self.origin.is_finite() {
            return Err(CoreError::invalid("origin", format!("{}", self.origin)));
        }
        if self.users > self.dynamic {
            return Err(CoreError::invalid(
                "users",
                format!("{} users but only {} dynamic objects", self.users, self.dynamic),
            ));
        }
        if !(self.max_height.is_finite() && self.max_height >= 0.0) {
            return Err(CoreError::invalid("max height", format!("{}", self.max_height)));
        }
        if let Placement::Clustered { hotspots, fraction, spread } = self.placement
            && (hotspots == 0 || !(0.0..=1.0).contains(&fraction) || !(spread.is_finite() && spread > 0.0))
        {
            return Err(CoreError::invalid("clustered placement", format!("{:?}", self.placement)));
        }
        Ok(())
    }

    /// Where the terrain of this spec lies: over the whole map, its floor at the origin.
    pub fn terrain_placement(&self) -> TerrainPlacement {
        TerrainPlacement {
            origin_x: self.origin.x,
            origin_z: self.origin.z,
            extent_x: self.world_size,
            extent_z: self.world_size,
            base_y: self.origin.y,
        }
    }

    /// Whether `self` and `other` generate the same map: the same bounds, terrain and
    /// static objects. The map is made from these fields alone (the statics draw from a
    /// stream of their own), so worlds that differ only in their moving objects (counts,
    /// users, placement) share it: a gateway serving a reference scenario's map can front
    /// zones that run more NPCs on it.
    pub fn same_map(&self, other: &ScenarioSpec) -> bool {
        self.seed == other.seed
            && self.static_objects == other.static_objects
            && self.world_size == other.world_size
            && self.origin == other.origin
            && self.terrain_samples == other.terrain_samples
            && self.max_height == other.max_height
    }

    /// Generates the world, terrain included.
    pub fn build(&self) -> Result<World, CoreError> {
        self.validate()?;
        let at = self.terrain_placement();
        let (n, h) = (self.terrain_samples, self.max_height);
        let terrain = Terrain::generate(self.seed, n, n, h, at)?;
        self.build_on(terrain)
    }

    /// Generates the world on a given terrain (for instance one loaded from a file with
    /// [`ScenarioSpec::terrain_placement`]).
    pub fn build_on(&self, terrain: Terrain) -> Result<World, CoreError> {
        self.validate()?;
        let mut world = World::new(self.bounds(), terrain, self.seed)?;
        self.place_statics(&mut world)?;
        self.place_dynamics(&mut world)?;
        Ok(world)
    }

    fn place_statics(&self, world: &mut World) -> Result<(), CoreError> {
        let mut rng = Stream::new(self.seed, streams::STATIC);
        let [trees, crates, rocks] = self.static_kinds();
        let kinds = std::iter::repeat_n(StaticKind::Tree, trees as usize)
            .chain(std::iter::repeat_n(StaticKind::Crate, crates as usize))
            .chain(std::iter::repeat_n(StaticKind::Rock, rocks as usize));
        let (lo, hi) = (self.origin.x + 3.0, self.origin.x + self.world_size - 3.0);
        let (lo_z, hi_z) = (self.origin.z + 3.0, self.origin.z + self.world_size - 3.0);
        for kind in kinds {
            let x = rng.range(lo, hi);
            let z = rng.range(lo_z, hi_z);
            let ground = world.terrain.height_at(x, z);
            let s = rng.range(0.8, 1.6);
            let prims: Vec<(Shape, Vec3)> = match kind {
                StaticKind::Tree => {
                    let (r, hh) = (0.3 * s, 1.5 * s);
                    let trunk_y = ground + hh + r - 0.2;
                    let top = trunk_y + hh + r;
                    let low = Vec3::new(1.2, 0.6, 1.2) * s;
                    let high = Vec3::new(0.7, 0.5, 0.7) * s;
                    vec![
                        (Shape::Capsule { radius: r, half_height: hh }, Vec3::new(x, trunk_y, z)),
                        (Shape::Box { half: low }, Vec3::new(x, top + low.y, z)),
                        (Shape::Box { half: high }, Vec3::new(x, top + 2.0 * low.y + high.y, z)),
                    ]
                }
                StaticKind::Crate => {
                    let half = Vec3::new(rng.range(0.5, 2.0), rng.range(0.5, 2.0), rng.range(0.5, 2.0));
                    vec![(Shape::Box { half }, Vec3::new(x, ground + half.y - 0.1, z))]
                }
                StaticKind::Rock | StaticKind::Other => {
                    let base = Vec3::new(rng.range(1.0, 2.5), rng.range(0.4, 0.8), rng.range(1.0, 2.5)) * s;
                    let top = base * 0.6;
                    let by = ground + base.y - 0.2;
                    vec![
                        (Shape::Box { half: base }, Vec3::new(x, by, z)),
                        (Shape::Box { half: top }, Vec3::new(x + 0.2 * base.x, by + base.y + top.y, z)),
                    ]
                }
            };
            world.statics.add(kind, &prims)?;
        }
        Ok(())
    }

    fn place_dynamics(&self, world: &mut World) -> Result<(), CoreError> {
        let mut rng = Stream::new(self.seed, streams::DYNAMIC);
        let [spheres, boxes, _] = self.dynamic_shapes();
        let hotspots: Vec<(f32, f32)> = match self.placement {
            Placement::Uniform => Vec::new(),
            Placement::Clustered { hotspots, .. } => {
                let mut h = Stream::new(self.seed, streams::HOTSPOT);
                let m = 0.1 * self.world_size;
                (0..hotspots)
                    .map(|_| {
                        (
                            h.range(self.origin.x + m, self.origin.x + self.world_size - m),
                            h.range(self.origin.z + m, self.origin.z + self.world_size - m),
                        )
                    })
                    .collect()
            }
        };
        let n = self.dynamic as u64;
        let users = self.users as u64;
        let margin = 2.0;
        let (lo_x, hi_x) = (self.origin.x + margin, self.origin.x + self.world_size - margin);
        let (lo_z, hi_z) = (self.origin.z + margin, self.origin.z + self.world_size - margin);
        for i in 0..self.dynamic {
            let s = rng.range(0.8, 1.2);
            let shape = if i < spheres {
                Shape::Sphere { radius: 0.5 * s }
            } else if i < spheres + boxes {
                Shape::Box { half: Vec3::splat(0.5 * s) }
            } else {
                Shape::Capsule { radius: 0.35 * s, half_height: 0.55 * s }
            };
            // Users spread evenly: object i is a user when ⌊i·u/n⌋ steps up at i.
            let iu = i as u64;
            let kind = if (iu + 1) * users / n != iu * users / n { ObjectKind::User } else { ObjectKind::Npc };
            let (x, z) = match self.placement {
                Placement::Clustered { fraction, spread, .. } if rng.unit() < fraction => {
                    let (cx, cz) = hotspots[rng.below(hotspots.len() as u32) as usize];
                    (
                        (cx + rng.normalish() * spread).clamp(lo_x, hi_x),
                        (cz + rng.normalish() * spread).clamp(lo_z, hi_z),
                    )
                }
                _ => (rng.range(lo_x, hi_x), rng.range(lo_z, hi_z)),
            };
            let y = world.terrain.height_at(x, z) + shape.half_extents().y + 0.01;
            world.dynamics.spawn(shape, Vec3::new(x, y, z), kind)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shape::ShapeKind;

    fn small(mut s: ScenarioSpec) -> ScenarioSpec {
        s.terrain_samples = 65;
        s
    }

    #[test]
    fn the_map_does_not_depend_on_the_moving_objects() {
        let reference = small(ScenarioSpec::reference(1, 4).unwrap());
        let more = ScenarioSpec {
            name: "custom".into(),
            dynamic: 9_000,
            users: 50,
            placement: Placement::Clustered { hotspots: 3, fraction: 0.5, spread: 20.0 },
            ..reference.clone()
        };
        assert!(more.same_map(&reference));
        let (a, b) = (reference.build().unwrap(), more.build().unwrap());
        assert_eq!(a.bounds, b.bounds);
        assert_eq!(a.terrain.samples(), b.terrain.samples());
        assert_eq!(a.statics.positions(), b.statics.positions());
        assert_eq!(a.statics.shapes(), b.statics.shapes());
        assert_ne!(a.dynamics.len(), b.dynamics.len());
        for other in [
            ScenarioSpec { static_objects: 2_999, ..reference.clone() },
            ScenarioSpec { seed: 5, ..reference.clone() },
            ScenarioSpec { world_size: reference.world_size + 1.0, ..reference.clone() },
            ScenarioSpec { max_height: 1.0, ..reference.clone() },
        ] {
            assert!(!other.same_map(&reference), "{other:?}");
        }
    }

    #[test]
    fn reference_counts_are_exact() {
        let s3 = ScenarioSpec::reference(3, 1).unwrap();
        assert_eq!(s3.dynamic_shapes(), [86_668, 86_666, 86_666]);
        assert_eq!(ScenarioSpec::reference(2, 1).unwrap().dynamic_shapes(), [18_334, 18_333, 18_333]);
        assert_eq!(s3.static_kinds(), [33_333, 33_333, 33_333]);
        assert!(ScenarioSpec::reference(5, 1).is_err());
        assert!(ScenarioSpec::reference(0, 1).is_err());

        let w = small(ScenarioSpec::reference(1, 9).unwrap()).build().unwrap();
        assert_eq!(w.statics.objects().len(), 3_000);
        assert_eq!(w.statics.prims_by_shape(), [0, 5_000, 1_000]);
        assert_eq!(w.dynamics.len(), 6_000);
        let mut shapes = [0; 3];
        for s in w.dynamics.shapes() {
            shapes[*s as usize] += 1;
        }
        assert_eq!(shapes, [2_000, 2_000, 2_000]);
        let users = w.dynamics.kinds().iter().filter(|k| **k == ObjectKind::User).count();
        assert_eq!(users, 1_000);
        // Users are spread over every shape, not bunched at one end.
        let user_shapes: std::collections::HashSet<ShapeKind> = (0..w.dynamics.len())
            .filter(|&s| w.dynamics.kinds()[s] == ObjectKind::User)
            .map(|s| w.dynamics.shapes()[s])
            .collect();
        assert_eq!(user_shapes.len(), 3);
    }

    /// Scenario 4 is scenario 3 five times over at its density; generating its 1.8 M
    /// objects is left to release builds (`myriad sim --scenario 4`, docs/benchmarks.md).
    #[test]
    fn scenario_4_is_scenario_3_scaled_to_50_000_players() {
        let (s3, s4) = (ScenarioSpec::reference(3, 1).unwrap(), ScenarioSpec::reference(4, 1).unwrap());
        assert_eq!((s4.dynamic, s4.users, s4.static_objects), (1_300_000, 50_000, 500_000));
        assert_eq!((s4.world_size, s4.terrain_samples), (2_290.0, 2_291));
        assert_eq!(s4.dynamic_shapes(), [433_334, 433_333, 433_333]);
        assert_eq!(s4.static_kinds(), [166_668, 166_666, 166_666]);
        let density = |s: &ScenarioSpec, n: u32| f64::from(n) / f64::from(s.world_size).powi(2);
        for (n3, n4) in [(s3.dynamic, s4.dynamic), (s3.static_objects, s4.static_objects), (s3.users, s4.users)] {
            let ratio = density(&s4, n4) / density(&s3, n3);
            assert!((ratio - 1.0).abs() < 1e-3, "density ratio {ratio} for {n3} → {n4}");
        }
        let spacing = |s: &ScenarioSpec| s.world_size / (s.terrain_samples - 1) as f32;
        assert_eq!(spacing(&s4), spacing(&s3));
        assert_eq!((s4.max_height, s4.origin, s4.placement), (s3.max_height, s3.origin, s3.placement));
        assert_eq!(s4.name, "4");
        assert_eq!(s4.seed, 1);
        for n in NUMBERED_SCENARIOS {
            assert!(ScenarioSpec::reference(n, 1).is_ok(), "{n}");
        }
    }

    #[test]
    fn same_seed_same_world_and_everything_inside_bounds() {
        let mut spec = small(ScenarioSpec::custom(5));
        spec.origin = Vec3::new(-5000.0, -300.0, 12_000.0);
        spec.world_size = 3000.0;
        spec.dynamic = 900;
        spec.users = 90;
        spec.static_objects = 300;
        let a = spec.build().unwrap();
        let b = spec.build().unwrap();
        assert_eq!(a.state_hash(), b.state_hash());
        assert_eq!(a.statics.positions(), b.statics.positions());
        let mut other = spec.clone();
        other.seed = 6;
        assert_ne!(other.build().unwrap().state_hash(), a.state_hash());
        for s in 0..a.dynamics.len() {
            let bb = a.dynamics.aabb(s);
            assert!(a.bounds.contains_point(bb.min) && a.bounds.contains_point(bb.max), "slot {s}: {bb:?}");
            let p = a.dynamics.positions()[s];
            assert!(bb.min.y >= a.terrain.height_at(p.x, p.z));
        }
    }

    #[test]
    fn clustered_placement_crowds_hot_spots() {
        let mut spec = small(ScenarioSpec::clustered(3));
        spec.dynamic = 4_000;
        spec.users = 100;
        spec.static_objects = 30;
        let w = spec.build().unwrap();
        // Count objects per 32-unit cell: a crowd puts far more in the busiest cell than
        // the uniform average (4000 / 1024 cells ≈ 4).
        let mut cells = std::collections::HashMap::new();
        for p in w.dynamics.positions() {
            *cells.entry(((p.x / 32.0) as i32, (p.z / 32.0) as i32)).or_insert(0) += 1;
        }
        let busiest = cells.values().max().copied().unwrap();
        assert!(busiest > 100, "busiest cell holds {busiest}");
    }

    #[test]
    fn invalid_specs_are_rejected() {
        let mut s = ScenarioSpec::custom(1);
        s.users = s.dynamic + 1;
        assert!(s.build().is_err());
        let mut s = ScenarioSpec::custom(1);
        s.world_size = f32::INFINITY;
        assert!(s.build().is_err());
    }
}
