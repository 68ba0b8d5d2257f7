//! The world state.
//!
//! Dynamic objects are kept as a structure of arrays ([`Dynamics`]): one vector per
//! field, all of the same length, indexed by *slot*. Slots are dense (`0..len`) so that
//! backends can upload and sweep them as flat arrays; an object's stable identity is its
//! [`EntityId`], which survives removals of other objects (removal moves the last object
//! into the freed slot).
//!
//! Invariants:
//! - every per-slot vector of [`Dynamics`] has the same length;
//! - `slot_of[id[s]] == s` for every slot `s`;
//! - positions are finite (backends keep them inside the world bounds and above the
//!   terrain after every step).

use std::collections::hash_map::Entry;
use std::sync::{Arc, OnceLock};

use crate::stamp::Stamp;

use glam::Vec3;
use serde::{Deserialize, Serialize};
use xxhash_rust::xxh3::Xxh3;

use crate::aabb::Aabb;
use crate::action::Action;
use crate::error::CoreError;
use crate::shape::{Shape, ShapeKind};
use crate::terrain::Terrain;

/// The stable identity of a dynamic object (what clients see).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct EntityId(pub u32);

/// Who drives a dynamic object.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[repr(u8)]
pub enum ObjectKind {
    /// Moved by the server's random walk.
    Npc = 0,
    /// Moved by a player's actions.
    User = 1,
}

/// Per-object flag bits kept in [`Dynamics::flags`].
pub mod flags {
    /// The object ended the last step resting on (or just above) the terrain.
    pub const ON_TERRAIN: u8 = 1 << 0;
    /// A contact this step pushed the object upwards: it stands on another object.
    pub const SUPPORTED: u8 = 1 << 1;
}

/// The accessors of the structures of arrays [`Dynamics`] and [`Statics`], whose fields
/// `half`, `radius`, `shape`, `generation` and `stamp` mean the same in both, and whose
/// private `centres()` gives the positions: a
/// read-only slice of each of those four per-element vectors and of each one listed
/// (`name: field: type, "doc";`), the shape and the bounding box of element `i`, the
/// generation and the stamp. The literal first names an element in the docs.
macro_rules! soa_accessors {
    ($what:literal; $($name:ident: $field:ident: $t:ty, $doc:literal;)*) => {
        $(
            #[doc = $doc]
            pub fn $name(&self) -> &[$t] {
                &self.$field
            }
        )*
        #[doc = concat!("Centres (current positions) by ", $what, ". The dynamics' positions may be held by the")]
        #[doc = "backend whose step computed them: the first read fetches them all"]
        #[doc = "([`Dynamics::positions_at`] reads a few without)."]
        pub fn positions(&self) -> &[Vec3] {
            self.centres()
        }
        #[doc = concat!("Bounding-box half extents by ", $what, ".")]
        pub fn half_extents(&self) -> &[Vec3] {
            &self.half
        }
        #[doc = concat!("Radii by ", $what, " (0 for boxes).")]
        pub fn radii(&self) -> &[f32] {
            &self.radius
        }
        #[doc = concat!("Shape kinds by ", $what, ".")]
        pub fn shapes(&self) -> &[ShapeKind] {
            &self.shape
        }
        #[doc = concat!("The shape of the ", $what, " `i`.")]
        pub fn shape_of(&self, i: usize) -> Shape {
            Shape::from_compact(self.shape[i], self.half[i], self.radius[i])
        }
        #[doc = concat!("The bounding box of the ", $what, " `i`.")]
        pub fn aabb(&self, i: usize) -> Aabb {
            Aabb::from_center_half(self.centres()[i], self.half[i])
        }
        /// A counter bumped by every change made through this type's methods.
        pub fn generation(&self) -> u64 {
            self.generation
        }
        /// This value's process-unique stamp (a clone has its own): with the
        /// generation(s), what a device copy is keyed on.
        pub fn stamp(&self) -> u64 {
            self.stamp.get()
        }
    };
}

