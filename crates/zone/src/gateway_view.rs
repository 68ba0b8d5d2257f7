//! What a gateway holds of each zone: the objects of the zone's last view it took, which
//! the next view changes (states by interest, [`crate::views`]), or replaces (a whole
//! view, and every mirror's states message).

use std::collections::BTreeMap;

use myriad_core::{EntityId, ObjectState, Vec3};

/// One part of a zone's message of one tick, as the gateway files it.
#[derive(Clone, Debug, Default, PartialEq)]
pub(crate) struct Part {
    /// `None`: whole (replaces what the gateway holds of the zone); `Some(c)`: the
    /// changes since tick `c`.
    pub base: Option<u64>,
    /// Whole states, ids ascending.
    pub objects: Vec<ObjectState>,
    /// New positions of objects held.
    pub moves: Vec<(EntityId, Vec3)>,
    /// Ids to drop.
    pub gone: Vec<EntityId>,
}

/// Each zone's objects, as the gateway holds them.
#[derive(Debug, Default)]
pub(crate) struct ZoneViews {
    zones: BTreeMap<u16, BTreeMap<EntityId, ObjectState>>,
}

impl ZoneViews {
    /// Forgets everything (a new run of the zones: only whole views apply now).
    pub fn clear(&mut self) {
        self.zones.clear();
    }

    /// Whether a zone's parts of one tick can be applied on what the gateway holds, the
    /// zones' tick `taken` (none: nothing of this run): a whole view always; changes
    /// since a tick the gateway has reached.
    pub fn applicable(parts: &[Part], taken: Option<u64>) -> bool {
        parts.iter().all(|p| p.base.is_none_or(|c| taken.is_some_and(|t| c <= t)))
    }

    /// Applies zone `zone`'s parts of one tick (all of the same base); returns how many
    /// moves named an object not held (ignored: never sent to a gateway that holds what
    /// it confirmed).
    pub fn apply(&mut self, zone: u16, parts: Vec<Part>) -> u64 {
        let held = self.zones.entry(zone).or_default();
        let mut parts = parts.into_iter().peekable();
        if parts.peek().is_some_and(|p| p.base.is_none()) {
            // Whole: built at once from the sorted records.
            let first = parts.next().expect("peeked");
            *held = first.objects.into_iter().map(|o| (o.id, o)).collect();
        }
        let mut unknown = 0;
        for p in parts {
            for id in &p.gone {
                held.remove(id);
            }
            held.extend(p.objects.into_iter().map(|o| (o.id, o)));
            for (id, pos) in p.moves {
                match held.get_mut(&id) {
                    Some(o) => o.pos = pos,
                    None => unknown += 1,
                }
            }
        }
        unknown
    }

    /// Every zone's objects with the zone that sent each, sorted by id (an object two
    /// zones hold appears twice: the caller counts and drops the duplicate).
    pub fn assemble(&self) -> Vec<(ObjectState, u16)> {
        let mut all: Vec<(ObjectState, u16)> =
            self.zones.iter().flat_map(|(&z, held)| held.values().map(move |o| (*o, z))).collect();
        all.sort_by_key(|(o, _)| o.id);
        all
    }
}
