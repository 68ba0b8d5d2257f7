//! A zone's world, kept from tick to tick: what it owns and the ghosts it borrows, in
//! entity-id order, changed each tick only where something changed.
//!
//! After a step the world holds the zone's owned objects at their new states (correct:
//! stepped with every partner) and its ghosts at states computed without all their
//! partners (wrong, and never used). Before the next step [`ResidentWorld::apply`] takes
//! the neighbours' records of that tick and makes the world the one the zone must step:
//! - an owned object still in the zone's region stays owned, untouched;
//! - an owned object that left the region stays as a ghost while the zone still sees it
//!   (its state is the one its new owner receives), and goes when it does not;
//! - a ghost is overwritten by its owner's record, or goes when no record came;
//! - a record of an object not here is inserted (owned when it is a hand-off);
//! - players' leaves, orphans (a dead gateway's players) and joins as the intent book
//!   says.
//!
//! All of it is one [`SortedEdit`], applied in one pass that keeps ids ascending (the
//! physics sums partners in slot order, and one process's slots follow ids), and
//! recorded for a device copy ([`myriad_core::world::Changes`]). One tight pass over the
//! positions finds the slots near the zone's edges (ghosts, and owned objects whose
//! square of half side `reach` is not inside the region: four comparisons each); the
//! sending, the records and the decisions look only at those and at the players' slots,
//! so beyond that pass and the moving of slots (at memory speed) the host work of a tick
//! grows with the objects near the edges, not with the zone's population.

use std::time::Instant;

use myriad_core::world::SortedEdit;
use myriad_core::{EntityId, ObjectState, Statics, Vec3, World};

use crate::error::ZoneError;
use crate::gateway::player_ids;
use crate::intents::IntentBook;
use crate::layout::{Rect, ZoneId, ZoneLayout};
use crate::stats::ZoneStats;
use crate::wire::BorderRecord;

/// A zone's world and which of its objects it owns (see the module docs).
pub struct ResidentWorld {
    /// Bounds, terrain, the statics within reach, and the objects, ids ascending.
    pub(crate) world: World,
    /// Whether the zone owns the object in each slot.
    owned: Vec<bool>,
    /// How many slots are owned.
    owned_count: usize,
    /// Every static object of the world, for a new subset when the cuts move.
    all_statics: Statics,
    /// This tick's edit (reused).
    edit: SortedEdit,
    /// Whether each inserted object is owned, in the order of `edit.insert` (reused).
    insert_owned: Vec<bool>,
    /// The slots near the edges (ghosts, and owned objects not deep inside the region),
    /// ascending, and the dynamics generation and layout they were found for: the only
    /// slots a tick looks at, found by one tight pass ([`ResidentWorld::scan_edges`]).
    edge: Vec<u32>,
    edge_for: Option<(u64, Rect, u32)>,
}

impl ResidentWorld {
    /// A world of `owned` (every one owned by the zone, at `template.tick`), with
    /// `template`'s bounds, terrain, seed and tick, and its statics within reach of `z`.
    pub fn new(
        template: &World,
        layout: &ZoneLayout,
        z: ZoneId,
        mut owned: Vec<ObjectState>,
    ) -> Result<ResidentWorld, ZoneError> {
        owned.sort_unstable_by_key(|o| o.id);
        let mut world = World::new(template.bounds, template.terrain.clone(), template.seed)?;
        world.tick = template.tick;
        world.statics = statics_within(&template.statics, layout, z);
        let n = owned.len();
        world.dynamics.insert_all(owned.into_iter())?;
        Ok(ResidentWorld {
            world,
            owned: vec![true; n],
            owned_count: n,
            all_statics: template.statics.clone(),
            edit: SortedEdit::default(),
            insert_owned: Vec::new(),
            edge: Vec::new(),
            edge_for: None,
        })
    }

    /// The world (for the backend's step).
    pub fn world(&self) -> &World {
        &self.world
    }

    /// Objects owned.
    pub fn owned_count(&self) -> usize {
        self.owned_count
    }