/// Dynamic objects, structure of arrays. See the module documentation for invariants.
#[derive(Clone, Debug, Default)]
pub struct Dynamics {
    id: Vec<EntityId>,
    half: Vec<Vec3>,
    radius: Vec<f32>,
    shape: Vec<ShapeKind>,
    kind: Vec<ObjectKind>,
    action: Vec<u8>,
    /// Positions, previous positions and flag bits: here, or held by the backend that
    /// stepped them until something reads them ([`Dynamics::state_mut_holding`]).
    late: Late,
    /// Slot by id, built when first asked for: a zone rebuilds its world every tick
    /// from states in id order and rarely asks, so it never pays for the map. Seeded
    /// foldhash, not SipHash: the server looks up every player's slot every tick, and
    /// SipHash was most of that (70 ns a lookup on 260,000 objects).
    slot_of: OnceLock<foldhash::HashMap<EntityId, u32>>,
    next_id: u32,
    /// Bumped by every mutation; backends use it to notice host-side changes.
    generation: u64,
    /// Bumped when objects are added or removed (slots change meaning).
    layout_generation: u64,
    /// Which dynamics these are, for device copies (a clone has its own).
    stamp: Stamp,
    /// Bumped (with `generation`) by [`Dynamics::set_action`] alone.
    action_generation: u64,
    /// What changed since the last step, while every change is recorded
    /// ([`Dynamics::changes`]).
    journal: Option<Changes>,
}

/// One dynamic object's whole state, detached from any world: what a zone hands to its
/// neighbour when the object crosses a boundary, what it lends as a ghost, and what a
/// checkpoint stores. [`Dynamics::state_of`] reads one, [`Dynamics::insert`] puts one
/// back under the same id.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ObjectState {
    /// Stable identity.
    pub id: EntityId,
    /// NPC or user.
    pub kind: ObjectKind,
    /// Shape kind (compact form with `half` and `radius`).
    pub shape: ShapeKind,
    /// Bounding-box half extents.
    pub half: Vec3,
    /// Radius (0 for boxes).
    pub radius: f32,
    /// Current position.
    pub pos: Vec3,
    /// Position one step ago.
    pub prev: Vec3,
    /// Held action mask.
    pub action: u8,
    /// Flag bits (see [`flags`]).
    pub flags: u8,
}

impl ObjectState {
    /// Checks what [`Dynamics::insert`] needs: a valid compact shape, finite positions,
    /// an action of the five known bits and only known flag bits.
    pub fn validate(&self) -> Result<(), CoreError> {
        // The compact form itself is checked (rebuilding a capsule's half height and
        // back need not round-trip bit for bit).
        let r = self.radius;
        let consistent = match self.shape {
            ShapeKind::Sphere => self.half == Vec3::splat(r),
            ShapeKind::Box => r == 0.0,
            ShapeKind::Capsule => self.half.x == r && self.half.z == r && self.half.y >= r,
        };
        if !consistent || !Shape::from_compact(self.shape, self.half, r).is_valid() {
            return Err(CoreError::invalid("shape", format!("{:?} {} {r}", self.shape, self.half)));
        }
        if !self.pos.is_finite() || !self.prev.is_finite() {
            return Err(CoreError::invalid("position", format!("{} (previous {})", self.pos, self.prev)));
        }
        if Action::from_bits(self.action).is_none() || self.flags & !(flags::ON_TERRAIN | flags::SUPPORTED) != 0 {
            return Err(CoreError::invalid("action or flags", format!("{} {}", self.action, self.flags)));
        }
        Ok(())
    }
}

/// Mutable views of the per-slot state a physics step writes, borrowed together.
pub struct DynamicsMut<'a> {
    /// Current positions.
    pub pos: &'a mut [Vec3],
    /// Positions one step ago (Verlet).
    pub prev: &'a mut [Vec3],
    /// Held actions (NPC actions are rewritten by the step).
    pub action: &'a mut [u8],
    /// Flag bits (see [`flags`]).
    pub flags: &'a mut [u8],
    /// Half extents (read-only during a step).
    pub half: &'a [Vec3],
    /// Radii.
    pub radius: &'a [f32],
    /// Shape kinds.
    pub shape: &'a [ShapeKind],
    /// NPC or user.
    pub kind: &'a [ObjectKind],
    /// Entity ids.
    pub id: &'a [EntityId],
}

