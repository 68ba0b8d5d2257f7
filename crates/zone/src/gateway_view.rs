//! What a gateway holds of each zone: the objects of the zone's last view it took, which
//! the next view changes (states by interest, [`crate::views`]), or replaces (a whole
//! view, and every mirror's states message); and the positions it held at the ticks it
//! took in the last [`NUDGE_WINDOW`], the bases a view's nudges start from.

use std::collections::{BTreeMap, VecDeque};

use myriad_core::{EntityId, ObjectState, Vec3};

use crate::views::{NUDGE_WINDOW, Positions, seek};
use crate::wire::{Ground, GroundWorld, Nudge};

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
    /// New positions of objects held, from their positions at `base`.
    pub nudges: Vec<Nudge>,
    /// Ids to drop.
    pub gone: Vec<EntityId>,
    /// New actions of objects held.
    pub acts: Vec<(EntityId, u8)>,
}

/// Whether a zone's parts of one tick can be applied.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Applicable {
    /// Yes.
    Yes,
    /// Changes since a tick the gateway has not reached (never sent to a gateway that
    /// confirmed what it holds).
    Ahead,
    /// Nudges from a tick whose positions the gateway no longer has (a zone nudges only
    /// from bases within [`NUDGE_WINDOW`], which the gateway keeps): only whole views
    /// can bring it back.
    Lost,
}

/// Applies `updates` (ids ascending, as every list of a view is) to the objects of
/// `held` they name with `f`, which says whether it could; returns how many it could not
/// or that named no object held. Many updates are merged with the held objects in one
/// ordered pass (a million objects' nudges every tick); a few are looked up.
fn update_sorted<T>(
    held: &mut BTreeMap<EntityId, ObjectState>,
    updates: Vec<T>,
    id: impl Fn(&T) -> EntityId,
    mut f: impl FnMut(&mut ObjectState, T) -> bool,
) -> u64 {
    let mut unknown = 0;
    let Some(first) = updates.first().map(&id) else { return 0 };
    if updates.len() * 16 < held.len() {
        for u in updates {
            match held.get_mut(&id(&u)) {
                Some(o) => unknown += u64::from(!f(o, u)),
                None => unknown += 1,
            }
        }
        return unknown;
    }
    let mut objects = held.range_mut(first..).peekable();
    for u in updates {
        let want = id(&u);
        while objects.next_if(|(k, _)| **k < want).is_some() {}
        match objects.peek_mut() {
            Some((k, o)) if **k == want => unknown += u64::from(!f(o, u)),
            _ => unknown += 1,
        }
    }
    unknown
}

/// Each zone's objects, as the gateway holds them.
#[derive(Debug, Default)]
pub(crate) struct ZoneViews {
    zones: BTreeMap<u16, BTreeMap<EntityId, ObjectState>>,
    /// Per zone, the positions held after each tick taken in the window (oldest first).
    history: BTreeMap<u16, VecDeque<(u64, Positions)>>,
}

impl ZoneViews {
    /// Forgets everything (a new run of the zones: only whole views apply now).
    pub fn clear(&mut self) {
        self.zones.clear();
        self.history.clear();
    }

    /// Whether zone `zone`'s parts of one tick can be applied on what the gateway holds,
    /// the zones' tick `taken` (none: nothing of this run): a whole view always; changes
    /// since a tick the gateway has reached, and nudges from one whose positions it kept.
    pub fn applicable<'a>(
        &self,
        zone: u16,
        parts: impl IntoIterator<Item = &'a Part> + Clone,
        taken: Option<u64>,
    ) -> Applicable {
        if !parts.clone().into_iter().all(|p| p.base.is_none_or(|c| taken.is_some_and(|t| c <= t))) {
            return Applicable::Ahead;
        }
        let kept = |c: u64| self.history.get(&zone).is_some_and(|h| h.iter().any(|(t, _)| *t == c));
        // Predicted nudges start from the tick before the base too.
        let bases_kept = |p: &Part| {
            let needs_before = p.nudges.iter().any(|n| n.prediction.needs_before());
            p.base.is_some_and(|c| kept(c) && (!needs_before || c.checked_sub(1).is_some_and(kept)))
        };
        match parts.into_iter().all(|p| p.nudges.is_empty() || bases_kept(p)) {
            true => Applicable::Yes,
            false => Applicable::Lost,
        }
    }

    /// Applies zone `zone`'s parts of one tick (all of the same base; checked with
    /// [`ZoneViews::applicable`]), ground nudges on `ground`; returns how many moves,
    /// nudges or acts named an object not held (ignored: never sent to a gateway that
    /// holds what it confirmed) or gave no position.
    pub fn apply(&mut self, zone: u16, parts: Vec<Part>, ground: GroundWorld<'_>) -> u64 {
        let held = self.zones.entry(zone).or_default();
        let history = self.history.get(&zone);
        let mut parts = parts.into_iter().peekable();
        if parts.peek().is_some_and(|p| p.base.is_none()) {
            // Whole: built at once from the sorted records.
            let first = parts.next().expect("peeked");
            *held = first.objects.into_iter().map(|o| (o.id, o)).collect();
        }
        let mut parts: Vec<Part> = parts.collect();
        let mut unknown = 0;
        // Every part's records and acts before any part's nudges: a ground nudge reads
        // the object's action, which another part of the tick may carry.
        for p in &mut parts {
            for id in &p.gone {
                held.remove(id);
            }
            held.extend(p.objects.drain(..).map(|o| (o.id, o)));
            let acts = std::mem::take(&mut p.acts);
            unknown += update_sorted(
                held,
                acts,
                |a| a.0,
                |o, (_, action)| {
                    o.action = action;
                    true
                },
            );
        }
        for p in parts {
            unknown += update_sorted(
                held,
                p.moves,
                |m| m.0,
                |o, (_, pos)| {
                    o.pos = pos;
                    true
                },
            );
            let at = |c: Option<u64>| {
                c.and_then(|c| history?.iter().find(|(t, _)| *t == c)).map(|(_, at)| &at[..]).unwrap_or_default()
            };
            // Nudges come ids ascending, as the positions of the base (and of the tick
            // before, for predicted ones) are: one merge each.
            let (at_base, mut b) = (at(p.base), 0);
            let (at_prior, mut q) = (at(p.base.and_then(|c| c.checked_sub(1))), 0);
            unknown += update_sorted(
                held,
                p.nudges,
                |n| n.id,
                |o, n| {
                    let Some(from) = seek(at_base, &mut b, n.id) else { return false };
                    let before = if n.prediction.needs_before() { seek(at_prior, &mut q, n.id) } else { None };
                    let on = Ground { world: ground, action: o.action, half_y: o.half.y };
                    n.apply(before, from, Some(&on)).map(|pos| o.pos = pos).is_some()
                },
            );
        }
        unknown
    }

    /// After taking tick `tick`: keeps every zone's positions of it (the base of later
    /// nudges) and drops those older than the window.
    pub fn remember(&mut self, tick: u64) {
        for (&zone, held) in &self.zones {
            let h = self.history.entry(zone).or_default();
            h.retain(|(t, _)| *t < tick && *t + NUDGE_WINDOW >= tick);
            let mut now = match h.len() as u64 > NUDGE_WINDOW {
                true => h.pop_front().map(|(_, p)| p).unwrap_or_default(),
                false => Positions::new(),
            };
            now.clear();
            now.extend(held.values().map(|o| (o.id, o.pos)));
            h.push_back((tick, now));
        }
        self.history.retain(|zone, _| self.zones.contains_key(zone));
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
