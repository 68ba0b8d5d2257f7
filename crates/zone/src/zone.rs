//! One zone: the objects it owns, the ghosts it borrows, and its tick.
//!
//! A tick at `t`, for zone `Z` (see `docs/zones.md` for why each step keeps one
//! process's bits):
//! 1. *Send.* Every object `Z` stepped last (its *advanced* set) goes to each neighbour
//!    that sees it ([`ZoneLayout::seers`]), marked *yours* for the neighbour whose region
//!    now holds its centre: a ghost and a hand-off are one record.
//! 2. *Gather.* `Z` waits for the border states of tick `t` from each neighbour (not a
//!    global barrier), authenticating and ordering them in its inbox.
//! 3. *Step.* `Z` assembles a world of what it owns (advanced objects still in its region,
//!    plus those handed to it) and its ghosts (every other object it sees), sorted by
//!    entity id, and steps it with any backend. Because a step sums each object's
//!    responses in the order of its partners' slots, and slots follow entity ids in both
//!    the zone's world and a scenario's world, an owned object gets the same bits as in
//!    one process — provided every partner is there, which `reach` guarantees.
//! 4. *Keep.* The owned objects' new states become the advanced set; ghosts' results are
//!    dropped (their owners computed them with all their partners).

use std::collections::BTreeMap;
use std::ops::ControlFlow;
use std::sync::Arc;
use std::time::{Duration, Instant};

use myriad_core::{ObjectState, ScriptedAction, Statics, World};
use myriad_physics::{Backend, TickConstants};

use crate::error::ZoneError;
use crate::fabric::Fabric;
use crate::intents::IntentBook;
use crate::layout::{ZoneId, ZoneLayout};
use crate::stats::ZoneStats;
use crate::wire::{
    ALL, Border, BorderRecord, ClusterKey, HEADER_LEN, Message, RECORD_LEN, TAG_LEN, decode, encode_border,
    encode_states,
};

/// What a zone needs besides its world: identity, cluster and patience.
#[derive(Clone, Debug)]
pub struct ZoneConfig {
    /// This zone.
    pub id: ZoneId,
    /// The run (epoch) of the cluster: messages of other runs are refused.
    pub run: u64,
    /// The key every message is signed with.
    pub key: ClusterKey,
    /// How long to wait for a neighbour's border state before declaring it stalled.
    pub wait: Duration,
    /// Whether the zone serves gateways: it publishes its owned objects' states after
    /// every step ([`Fabric::publish_states`]). Players' intents are taken either way.
    pub live: bool,
}

/// How a zone's tick ended (a [`Zone::step`] that returns `Ok`).
#[derive(Clone, Debug, PartialEq)]
pub enum TickEnd {
    /// The zone stepped to the next tick, applying this many of the tick's scripted
    /// actions (those of objects it owns).
    Stepped(usize),
    /// The supervisor's halt or start arrived while the zone waited for its neighbours:
    /// the tick did not happen (the zone is still at it), and the caller decides what
    /// the message means (a zone process ends its epoch on a newer one).
    Interrupted(Message),
}

/// The parts of one neighbour's border state for one tick.
#[derive(Default)]
struct Parts {
    parts: u16,
    got: Vec<Option<Vec<BorderRecord>>>,
}

impl Parts {
    fn complete(&self) -> bool {
        self.parts > 0 && self.got.iter().all(Option::is_some)
    }
}

/// An object of the step being assembled, with whether this zone owns it (steps it as
/// owner and keeps its result) or only sees it (a ghost).
#[derive(Clone, Copy)]
struct Member {
    state: ObjectState,
    owned: bool,
}

