//! Objects for the crate's unit tests: one NPC sphere at a given place, at rest.

use myriad_core::{EntityId, ObjectKind, ObjectState, ShapeKind, Vec3};

/// An NPC sphere of radius 0.5 with id `id`, at rest at `pos`, no action, no flags.
pub(crate) fn npc_at(id: u32, pos: Vec3) -> ObjectState {
    ObjectState {
        id: EntityId(id),
        kind: ObjectKind::Npc,
        shape: ShapeKind::Sphere,
        half: Vec3::splat(0.5),
        radius: 0.5,
        pos,
        prev: pos,
        action: 0,
        flags: 0,
    }
}
