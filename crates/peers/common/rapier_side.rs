//! The Rapier side of the comparisons: Rapier's broad phase (`BroadPhaseBvh`, rapier3d
//! 0.36) on an [`AabbSet`], and a Myriad world rebuilt as a Rapier world and stepped by
//! its `PhysicsPipeline`.
//!
//! rapier3d is a dev-dependency of `myriad-peers`, so this file cannot live in the
//! library: the `rapier` bench and the `broad_phase_pairs` test include it with `#[path]`.
//! Each uses only part of it, hence the `dead_code` allowance.
//!
//! # Giving Rapier exactly our boxes
//! Every box becomes a standalone cuboid collider centred on our centre with our half
//! extents, so its AABB is `centre ± half` in `f32`, the pipeline's expression
//! ([`RapierBroad::check_aabbs`] verifies this bit for bit). Rapier keeps one tree for
//! all colliders and filters pairs afterwards; collision groups make it drop
//! static–static pairs (dynamics are in group 1 and see groups 1 and 2, statics are in
//! group 2 and see group 1), which is what our pipeline never computes either.
//!
//! Rapier pads boxes twice, which our broad phase does not: by half the prediction
//! distance when it computes a collider's AABB, and by a "change-detection skin"
//! (`0.04 × length_unit`) when a moved leaf is re-fattened. [`Skin::Exact`] sets the
//! prediction distance to 0 and the length unit to 1e-30, so the skin is 4e-32: added to
//! coordinates of magnitude above ~1e-24 it changes nothing, so the boxes are exact. The
//! skin is not exactly 0 because with 0 parry's in-place leaf update sets no change flag,
//! which the change-detecting pair traversal relies on; pairs then still came out right
//! in our tests (through re-insertion and the optimizer, it seems), but a positive skin
//! keeps Rapier on its ordinary incremental path.
//!
//! Both broad phases use closed intervals (`min <= max` on every axis, parry's
//! `BvhNode::intersects` and our `Aabb::overlaps`), so touching boxes are a pair on
//! both sides.

#![allow(dead_code)]

use std::collections::HashSet;

use myriad_core::{PhysicsConfig, ShapeKind, Vec3 as MyVec3, World};
use myriad_peers::{AabbSet, Pairs, pack};
use rapier3d::prelude::*;

/// Our vector as Rapier's (glam versions differ).
fn v(p: MyVec3) -> Vector {
    Vector::new(p.x, p.y, p.z)
}

/// How Rapier pads the boxes it is given.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Skin {
    /// No padding that changes any coordinate: Rapier's pairs must equal ours.
    Exact,
    /// Rapier's defaults (length unit 1: prediction distance 0.002, skin 0.04 on moved
    /// leaves): more pairs than exact boxes give, as Rapier ships.
    Default,
}

impl Skin {
    /// A label for reports.
    pub fn name(self) -> &'static str {
        match self {
            Skin::Exact => "exact",
            Skin::Default => "default skin",
        }
    }

    fn params(self) -> IntegrationParameters {
        let mut p = IntegrationParameters::default();
        if self == Skin::Exact {
            p.normalized_prediction_distance = 0.0;
            p.length_unit = 1e-30;
        }
        p
    }
}

/// Rapier's broad phase over the boxes of an [`AabbSet`]: collider `i` is dynamic box `i`
/// for `i < n`, static box `i - n` after.
pub struct RapierBroad {
    params: IntegrationParameters,
    bodies: RigidBodySet,
    colliders: ColliderSet,
    broad: BroadPhaseBvh,
    n_dynamic: u32,
    all: Vec<ColliderHandle>,
    dynamic: Vec<ColliderHandle>,
    moved: Vec<ColliderHandle>,
    events: Vec<BroadPhasePairEvent>,
    /// The current pairs by collider index, lower first, folded from the events.
    live: HashSet<(u32, u32)>,
}

