//! A gateway's world: the zones step it, the gateway mirrors it.
//!
//! A gateway is the ordinary server (TLS login, UDP sessions, interest management,
//! sealing, persistence) whose physics backend is [`ZonesBackend`], of kind
//! [`BackendKind::Zones`]: its step is remote. It sends the zones what the gateway's
//! players asked since the last tick and takes the newest world the zones finished. So every player's session stays at its gateway while its object
//! moves from zone to zone; a player near a boundary sees the objects of both sides
//! because the mirror holds them all; and a rollback of the zones changes the mirror,
//! not the sessions.
//!
//! Each step:
//! 1. **Intents.** The gateway's own players are the objects in its id range
//!    ([`player_ids`]; a restarted gateway starts at another place in it). A new one is a *join* (its whole state), a changed action an
//!    *action*, a missing one a *leave*; each kind goes to every zone in one signed
//!    message ([`crate::intents`] says how zones keep them). Every `refresh` ticks, and at
//!    once after a rollback, the gateway sends every player's action again, and the join
//!    of every player the zones have not shown for a while: intents are lost when a zone
//!    restarts.
//! 2. **Subscription** (states by interest, [`GatewayConfig::interest`]): the cells its
//!    players can see ([`crate::subscription`]), with the last zones' tick it took,
//!    to every zone ([`crate::wire::Subscription`]), every step.
//! 3. **World.** After every step each zone sends the gateway its view: the objects in
//!    its cells that changed since a base tick (the last view sent, or the tick it
//!    confirmed), and those gone ([`crate::wire::Message::View`], [`crate::views`]); or,
//!    in mirror mode, all its owned objects ([`crate::wire::Message::States`]). The
//!    backend takes, in order, the complete ticks (every zone's message complete) that
//!    apply on what it holds, skipping to the newest where views allow (waiting up to
//!    `wait` when none is newer than the last), applies them to what it holds of each
//!    zone, and replaces the world's objects with the result. The gateway's players that the
//!    zones have not adopted yet stay as they are; players that left are left out; the
//!    newest action a player asked for is kept on its object.
//!
//! The world's tick is the gateway's own: it advances by one per step (the backend
//! contract), whatever tick the zones are at, and never goes back when they roll back.

use std::collections::{BTreeMap, HashMap};
use std::time::{Duration, Instant};

use myriad_core::{Aabb, EntityId, ObjectState, World};
use myriad_physics::{AoiResults, Backend, BackendKind, PhysicsError, StepReport, TickConstants, ZoneCuts};

use crate::error::ZoneError;
use crate::fabric::GatewayLink;
use crate::gateway_cuts::CutsBook;
use crate::gateway_view::{Applicable, Part, ZoneViews};
use crate::subscription::{Interest, InterestConfig};
use crate::wire::{
    ClusterKey, FingerprintCache, GroundWorld, IntentKind, Intents, MAX_RESYNCS, Message, Subscription, decode,
    encode_intents, encode_subscription,
};

/// Gateways a cluster can have (each owns a range of player ids).
pub const MAX_GATEWAYS: u16 = 64;

/// Records in one intents message (well under NATS's default 1 MiB).
const INTENTS_PER_MESSAGE: usize = 16_384;

/// Ticks of zones' states kept while incomplete.
const PENDING_TICKS: usize = 16;

/// Gateway steps after asking the zones for views relative to its confirmation before
/// it asks again (a round trip is a few steps).
const RESYNC_STEPS: u64 = 8;

/// The entity ids gateway `g` gives its players: its own range, so two gateways never
/// spawn the same id, and far above any generated world's objects.
pub fn player_ids(gateway: u16) -> std::ops::Range<u32> {
    let start = (1u32 << 30) + u32::from(gateway) * (1 << 24);
    start..start + (1 << 24)
}

/// The gateway whose id range holds `id`, if any.
pub fn gateway_of(id: EntityId) -> Option<u16> {
    let first = player_ids(0).start;
    let g = id.0.checked_sub(first)? >> 24;
    u16::try_from(g).ok().filter(|g| *g < MAX_GATEWAYS)
}

/// Ids per slot of a gateway's range.
const SLOT: u32 = 1 << 16;

/// The ids gateway `gateway` gives its players in its incarnation `incarnation`: one of
/// the 256 slots of its range, chosen by the incarnation, so that a restarted gateway's
/// players never take the ids of its earlier players, and a zone can tell the two apart
/// (it removes the earlier ones; [`crate::intents`]). Within a slot ids wrap around.
pub fn incarnation_ids(gateway: u16, incarnation: u64) -> std::ops::Range<u32> {
    let start = player_ids(gateway).start + ((incarnation / 1000 % 256) as u32) * SLOT;
    start..start + SLOT
}

