//! One zone: the objects it owns, the ghosts it borrows, and its tick.
//!
//! A tick at `t`, for zone `Z` (see `docs/zones.md` for why each step keeps one
//! process's bits):
//! 1. *Send.* Every object `Z` stepped last (its *advanced* set) goes to each neighbour
//!    that sees it ([`ZoneLayout::seers`]), marked *yours* for the neighbour whose region
//!    now holds its centre: a ghost and a hand-off are one record.
//! 2. *Gather.* `Z` waits for the border states of tick `t` from each neighbour (not a
//!    global barrier), authenticating and ordering them in its inbox.
//! 3. *Step.* `Z` brings its world up to date: the world it keeps from tick to tick
//!    ([`ResidentWorld`]) holds what it owns and the ghosts it sees, sorted by entity id;
//!    the neighbours' records overwrite its ghosts, hand-offs become owned, objects it no
//!    longer sees go, new ones are inserted, all in one pass that keeps ids ascending.
//!    It applies this tick's actions to the objects it owns and steps the world with any
//!    backend. Because a step sums each object's responses in the order of its partners'
//!    slots, and slots follow entity ids in both the zone's world and a scenario's world,
//!    an owned object gets the same bits as in one process — provided every partner is
//!    there, which `reach` guarantees.
//! 4. *Keep.* The owned objects' new states are the world's; ghosts' results are
//!    overwritten at the next exchange (their owners computed them with all their
//!    partners).

use std::collections::BTreeMap;
use std::ops::ControlFlow;
use std::sync::Arc;
use std::time::{Duration, Instant};

use myriad_core::{ObjectState, ScriptedAction, World};
use myriad_physics::{Backend, Stage, TickConstants};

use crate::error::ZoneError;
use crate::fabric::Fabric;
use crate::intents::IntentBook;
use crate::layout::{ZoneId, ZoneLayout};
use crate::rebalance::live::CutBook;
use crate::replay::IntentLog;
use crate::resident::ResidentWorld;
use crate::stats::ZoneStats;
use crate::views::Subscribers;
use crate::wire::{
    ALL, Border, BorderRecord, ClusterKey, GroundWorld, HEADER_LEN, Message, RECORD_LEN, TAG_LEN, decode,
    encode_border, encode_states,
};

mod cuts;

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
    /// Whether the zone serves gateways: after every step it sends each subscribed
    /// gateway its view ([`crate::views`]) and, unless [`Zone::set_mirror`] turned it
    /// off, publishes its owned objects' states for every gateway (the mirror,
    /// [`Fabric::publish_states`]). Players' intents are taken either way.
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

