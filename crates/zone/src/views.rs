//! States by interest, the zone's side: each gateway's subscription, and after each step
//! the view the zone sends it (see `docs/zones.md`, "States by interest").
//!
//! A gateway's **view** of a zone at tick t is the set V: the zone's owned objects whose
//! centres lie in the gateway's subscribed cells, and the gateway's own players wherever
//! they are. The zone remembers which objects of V the gateway was sent (`known`, each
//! with the tick it entered) and sends, relative to a **base** tick `c` (see
//! [Bases](#bases)):
//! - every object of V that entered V after c, whole (48 bytes), and the new position
//!   of every other object of V that changed after c (its state differs bit for bit
//!   from the tick before), since an object's id, kind, shape and extents never change
//!   and nothing at a gateway reads another object's previous position or flags (the
//!   gateway's own players always come whole): a *nudge*, the change of the position's
//!   bits since its state at c (1 to 14 bytes, [`crate::wire::Nudge`]), when the zone
//!   still has its positions of tick c ([`NUDGE_WINDOW`]) and the change is small, else
//!   a *move* of 16 bytes; and, for each such object whose action changed after c, its
//!   action (*acts*: a gateway keeps every object's action for the ground prediction of
//!   nudges, which reads it);
//! - the ids of objects that left V (moved out of the cells, cells unsubscribed, handed
//!   to another zone, removed) after c: **gone** (kept until the gateway confirms past
//!   them, for the views relative to its confirmation);
//! - with no base (a new subscriber, a restarted gateway, a new run after a rollback)
//!   the **whole** view, which replaces what the gateway had of this zone.
//!
//! So a gateway that has the zone's view of any tick s with c ≤ s < t and applies the
//! view of tick t has exactly V at t: what is unchanged since c it already holds, the
//! rest is in the message. An object at rest costs nothing after it was sent once.
//!
//! # Bases
//! A view's base is either the last tick the gateway **confirmed** having whole (every
//! subscription carries it), which it always holds, or the tick of the **last view**
//! the zone sent it, which it holds if it took every view in order: a **chain**. A live
//! gateway confirms a few ticks behind the zones (a round trip), so a view relative to
//! its confirmation carries again, every tick, each change of those few ticks; a chain
//! sends each change once, and its nudges span one tick. The zone chains while the
//! gateway's confirmation is within [`CHAIN_LAG`] ticks (a gateway further behind takes
//! only the newest of the ticks it has, which views relative to its confirmation allow),
//! and the gateway asks for a view relative to its confirmation again (its
//! subscription's `resyncs` grows) when a view of the chain was lost: the views after a
//! new `resyncs` are relative to the confirmation, or whole without one, until the
//! gateway confirms one of them. Not just the next one: the zones hear the subscription
//! at different ticks, and the gateway takes a tick only when every zone's view of it
//! applies, which views relative to its confirmation always do.
//!
//! The work per tick is one pass over the owned objects that keeps each one's last
//! change (a merge by id with the last tick's), one pass that buckets them by cell
//! (shared by every gateway with that grid), and for each gateway only its subscribed
//! cells' buckets and its known set: never a scan of every object for every gateway.
//! A gateway's objects are marked in a bitmap over the owned objects (a bit each) and
//! then taken in id order, so that what it knows and the base tick's positions are
//! merged with them in one pass, without a look-up per object: at a million objects
//! the views are most of a zone's host work.
//! A zone sends a gateway nothing until the gateway subscribes; a gateway subscribes
//! every tick (the message also carries its confirmation), so a zone that restarted
//! learns every subscription within a gateway tick. A subscriber not heard from for
//! [`EXPIRE_TICKS`] is dropped.

use std::collections::{BTreeMap, HashMap, VecDeque};

use myriad_core::{Aabb, EntityId, ObjectState, Vec3};

