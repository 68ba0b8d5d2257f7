//! The boxes both broad phases are given: centres and half extents, exactly as the
//! pipeline forms them (`Aabb::from_center_half`, no margin; the `cpu` backend adds none).

use myriad_core::rng::Stream;
use myriad_core::{Aabb, Vec3, World};

/// A set of dynamic and static boxes with the bounds the Morton codes span.
#[derive(Clone, Debug)]
pub struct AabbSet {
    /// A label for reports (`1`, `2`, `3`, `clustered`, `lattice`).
    pub name: String,
    /// Bounds of everything (the world's bounds for a world).
    pub bounds: Aabb,
    /// Centres of the dynamic boxes, by slot.
    pub dynamic_centres: Vec<Vec3>,
    /// Half extents of the dynamic boxes, by slot.
    pub dynamic_halves: Vec<Vec3>,
    /// Centres of the static primitives' boxes.
    pub static_centres: Vec<Vec3>,
    /// Half extents of the static primitives' boxes.
    pub static_halves: Vec<Vec3>,
}

impl AabbSet {
    /// The boxes of a world's dynamic objects (current positions) and static primitives.
    pub fn from_world(name: &str, world: &World) -> AabbSet {
        let (d, s) = (&world.dynamics, &world.statics);
        AabbSet {
            name: name.into(),
            bounds: world.bounds,
            dynamic_centres: d.positions().to_vec(),
            dynamic_halves: d.half_extents().to_vec(),
            static_centres: s.positions().to_vec(),
            static_halves: s.half_extents().to_vec(),
        }
    }

    /// Number of dynamic boxes.
    pub fn dynamic_len(&self) -> usize {
        self.dynamic_centres.len()
    }

    /// Number of static boxes.
    pub fn static_len(&self) -> usize {
        self.static_centres.len()
    }

    /// The dynamic boxes, with the pipeline's expression.
    pub fn dynamic_aabbs(&self) -> Vec<Aabb> {
        let mut out = Vec::new();
        self.dynamic_aabbs_into(&mut out);
        out
    }

    /// [`AabbSet::dynamic_aabbs`] into a reused buffer.
    pub fn dynamic_aabbs_into(&self, out: &mut Vec<Aabb>) {
        out.clear();
        out.extend(self.dynamic_centres.iter().zip(&self.dynamic_halves).map(|(c, h)| Aabb::from_center_half(*c, *h)));
    }

    /// The static boxes, with the pipeline's expression.
    pub fn static_aabbs(&self) -> Vec<Aabb> {
        self.static_centres.iter().zip(&self.static_halves).map(|(c, h)| Aabb::from_center_half(*c, *h)).collect()
    }

    /// Moves the dynamic boxes to new centres (same objects, same order).
    pub fn set_dynamic_centres(&mut self, centres: &[Vec3]) {
        assert_eq!(centres.len(), self.dynamic_centres.len(), "same objects, new positions");
        self.dynamic_centres.copy_from_slice(centres);
    }
}

/// A duplicate-heavy set on an integer lattice: every centre is a lattice point and every
/// half extent is 0.5, 1.0 or 1.5, so all box faces fall on exact multiples of 0.5.
/// Neighbouring boxes therefore *touch* exactly (face, edge or corner), many boxes share a
/// centre (several per lattice point when `dynamic > side³`), and the Morton codes are
/// full of duplicates: the boundary cases where two broad phases are most likely to
/// disagree.
#[derive(Clone, Copy, Debug)]
pub struct Lattice {
    /// Dynamic boxes.
    pub dynamic: u32,
    /// Static boxes.
    pub statics: u32,
    /// Lattice points per side of the cube the centres are drawn from.
    pub side: u32,
    /// Seed of the draws.
    pub seed: u64,
}

impl Lattice {
    /// Where the lattice starts. Away from 0 on purpose: a peer that pads boxes by a
    /// vanishing margin (see the Rapier side) must not move a face that sits at 0.0.
    pub const ORIGIN: Vec3 = Vec3::splat(100.0);

    /// Generates the set.
    pub fn build(&self, name: &str) -> AabbSet {
        assert!(self.side >= 2, "a lattice needs at least 2 points per side");
        let mut rng = Stream::new(self.seed, 0x1a77);
        let point = |rng: &mut Stream| {
            let mut c = || rng.below(self.side) as f32;
            Lattice::ORIGIN + Vec3::new(c(), c(), c())
        };
        let mut set = AabbSet {
            name: name.into(),
            bounds: Aabb::new(
                Lattice::ORIGIN - Vec3::splat(2.0),
                Lattice::ORIGIN + Vec3::splat(self.side as f32 + 2.0),
            ),
            dynamic_centres: Vec::new(),
            dynamic_halves: Vec::new(),
            static_centres: Vec::new(),
            static_halves: Vec::new(),
        };
        for i in 0..self.dynamic {
            set.dynamic_centres.push(point(&mut rng));
            // Mostly unit cubes (touching their six face neighbours), some tall boxes like
            // capsules' and some of twice the size, reaching the neighbours' centres.
            set.dynamic_halves.push(match i % 4 {
                0 | 1 => Vec3::splat(0.5),
                2 => Vec3::new(0.5, 1.0, 0.5),
                _ => Vec3::splat(1.0),
            });
        }
        for i in 0..self.statics {
            set.static_centres.push(point(&mut rng));
            set.static_halves.push(if i % 2 == 0 { Vec3::splat(0.5) } else { Vec3::new(1.5, 0.5, 0.5) });
        }
        set
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lattice_has_duplicates_and_touching_boxes() {
        let set = Lattice { dynamic: 2_000, statics: 200, side: 10, seed: 1 }.build("lattice");
        let mut centres: Vec<[u32; 3]> = set.dynamic_centres.iter().map(|c| c.to_array().map(f32::to_bits)).collect();
        centres.sort_unstable();
        centres.dedup();
        assert!(centres.len() < 1_000, "{} distinct centres of 2000", centres.len());
        let boxes = set.dynamic_aabbs();
        let touching = (0..200)
            .flat_map(|i| (0..200).map(move |j| (i, j)))
            .filter(|&(i, j)| {
                let (a, b) = (boxes[i], boxes[j]);
                a.overlaps(&b) && (a.max.x == b.min.x || a.max.y == b.min.y || a.max.z == b.min.z)
            })
            .count();
        assert!(touching > 0);
    }
}