/// One zone of a world split over several (see the module documentation).
pub struct Zone {
    cfg: ZoneConfig,
    layout: Arc<ZoneLayout>,
    /// The zone's world, kept from tick to tick, and which objects it owns.
    resident: ResidentWorld,
    inbox: BTreeMap<(u64, ZoneId), Parts>,
    backend: Box<dyn Backend>,
    fabric: Box<dyn Fabric>,
    stats: ZoneStats,
    /// Gateways' joins, actions and leaves for players' objects.
    intents: IntentBook,
    /// The intents taken since the last checkpoint, when the zone logs them
    /// ([`Zone::checkpoint_log`]).
    log: Option<IntentLog>,
    /// The supervisor's cut move held for a coming tick ([`crate::rebalance::live`]).
    cuts: CutBook,
    /// The layout of the last step (or the one the zone started with): the cuts its
    /// objects were stepped to this tick with, which a checkpoint of this tick records.
    stepped_with: Arc<ZoneLayout>,
    /// The gateways' subscriptions (states by interest).
    subscribers: Subscribers,
    /// Whether a live zone also publishes the whole mirror.
    mirror: bool,
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
        owned: Vec<ObjectState>,
        backend: Box<dyn Backend>,
        fabric: Box<dyn Fabric>,
    ) -> Result<Zone, ZoneError> {
        if cfg.id.0 as usize >= layout.len() {
            return Err(ZoneError::Layout(format!("zone {} of a layout of {}", cfg.id.0, layout.len())));
        }
        let resident = ResidentWorld::new(world, &layout, cfg.id, owned)?;
        let stats = ZoneStats { owned: resident.owned_count(), tick: world.tick, ..ZoneStats::default() };
        Ok(Zone {
            stepped_with: layout.clone(),
            layout,
            resident,
            inbox: BTreeMap::new(),
            backend,
            fabric,
            stats,
            intents: IntentBook::new(world.tick),
            log: None,
            cuts: CutBook::default(),
            subscribers: Subscribers::default(),
            mirror: cfg.live,
            cfg,
        })
    }

    /// Whether a live zone publishes the whole mirror for every gateway besides the
    /// subscribed gateways' views (on by default for a live zone; `myriad cluster
    /// --gateway-states interest` turns it off).
    pub fn set_mirror(&mut self, on: bool) {
        self.mirror = on && self.cfg.live;
    }

    /// This zone's id.
    pub fn id(&self) -> ZoneId {
        self.cfg.id
    }

    /// The tick the next step starts.
    pub fn tick(&self) -> u64 {
        self.resident.world().tick
    }

    /// The states of the objects this zone stepped last as their owner, by id: after the
    /// last tick the zones' advanced sets partition the world.
    pub fn advanced(&self) -> Vec<ObjectState> {
        self.resident.owned_states().collect()
    }

    /// Takes the intent book a replay starts with (the live zone's at that tick).
    pub fn restore_book(&mut self, book: IntentBook) {
        self.intents = book;
    }

    /// Cuts the intent log at a checkpoint of the current tick: returns the segment of
    /// the ticks since the last cut (signed, of epoch `epoch`, with its first tick) and
    /// starts the next one here. The first call only starts a log; a second call at the
    /// same tick keeps the log (the tick was tried again).
    pub fn checkpoint_log(&mut self, epoch: u64) -> Option<(u64, Vec<u8>)> {
        let t = self.tick();
        match &self.log {
            Some(log) if log.from() == t => None,
            Some(log) => {
                let sealed = (log.from(), log.seal(&self.cfg.key, self.cfg.id, epoch, t));
                self.log = Some(IntentLog::start(t, &self.intents));
                Some(sealed)
            }
            None => {
                self.log = Some(IntentLog::start(t, &self.intents));
                None
            }
        }
    }

    /// Offers one intents message (a replay's): whether it was taken. Anything else, or
    /// intents the book refuses, is counted as [`Zone::offer`] counts it.
    pub fn offer_intents(&mut self, bytes: &[u8]) -> bool {
        let t = self.tick();
        match decode(&self.cfg.key, bytes) {
            Ok(Message::Intents(i)) => self.take_intents(i, bytes, t),
            Ok(_) => {
                self.reject("kind", t);
                false
            }
            Err(e) => {
                self.reject(e.label(), t);
                false
            }
        }
    }

    /// Files one authenticated intents message in the book (and the log), or counts why
    /// not: whether it was taken.
    fn take_intents(&mut self, i: crate::wire::Intents, bytes: &[u8], t: u64) -> bool {
        match self.intents.offer(i, t) {
            Ok(()) => {
                self.stats.messages.1 += 1;
                if let Some(log) = &mut self.log {
                    log.record(t, bytes);
                }
                true
            }
            Err(refused) => {
                self.reject(refused.label(), t);
                false
            }
        }
    }

    /// Follows a new layout (cuts moved) from the next tick on. Every zone of the world
    /// must switch at the same tick, before stepping it: the objects between an old cut
    /// and its new place are then handed over at that tick's exchange like any object
    /// that crossed a boundary. The layout must have this zone's shape.
    pub fn set_layout(&mut self, layout: Arc<ZoneLayout>) -> Result<(), ZoneError> {
        if layout.shape() != self.layout.shape() {
            return Err(ZoneError::Layout(format!(
                "a {:?} layout for a zone of a {:?} one",
                layout.shape(),
                self.layout.shape()
            )));
        }
        self.resident.set_layout(&layout, self.cfg.id);
        self.layout = layout;
        self.stats.cut_moves += 1;
        Ok(())
    }

    /// The counters.
    pub fn stats(&self) -> &ZoneStats {
        &self.stats
    }

    /// Static primitives this zone holds.
    pub fn static_prims(&self) -> usize {
        self.resident.world().statics.prim_count()
    }

    /// One tick: exchange border states with the neighbours, then step. `actions` are
    /// the actions of this tick for the whole world; those of objects this zone owns are
    /// applied ([`TickEnd::Stepped`] says how many), unless the supervisor interrupts
    /// the tick.
    pub fn step(&mut self, actions: &[ScriptedAction], k: &TickConstants) -> Result<TickEnd, ZoneError> {
        let t = self.tick();
        // A cut move held for this tick: every zone follows it before sending this
        // tick's borders, so the objects it moves are handed over at this exchange.
        if let Some(held) = self.cuts.due(t) {
            self.set_layout(held.layout)?;
            if let Some(log) = &mut self.log {
                log.record(t, &held.bytes);
            }
            tracing::info!(zone = self.cfg.id.0, tick = t, "cut move applied");
        }
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
        let mut received = received;
        self.resident.apply(&self.layout, self.cfg.id, &mut received, &mut self.intents, &mut self.stats)?;
        let applied = self.resident.set_actions(actions, &self.intents);
        let physics = Instant::now();
        let report = self.backend.step(&mut self.resident.world, k)?;
        self.stepped_with = self.layout.clone();
        self.stats.physics += physics.elapsed();
        self.stats.copies += Duration::from_secs_f64(report.stage_ms[Stage::Upload as usize].max(0.0) / 1e3);
        self.stats.ticks += 1;
        self.stats.owned = self.resident.owned_count();
        self.stats.tick = self.tick();
        self.stats.step += start.elapsed();
        if self.cfg.live {
            let publish = Instant::now();
            if self.mirror {
                self.publish_states()?;
            }
            self.publish_views()?;
            self.stats.publish += publish.elapsed();
        }
        self.intents.expire(self.tick());
        self.stats.bytes = self.fabric.bytes();
        Ok(TickEnd::Stepped(applied))
    }

    /// The advanced set, at the tick just reached, to every gateway.
    fn publish_states(&mut self) -> Result<(), ZoneError> {
        let owned = self.advanced();
        for (part, parts, chunk) in split(&owned, self.records_per_part())? {
            let m = Border {
                run: self.cfg.run,
                tick: self.tick(),
                from: self.cfg.id,
                to: ALL,
                part,
                parts,
                objects: chunk.iter().copied().map(BorderRecord::seen).collect(),
            };
            let bytes = encode_states(&self.cfg.key, &m)?;
            self.stats.states_bytes += bytes.len() as u64;
            self.fabric.publish_states(bytes)?;
            self.stats.messages.0 += 1;
        }
        Ok(())
    }

    /// Each subscribed gateway's view, at the tick just reached.
    fn publish_views(&mut self) -> Result<(), ZoneError> {
        let at = (self.cfg.run, self.tick(), self.cfg.id);
        let max = self.fabric.max_message();
        let fabric = &mut self.fabric;
        let world = self.resident.world();
        let ground = GroundWorld { terrain: &world.terrain, bounds: &world.bounds };
        let owned = self.resident.owned_states();
        let sent = self.subscribers.publish(&self.cfg.key, at, owned, ground, max, |g, b| fabric.send_view(g, b))?;
        for (g, s) in sent {
            let v = self.stats.views.entry(g).or_default();
            v.0 += s.bytes;
            v.1 += s.objects;
            self.stats.messages.0 += s.messages;
        }
        self.stats.subscribers = self.subscribers.len();
        Ok(())
    }

    fn records_per_part(&self) -> usize {
        ((self.fabric.max_message() - HEADER_LEN - TAG_LEN) / RECORD_LEN).max(1)
    }

    /// Step 1: the advanced set to every neighbour that sees it (only objects near the
    /// zone's edges can be seen by another).
    fn send_borders(&mut self, t: u64) -> Result<(), ZoneError> {
        let me = self.cfg.id;
        let neighbours = self.layout.neighbours(me);
        let mut out: Vec<Vec<BorderRecord>> = vec![Vec::new(); neighbours.len()];
        for o in self.resident.near_edges(&self.layout, me, &mut self.stats) {
            let owner = self.layout.zone_at(o.pos);
            for z in self.layout.seers(o.pos).filter(|&z| z != me) {
                let i =
                    neighbours.iter().position(|&n| n == z).ok_or(ZoneError::TooFar { id: o.id, from: me, to: z })?;
                out[i].push(BorderRecord { state: o, yours: z == owner });
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
    /// supervisor's halt and start are handed back: they interrupt the tick. Intents go
    /// to the intent book, the supervisor's cut moves to the cut book.
    pub fn offer(&mut self, bytes: &[u8]) -> Option<Message> {
        let t = self.tick();
        let m = match decode(&self.cfg.key, bytes) {
            Ok(Message::Border(m)) => m,
            Ok(control @ (Message::Halt { .. } | Message::Start { .. })) => return Some(control),
            Ok(Message::Intents(i)) => {
                self.take_intents(i, bytes, t);
                return None;
            }
            Ok(Message::CutMove { run, cut }) => {
                self.take_cut_move(run, cut, bytes, t);
                return None;
            }
            Ok(Message::Subscription(s)) => {
                let bounds = self.resident.world().bounds;
                return match self.subscribers.offer(s, self.cfg.run, t, &bounds) {
                    Ok(()) => {
                        self.stats.messages.1 += 1;
                        None
                    }
                    Err(e) => self.reject(e.label(), t),
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