use crate::error::ZoneError;
use crate::gateway::{MAX_GATEWAYS, player_ids};
use crate::layout::ZoneId;
use crate::subscription::{CellGrid, CellSet};
use crate::wire::{
    ACT_LEN, ClusterKey, FingerprintCache, Ground, GroundWorld, HEADER_LEN, MOVE_LEN, NUDGE_MAX_LEN, Nudge, RECORD_LEN,
    Subscription, TAG_LEN, VIEW_FIXED, View, encode_view,
};

/// Ticks after which a silent subscriber is dropped (5 s at 30 Hz, as a silent
/// gateway's players are: [`crate::intents`]).
pub const EXPIRE_TICKS: u64 = 150;

/// How far back a view's base may be for its moves to go as nudges: a zone keeps its
/// objects' positions of the ticks `t - NUDGE_WINDOW ..= t`, and a gateway its own of
/// the ticks it took in the same span before its newest (`gateway_view.rs`). A
/// gateway confirms what it took, so a base the zone nudges from is always one the
/// gateway still has.
pub const NUDGE_WINDOW: u64 = 8;

/// How far behind the zone's tick a gateway's confirmation may be for its views to
/// chain (each relative to the last one sent): a gateway further behind is taking only
/// the newest of the ticks it has, so it gets views relative to its confirmation, which
/// allow that. Within [`NUDGE_WINDOW`], so a chain's bases always have positions.
pub const CHAIN_LAG: u64 = NUDGE_WINDOW;

/// The owned objects' positions after one tick, ids ascending.
pub(crate) type Positions = Vec<(EntityId, Vec3)>;

/// `id`'s position in `at` (ids ascending), searching on from `*i` and leaving `*i` there:
/// a merge of ascending ids with positions, a step or a few each, no look-up.
pub(crate) fn seek(at: &[(EntityId, Vec3)], i: &mut usize, id: EntityId) -> Option<Vec3> {
    while *i < at.len() && at[*i].0 < id {
        *i += 1;
    }
    at.get(*i).filter(|p| p.0 == id).map(|p| p.1)
}

/// Where a gateway's views stand after a new `resyncs` (or a dropped confirmation).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Resync {
    /// No resync: views may chain.
    Off,
    /// Asked: the next view goes relative to the confirmation.
    Asked,
    /// Views go relative to the confirmation since this tick, until the gateway
    /// confirms it or a later one.
    Since(u64),
}

/// Why a zone refused a subscription (counted by [`SubscriptionError::label`]).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum SubscriptionError {
    /// A gateway number no cluster has.
    #[error("gateway {0} (at most {MAX_GATEWAYS})")]
    Stranger(u16),
    /// A grid other than the one its cell side gives over this world.
    #[error("a grid of {got:?} cells where the world has {expected:?}")]
    Grid {
        /// The message's columns and rows.
        got: (u16, u16),
        /// This world's.
        expected: (u16, u16),
    },
    /// An earlier incarnation of the gateway, or an older version of its cells.
    #[error("incarnation {incarnation} version {version} is older than the one held")]
    Stale {
        /// The message's incarnation.
        incarnation: u64,
        /// The message's version.
        version: u64,
    },
    /// A confirmation of a tick this zone has not reached.
    #[error("confirms tick {confirmed}, the zone is at {tick}")]
    Ahead {
        /// What it confirms.
        confirmed: u64,
        /// The zone's tick.
        tick: u64,
    },
}

impl SubscriptionError {
    /// A short stable name, for metrics labels.
    pub fn label(&self) -> &'static str {
        match self {
            SubscriptionError::Stranger(_) => "subscription_stranger",
            SubscriptionError::Grid { .. } => "subscription_grid",
            SubscriptionError::Stale { .. } => "subscription_stale",
            SubscriptionError::Ahead { .. } => "subscription_ahead",
        }
    }
}