    /// The owned objects' states, by id: after a step, the zone's advanced set.
    pub fn owned_states(&self) -> impl Iterator<Item = ObjectState> + '_ {
        let d = &self.world.dynamics;
        (0..d.len()).filter(|&s| self.owned[s]).map(|s| d.state_of(s))
    }

    /// Finds the slots near the edges of `z`'s region (see the `edge` field), unless they
    /// are known for the world and layout as they are; the pass's time goes to
    /// `stats.scan`.
    pub fn scan_edges(&mut self, layout: &ZoneLayout, z: ZoneId, stats: &mut ZoneStats) {
        let inner = Inner::of(layout, z);
        let key = (self.world.dynamics.generation(), inner.region, inner.reach.to_bits());
        if self.edge_for == Some(key) {
            return;
        }
        let start = Instant::now();
        let positions = self.world.dynamics.positions();
        self.edge.clear();
        // Zipped slices and a test without branches: the pass runs at memory speed, and
        // the one branch left (an edge slot, a few in a hundred) is well predicted.
        for (s, (&p, &owned)) in positions.iter().zip(&self.owned).enumerate() {
            if !(owned & inner.holds(p)) {
                self.edge.push(s as u32);
            }
        }
        self.edge_for = Some(key);
        stats.scan += start.elapsed();
    }

    /// The owned objects a neighbour may need: every owned object except those whose
    /// square of half side `reach` lies inside `z`'s region (four comparisons; those are
    /// seen by `z` alone and stay its own).
    pub fn near_edges<'a>(
        &'a mut self,
        layout: &ZoneLayout,
        z: ZoneId,
        stats: &mut ZoneStats,
    ) -> impl Iterator<Item = ObjectState> + use<'a> {
        self.scan_edges(layout, z, stats);
        let d = &self.world.dynamics;
        let owned = &self.owned;
        self.edge.iter().map(|&s| s as usize).filter(|&s| owned[s]).map(move |s| d.state_of(s))
    }

    /// Statics for a new layout (cuts moved): the ones within reach of `z`'s new region.
    pub fn set_layout(&mut self, layout: &ZoneLayout, z: ZoneId) {
        self.world.statics = statics_within(&self.all_statics, layout, z);
    }

    /// Makes the world the one zone `z` steps this tick (see the module docs):
    /// `received` are the neighbours' records of the tick (sorted here), `book` the
    /// players' intents. Fails on a duplicate (a record of an object this zone owns, or
    /// two records of one object). Looks only at the slots near the edges, the players'
    /// and the records'.
    pub fn apply(
        &mut self,
        layout: &ZoneLayout,
        z: ZoneId,
        received: &mut [BorderRecord],
        book: &mut IntentBook,
        stats: &mut ZoneStats,
    ) -> Result<(), ZoneError> {
        let tick = self.world.tick;
        // Each neighbour's records ascend; the stable sort merges the runs.
        received.sort_by_key(|r| r.state.id);
        if let Some(w) = received.windows(2).find(|w| w[0].state.id == w[1].state.id) {
            return Err(ZoneError::Duplicate(w[0].state.id, tick));
        }
        stats.ghosts_in += received.len() as u64;
        stats.handoffs_in += received.iter().filter(|r| r.yours).count() as u64;
        self.scan_edges(layout, z, stats);
        let start = Instant::now();
        let d = &self.world.dynamics;
        let (ids, positions) = (d.ids(), d.positions());
        let n = d.len() as u32;
        // Players' objects (ids from 2^30 on) are the last slots: each is looked at for
        // leaves and dead gateways, wherever it is.
        let players = ids.partition_point(|id| *id < EntityId(player_ids(0).start)) as u32;
        let before_players = self.edge.partition_point(|s| *s < players);
        let look = self.edge[..before_players].iter().copied().chain(players..n);
        let e = &mut self.edit;
        e.clear();
        self.insert_owned.clear();
        let mut inserts: Vec<(ObjectState, bool)> = Vec::new();
        let mut owned_count = self.owned_count;
        let mut r = 0;
        // A record of an object at no slot looked at: new here, or one this zone owns
        // deep inside its region (a duplicate).
        let unmatched = |rec: &BorderRecord, inserts: &mut Vec<(ObjectState, bool)>| {
            if d.slot_in_order(rec.state.id).is_some() {
                return Err(ZoneError::Duplicate(rec.state.id, tick));
            }
            inserts.push((rec.state, rec.yours));
            Ok(())
        };
        for s in look.map(|s| s as usize) {
            let id = ids[s];
            while r < received.len() && received[r].state.id < id {
                unmatched(&received[r], &mut inserts)?;
                r += 1;
            }
            let record = (r < received.len() && received[r].state.id == id).then(|| {
                r += 1;
                received[r - 1]
            });
            let was = self.owned[s];
            let keep = match (was, record) {
                (true, Some(_)) => return Err(ZoneError::Duplicate(id, tick)),
                (false, Some(rec)) => {
                    e.write.push((s as u32, rec.state));
                    Some(rec.yours)
                }
                (false, None) => None,
                (true, None) => {
                    let p = positions[s];
                    if layout.zone_at(p) == z { Some(true) } else { layout.sees(z, p).then_some(false) }
                }
            };
            let keep = match keep {
                Some(true) if s as u32 >= players && book.left(id) => {
                    stats.leaves += 1;
                    None
                }
                Some(true) if s as u32 >= players && !book.keeps(id, tick) => {
                    stats.orphans += 1;
                    None
                }
                k => k,
            };
            match keep {
                Some(now) => self.owned[s] = now,
                None => e.remove.push(s as u32),
            }
            owned_count = owned_count + usize::from(keep == Some(true)) - usize::from(was);
        }
        for rec in &received[r..] {
            unmatched(rec, &mut inserts)?;
        }
        // Hand-offs of players that left, or whose gateway died, are not adopted.
        inserts.retain(|&(o, owned)| {
            let gone = owned && book.left(o.id);
            stats.leaves += gone as u64;
            !gone
        });
        inserts.retain(|&(o, owned)| {
            let orphan = owned && !book.keeps(o.id, tick);
            stats.orphans += orphan as u64;
            !orphan
        });
        // Joins: adopted by the zone whose region holds them, once.
        for j in book.take_joins() {
            if layout.zone_at(j.pos) != z || book.left(j.id) {
                continue;
            }
            let here = d.slot_in_order(j.id).is_some_and(|s| e.remove.binary_search(&(s as u32)).is_err());
            if !here && !inserts.iter().any(|(o, _)| o.id == j.id) {
                inserts.push((j, true));
                stats.joins += 1;
            }
        }
        inserts.sort_by_key(|(o, _)| o.id);
        e.insert.extend(inserts.iter().map(|(o, _)| *o));
        self.insert_owned.extend(inserts.iter().map(|(_, owned)| *owned));
        // The same plan that moved the objects moves the flags.
        let moving = Instant::now();
        let plan = self.world.dynamics.apply_sorted(e)?;
        let insert_owned = &self.insert_owned;
        plan.apply(&mut self.owned, |j| insert_owned[j]);
        stats.moving += moving.elapsed();
        stats.slots_inserted += e.insert.len() as u64;
        stats.slots_removed += e.remove.len() as u64;
        stats.moving_ticks += u64::from(!e.insert.is_empty() || !e.remove.is_empty());
        self.owned_count = owned_count + self.insert_owned.iter().filter(|o| **o).count();
        self.edge_for = None;
        debug_assert_eq!(self.owned_count, self.owned.iter().filter(|o| **o).count());
        stats.ghosts = self.owned.len() - self.owned_count;
        stats.edit += start.elapsed();
        Ok(())
    }

    /// Sets the actions of this tick on the objects the zone owns: the script's
    /// (`actions`, whole world) and the players' newest from `book` (only where they
    /// differ: an unchanged action is no change). Returns how many scripted ones applied.
    pub fn set_actions(&mut self, actions: &[myriad_core::ScriptedAction], book: &IntentBook) -> usize {
        let d = &mut self.world.dynamics;
        let mut applied = 0;
        for a in actions {
            if let Some(s) = d.slot_in_order(a.entity)
                && self.owned[s]
            {
                d.set_action_at(s, a.action);
                applied += 1;
            }
        }
        for (id, action) in book.actions() {
            if let Some(s) = d.slot_in_order(id)
                && self.owned[s]
                && d.actions()[s] != action
            {
                d.set_action_at(s, myriad_core::Action::from_bits_truncate(action));
            }
        }
        applied
    }
}