/// How a gateway follows its cluster.
#[derive(Clone, Debug)]
pub struct GatewayConfig {
    /// This gateway (below [`MAX_GATEWAYS`]).
    pub gateway: u16,
    /// The cluster's key.
    pub key: ClusterKey,
    /// Zones in the cluster.
    pub zones: usize,
    /// Longest wait in a step for a newer world (then the step keeps the last one).
    pub wait: Duration,
    /// Ticks between re-sending every player's action (and missing joins).
    pub refresh: u64,
    /// States by interest: how the gateway subscribes to what its players see. `None`:
    /// the mirror (every zone's every object, every tick).
    pub interest: Option<InterestConfig>,
}

/// What a gateway's backend counts.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GatewayStats {
    /// Worlds taken from the zones.
    pub mirrors: u64,
    /// Steps that found no newer world in time (the world stood still for a tick).
    pub stale_steps: u64,
    /// Zone ticks skipped because a newer one was complete (or dropped incomplete).
    pub skipped: u64,
    /// Times the gateway asked the zones for views relative to its confirmation, a view
    /// of a chain having been lost (`crate::views`, "Bases").
    pub resyncs: u64,
    /// Objects two zones both claimed in one tick (kept once).
    pub duplicates: u64,
    /// Rollbacks seen (a newer run of the zones).
    pub rollbacks: u64,
    /// Steps whose fabric work failed (sending intents or taking the zones' world).
    pub errors: u64,
    /// Times one of this gateway's players' objects changed zone (its session stayed).
    pub player_handoffs: u64,
    /// Intent records sent, by kind (join, action, leave).
    pub intents: [u64; 3],
    /// States messages refused, by reason.
    pub rejected: BTreeMap<&'static str, u64>,
    /// The zones' tick of the mirror.
    pub zone_tick: u64,
    /// Bytes of the zones' states messages taken (what this gateway receives from the
    /// zones, beside its intents out).
    pub zone_bytes_in: u64,
    /// Object records in those messages (whole, or moves of objects held).
    pub zone_objects_in: u64,
    /// Ids of objects the zones' views said were gone (states by interest).
    pub zone_gone_in: u64,
    /// Of the object records in, the nudges (positions as changes from a base tick).
    pub zone_nudges_in: u64,
    /// Subscriptions sent (one a step, states by interest).
    pub subscriptions: u64,
    /// Their bytes.
    pub subscription_bytes_out: u64,
    /// Cells of the subscription after the last step.
    pub subscription_cells: usize,
    /// New cut moves and starts heard from the supervisor (for the map of the cuts:
    /// `gateway_cuts.rs`; repeats are not counted, refusals are in `rejected`).
    pub cut_news: u64,
    /// Objects of the zones' world as last taken: what the gateway holds (by interest,
    /// only those its players can see), the larger part of its memory.
    pub held_objects: usize,
}

impl GatewayStats {
    /// Publishes the counters through the `metrics` facade.
    pub fn export(&self) {
        metrics::counter!("myriad_gateway_mirrors_total").absolute(self.mirrors);
        metrics::counter!("myriad_gateway_stale_steps_total").absolute(self.stale_steps);
        metrics::counter!("myriad_gateway_skipped_ticks_total").absolute(self.skipped);
        metrics::counter!("myriad_gateway_resyncs_total").absolute(self.resyncs);
        metrics::counter!("myriad_gateway_duplicates_total").absolute(self.duplicates);
        metrics::counter!("myriad_gateway_rollbacks_total").absolute(self.rollbacks);
        metrics::counter!("myriad_gateway_errors_total").absolute(self.errors);
        metrics::counter!("myriad_gateway_player_handoffs_total").absolute(self.player_handoffs);
        for (kind, n) in ["join", "action", "leave"].into_iter().zip(self.intents) {
            metrics::counter!("myriad_gateway_intents_total", "kind" => kind).absolute(n);
        }
        for (reason, n) in &self.rejected {
            metrics::counter!("myriad_gateway_rejected_total", "reason" => *reason).absolute(*n);
        }
        metrics::gauge!("myriad_gateway_zone_tick").set(self.zone_tick as f64);
        metrics::counter!("myriad_gateway_zone_bytes_in_total").absolute(self.zone_bytes_in);
        metrics::counter!("myriad_gateway_zone_objects_in_total").absolute(self.zone_objects_in);
        metrics::counter!("myriad_gateway_zone_gone_in_total").absolute(self.zone_gone_in);
        metrics::counter!("myriad_gateway_zone_nudges_in_total").absolute(self.zone_nudges_in);
        metrics::counter!("myriad_gateway_subscriptions_total").absolute(self.subscriptions);
        metrics::counter!("myriad_gateway_subscription_bytes_out_total").absolute(self.subscription_bytes_out);
        metrics::gauge!("myriad_gateway_subscription_cells").set(self.subscription_cells as f64);
        metrics::counter!("myriad_gateway_cut_news_total").absolute(self.cut_news);
        metrics::gauge!("myriad_gateway_held_objects").set(self.held_objects as f64);
    }
}