impl Dynamics {
    /// Number of objects.
    pub fn len(&self) -> usize {
        self.id.len()
    }
    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.id.is_empty()
    }

    /// Adds an object at rest and returns its id. Fails on a non-finite position or an
    /// invalid shape.
    pub fn spawn(&mut self, shape: Shape, pos: Vec3, kind: ObjectKind) -> Result<EntityId, CoreError> {
        if !shape.is_valid() {
            return Err(CoreError::invalid("shape", format!("{shape:?}")));
        }
        if !pos.is_finite() {
            return Err(CoreError::invalid("position", format!("{pos}")));
        }
        let id = EntityId(self.next_id);
        if id.0 == u32::MAX {
            return Err(CoreError::invalid("entity id", "all 2^32 ids are used"));
        }
        let (half, radius) = (shape.half_extents(), shape.radius());
        let state = ObjectState { id, kind, shape: shape.kind(), half, radius, pos, prev: pos, action: 0, flags: 0 };
        self.insert_all(std::iter::once(state))?;
        Ok(id)
    }

    /// The id the next [`Dynamics::spawn`] gives (ids already used are never reused).
    pub fn next_id(&self) -> EntityId {
        EntityId(self.next_id)
    }

    /// Makes spawns continue from `id`: a process that mirrors a world stepped elsewhere
    /// (a zones gateway) spawns its players in a range of ids of its own, so that two
    /// such processes never give out the same id. A spawn onto an id that is taken
    /// fails; it never replaces an object.
    pub fn set_next_id(&mut self, id: EntityId) {
        self.next_id = id.0;
    }

    /// Removes an object; the last object moves into its slot. Returns false if the id is
    /// unknown.
    pub fn despawn(&mut self, id: EntityId) -> bool {
        let Some(slot) = self.slots_mut().remove(&id) else {
            return false;
        };
        let s = slot as usize;
        self.id.swap_remove(s);
        self.half.swap_remove(s);
        self.radius.swap_remove(s);
        self.shape.swap_remove(s);
        self.kind.swap_remove(s);
        self.action.swap_remove(s);
        let late = self.late.get_mut();
        late.pos.swap_remove(s);
        late.prev.swap_remove(s);
        late.flags.swap_remove(s);
        if s < self.id.len() {
            let moved = self.id[s];
            self.slots_mut().insert(moved, slot);
        }
        self.generation += 1;
        self.layout_generation += 1;
        self.journal = None;
        true
    }

    /// The whole state of the object in `slot`.
    pub fn state_of(&self, slot: usize) -> ObjectState {
        let late = self.late.get();
        ObjectState {
            id: self.id[slot],
            kind: self.kind[slot],
            shape: self.shape[slot],
            half: self.half[slot],
            radius: self.radius[slot],
            pos: late.pos[slot],
            prev: late.prev[slot],
            action: self.action[slot],
            flags: late.flags[slot],
        }
    }

    /// Adds an object with a state taken from elsewhere (another zone, a checkpoint),
    /// keeping its id. Fails, adding nothing, when the id is already here or is
    /// `u32::MAX` (which would leave no id for [`Dynamics::spawn`]), or when the shape,
    /// the positions, the action or the flags are not valid.
    pub fn insert(&mut self, s: &ObjectState) -> Result<(), CoreError> {
        self.insert_all(std::iter::once(*s))
    }

    /// [`Dynamics::insert`] for many objects at once, all or none: a zone rebuilds its
    /// world from states every tick. When the world is empty and the ids ascend (a zone's
    /// case) no map is needed to prove them unique, and none is built.
    pub fn insert_all<I>(&mut self, states: I) -> Result<(), CoreError>
    where
        I: ExactSizeIterator<Item = ObjectState> + Clone,
    {
        let before = self.len();
        let n = states.len();
        let mut last: Option<EntityId> = None;
        let mut ascending = before == 0;
        for s in states.clone() {
            s.validate()?;
            if s.id.0 == u32::MAX {
                return Err(CoreError::invalid("entity id", "u32::MAX is reserved"));
            }
            ascending &= last.is_none_or(|l| l < s.id);
            last = Some(s.id);
        }
        if !ascending {
            let map = self.slots_mut();
            for (i, s) in states.clone().enumerate() {
                if let Entry::Vacant(v) = map.entry(s.id) {
                    v.insert((before + i) as u32);
                } else {
                    // Undo the slots already claimed: all or none.
                    for s in states.take(i) {
                        map.remove(&s.id);
                    }
                    return Err(CoreError::invalid("entity id", format!("{} is taken", s.id.0)));
                }
            }
        } else {
            // Slots change meaning: a map built before is stale.
            self.slot_of.take();
        }
        let late = self.late.get_mut();
        self.id.reserve(n);
        late.pos.reserve(n);
        late.prev.reserve(n);
        self.half.reserve(n);
        self.radius.reserve(n);
        self.shape.reserve(n);
        self.kind.reserve(n);
        self.action.reserve(n);
        late.flags.reserve(n);
        let mut max = self.next_id;
        for s in states {
            self.id.push(s.id);
            late.pos.push(s.pos);
            late.prev.push(s.prev);
            self.half.push(s.half);
            self.radius.push(s.radius);
            self.shape.push(s.shape);
            self.kind.push(s.kind);
            self.action.push(s.action);
            late.flags.push(s.flags);
            max = max.max(s.id.0 + 1);
        }
        self.next_id = max;
        self.generation += 1;
        self.layout_generation += 1;
        self.journal = None;
        Ok(())
    }

    /// Removes every object. Ids are not reused afterwards, and the generations move on
    /// (never back), so a backend still notices the change.
    pub fn clear(&mut self) {
        self.id.clear();
        self.half.clear();
        self.radius.clear();
        self.shape.clear();
        self.kind.clear();
        self.action.clear();
        // Nothing left to fetch: whatever held the old values is forgotten.
        self.late = Late::default();
        self.slot_of.take();
        self.generation += 1;
        self.layout_generation += 1;
        self.journal = None;
    }

    /// The slot of an entity, if it exists.
    pub fn slot(&self, id: EntityId) -> Option<usize> {
        self.slots().get(&id).map(|&s| s as usize)
    }

    /// The slot of an entity, trying `hint` (a slot it had) first: a caller that keeps
    /// each entity's last slot (the server, for every player every tick) reads one id
    /// instead of looking it up in the map of every object, a cache miss or two at a
    /// million objects. Any hint is safe: a wrong or stale one costs the look-up.
    pub fn slot_hinted(&self, id: EntityId, hint: Option<u32>) -> Option<usize> {
        match hint.map(|h| h as usize) {
            Some(s) if self.id.get(s) == Some(&id) => Some(s),
            _ => self.slot(id),
        }
    }

    /// The slot map, built from the ids if nobody asked since the slots last changed.
    fn slots(&self) -> &foldhash::HashMap<EntityId, u32> {
        self.slot_of.get_or_init(|| self.id.iter().enumerate().map(|(s, id)| (*id, s as u32)).collect())
    }

    /// The slot map, to change.
    fn slots_mut(&mut self) -> &mut foldhash::HashMap<EntityId, u32> {
        self.slots();
        self.slot_of.get_mut().expect("built just above")
    }

    /// Sets the held action of an entity. Returns false if the id is unknown.
    pub fn set_action(&mut self, id: EntityId, action: Action) -> bool {
        let Some(s) = self.slot(id) else { return false };
        self.set_action_at(s, action)
    }

    /// Sets the held action of the object in `slot`. Returns false if there is none.
    pub fn set_action_at(&mut self, slot: usize, action: Action) -> bool {
        let Some(a) = self.action.get_mut(slot) else { return false };
        *a = action.bits();
        self.generation += 1;
        self.action_generation += 1;
        if let Some(j) = &mut self.journal {
            j.actions = true;
        }
        true
    }

    /// Moves an entity to `pos` at rest. Returns false if the id is unknown or the
    /// position is not finite.
    pub fn teleport(&mut self, id: EntityId, pos: Vec3) -> bool {
        let Some(s) = self.slot(id) else { return false };
        if !pos.is_finite() {
            return false;
        }
        let late = self.late.get_mut();
        late.pos[s] = pos;
        late.prev[s] = pos;
        self.generation += 1;
        self.journal = None;
        true
    }

    /// Borrows the per-slot state for a physics step (bumps the generation).
    pub fn state_mut(&mut self) -> DynamicsMut<'_> {
        self.generation += 1;
        self.restart_journal();
        let late = self.late.get_mut();
        DynamicsMut {
            pos: &mut late.pos,
            prev: &mut late.prev,
            action: &mut self.action,
            flags: &mut late.flags,
            half: &self.half,
            radius: &self.radius,
            shape: &self.shape,
            kind: &self.kind,
            id: &self.id,
        }
    }

    /// [`Dynamics::state_mut`] for a step that leaves the positions, the previous
    /// positions and the flags with `holder` (where the step computed them): the step
    /// writes the actions it returns, and the others are fetched from `holder` when
    /// something first reads or changes them (module `late`), or only some positions
    /// when a reader asks for those ([`Dynamics::positions_at`]). Whatever held them
    /// before is forgotten unread: this step's values are newer. Bumps the generation.
    pub fn state_mut_holding(&mut self, holder: Arc<dyn HeldState>) -> &mut [u8] {
        self.generation += 1;
        self.restart_journal();
        self.late.hold(holder);
        &mut self.action
    }

    /// The positions of the objects in `slots`, in that order, into `out` (cleared
    /// first). Equal to indexing [`Dynamics::positions`], but when the last step left
    /// the positions with its backend only these come back (a GPU server reads its
    /// players' positions every tick, a few percent of the objects) and the rest stay
    /// where they are. Panics on a slot out of range, as indexing would.
    pub fn positions_at(&self, slots: &[u32], out: &mut Vec<Vec3>) {
        out.clear();
        out.resize(slots.len(), Vec3::ZERO);
        self.late.positions_at(slots, out);
    }

    /// Whether the positions, previous positions and flags are held by the backend whose
    /// step computed them, not read whole since ([`Dynamics::state_mut_holding`]): a
    /// GPU server reads its players' positions every tick without fetching them.
    pub fn state_held(&self) -> bool {
        self.late.is_held()
    }

    /// The current positions, here or fetched (the accessors' `positions`).
    fn centres(&self) -> &[Vec3] {
        &self.late.get().pos
    }

    soa_accessors! {
        "slot";
        ids: id: EntityId, "Entity ids by slot.";
        kinds: kind: ObjectKind, "NPC or user, by slot.";
        actions: action: u8, "Held action masks by slot.";
    }
    /// Previous positions by slot (velocity per tick is `pos - prev`); fetched first,
    /// like [`Dynamics::positions`], when the last step left them with its backend.
    pub fn prev_positions(&self) -> &[Vec3] {
        &self.late.get().prev
    }
    /// Flag bits by slot (see [`flags`]); fetched first like
    /// [`Dynamics::prev_positions`].
    pub fn flags(&self) -> &[u8] {
        &self.late.get().flags
    }
    /// A counter bumped whenever objects are added or removed.
    pub fn layout_generation(&self) -> u64 {
        self.layout_generation
    }
    /// A counter bumped, together with [`Dynamics::generation`], by every
    /// [`Dynamics::set_action`] and by nothing else. A backend that last saw generations
    /// `(g, a)` knows that only actions changed since when
    /// `generation() - g == action_generation() - a`: then it need copy nothing but the
    /// actions (a server sets a few thousand actions a tick, and nothing else).
    pub fn action_generation(&self) -> u64 {
        self.action_generation
    }
}