/// One zone of a world split over several (see the module documentation).
pub struct Zone {
    cfg: ZoneConfig,
    layout: Arc<ZoneLayout>,
    /// Bounds, terrain, the statics within reach, and the objects of the current step.
    world: World,
    /// The objects this zone stepped as owner last tick, by id (their states now).
    advanced: Vec<ObjectState>,
    inbox: BTreeMap<(u64, ZoneId), Parts>,
    backend: Box<dyn Backend>,
    fabric: Box<dyn Fabric>,
    stats: ZoneStats,
    /// Whether each slot of the last step was owned (scratch).
    owned_slots: Vec<bool>,
    /// The objects of the step being assembled (scratch).
    scratch: Vec<Member>,
    /// Gateways' joins, actions and leaves for players' objects.
    intents: IntentBook,
}

impl Zone {
    /// The zone `cfg.id` of `world` (whole, at its current tick): it takes the objects
    /// whose centres lie in its region and the static objects within reach.
    pub fn new(
        cfg: ZoneConfig,
        layout: Arc<ZoneLayout>,
        world: &World,
        backend: Box<dyn Backend>,
        fabric: Box<dyn Fabric>,
    ) -> Result<Zone, ZoneError> {
        let d = &world.dynamics;
        let mut advanced: Vec<ObjectState> =
            (0..d.len()).filter(|&s| layout.zone_at(d.positions()[s]) == cfg.id).map(|s| d.state_of(s)).collect();
        advanced.sort_unstable_by_key(|o| o.id);
        Zone::resume(cfg, layout, world, advanced, backend, fabric)
    }

    /// The zone `cfg.id` resuming from its own objects (`owned`, at `world.tick`), as
    /// after a checkpoint; `world` supplies bounds, terrain, statics, seed and tick (its
    /// dynamic objects are ignored).
    pub fn resume(
        cfg: ZoneConfig,
        layout: Arc<ZoneLayout>,
        world: &World,
        mut owned: Vec<ObjectState>,
        backend: Box<dyn Backend>,
        fabric: Box<dyn Fabric>,
    ) -> Result<Zone, ZoneError> {
        if cfg.id.0 as usize >= layout.len() {
            return Err(ZoneError::Layout(format!("zone {} of a layout of {}", cfg.id.0, layout.len())));
        }
        owned.sort_unstable_by_key(|o| o.id);
        let mut own = World::new(world.bounds, world.terrain.clone(), world.seed)?;
        own.tick = world.tick;
        own.statics = statics_within(&world.statics, &layout, cfg.id);
        let stats = ZoneStats { owned: owned.len(), ..ZoneStats::default() };
        Ok(Zone {
            cfg,
            layout,
            world: own,
            advanced: owned,
            inbox: BTreeMap::new(),
            backend,
            fabric,
            stats,
            owned_slots: Vec::new(),
            scratch: Vec::new(),
            intents: IntentBook::new(world.tick),
        })
    }

    /// This zone's id.
    pub fn id(&self) -> ZoneId {
        self.cfg.id
    }

    /// The tick the next step starts.
    pub fn tick(&self) -> u64 {
        self.world.tick
    }

    /// The states of the objects this zone stepped last, by id: after the last tick
    /// the zones' advanced sets partition the world.
    pub fn advanced(&self) -> &[ObjectState] {
        &self.advanced
    }

    /// The counters.
    pub fn stats(&self) -> &ZoneStats {
        &self.stats
    }

    /// Static primitives this zone holds.
    pub fn static_prims(&self) -> usize {
        self.world.statics.prim_count()
    }