/// The zones' world at one of their ticks: every object with the zone that owns it,
/// sorted by id.
type ZonesWorld = (u64, Vec<(ObjectState, u16)>);

/// One of the gateway's players, as the backend tracks it.
#[derive(Clone, Copy, Debug)]
struct Mine {
    /// Its newest state in the world.
    state: ObjectState,
    /// The gateway tick its join was last sent.
    joined_at: u64,
    /// Whether the zones' world has shown it since then.
    seen: bool,
    /// The zone that owned it in the last world shown.
    zone: Option<u16>,
}

/// The zones' states (or views) of one tick, as they arrive.
#[derive(Default)]
struct TickParts {
    /// Per zone: (parts announced, parts received).
    zones: HashMap<u16, (u16, BTreeMap<u16, Part>)>,
}

impl TickParts {
    fn complete(&self, zones: usize) -> bool {
        self.zones.len() == zones && self.zones.values().all(|(n, got)| got.len() == *n as usize)
    }
}

/// The physics backend of a gateway (see the module docs), of kind
/// [`BackendKind::Zones`]: its step is remote. It computes no physics: it sends the
/// players' intents to the zones and mirrors the world they stepped, over the fabric
/// (NATS I/O inside [`Backend::step`], bounded by [`GatewayConfig::wait`]). Its AOI queries
/// run on the mirror, on the CPU.
pub struct ZonesBackend {
    cfg: GatewayConfig,
    link: Box<dyn GatewayLink>,
    incarnation: u64,
    aoi: Box<dyn Backend>,
    /// The ids this incarnation gives its players.
    ids: std::ops::Range<u32>,
    /// The zones' run being followed, and the last tick taken from it.
    run: u64,
    taken: Option<u64>,
    pending: BTreeMap<u64, TickParts>,
    mine: BTreeMap<EntityId, Mine>,
    /// Players that left (their last state), until the zones drop them.
    gone: BTreeMap<EntityId, ObjectState>,
    /// The action each player's object held after the last step (what the zones were
    /// last asked for).
    written: HashMap<EntityId, u8>,
    refresh_now: bool,
    /// The gateway tick of the last intents sent.
    last_tick: u64,
    /// Whether the last step's fabric work failed (for logging changes only).
    failing: bool,
    stats: GatewayStats,
    /// The subscription, with states by interest.
    interest: Option<Interest>,
    /// What the gateway holds of each zone's view.
    views: ZoneViews,
    /// Times it found a chain of views broken (its subscriptions carry it).
    resyncs: u32,
    /// The gateway tick it last asked for a resync, until a tick is taken.
    resync_asked: Option<u64>,
    /// The AOI boxes the server queried last (the subscription covers them too).
    boxes: Vec<Aabb>,
    /// The zones' cuts as the supervisor announced them (made at the first step, from
    /// the world's bounds; `None` before it, or when the bounds make no layout).
    cuts: Option<CutsBook>,
    /// The ground fingerprint of its world, which its subscriptions name.
    fingerprint: FingerprintCache,
    /// Whether the first step has made `cuts`.
    cuts_made: bool,
}