/// What a static object represents (the reference's three kinds).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[repr(u8)]
pub enum StaticKind {
    /// A capsule trunk under two boxes of crown.
    Tree = 0,
    /// One box (a crate).
    Crate = 1,
    /// Two boxes, a wide base and a smaller top.
    Rock = 2,
    /// Anything else (imported scenery).
    Other = 3,
}

/// One static object: a run of primitives in [`Statics`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct StaticObject {
    /// What it is.
    pub kind: StaticKind,
    /// Index of its first primitive.
    pub first: u32,
    /// Number of primitives.
    pub count: u32,
}

/// Static scenery: objects made of primitives that never move. Primitives are kept as
/// a structure of arrays in the same compact shape form as dynamic objects.
#[derive(Clone, Debug, Default)]
pub struct Statics {
    objects: Vec<StaticObject>,
    pos: Vec<Vec3>,
    half: Vec<Vec3>,
    radius: Vec<f32>,
    shape: Vec<ShapeKind>,
    owner: Vec<u32>,
    /// Bumped by every change, so backends know when to rebuild their static tree.
    generation: u64,
    /// Which statics these are, for device copies (a clone has its own).
    stamp: Stamp,
}

impl Statics {
    /// Adds an object made of `(shape, position)` primitives. Fails on an invalid shape or
    /// a non-finite position, adding nothing.
    pub fn add(&mut self, kind: StaticKind, prims: &[(Shape, Vec3)]) -> Result<u32, CoreError> {
        for (shape, pos) in prims {
            if !shape.is_valid() || !pos.is_finite() {
                return Err(CoreError::invalid("static primitive", format!("{shape:?} at {pos}")));
            }
        }
        let index = self.objects.len() as u32;
        self.objects.push(StaticObject { kind, first: self.pos.len() as u32, count: prims.len() as u32 });
        for (shape, pos) in prims {
            self.pos.push(*pos);
            self.half.push(shape.half_extents());
            self.radius.push(shape.radius());
            self.shape.push(shape.kind());
            self.owner.push(index);
        }
        self.generation += 1;
        Ok(index)
    }