    /// One tick: exchange border states with the neighbours, then step. `actions` are
    /// the actions of this tick for the whole world; those of objects this zone owns are
    /// applied ([`TickEnd::Stepped`] says how many), unless the supervisor interrupts
    /// the tick.
    pub fn step(&mut self, actions: &[ScriptedAction], k: &TickConstants) -> Result<TickEnd, ZoneError> {
        let t = self.world.tick;
        let send = Instant::now();
        self.send_borders(t)?;
        self.stats.send += send.elapsed();
        let received = match self.gather(t)? {
            ControlFlow::Continue(received) => received,
            ControlFlow::Break(control) => return Ok(TickEnd::Interrupted(control)),
        };
        if let Some(control) = self.drain_ready()? {
            return Ok(TickEnd::Interrupted(control));
        }
        let start = Instant::now();
        let applied = self.assemble(received, actions)?;
        let physics = Instant::now();
        self.backend.step(&mut self.world, k)?;
        self.stats.physics += physics.elapsed();
        let d = &self.world.dynamics;
        self.advanced.clear();
        self.advanced.extend((0..d.len()).filter(|&s| self.owned_slots[s]).map(|s| d.state_of(s)));
        self.stats.ticks += 1;
        self.stats.owned = self.advanced.len();
        self.stats.step += start.elapsed();
        if self.cfg.live {
            self.publish_states()?;
        }
        self.intents.expire(self.world.tick);
        self.stats.bytes = self.fabric.bytes();
        Ok(TickEnd::Stepped(applied))
    }

    /// The advanced set, at the tick just reached, to every gateway.
    fn publish_states(&mut self) -> Result<(), ZoneError> {
        for (part, parts, chunk) in split(&self.advanced, self.records_per_part())? {
            let m = Border {
                run: self.cfg.run,
                tick: self.world.tick,
                from: self.cfg.id,
                to: ALL,
                part,
                parts,
                objects: chunk.iter().copied().map(BorderRecord::seen).collect(),
            };
            self.fabric.publish_states(encode_states(&self.cfg.key, &m)?)?;
            self.stats.messages.0 += 1;
        }
        Ok(())
    }

    fn records_per_part(&self) -> usize {
        ((self.fabric.max_message() - HEADER_LEN - TAG_LEN) / RECORD_LEN).max(1)
    }

    /// Step 1: the advanced set to every neighbour that sees it.
    fn send_borders(&mut self, t: u64) -> Result<(), ZoneError> {
        let me = self.cfg.id;
        let neighbours = self.layout.neighbours(me);
        let mut out: Vec<Vec<BorderRecord>> = vec![Vec::new(); neighbours.len()];
        for o in &self.advanced {
            let owner = self.layout.zone_at(o.pos);
            for z in self.layout.seers(o.pos).filter(|&z| z != me) {
                let i =
                    neighbours.iter().position(|&n| n == z).ok_or(ZoneError::TooFar { id: o.id, from: me, to: z })?;
                out[i].push(BorderRecord { state: *o, yours: z == owner });
                self.stats.handoffs_out += (z == owner) as u64;
            }
        }
        let per_part = self.records_per_part();
        for (&to, objects) in neighbours.iter().zip(out) {
            self.stats.ghosts_out += objects.len() as u64;
            for (part, parts, chunk) in split(&objects, per_part)? {
                let m = Border { run: self.cfg.run, tick: t, from: me, to, part, parts, objects: chunk.to_vec() };
                self.fabric.send(to, encode_border(&self.cfg.key, &m)?)?;
                self.stats.messages.0 += 1;
            }
        }
        Ok(())
    }

    /// Step 2: every neighbour's border state for tick `t`, or the supervisor's message
    /// that interrupted the wait.
    fn gather(&mut self, t: u64) -> Result<ControlFlow<Message, Vec<BorderRecord>>, ZoneError> {
        let start = Instant::now();
        let deadline = start + self.cfg.wait;
        let neighbours = self.layout.neighbours(self.cfg.id).to_vec();
        let complete = |inbox: &BTreeMap<(u64, ZoneId), Parts>| {
            neighbours.iter().all(|n| inbox.get(&(t, *n)).is_some_and(Parts::complete))
        };
        while !complete(&self.inbox) {
            match self.fabric.recv(deadline)? {
                Some(bytes) => {
                    if let Some(control) = self.offer(&bytes) {
                        return Ok(ControlFlow::Break(control));
                    }
                }
                None => {
                    let missing = neighbours
                        .iter()
                        .filter(|n| !self.inbox.get(&(t, **n)).is_some_and(Parts::complete))
                        .copied()
                        .collect();
                    return Err(ZoneError::Stalled {
                        zone: self.cfg.id,
                        tick: t,
                        waited_ms: self.cfg.wait.as_millis() as u64,
                        missing,
                    });
                }
            }
        }
        self.stats.wait += start.elapsed();
        let mut received = Vec::new();
        for n in &neighbours {
            let parts = self.inbox.remove(&(t, *n)).expect("complete");
            received.extend(parts.got.into_iter().flatten().flatten());
        }
        Ok(ControlFlow::Continue(received))
    }

