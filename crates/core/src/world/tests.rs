//! Tests of the world state: slots, ids, hashes.

use super::*;
use crate::terrain::TerrainPlacement;

fn world() -> World {
    let bounds = Aabb::new(Vec3::new(-10.0, -5.0, -10.0), Vec3::new(10.0, 20.0, 10.0));
    let terrain = Terrain::flat(TerrainPlacement {
        origin_x: -10.0,
        origin_z: -10.0,
        extent_x: 20.0,
        extent_z: 20.0,
        base_y: -5.0,
    });
    World::new(bounds, terrain, 1).unwrap()
}

#[test]
fn despawn_keeps_slots_dense_and_ids_stable() {
    let mut w = world();
    let d = &mut w.dynamics;
    let a = d.spawn(Shape::Sphere { radius: 1.0 }, Vec3::ZERO, ObjectKind::Npc).unwrap();
    let b = d.spawn(Shape::Box { half: Vec3::ONE }, Vec3::X, ObjectKind::User).unwrap();
    let c = d.spawn(Shape::Capsule { radius: 0.5, half_height: 1.0 }, Vec3::Y, ObjectKind::Npc).unwrap();
    assert!(d.despawn(a));
    assert!(!d.despawn(a));
    assert_eq!(d.len(), 2);
    assert_eq!(d.slot(c), Some(0));
    assert_eq!(d.positions()[0], Vec3::Y);
    assert_eq!(d.slot(b), Some(1));
    assert_eq!(d.shape_of(0), Shape::Capsule { radius: 0.5, half_height: 1.0 });
    let (g, a) = (d.generation(), d.action_generation());
    assert!(d.set_action(b, Action::from_bits(Action::JUMP).unwrap()));
    assert_eq!(d.actions()[1], Action::JUMP);
    assert_eq!((d.generation() - g, d.action_generation() - a), (1, 1), "only an action changed");
    assert!(d.teleport(b, Vec3::ONE));
    assert_ne!(d.generation() - g, d.action_generation() - a, "a teleport is more than an action");
    assert!(d.spawn(Shape::Sphere { radius: -1.0 }, Vec3::ZERO, ObjectKind::Npc).is_err());
    assert!(d.spawn(Shape::Sphere { radius: 1.0 }, Vec3::NAN, ObjectKind::Npc).is_err());
}

/// A hint that still names the entity's slot is taken; a stale, wrong or absent one
/// falls back to the look-up, and an unknown entity has no slot whatever the hint.
#[test]
fn a_slot_hint_is_taken_only_while_it_names_the_entity() {
    let mut w = world();
    let d = &mut w.dynamics;
    let a = d.spawn(Shape::Sphere { radius: 1.0 }, Vec3::ZERO, ObjectKind::Npc).unwrap();
    let b = d.spawn(Shape::Sphere { radius: 1.0 }, Vec3::X, ObjectKind::User).unwrap();
    let c = d.spawn(Shape::Sphere { radius: 1.0 }, Vec3::Y, ObjectKind::Npc).unwrap();
    assert_eq!(d.slot_hinted(b, Some(1)), Some(1));
    for hint in [None, Some(0), Some(2), Some(7), Some(u32::MAX)] {
        assert_eq!(d.slot_hinted(b, hint), Some(1), "hint {hint:?}");
    }
    // `a` goes: `c` moves into its slot, and `c`'s old hint is stale.
    assert!(d.despawn(a));
    assert_eq!(d.slot_hinted(c, Some(2)), Some(0));
    assert_eq!(d.slot_hinted(a, Some(0)), None);
    assert_eq!(d.slot_hinted(a, None), None);
}

#[test]
fn insert_keeps_the_id_and_refuses_bad_states() {
    let mut w = world();
    let a = w.dynamics.spawn(Shape::Sphere { radius: 1.0 }, Vec3::ZERO, ObjectKind::Npc).unwrap();
    let mut s = w.dynamics.state_of(0);
    assert_eq!(s.id, a);
    assert!(w.dynamics.insert(&s).is_err(), "the id is taken");
    s.id = EntityId(40);
    s.prev = Vec3::X;
    let g = w.dynamics.generation();
    w.dynamics.insert(&s).unwrap();
    assert!(w.dynamics.generation() > g);
    assert_eq!(w.dynamics.state_of(1), s);
    assert_eq!(w.dynamics.spawn(Shape::Sphere { radius: 1.0 }, Vec3::ZERO, ObjectKind::Npc).unwrap(), EntityId(41));
    for bad in [
        ObjectState { id: EntityId(50), pos: Vec3::NAN, ..s },
        ObjectState { id: EntityId(50), radius: -1.0, ..s },
        ObjectState { id: EntityId(50), half: Vec3::new(2.0, 1.0, 1.0), ..s },
        ObjectState { id: EntityId(50), action: 32, ..s },
        ObjectState { id: EntityId(50), flags: 4, ..s },
        ObjectState { id: EntityId(u32::MAX), ..s },
    ] {
        assert!(w.dynamics.insert(&bad).is_err(), "{bad:?}");
    }
    assert_eq!(w.dynamics.len(), 3);
    // All or none: a bad state in the middle leaves the world as it was.
    let good = ObjectState { id: EntityId(60), ..s };
    let dup = ObjectState { id: EntityId(61), ..s };
    let h = w.state_hash();
    assert!(w.dynamics.insert_all([good, dup, ObjectState { id: EntityId(61), ..s }].into_iter()).is_err());
    assert_eq!(w.state_hash(), h);
    assert!(w.dynamics.slot(EntityId(60)).is_none());
    w.dynamics.insert_all([good, dup].into_iter()).unwrap();
    assert_eq!(w.dynamics.state_of(4), dup);
    assert_eq!(w.dynamics.slot(EntityId(61)), Some(4));
    let h = w.state_hash();
    w.dynamics.clear();
    assert!(w.dynamics.is_empty());
    assert_ne!(w.state_hash(), h);
}

#[test]
fn hash_changes_with_state() {
    let mut w = world();
    let id = w.dynamics.spawn(Shape::Sphere { radius: 1.0 }, Vec3::ZERO, ObjectKind::Npc).unwrap();
    let h0 = w.state_hash();
    assert_eq!(h0, w.clone().state_hash());
    w.dynamics.teleport(id, Vec3::new(0.0, 1e-6, 0.0));
    assert_ne!(w.state_hash(), h0);
}

#[test]
fn rejects_empty_bounds() {
    let t = Terrain::flat(TerrainPlacement { origin_x: 0.0, origin_z: 0.0, extent_x: 1.0, extent_z: 1.0, base_y: 0.0 });
    assert!(World::new(Aabb::new(Vec3::ZERO, Vec3::new(1.0, 0.0, 1.0)), t, 0).is_err());
}