    /// The objects `keep` accepts (by index), in their order, primitives copied in
    /// compact form bit for bit (a zone holds the scenery within its reach this way, and
    /// each object's static responses keep their order).
    pub fn subset(&self, mut keep: impl FnMut(usize, &StaticObject) -> bool) -> Statics {
        let mut out = Statics::default();
        for (i, obj) in self.objects.iter().enumerate() {
            if !keep(i, obj) {
                continue;
            }
            let index = out.objects.len() as u32;
            out.objects.push(StaticObject { first: out.pos.len() as u32, ..*obj });
            let prims = obj.first as usize..(obj.first + obj.count) as usize;
            out.pos.extend_from_slice(&self.pos[prims.clone()]);
            out.half.extend_from_slice(&self.half[prims.clone()]);
            out.radius.extend_from_slice(&self.radius[prims.clone()]);
            out.shape.extend_from_slice(&self.shape[prims.clone()]);
            out.owner.extend(prims.map(|_| index));
        }
        out.generation = 1;
        out
    }

    /// The objects.
    pub fn objects(&self) -> &[StaticObject] {
        &self.objects
    }
    /// Number of primitives.
    pub fn prim_count(&self) -> usize {
        self.pos.len()
    }
    /// The primitives' centres (the accessors' `positions`).
    fn centres(&self) -> &[Vec3] {
        &self.pos
    }
    soa_accessors! {
        "primitive";
        owners: owner: u32, "The object each primitive belongs to.";
    }
    /// Number of primitives of each kind, in [`ShapeKind`] order.
    pub fn prims_by_shape(&self) -> [usize; 3] {
        let mut n = [0; 3];
        for s in &self.shape {
            n[*s as usize] += 1;
        }
        n
    }
}