/// One gateway's subscription and what it was sent.
#[derive(Debug)]
struct Subscriber {
    incarnation: u64,
    version: u64,
    grid: CellGrid,
    cells: CellSet,
    /// The last tick of this zone's run the gateway has whole.
    confirmed: Option<u64>,
    /// The gateway's count of broken chains, as last heard.
    resyncs: u32,
    /// Whether views go relative to the confirmation (a new `resyncs`).
    resync: Resync,
    /// The run, tick and base of the last view sent (its tick is the base of a chain).
    last_sent: Option<(u64, u64, Option<u64>)>,
    heard_at: u64,
    /// The objects of V the gateway was sent, each with the tick it entered V, ids
    /// ascending.
    known: Vec<(EntityId, u64)>,
    /// Objects that left its view, with the tick they left, until it confirms past it.
    gone: HashMap<EntityId, u64>,
    /// The ground fingerprint its subscription names (0: none): its nudges are
    /// predicted on the ground when it is this zone's.
    ground: u64,
}

impl Subscriber {
    /// The tick before `base` when the gateway took it before the base, so that it holds
    /// the positions nudges are predicted from: along a chain (the last view, of the tick
    /// before, was relative to the tick before that).
    fn prior(&self, run: u64, tick: u64, base: Option<u64>) -> Option<u64> {
        let before = base.filter(|&b| b + 1 == tick && b > 0)? - 1;
        (self.last_sent == Some((run, before + 1, Some(before)))).then_some(before)
    }

    /// The base of its view of `tick` in run `run` (see [Bases](self#bases)): the last
    /// view sent while the chain holds, else the confirmation (`None`: whole).
    fn base(&self, run: u64, tick: u64) -> Option<u64> {
        let chain = self.last_sent.filter(|&(r, t, _)| r == run && t < tick).map(|(_, t, _)| t);
        match (chain, self.confirmed) {
            _ if self.resync != Resync::Off => self.confirmed,
            // Whole views went out, and the gateway has not confirmed one yet.
            (Some(last), None) => Some(last),
            (Some(last), Some(c)) if tick.saturating_sub(c) <= CHAIN_LAG => Some(last),
            _ => self.confirmed,
        }
    }
}

/// An owned object, the last tick its state changed and the last its action did.
#[derive(Clone, Copy, Debug)]
struct Tracked {
    state: ObjectState,
    changed_at: u64,
    acted_at: u64,
}

/// The owned objects of one grid, by cell.
#[derive(Default)]
struct Buckets {
    /// `order[start[c]..start[c + 1]]` are the indices (into the tracked objects) in cell `c`.
    start: Vec<u32>,
    order: Vec<u32>,
    /// Each tracked object's cell.
    cell: Vec<u32>,
}

impl Buckets {
    fn fill(&mut self, grid: &CellGrid, tracked: &[Tracked]) {
        self.cell.clear();
        self.cell.extend(tracked.iter().map(|t| grid.cell_of(t.state.pos)));
        self.start.clear();
        self.start.resize(grid.len() + 1, 0);
        for &c in &self.cell {
            self.start[c as usize + 1] += 1;
        }
        for i in 1..self.start.len() {
            self.start[i] += self.start[i - 1];
        }
        let mut next = self.start.clone();
        self.order.clear();
        self.order.resize(tracked.len(), 0);
        for (i, &c) in self.cell.iter().enumerate() {
            self.order[next[c as usize] as usize] = i as u32;
            next[c as usize] += 1;
        }
    }

    fn of(&self, cell: u32) -> &[u32] {
        let c = cell as usize;
        &self.order[self.start[c] as usize..self.start[c + 1] as usize]
    }
}

/// Whether two states are the same bits (floats compared as bits: a state that did not
/// change is bit for bit the same).
fn same(a: &ObjectState, b: &ObjectState) -> bool {
    let bits = |o: &ObjectState| {
        [o.half.x, o.half.y, o.half.z, o.radius, o.pos.x, o.pos.y, o.pos.z, o.prev.x, o.prev.y, o.prev.z]
            .map(f32::to_bits)
    };
    a.id == b.id
        && a.kind == b.kind
        && a.shape == b.shape
        && a.action == b.action
        && a.flags == b.flags
        && bits(a) == bits(b)
}