impl ZonesBackend {
    /// A gateway following the zones through `link`, whose incarnation is the time now.
    pub fn new(cfg: GatewayConfig, link: Box<dyn GatewayLink>) -> Result<ZonesBackend, ZoneError> {
        // Milliseconds since the epoch: a restarted gateway's intents are newer.
        let incarnation = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_millis() as u64)
            .unwrap_or(1);
        ZonesBackend::with_incarnation(cfg, link, incarnation)
    }

    /// [`ZonesBackend::new`] with a given incarnation (its players' ids follow from it:
    /// [`incarnation_ids`]), for runs that must be the same twice. It must grow from one
    /// start of a gateway to the next.
    pub fn with_incarnation(
        cfg: GatewayConfig,
        link: Box<dyn GatewayLink>,
        incarnation: u64,
    ) -> Result<ZonesBackend, ZoneError> {
        if cfg.gateway >= MAX_GATEWAYS {
            return Err(ZoneError::Layout(format!("gateway {} of at most {MAX_GATEWAYS}", cfg.gateway)));
        }
        if cfg.zones == 0 {
            return Err(ZoneError::Layout("a gateway needs at least one zone".into()));
        }
        let aoi = myriad_physics::create_cpu_backend(BackendKind::Cpu)?;
        let interest = cfg.interest.map(Interest::new);
        Ok(ZonesBackend {
            ids: incarnation_ids(cfg.gateway, incarnation),
            cfg,
            link,
            incarnation,
            aoi,
            run: 0,
            taken: None,
            pending: BTreeMap::new(),
            mine: BTreeMap::new(),
            gone: BTreeMap::new(),
            written: HashMap::new(),
            refresh_now: false,
            last_tick: 0,
            failing: false,
            stats: GatewayStats::default(),
            interest,
            views: ZoneViews::default(),
            resyncs: 0,
            resync_asked: None,
            boxes: Vec::new(),
            cuts: None,
            cuts_made: false,
            fingerprint: FingerprintCache::default(),
        })
    }

    /// Makes `world` ready to mirror the zones: its own objects are dropped (the zones'
    /// replace them at the first step) and spawns continue in this gateway's id range.
    pub fn prepare(&self, world: &mut World) {
        world.dynamics.clear();
        world.dynamics.set_next_id(EntityId(self.ids.start));
    }

    /// The counters.
    pub fn stats(&self) -> &GatewayStats {
        &self.stats
    }

    fn is_mine(&self, id: EntityId) -> bool {
        self.ids.contains(&id.0)
    }

    /// Step 1: what the gateway's players asked since the last step.
    fn send_intents(&mut self, world: &World) -> Result<(), ZoneError> {
        let t = world.tick;
        self.last_tick = t;
        let d = &world.dynamics;
        let mut joins = Vec::new();
        let mut actions = Vec::new();
        let mut present = Vec::new();
        for s in 0..d.len() {
            let id = d.ids()[s];
            if !self.is_mine(id) {
                continue;
            }
            let state = d.state_of(s);
            present.push(id);
            match self.mine.get_mut(&id) {
                None => {
                    self.mine.insert(id, Mine { state, joined_at: t, seen: false, zone: None });
                    joins.push(state);
                }
                Some(m) => {
                    m.state = state;
                    if self.written.get(&id) != Some(&state.action) {
                        actions.push(state);
                    }
                }
            }
        }
        present.sort_unstable();
        let left: Vec<EntityId> = self.mine.keys().filter(|id| present.binary_search(id).is_err()).copied().collect();
        let mut leaves = Vec::new();
        for id in left {
            let m = self.mine.remove(&id).expect("listed");
            self.written.remove(&id);
            self.gone.insert(id, m.state);
            leaves.push(m.state);
        }
        let due = self.cfg.refresh > 0 && t.is_multiple_of(self.cfg.refresh);
        if self.refresh_now || due {
            self.refresh_now = false;
            actions = self.mine.values().map(|m| m.state).collect();
            for m in self.mine.values_mut() {
                if !m.seen
                    && t.saturating_sub(m.joined_at) >= self.cfg.refresh
                    && !joins.iter().any(|j| j.id == m.state.id)
                {
                    m.joined_at = t;
                    joins.push(m.state);
                }
            }
            leaves.extend(self.gone.values().copied());
        }
        for (kind, objects) in [(IntentKind::Join, joins), (IntentKind::Action, actions), (IntentKind::Leave, leaves)] {
            self.stats.intents[kind as usize] += objects.len() as u64;
            // Zones take a gateway that has not been heard of for a while for dead (and
            // remove its players' objects): with no action to send, an empty message
            // says it is alive.
            let keep_alive = due && kind == IntentKind::Action;
            self.send_kind(t, kind, &objects, keep_alive)?;
        }
        Ok(())
    }

    /// Sends `objects` as intents of `kind` at gateway tick `tick`, in messages of at
    /// most [`INTENTS_PER_MESSAGE`] records; with none, one empty message if
    /// `keep_alive`, else nothing.
    fn send_kind(
        &mut self,
        tick: u64,
        kind: IntentKind,
        objects: &[ObjectState],
        keep_alive: bool,
    ) -> Result<(), ZoneError> {
        let chunks: Vec<&[ObjectState]> =
            if objects.is_empty() && keep_alive { vec![&[]] } else { objects.chunks(INTENTS_PER_MESSAGE).collect() };
        for chunk in chunks {
            let m = Intents {
                incarnation: self.incarnation,
                tick,
                gateway: self.cfg.gateway,
                kind,
                objects: chunk.to_vec(),
            };
            self.link.send_intents(encode_intents(&self.cfg.key, &m)?)?;
        }
        Ok(())
    }

    /// Step 2 (states by interest): the subscription for the world as it is, with the
    /// confirmation of the last zones' tick taken, to every zone.
    fn send_subscription(&mut self, world: &World) -> Result<(), ZoneError> {
        let Some(interest) = &mut self.interest else { return Ok(()) };
        let players = self.mine.values().map(|m| m.state.pos);
        interest.update(&world.bounds, world.tick + 1, players, &self.boxes)?;
        let grid = *interest.grid().expect("set by the update");
        let (cells, version) = interest.cells();
        let (cols, rows) = grid.shape();
        let s = Subscription {
            incarnation: self.incarnation,
            gateway: self.cfg.gateway,
            version,
            confirmed: self.taken.map(|t| (self.run, t)),
            resyncs: self.resyncs,
            cell: grid.cell(),
            cols,
            rows,
            cells: cells.to_bytes(cols, rows),
            ground: self.fingerprint.of(GroundWorld { terrain: &world.terrain, bounds: &world.bounds }),
        };
        self.stats.subscription_cells = cells.count();
        let bytes = encode_subscription(&self.cfg.key, &s)?;
        self.stats.subscriptions += 1;
        self.stats.subscription_bytes_out += bytes.len() as u64;
        self.link.send_subscription(bytes)
    }

    fn reject(&mut self, reason: &'static str) {
        *self.stats.rejected.entry(reason).or_default() += 1;
    }

    /// Counts what the book of cuts made of a start or cut move (`None`: no book yet,
    /// before the first step: nothing is heard then).
    fn cut_news(&mut self, taken: Option<Result<bool, &'static str>>) {
        match taken {
            Some(Ok(true)) => self.stats.cut_news += 1,
            Some(Ok(false)) | None => {}
            Some(Err(reason)) => {
                tracing::warn!("the supervisor's cuts do not fit the cluster's layout (refused)");
                self.reject(reason);
            }
        }
    }

    /// Files one message of states (mirror) or of a view (by interest); returns nothing,
    /// counts what it refuses.
    fn offer(&mut self, bytes: &[u8]) {
        let (m, part) = match (decode(&self.cfg.key, bytes), self.interest.is_some()) {
            (Ok(Message::States(m)), false) => {
                let objects = m.objects.iter().map(|r| r.state).collect();
                let part = Part { base: None, objects, ..Part::default() };
                ((m.run, m.tick, m.from, m.part, m.parts), part)
            }
            (Ok(Message::View(v)), true) => {
                if v.gateway != self.cfg.gateway {
                    return self.reject("misrouted");
                }
                let part = Part {
                    base: v.base,
                    objects: v.objects,
                    moves: v.moves,
                    nudges: v.nudges,
                    gone: v.gone,
                    acts: v.acts,
                };
                ((v.run, v.tick, v.zone, v.part, v.parts), part)
            }
            // The supervisor's word to the zones, heard for the map of the cuts.
            (Ok(Message::Start { run, tick, cuts }), _) => {
                let taken = self.cuts.as_mut().map(|b| b.start(run, tick, cuts).map(|()| true));
                return self.cut_news(taken);
            }
            (Ok(Message::CutMove { run, cut }), _) => {
                let taken = self.cuts.as_mut().map(|b| b.cut_move(run, cut));
                return self.cut_news(taken);
            }
            (Ok(Message::Halt { .. }), _) => return,
            // The mirror to a gateway that subscribes, or a view to one that does not.
            (Ok(Message::States(_) | Message::View(_)), _) => return self.reject("mode"),
            (Ok(_), _) => return self.reject("kind"),
            (Err(e), _) => return self.reject(e.label()),
        };
        let (run, tick, from, part_no, parts) = m;
        if from.0 as usize >= self.cfg.zones || from == crate::wire::ALL {
            return self.reject("stranger");
        }
        if run < self.run {
            return self.reject("run");
        }
        if run > self.run {
            // The zones rolled back (or this gateway joined a running cluster): follow
            // the new run from whatever tick it starts at, from whole views.
            if self.taken.is_some() {
                self.stats.rollbacks += 1;
                self.refresh_now = true;
                for m in self.mine.values_mut() {
                    m.seen = false;
                    m.joined_at = 0;
                }
            }
            self.run = run;
            self.taken = None;
            self.pending.clear();
            self.views.clear();
        }
        if self.taken.is_some_and(|t| tick <= t) {
            return self.reject("stale");
        }
        let entry = self.pending.entry(tick).or_default();
        let (announced, got) = entry.zones.entry(from.0).or_insert((parts, BTreeMap::new()));
        if *announced != parts || got.values().next().is_some_and(|p| p.base != part.base) {
            return self.reject("parts");
        }
        if got.contains_key(&part_no) {
            return self.reject("replayed");
        }
        self.stats.zone_bytes_in += bytes.len() as u64;
        self.stats.zone_objects_in += (part.objects.len() + part.moves.len() + part.nudges.len()) as u64;
        self.stats.zone_gone_in += part.gone.len() as u64;
        self.stats.zone_nudges_in += part.nudges.len() as u64;
        got.insert(part_no, part);
        while self.pending.len() > PENDING_TICKS {
            self.pending.pop_first();
            self.stats.skipped += 1;
        }
    }

    /// Takes what it can of the complete ticks, in order: each time the newest complete
    /// tick whose parts all apply on what the gateway holds (views relative to its
    /// confirmation let it skip to the newest; a chain of views takes every tick, each
    /// relative to the one before), until none does. Returns the world of the last one
    /// taken: its objects with the zone that sent each, sorted by id. A complete tick that
    /// does not apply never will (each zone's messages come in order, so an earlier tick
    /// still incomplete lost one of them): such ticks are dropped and counted, and the
    /// zones asked for views relative to the confirmation ([`ZonesBackend::ask_resync`]).
    fn take_complete(&mut self, ground: GroundWorld<'_>) -> Option<ZonesWorld> {
        let mut took = None;
        loop {
            let complete: Vec<u64> =
                self.pending.iter().filter(|(_, p)| p.complete(self.cfg.zones)).map(|(t, _)| *t).collect();
            let Some(&newest) = complete.last() else { break };
            let verdicts = |t: &u64| -> Vec<Applicable> {
                let parts = &self.pending[t].zones;
                parts.iter().map(|(z, (_, got))| self.views.applicable(*z, got.values(), self.taken)).collect()
            };
            let Some(tick) = complete.iter().rev().find(|t| verdicts(t).iter().all(|v| *v == Applicable::Yes)) else {
                let lost = verdicts(&newest).contains(&Applicable::Lost);
                let rest = self.pending.split_off(&(newest + 1));
                let dropped = std::mem::replace(&mut self.pending, rest);
                let dropped_complete = dropped.values().filter(|p| p.complete(self.cfg.zones)).count() as u64;
                self.stats.skipped += dropped.len() as u64 - dropped_complete;
                if lost {
                    // Nudges from positions this gateway no longer has: start again from
                    // whole views (the next subscription confirms nothing).
                    self.reject("nudge_base");
                    self.views.clear();
                    self.taken = None;
                } else {
                    // Changes since a tick this gateway does not hold: a view of a chain
                    // was lost (or a tick dropped before it was complete).
                    *self.stats.rejected.entry("base").or_default() += dropped_complete;
                }
                self.ask_resync();
                break;
            };
            let tick = *tick;
            let mut older = self.pending.split_off(&tick);
            std::mem::swap(&mut older, &mut self.pending);
            self.stats.skipped += older.len() as u64;
            let parts = self.pending.pop_first().expect("the complete tick").1;
            for (z, (_, got)) in parts.zones {
                let unknown = self.views.apply(z, got.into_values().collect(), ground);
                if unknown > 0 {
                    *self.stats.rejected.entry("move").or_default() += unknown;
                }
            }
            self.taken = Some(tick);
            self.views.remember(tick);
            self.resync_asked = None;
            took = Some(tick);
        }
        let tick = took?;
        let mut all = self.views.assemble();
        let before = all.len();
        all.dedup_by_key(|(o, _)| o.id);
        self.stats.duplicates += (before - all.len()) as u64;
        self.stats.held_objects = all.len();
        Some((tick, all))
    }

    /// Asks every zone, through the next subscriptions, for its next view relative to
    /// the confirmation (`resyncs` grows): once a break, and again if no tick was taken
    /// in [`RESYNC_STEPS`] steps (that view was lost too).
    fn ask_resync(&mut self) {
        let now = self.last_tick;
        if self.resync_asked.is_none_or(|at| now >= at + RESYNC_STEPS) {
            self.resyncs = (self.resyncs + 1) % MAX_RESYNCS;
            self.resync_asked = Some(now);
            self.stats.resyncs += 1;
        }
    }

    /// Step 2: the newest world of the zones, waiting up to `wait` for one newer than
    /// the last (ground nudges predicted on `world`'s ground, which the subscriptions
    /// name).
    fn next_world(&mut self, world: &World) -> Result<Option<ZonesWorld>, ZoneError> {
        let ground = GroundWorld { terrain: &world.terrain, bounds: &world.bounds };
        let deadline = Instant::now() + self.cfg.wait;
        let mut now = Instant::now();
        loop {
            // Everything that has arrived, then the newest complete tick.
            while let Some(bytes) = self.link.recv_states(now)? {
                self.offer(&bytes);
            }
            if let Some(found) = self.take_complete(ground) {
                return Ok(Some(found));
            }
            match self.link.recv_states(deadline)? {
                Some(bytes) => self.offer(&bytes),
                None => return Ok(None),
            }
            now = Instant::now();
        }
    }

    /// Replaces the world's objects with the zones' `objects`, keeping this gateway's
    /// players' own view (see the module docs).
    fn mirror(&mut self, world: &mut World, objects: Vec<(ObjectState, u16)>) -> Result<(), ZoneError> {
        let d = &world.dynamics;
        // The action each player asked for last: the world's, which the tick set.
        let asked: HashMap<EntityId, u8> =
            (0..d.len()).filter(|&s| self.is_mine(d.ids()[s])).map(|s| (d.ids()[s], d.actions()[s])).collect();
        let next = d.next_id();
        let mut owners = HashMap::new();
        let mut all: Vec<ObjectState> = Vec::with_capacity(objects.len() + self.mine.len());
        // Players that left and the zones still show: left out, and their leaves go
        // again at the next refresh; the others are forgotten.
        let mut still_shown = Vec::new();
        for (o, z) in objects {
            if self.gone.contains_key(&o.id) {
                still_shown.push(o.id);
                continue;
            }
            if self.is_mine(o.id) {
                owners.insert(o.id, z);
            }
            all.push(o);
        }
        self.gone.retain(|id, _| still_shown.contains(id));
        for (id, m) in self.mine.iter_mut() {
            if let Some(&z) = owners.get(id) {
                m.seen = true;
                if m.zone.is_some_and(|was| was != z) {
                    self.stats.player_handoffs += 1;
                }
                m.zone = Some(z);
            } else {
                // Not adopted yet (or lost in a rollback): the player keeps its own state,
                // and its join goes again at the next refresh.
                m.seen = false;
                all.push(m.state);
            }
        }
        all.sort_unstable_by_key(|o| o.id);
        for o in &mut all {
            if let Some(a) = asked.get(&o.id) {
                o.action = *a;
            }
        }
        let d = &mut world.dynamics;
        d.clear();
        d.insert_all(all.iter().copied())?;
        // Ids wrap within this incarnation's slot (a spawn onto an id still taken fails).
        d.set_next_id(if self.ids.contains(&next.0) { next } else { EntityId(self.ids.start) });
        self.written = asked;
        Ok(())
    }
}