/// The whole simulated world.
#[derive(Clone, Debug)]
pub struct World {
    /// Objects are kept inside these bounds; arbitrary, need not start at the origin.
    pub bounds: Aabb,
    /// The ground.
    pub terrain: Terrain,
    /// Scenery.
    pub statics: Statics,
    /// Moving objects.
    pub dynamics: Dynamics,
    /// Seed of the random numbers NPCs draw.
    pub seed: u64,
    /// Steps taken so far.
    pub tick: u64,
}

impl World {
    /// An empty world over `bounds` with the given terrain.
    pub fn new(bounds: Aabb, terrain: Terrain, seed: u64) -> Result<World, CoreError> {
        if !bounds.is_valid() || bounds.size().cmple(Vec3::ZERO).any() {
            return Err(CoreError::invalid("world bounds", format!("{bounds:?}")));
        }
        Ok(World { bounds, terrain, statics: Statics::default(), dynamics: Dynamics::default(), seed, tick: 0 })
    }

    /// A stable 64-bit hash of the simulated state: tick, and per slot the id, position,
    /// previous position, action and flags, as little-endian bytes (xxh3). Equal hashes
    /// mean bit-identical worlds for all practical purposes; the value is the same on
    /// every platform.
    pub fn state_hash(&self) -> u64 {
        let d = &self.dynamics;
        hash_state((0..d.len()).map(|s| d.state_of(s)), self.tick, d.len())
    }
}

/// [`World::state_hash`] of a world at `tick` whose slots hold `objects` in this order
/// (`len` of them): how a world split over several zones is compared with one process.
pub fn hash_state(objects: impl Iterator<Item = ObjectState>, tick: u64, len: usize) -> u64 {
    let mut h = Xxh3::new();
    h.update(&tick.to_le_bytes());
    h.update(&(len as u64).to_le_bytes());
    for o in objects {
        h.update(&o.id.0.to_le_bytes());
        for v in [o.pos, o.prev] {
            for c in v.to_array() {
                h.update(&c.to_bits().to_le_bytes());
            }
        }
        h.update(&[o.action, o.flags]);
    }
    h.digest()
}

mod edit;
mod late;

pub use edit::{Changes, EditPlan, SlotRun, SortedEdit};
pub use late::HeldState;

use late::Late;

#[cfg(test)]
mod tests;