/// A zone's region shrunk by the reach: a point whose square of half side `reach` lies
/// inside is seen by that zone alone ([`ZoneLayout::seers`], whose comparisons these
/// repeat: `v - reach` at or past the lower cut, `v + reach` short of the upper one).
struct Inner {
    region: Rect,
    reach: f32,
}

impl Inner {
    fn of(layout: &ZoneLayout, z: ZoneId) -> Inner {
        Inner { region: layout.region(z), reach: layout.reach() }
    }

    #[inline]
    fn holds(&self, p: Vec3) -> bool {
        let (r, h) = (&self.region, self.reach);
        (p.x - h >= r.min_x) & (p.x + h < r.max_x) & (p.z - h >= r.min_z) & (p.z + h < r.max_z)
    }
}

/// The static objects with a primitive within reach of zone `z`, in their original order
/// (so that each object's static responses are summed in the same order as in one
/// process).
fn statics_within(all: &Statics, layout: &ZoneLayout, z: ZoneId) -> Statics {
    let region = layout.region(z);
    all.subset(|_, obj| {
        (obj.first..obj.first + obj.count).any(|i| {
            let b = all.aabb(i as usize);
            let r = Rect { min_x: b.min.x, min_z: b.min.z, max_x: b.max.x, max_z: b.max.z };
            region.distance_to(&r) <= layout.reach()
        })
    })
}