impl Drop for ZonesBackend {
    /// A gateway that stops (its server shut down, its sessions closed) tells the zones
    /// its players left, so their objects go at once rather than when the zones time the
    /// gateway out. Best effort: a gateway that dies sends nothing, and the timeout
    /// covers it.
    fn drop(&mut self) {
        let leaves: Vec<ObjectState> = self.mine.values().map(|m| m.state).collect();
        if leaves.is_empty() {
            return;
        }
        let tick = self.last_tick.saturating_add(1);
        if let Err(e) = self.send_kind(tick, IntentKind::Leave, &leaves, false) {
            tracing::debug!(error = %e, "a stopping gateway's leaves were not all sent");
        }
        self.link.flush();
    }
}

impl Backend for ZonesBackend {
    /// [`BackendKind::Zones`]: the step is remote (the zones' own backends are theirs to
    /// report); only the AOI queries run here, on the CPU.
    fn kind(&self) -> BackendKind {
        BackendKind::Zones
    }

    fn description(&self) -> String {
        format!(
            "zones: gateway {} of a cluster of {} zones (the zones step the world over NATS; AOI on the cpu)",
            self.cfg.gateway, self.cfg.zones
        )
    }

    /// Remote: sends the players' intents to the zones and takes the zones' newest world,
    /// over the fabric (NATS between processes), waiting up to the configured `wait`; no
    /// physics runs here. The time goes in the `upload` stage (the other stages are the
    /// zones'). A fabric error is counted and logged when it starts and when it ends, and
    /// the step goes on (the world stands still for the tick): the sessions never see
    /// it, and the tick still advances by one.
    fn step(&mut self, world: &mut World, _k: &TickConstants) -> Result<StepReport, PhysicsError> {
        let start = Instant::now();
        if !self.cuts_made {
            self.cuts_made = true;
            // Only the operators' map needs it: a world whose bounds make no layout
            // (the zones would refuse it too) leaves the map without cuts.
            self.cuts = CutsBook::new(&world.bounds, self.cfg.zones)
                .inspect_err(|e| tracing::warn!(error = %e, "no layout of the zone cuts for this world"))
                .ok();
        }
        let sent = self.send_intents(world).and_then(|()| self.send_subscription(world));
        let taken = self.next_world(world).and_then(|next| match next {
            Some((tick, objects)) => {
                self.mirror(world, objects)?;
                self.stats.mirrors += 1;
                self.stats.zone_tick = tick;
                Ok(())
            }
            None => {
                self.stats.stale_steps += 1;
                Ok(())
            }
        });
        match sent.and(taken) {
            Ok(()) if self.failing => {
                self.failing = false;
                tracing::info!("the zones' fabric works again");
            }
            Ok(()) => {}
            Err(e) => {
                self.stats.errors += 1;
                if !self.failing {
                    self.failing = true;
                    tracing::warn!(error = %e, "the zones' fabric failed; the world stands still until it works");
                }
            }
        }
        world.tick += 1;
        self.stats.export();
        let mut report = StepReport::default();
        report.stage_ms[myriad_physics::Stage::Upload as usize] = start.elapsed().as_secs_f64() * 1e3;
        Ok(report)
    }