impl RapierBroad {
    /// Colliders for every box of `set`; the broad phase is still empty.
    pub fn new(set: &AabbSet, skin: Skin) -> RapierBroad {
        let dynamic_groups =
            InteractionGroups::new(Group::GROUP_1, Group::GROUP_1 | Group::GROUP_2, InteractionTestMode::And);
        let static_groups = InteractionGroups::new(Group::GROUP_2, Group::GROUP_1, InteractionTestMode::And);
        let n = set.dynamic_len() + set.static_len();
        let mut colliders = ColliderSet::with_capacity(n);
        let boxes = set
            .dynamic_centres
            .iter()
            .zip(&set.dynamic_halves)
            .map(|b| (b, dynamic_groups))
            .chain(set.static_centres.iter().zip(&set.static_halves).map(|b| (b, static_groups)));
        let mut all = Vec::with_capacity(n);
        for ((c, h), groups) in boxes {
            let handle = colliders.insert(
                ColliderBuilder::cuboid(h.x, h.y, h.z)
                    .translation(v(*c))
                    .collision_groups(groups)
                    // Parentless colliders count as fixed; the groups do the filtering.
                    .active_collision_types(ActiveCollisionTypes::all()),
            );
            assert_eq!(handle.into_raw_parts().0 as usize, all.len(), "a fresh set numbers colliders in order");
            all.push(handle);
        }
        // Not the pipeline's: nobody clears the colliders' change flags, which only keeps
        // them eligible for every update we ask for.
        let _ = colliders.take_modified();
        let dynamic = all[..set.dynamic_len()].to_vec();
        RapierBroad {
            params: skin.params(),
            bodies: RigidBodySet::new(),
            colliders,
            broad: BroadPhaseBvh::new(),
            n_dynamic: set.dynamic_len() as u32,
            all,
            dynamic,
            moved: Vec::new(),
            events: Vec::new(),
            live: HashSet::new(),
        }
    }

    /// Checks that Rapier's broad-phase box of every collider is bit for bit the one the
    /// set gives (meaningful for [`Skin::Exact`]).
    pub fn check_aabbs(&self, set: &AabbSet) -> Result<(), String> {
        let ours = set.dynamic_aabbs().into_iter().chain(set.static_aabbs());
        for (i, (h, o)) in self.all.iter().zip(ours).enumerate() {
            let a = self.colliders[*h].compute_broad_phase_aabb(&self.params, &self.bodies);
            let same = a.mins.to_array().map(f32::to_bits) == o.min.to_array().map(f32::to_bits)
                && a.maxs.to_array().map(f32::to_bits) == o.max.to_array().map(f32::to_bits);
            if !same {
                return Err(format!("collider {i}: Rapier's box {a:?} is not ours {o:?}"));
            }
        }
        Ok(())
    }

    /// Drops the tree and the pairs (not timed: dropping a big tree costs time).
    pub fn reset(&mut self) {
        self.broad = BroadPhaseBvh::new();
        self.events.clear();
        self.live.clear();
    }

    /// One broad-phase update with every collider new: Rapier's full build.
    pub fn update_all(&mut self) {
        self.broad.update(&self.params, &self.colliders, &self.bodies, &self.all, &[], &mut self.events);
    }

    /// Moves the dynamic colliders to new centres; returns how many moved (only those
    /// are handed to the next [`RapierBroad::update_moved`], as the pipeline does).
    pub fn move_dynamics(&mut self, centres: &[MyVec3]) -> usize {
        self.moved.clear();
        for (h, c) in self.dynamic.iter().zip(centres) {
            let co = &mut self.colliders[*h];
            let t = v(*c);
            if co.translation() != t {
                co.set_translation(t);
                self.moved.push(*h);
            }
        }
        self.moved.len()
    }

    /// One incremental broad-phase update for the colliders moved last.
    pub fn update_moved(&mut self) {
        self.broad.update(&self.params, &self.colliders, &self.bodies, &self.moved, &[], &mut self.events);
    }

    /// Folds the events of the updates since the last call into the pair set.
    pub fn apply_events(&mut self) {
        for e in self.events.drain(..) {
            let key = |p: ColliderPair| {
                let (a, b) = (p.collider1.into_raw_parts().0, p.collider2.into_raw_parts().0);
                (a.min(b), a.max(b))
            };
            match e {
                BroadPhasePairEvent::AddPair(p) => {
                    self.live.insert(key(p));
                }
                BroadPhasePairEvent::DeletePair(p) => {
                    self.live.remove(&key(p));
                }
            }
        }
    }