    /// Takes every message already waiting (gateways' intents arrive whether or not this
    /// zone waits on neighbours; a zone without any would otherwise never read them), up
    /// to a supervisor's message that interrupts the tick (returned).
    fn drain_ready(&mut self) -> Result<Option<Message>, ZoneError> {
        while let Some(bytes) = self.fabric.recv(Instant::now())? {
            if let Some(control) = self.offer(&bytes) {
                return Ok(Some(control));
            }
        }
        Ok(None)
    }

    /// Files a message in the inbox, or rejects (and counts) it. Only authenticated
    /// border messages of this run, for this zone, from a neighbour, for this tick or the
    /// next (a neighbour is never further ahead), and not seen before, are kept. The
    /// supervisor's halt and start are handed back: they interrupt the tick.
    pub fn offer(&mut self, bytes: &[u8]) -> Option<Message> {
        let t = self.world.tick;
        let m = match decode(&self.cfg.key, bytes) {
            Ok(Message::Border(m)) => m,
            Ok(control @ (Message::Halt { .. } | Message::Start { .. })) => return Some(control),
            Ok(Message::Intents(i)) => {
                return match self.intents.offer(i, t) {
                    Ok(()) => {
                        self.stats.messages.1 += 1;
                        None
                    }
                    Err(refused) => self.reject(refused.label(), t),
                };
            }
            Ok(_) => return self.reject("kind", t),
            Err(e) => return self.reject(e.label(), t),
        };
        let reason = if m.run != self.cfg.run {
            "run"
        } else if m.to != self.cfg.id {
            "misrouted"
        } else if !self.layout.neighbours(self.cfg.id).contains(&m.from) {
            "stranger"
        } else if m.tick < t {
            "stale"
        } else if m.tick > t + 1 {
            "early"
        } else {
            let entry = self.inbox.entry((m.tick, m.from)).or_default();
            if entry.parts == 0 {
                entry.parts = m.parts;
                entry.got = vec![None; m.parts as usize];
            }
            if entry.parts != m.parts {
                "parts"
            } else if entry.got[m.part as usize].is_some() {
                "replayed"
            } else {
                self.stats.messages.1 += 1;
                entry.got[m.part as usize] = Some(m.objects);
                return None;
            }
        };
        self.reject(reason, t)
    }

    fn reject(&mut self, reason: &'static str, t: u64) -> Option<Message> {
        *self.stats.rejected.entry(reason).or_default() += 1;
        tracing::debug!(zone = self.cfg.id.0, tick = t, reason, "fabric message rejected");
        None
    }

    /// Gives the fabric back (a zone process keeps its connection across epochs).
    pub fn into_fabric(self) -> Box<dyn Fabric> {
        self.fabric
    }