    /// The AOI query on the gateway's world, on the CPU; the boxes are kept for the next
    /// subscription.
    fn query_aoi(&mut self, world: &World, boxes: &[Aabb], out: &mut AoiResults) -> Result<(), PhysicsError> {
        if self.interest.is_some() {
            self.boxes.clear();
            self.boxes.extend_from_slice(boxes);
        }
        self.aoi.query_aoi(world, boxes, out)
    }

    /// The cuts of the zones' world this gateway took last, as the supervisor announced
    /// them (`gateway_cuts.rs`); `None` before the first step.
    fn zone_cuts(&self) -> Option<ZoneCuts> {
        Some(self.cuts.as_ref()?.in_force(self.run, self.taken))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use myriad_core::{ObjectKind, ScenarioSpec, Shape, Vec3};

    /// A fabric that is down.
    struct Down;

    impl GatewayLink for Down {
        fn send_intents(&mut self, _: Vec<u8>) -> Result<(), ZoneError> {
            Err(ZoneError::Fabric("down".into()))
        }
        fn send_subscription(&mut self, _: Vec<u8>) -> Result<(), ZoneError> {
            Err(ZoneError::Fabric("down".into()))
        }
        fn recv_states(&mut self, _: Instant) -> Result<Option<Vec<u8>>, ZoneError> {
            Err(ZoneError::Fabric("down".into()))
        }
    }

    #[test]
    fn a_fabric_that_is_down_stands_the_world_still_and_the_tick_goes_on() {
        let mut spec = ScenarioSpec::custom(3);
        (spec.dynamic, spec.users, spec.static_objects, spec.world_size, spec.terrain_samples) = (0, 0, 0, 32.0, 9);
        let mut world = spec.build().unwrap();
        let cfg = GatewayConfig {
            gateway: 1,
            key: ClusterKey::random(),
            zones: 2,
            wait: Duration::from_millis(1),
            refresh: 30,
            interest: None,
        };
        let mut b = ZonesBackend::new(cfg, Box::new(Down)).unwrap();
        b.prepare(&mut world);
        let id =
            world.dynamics.spawn(Shape::Sphere { radius: 0.5 }, Vec3::new(1.0, 5.0, 1.0), ObjectKind::User).unwrap();
        assert!(player_ids(1).contains(&id.0) && incarnation_ids(1, b.incarnation).contains(&id.0));
        assert_eq!(gateway_of(id), Some(1));
        for t in 1..=3 {
            b.step(&mut world, &TickConstants::default()).unwrap();
            assert_eq!(world.tick, t, "one tick per step, fabric or not");
        }
        assert_eq!(b.stats().errors, 3);
        assert!(world.dynamics.slot(id).is_some(), "the player's object stays while the zones are out of reach");
    }

    #[test]
    fn the_backend_says_it_is_remote_and_cannot_be_chosen_by_name() {
        let cfg = GatewayConfig {
            gateway: 0,
            key: ClusterKey::random(),
            zones: 1,
            wait: Duration::ZERO,
            refresh: 30,
            interest: None,
        };
        let b = ZonesBackend::new(cfg, Box::new(Down)).unwrap();
        assert_eq!(b.kind(), BackendKind::Zones);
        assert!(b.description().starts_with("zones: "), "{}", b.description());
        assert!("zones".parse::<BackendKind>().is_err(), "no flag or config name selects it");
        let refused = myriad_physics::create_cpu_backend(BackendKind::Zones).err().expect("refused");
        assert!(refused.to_string().contains("choose a local backend"), "{refused}");
    }
}