/// What a zone sent one gateway in one tick.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Sent {
    /// Messages.
    pub messages: u64,
    /// Their bytes.
    pub bytes: u64,
    /// Object records.
    pub objects: u64,
}

/// Every gateway's subscription to one zone (see the module docs).
#[derive(Default)]
pub struct Subscribers {
    gateways: BTreeMap<u16, Subscriber>,
    tracked: Vec<Tracked>,
    /// The owned objects' positions after each of the last ticks (oldest first), the
    /// bases nudges start from.
    history: VecDeque<(u64, Positions)>,
    buckets: Vec<(CellGrid, Buckets)>,
    /// Scratch: a bit per tracked object, the objects of the gateway at hand.
    marks: Vec<u64>,
    /// The ground fingerprint of the world published from.
    fingerprint: FingerprintCache,
}

impl Subscribers {
    /// Gateways subscribed.
    pub fn len(&self) -> usize {
        self.gateways.len()
    }

    /// Whether no gateway is subscribed.
    pub fn is_empty(&self) -> bool {
        self.gateways.is_empty()
    }

    /// Cells gateway `g` subscribed to, if it did.
    pub fn cells_of(&self, g: u16) -> Option<usize> {
        self.gateways.get(&g).map(|s| s.cells.count())
    }

    /// Takes a subscription, at zone tick `tick` of run `run`, for a world of `bounds`.
    pub fn offer(&mut self, s: Subscription, run: u64, tick: u64, bounds: &Aabb) -> Result<(), SubscriptionError> {
        if s.gateway >= MAX_GATEWAYS {
            return Err(SubscriptionError::Stranger(s.gateway));
        }
        let grid = CellGrid::new(bounds, s.cell)
            .map_err(|_| SubscriptionError::Grid { got: (s.cols, s.rows), expected: (0, 0) })?;
        if grid.shape() != (s.cols, s.rows) {
            return Err(SubscriptionError::Grid { got: (s.cols, s.rows), expected: grid.shape() });
        }
        let confirmed = match s.confirmed {
            Some((r, c)) if r == run => {
                if c > tick {
                    return Err(SubscriptionError::Ahead { confirmed: c, tick });
                }
                Some(c)
            }
            // Nothing of this run yet (a whole view follows).
            _ => None,
        };
        let cells = CellSet::from_bytes(&s.cells, grid.len());
        match self.gateways.get_mut(&s.gateway) {
            Some(e) if (s.incarnation, s.version) < (e.incarnation, e.version) => {
                return Err(SubscriptionError::Stale { incarnation: s.incarnation, version: s.version });
            }
            Some(e) if s.incarnation == e.incarnation => {
                e.version = s.version;
                e.grid = grid;
                e.cells = cells;
                e.ground = s.ground;
                // Confirmations only grow; none (the gateway dropped what it had) asks
                // for a whole view, as one of another run does.
                let dropped = e.confirmed.is_some() && confirmed.is_none();
                let elsewhere = s.confirmed.is_some_and(|(r, _)| r != run);
                e.confirmed = confirmed.map(|c| e.confirmed.map_or(c, |was| was.max(c)));
                // A broken chain: the next view goes relative to the confirmation.
                if dropped || elsewhere || s.resyncs != e.resyncs {
                    e.resync = Resync::Asked;
                }
                e.resyncs = s.resyncs;
                // Over once the gateway confirms a view sent since.
                if let (Resync::Since(from), Some(c)) = (e.resync, e.confirmed)
                    && c >= from
                {
                    e.resync = Resync::Off;
                }
                e.heard_at = tick;
            }
            _ => {
                // A new subscriber, or a restarted gateway: whole views until it confirms.
                let fresh = Subscriber {
                    incarnation: s.incarnation,
                    version: s.version,
                    grid,
                    cells,
                    confirmed: None,
                    resyncs: s.resyncs,
                    resync: Resync::Off,
                    last_sent: None,
                    heard_at: tick,
                    known: Vec::new(),
                    gone: HashMap::new(),
                    ground: s.ground,
                };
                self.gateways.insert(s.gateway, fresh);
            }
        }
        Ok(())
    }