    /// Step 3: the zone's world for this tick, in entity-id order, with the owned
    /// objects' actions set.
    fn assemble(&mut self, received: Vec<BorderRecord>, actions: &[ScriptedAction]) -> Result<usize, ZoneError> {
        let me = self.cfg.id;
        let layout = &self.layout;
        // Reused from tick to tick: a zone's world is rebuilt every tick.
        let objects = &mut self.scratch;
        objects.clear();
        for o in &self.advanced {
            if layout.zone_at(o.pos) == me {
                objects.push(Member { state: *o, owned: true });
            } else if layout.sees(me, o.pos) {
                objects.push(Member { state: *o, owned: false });
            }
        }
        self.stats.ghosts_in += received.len() as u64;
        self.stats.handoffs_in += received.iter().filter(|r| r.yours).count() as u64;
        // A record handed to this zone is one it owns from now on.
        objects.extend(received.into_iter().map(|r| Member { state: r.state, owned: r.yours }));
        // Stable sort: the advanced set and each message are runs already sorted by id,
        // which the stable sort merges instead of sorting from scratch.
        objects.sort_by_key(|m| m.state.id);
        if let Some(w) = objects.windows(2).find(|w| w[0].state.id == w[1].state.id) {
            return Err(ZoneError::Duplicate(w[0].state.id, self.world.tick));
        }
        // Players: leaves remove what this zone owns, and so does the death or restart of
        // the object's gateway; joins are adopted by the zone whose region holds them
        // (once: not if the object is here already, or left).
        let (book, now) = (&self.intents, self.world.tick);
        let before = objects.len();
        objects.retain(|m| !(m.owned && book.left(m.state.id)));
        self.stats.leaves += (before - objects.len()) as u64;
        let before = objects.len();
        objects.retain(|m| !m.owned || book.keeps(m.state.id, now));
        self.stats.orphans += (before - objects.len()) as u64;
        for j in self.intents.take_joins() {
            if layout.zone_at(j.pos) != me || self.intents.left(j.id) {
                continue;
            }
            if let Err(at) = objects.binary_search_by_key(&j.id, |m| m.state.id) {
                objects.insert(at, Member { state: j, owned: true });
                self.stats.joins += 1;
            }
        }
        let d = &mut self.world.dynamics;
        d.clear();
        d.insert_all(objects.iter().map(|m| m.state))?;
        self.owned_slots.clear();
        self.owned_slots.extend(objects.iter().map(|m| m.owned));
        self.stats.ghosts = objects.len() - self.owned_slots.iter().filter(|o| **o).count();
        let mut applied = 0;
        for a in actions {
            // Slots are in id order: a search, not the id map (which would cost a map of
            // the whole zone every tick).
            if let Ok(s) = objects.binary_search_by_key(&a.entity, |m| m.state.id)
                && self.owned_slots[s]
            {
                d.set_action_at(s, a.action);
                applied += 1;
            }
        }
        for (id, action) in self.intents.actions() {
            if let Ok(s) = objects.binary_search_by_key(&id, |m| m.state.id)
                && self.owned_slots[s]
                && d.actions()[s] != action
            {
                d.set_action_at(s, myriad_core::Action::from_bits_truncate(action));
            }
        }
        Ok(applied)
    }
}

/// `items` in parts of at most `per_part` (at least one part, even when empty), each
/// with its index and the count, as a message in parts carries them.
fn split<T>(items: &[T], per_part: usize) -> Result<impl Iterator<Item = (u16, u16, &[T])>, ZoneError> {
    let parts = items.len().div_ceil(per_part).max(1);
    let count = u16::try_from(parts).map_err(|_| ZoneError::Fabric(format!("{parts} parts")))?;
    Ok((0..parts).map(move |i| {
        let chunk = &items[(i * per_part).min(items.len())..((i + 1) * per_part).min(items.len())];
        (i as u16, count, chunk)
    }))
}

/// The static objects with a primitive within reach of zone `z`, in their original order
/// (so that each object's static responses are summed in the same order as in one
/// process).
fn statics_within(all: &Statics, layout: &ZoneLayout, z: ZoneId) -> Statics {
    let region = layout.region(z);
    all.subset(|_, obj| {
        (obj.first..obj.first + obj.count).any(|i| {
            let b = all.aabb(i as usize);
            let r = crate::layout::Rect { min_x: b.min.x, min_z: b.min.z, max_x: b.max.x, max_z: b.max.z };
            region.distance_to(&r) <= layout.reach()
        })
    })
}