    /// The current pairs in our canonical form. Static–static pairs would be an error of
    /// the group set-up; they are counted in the second value.
    pub fn pairs(&self) -> (Pairs, usize) {
        let n = self.n_dynamic;
        let mut out = Pairs::default();
        let mut static_static = 0;
        for &(a, b) in &self.live {
            if b < n {
                out.dynamic.push(pack(a, b));
            } else if a < n {
                out.statics.push(pack(a, b - n));
            } else {
                static_static += 1;
            }
        }
        out.canonicalize();
        (out, static_static)
    }
}

/// A Myriad world rebuilt in Rapier: each dynamic object a dynamic rigid body with the
/// equivalent collider (ball, cuboid, `capsule_y`), rotations locked because Myriad's
/// shapes never rotate, and never put to sleep because Myriad's NPCs keep walking; each
/// static primitive a fixed collider; the terrain a heightfield with the same samples,
/// scale and placement (Rapier triangulates each cell where Myriad interpolates
/// bilinearly); gravity and time step from the [`PhysicsConfig`].
///
/// Rapier is built with its default features, without `parallel`: it steps on one thread.
pub struct RapierWorld {
    /// Everything Rapier steps.
    pub world: PhysicsWorld,
}

impl RapierWorld {
    /// Rebuilds `w` with `config`'s gravity, tick rate and restitution.
    pub fn from_world(w: &World, config: &PhysicsConfig) -> RapierWorld {
        let mut pw = PhysicsWorld::new();
        pw.gravity = Vector::new(0.0, -config.gravity, 0.0);
        pw.integration_parameters.dt = 1.0 / config.tick_rate;

        // Parry's heightfield is column-major with rows along z and columns along x,
        // centred on its collider and spanning `scale` on x and z.
        let t = &w.terrain;
        let (width, depth) = (t.width() as usize, t.depth() as usize);
        let (_, _, height_scale) = t.sampling_constants();
        let samples = t.samples();
        let mut heights = vec![0.0; width * depth];
        for z in 0..depth {
            for x in 0..width {
                heights[z + x * depth] = samples[z * width + x] as f32 * height_scale;
            }
        }
        let at = t.placement();
        pw.colliders.insert(
            ColliderBuilder::heightfield(
                Array2::new(depth, width, heights),
                Vector::new(at.extent_x, 1.0, at.extent_z),
            )
            .translation(Vector::new(
                at.origin_x + at.extent_x * 0.5,
                at.base_y,
                at.origin_z + at.extent_z * 0.5,
            )),
        );

        let collider = |kind: ShapeKind, half: MyVec3, radius: f32| match kind {
            ShapeKind::Sphere => ColliderBuilder::ball(radius),
            ShapeKind::Box => ColliderBuilder::cuboid(half.x, half.y, half.z),
            ShapeKind::Capsule => ColliderBuilder::capsule_y(half.y - radius, radius),
        };
        let s = &w.statics;
        for i in 0..s.prim_count() {
            pw.colliders.insert(
                collider(s.shapes()[i], s.half_extents()[i], s.radii()[i])
                    .translation(v(s.positions()[i]))
                    .restitution(config.restitution),
            );
        }
        let d = &w.dynamics;
        for i in 0..d.len() {
            let body = pw
                .bodies
                .insert(RigidBodyBuilder::dynamic().translation(v(d.positions()[i])).lock_rotations().can_sleep(false));
            pw.colliders.insert_with_parent(
                collider(d.shapes()[i], d.half_extents()[i], d.radii()[i]).restitution(config.restitution),
                body,
                &mut pw.bodies,
            );
        }
        RapierWorld { world: pw }
    }

    /// One step of Rapier's pipeline.
    pub fn step(&mut self) {
        self.world.step();
    }

    /// Contact pairs with at least one contact point after the last step.
    pub fn contact_pairs(&self) -> usize {
        self.world.narrow_phase.contact_pairs().filter(|p| p.has_any_active_contact()).count()
    }
}