    /// After the step that reached `tick`: each subscribed gateway's view of `owned`
    /// (the zone's owned objects, ids ascending), encoded in parts of at most
    /// `max_message` bytes and handed to `send(gateway, bytes)`. Nudges are predicted on
    /// the ground of `world` for the gateways whose subscriptions name its fingerprint.
    /// Returns what went to each gateway.
    pub fn publish(
        &mut self,
        key: &ClusterKey,
        (run, tick, zone): (u64, u64, ZoneId),
        owned: impl Iterator<Item = ObjectState>,
        world: GroundWorld<'_>,
        max_message: usize,
        mut send: impl FnMut(u16, Vec<u8>) -> Result<(), ZoneError>,
    ) -> Result<Vec<(u16, Sent)>, ZoneError> {
        self.gateways.retain(|_, s| tick.saturating_sub(s.heard_at) <= EXPIRE_TICKS);
        if self.gateways.is_empty() {
            // Nobody to compare with: a later subscriber starts with a whole view.
            self.tracked.clear();
            self.history.clear();
            return Ok(Vec::new());
        }
        self.track(tick, owned);
        self.buckets.retain(|(g, _)| self.gateways.values().any(|s| s.grid == *g));
        for s in self.gateways.values() {
            if !self.buckets.iter().any(|(g, _)| *g == s.grid) {
                self.buckets.push((s.grid, Buckets::default()));
            }
        }
        for (grid, b) in &mut self.buckets {
            b.fill(grid, &self.tracked);
        }
        let fingerprint = self.fingerprint.of(world);
        let mut out = Vec::with_capacity(self.gateways.len());
        for (&g, s) in &mut self.gateways {
            let ground = (s.ground == fingerprint).then_some(world);
            let buckets = &self.buckets.iter().find(|(grid, _)| *grid == s.grid).expect("filled").1;
            let base = s.base(run, tick);
            let positions = |c: Option<u64>| {
                c.and_then(|c| self.history.iter().find(|(t, _)| *t == c)).map(|(_, p)| &p[..]).unwrap_or_default()
            };
            let prior = s.prior(run, tick, base).map(|p| (p, positions(Some(p))));
            let at = Bases { base: positions(base), prior };
            let (objects, moves, nudges, gone, acts) =
                view_of(g, s, base, &self.tracked, buckets, tick, at, ground, &mut self.marks);
            if s.resync == Resync::Asked {
                s.resync = Resync::Since(tick);
            }
            s.last_sent = Some((run, tick, base));
            let mut sent = Sent { objects: (objects.len() + moves.len() + nudges.len()) as u64, ..Sent::default() };
            let lists = (&objects[..], &moves[..], &nudges[..], &gone[..], &acts[..]);
            for (part, parts, (records, moved, nudged, ids, acted)) in parts(lists, max_message)? {
                let v = View {
                    run,
                    tick,
                    zone,
                    gateway: g,
                    part,
                    parts,
                    base,
                    objects: records.to_vec(),
                    moves: moved.to_vec(),
                    nudges: nudged.to_vec(),
                    gone: ids.to_vec(),
                    acts: acted.to_vec(),
                };
                let bytes = encode_view(key, &v)?;
                sent.bytes += bytes.len() as u64;
                sent.messages += 1;
                send(g, bytes)?;
            }
            out.push((g, sent));
        }
        Ok(out)
    }

    /// Keeps each owned object's last change (one merge by id with the last tick's) and
    /// the positions of the last [`NUDGE_WINDOW`] ticks.
    fn track(&mut self, tick: u64, owned: impl Iterator<Item = ObjectState>) {
        let old = std::mem::take(&mut self.tracked);
        let mut i = 0;
        self.tracked.reserve(old.len());
        for state in owned {
            while i < old.len() && old[i].state.id < state.id {
                i += 1;
            }
            let (changed_at, acted_at) = match old.get(i) {
                Some(t) if same(&t.state, &state) => (t.changed_at, t.acted_at),
                Some(t) if t.state.id == state.id && t.state.action == state.action => (tick, t.acted_at),
                _ => (tick, tick),
            };
            self.tracked.push(Tracked { state, changed_at, acted_at });
        }
        // A rollback starts the ticks again: positions of a later tick are of no use.
        self.history.retain(|(t, _)| *t < tick && *t + NUDGE_WINDOW >= tick);
        let mut now = match self.history.len() as u64 >= NUDGE_WINDOW {
            true => self.history.pop_front().map(|(_, p)| p).unwrap_or_default(),
            false => Positions::new(),
        };
        now.clear();
        now.extend(self.tracked.iter().map(|t| (t.state.id, t.state.pos)));
        self.history.push_back((tick, now));
    }
}

/// What a view holds: whole records, moves, nudges, gone ids, acts (each ids ascending).
type ViewLists = (Vec<ObjectState>, Vec<(EntityId, Vec3)>, Vec<Nudge>, Vec<EntityId>, Vec<(EntityId, u8)>);

/// The owned objects' positions (ids ascending) that a view's nudges start from.
struct Bases<'a> {
    /// At the base tick (empty when the zone no longer has them: moves, then).
    base: &'a [(EntityId, Vec3)],
    /// The tick before it and its positions, when nudges may be predicted
    /// (`Subscriber::prior`).
    prior: Option<(u64, &'a [(EntityId, Vec3)])>,
}

/// Gateway `g`'s view at `tick` relative to `base` (`None`: whole), nudging from the
/// positions `at`, on `ground` when given. Updates what it was sent. `marks` is scratch.
#[allow(clippy::too_many_arguments)]
fn view_of(
    g: u16,
    s: &mut Subscriber,
    base: Option<u64>,
    tracked: &[Tracked],
    buckets: &Buckets,
    tick: u64,
    at: Bases<'_>,
    ground: Option<GroundWorld<'_>>,
    marks: &mut Vec<u64>,
) -> ViewLists {
    if base.is_none() {
        s.known.clear();
        s.gone.clear();
    }
    let c = base.unwrap_or(0);
    let players = player_ids(g);
    // V: the objects of the subscribed cells, and the gateway's own players wherever
    // they are (players' ids come last), marked a bit each.
    marks.clear();
    marks.resize(tracked.len().div_ceil(64), 0);
    let mut mark = |i: u32| marks[(i / 64) as usize] |= 1 << (i % 64);
    for cell in s.cells.iter() {
        buckets.of(cell).iter().for_each(|&i| mark(i));
    }
    let from = tracked.partition_point(|t| t.state.id.0 < players.start);
    let to = tracked.partition_point(|t| t.state.id.0 < players.end);
    (from..to).for_each(|i| mark(i as u32));
    // Then in id order, merged with what the gateway knows and the base's positions.
    let (mut objects, mut moves, mut nudges, mut acts) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let old = std::mem::take(&mut s.known);
    let mut known = Vec::with_capacity(old.len() + 64);
    let (mut k, mut b) = (0, 0);
    let mut q = 0;
    for (w, &word) in marks.iter().enumerate() {
        let mut bits = word;
        while bits != 0 {
            let i = w * 64 + bits.trailing_zeros() as usize;
            bits &= bits - 1;
            let t = &tracked[i];
            let id = t.state.id;
            // What the gateway knew before this object and no longer sees: gone.
            while k < old.len() && old[k].0 < id {
                s.gone.insert(old[k].0, tick);
                k += 1;
            }
            // Whole: new to the gateway since what it confirmed (it may lack the
            // record), or one of its own players that changed; else a move when it
            // changed.
            let (whole, moved, since) = if k < old.len() && old[k].0 == id {
                let since = old[k].1;
                k += 1;
                known.push((id, since));
                let whole = base.is_none() || since > c || (t.changed_at > c && players.contains(&id.0));
                (whole, !whole && t.changed_at > c, since)
            } else {
                known.push((id, tick));
                s.gone.remove(&id);
                (true, false, tick)
            };
            if whole {
                objects.push(t.state);
            } else if moved {
                // The gateway holds its action as of c or later: a newer one goes first
                // (it applies a tick's acts before its nudges).
                if t.acted_at > c {
                    acts.push((id, t.state.action));
                }
                // Known since c or before, so it was in V at c and the positions of c
                // hold it (when the zone still has them).
                let from = seek(at.base, &mut b, id);
                // Predicted when the gateway held it at the tick before the base too.
                let before = match at.prior {
                    Some((prior, positions)) if since <= prior => seek(positions, &mut q, id),
                    _ => None,
                };
                let on = ground.map(|world| Ground { world, action: t.state.action, half_y: t.state.half.y });
                let nudge = from.map(|from| Nudge::shortest(id, before, from, t.state.pos, on.as_ref()));
                match nudge {
                    Some(n) if n.compact() => nudges.push(n),
                    _ => moves.push((id, t.state.pos)),
                }
            }
        }
    }
    for &(id, _) in &old[k..] {
        s.gone.insert(id, tick);
    }
    s.known = known;
    // Kept while a view relative to the confirmation may need them.
    let confirmed = s.confirmed.unwrap_or(0);
    s.gone.retain(|_, left| *left > confirmed);
    let mut gone: Vec<EntityId> = match base {
        Some(_) => s.gone.iter().filter(|(_, left)| **left > c).map(|(id, _)| *id).collect(),
        None => Vec::new(),
    };
    gone.sort_unstable();
    // Taken in id order: every list is ascending already.
    (objects, moves, nudges, gone, acts)
}

/// One part's slices of a view's lists.
type PartLists<'a> = (&'a [ObjectState], &'a [(EntityId, Vec3)], &'a [Nudge], &'a [EntityId], &'a [(EntityId, u8)]);

/// A view's records, moves, nudges, gone ids and acts in parts that fit `max_message`
/// bytes (at least one part, even when empty): (part, parts, its slices).
fn parts(lists: PartLists<'_>, max_message: usize) -> Result<Vec<(u16, u16, PartLists<'_>)>, ZoneError> {
    let (objects, moves, nudges, gone, acts) = lists;
    // A fifth of a message for each list, so that a part with all five still fits
    // (nudges at their largest: every one the zone sends is compact).
    let room = max_message.saturating_sub(HEADER_LEN + TAG_LEN + VIEW_FIXED) / 5;
    let per = [RECORD_LEN, MOVE_LEN, NUDGE_MAX_LEN, 4, ACT_LEN].map(|len| (room / len).max(1));
    let lens = [objects.len(), moves.len(), nudges.len(), gone.len(), acts.len()];
    let n = lens.iter().zip(per).map(|(len, per)| len.div_ceil(per)).max().unwrap_or(0).max(1);
    let parts = u16::try_from(n).map_err(|_| ZoneError::Fabric(format!("a view of {n} parts")))?;
    fn chunk<T>(all: &[T], per: usize, i: usize) -> &[T] {
        &all[(i * per).min(all.len())..((i + 1) * per).min(all.len())]
    }
    Ok((0..n)
        .map(|i| {
            let lists = (
                chunk(objects, per[0], i),
                chunk(moves, per[1], i),
                chunk(nudges, per[2], i),
                chunk(gone, per[3], i),
                chunk(acts, per[4], i),
            );
            (i as u16, parts, lists)
        })
        .collect())
}

#[cfg(test)]
#[path = "views_tests.rs"]
mod tests;
