//! What one player's client holds, and what to send it next: the server half of
//! delta replication (protocol version 3's records, `myriad_protocol::delta`).
//!
//! Per player the server keeps, for each object in view, a `Track`: the newest state
//! the client acknowledged (the *baseline* of the next record) and the one it
//! acknowledged before (the *prior* a record may predict the baseline's move from), the
//! newest state sent,
//! and a *priority* that grows every tick the client lacks the object's current state.
//! Sent datagrams stay in flight, with the states they carried, until the client's
//! acknowledgements ([`AckField`]) name them or they are too old to be baselines.
//!
//! Each tick ([`Replica::build`]):
//! 1. the view (by ascending slot) is merged with last tick's tracks: objects that left
//!    it are dropped, new ones start with nothing held; acknowledgements that arrived
//!    turn in-flight states into baselines (also of an object back in view since);
//! 2. an object new in view is due at once; every other one whose current (quantized)
//!    state the client neither holds (its baseline, with no other state sent since) nor
//!    was just sent gains `1 / bound(d)` priority,
//!    where `bound(d)` is the refresh bound in ticks at its distance `d` from the
//!    player: `near_bound_ticks` within `near` units, growing linearly to
//!    `far_bound_ticks` at `far` units; an object the client holds unchanged gains `1 / refresh_ticks` (a cheap `Same` record confirms it now and
//!    then, so a client can tell a still object from one that left its view); a near
//!    object sent moving last tick that has not moved since is due at once, so that the
//!    client holds it still (two equal states) instead of carrying it on past its stop; a
//!    near object the client does not hold, not yet due, is offered after everything
//!    due, from what the budget would otherwise forfeit (beyond the tick's worth that
//!    carries over), if the client holds a baseline of it and acknowledged some datagram
//!    within `resend_ticks` (a slower or lossy link gets near objects at their bound:
//!    every record against an older baseline is larger);
//! 3. the objects due (priority at least 1) are taken into this tick's byte budget, near
//!    ones and ones the client lacks first, then by priority
//!    (`budget_bytes_per_tick`, with what earlier ticks left unspent, up to one tick's
//!    worth more, datagram header and tag counted); an object that has waited
//!    `max_wait_ticks` goes even over the budget, so nothing starves;
//! 4. they are written smallest form first against their baselines
//!    ([`DeltaRecord::choose`]), ids increasing, the player's own object in every
//!    datagram; what was sent restarts its priority at zero. Records are weighed against
//!    the budget at a conservative estimate of their bits (`charge_bits`); what the
//!    datagrams really took is what the tick spent, and the rest carries over.

use std::collections::VecDeque;

use myriad_protocol::ack::ACK_BITS;
use myriad_protocol::delta::{MAX_RECORD_LEN, STREAM_PARAMS_BITS};
use myriad_protocol::{
    AckField, Baseline, DELTA_HEADER_LEN, DatagramBatch, DeltaRecord, HEADER_LEN, MAX_BACK, MAX_BODY, QuantPos, Sealer,
    ShapeKind, TAG_LEN, UpdateHeader, pack_deltas,
};

use crate::config::TickInfo;

/// Bytes a datagram costs before its records: the packet header, the tag and the delta
/// update header.
pub const DATAGRAM_OVERHEAD: usize = HEADER_LEN + TAG_LEN + DELTA_HEADER_LEN;

/// How urgently objects are sent and how many bytes a player may get.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReplicationConfig {
    /// Bytes a player may be sent per tick, datagram headers and tags included (the
    /// server's `send_budget_kbps` over the tick rate). At least one datagram with the player's own
    /// object is sent every tick whatever the budget.
    pub budget_bytes_per_tick: f32,
    /// Objects within this distance (world units) of the player are near.
    pub near: f32,
    /// Refresh bound of a changing near object, in ticks.
    pub near_bound_ticks: f32,
    /// Refresh bound of a changing object `far` units away or more, in ticks; the bound
    /// grows linearly from `near_bound_ticks` at `near` to this at `far`.
    pub far_bound_ticks: f32,
    /// Distance (world units) from which the far bound applies.
    pub far: f32,
    /// An unchanged object the client holds is confirmed at least this often, in ticks.
    pub refresh_ticks: f32,
    /// How long an acknowledgement may take, in ticks: a state sent but not
    /// acknowledged after this many counts as lost and is due again, and a link that
    /// acknowledged nothing for this many gets no eager records.
    pub resend_ticks: u64,
    /// An object that has wanted sending for this many ticks is sent even over the
    /// budget (the starvation bound).
    pub max_wait_ticks: f32,
}

impl Default for ReplicationConfig {
    fn default() -> Self {
        Self {
            budget_bytes_per_tick: 8_000.0 / 30.0,
            near: 30.0,
            near_bound_ticks: 3.0,
            far_bound_ticks: 24.0,
            far: 60.0,
            refresh_ticks: 24.0,
            resend_ticks: 6,
            max_wait_ticks: 30.0,
        }
    }
}

impl ReplicationConfig {
    /// The refresh bound in ticks of a changing object `distance` units away.
    pub fn bound_ticks(&self, distance: f32) -> f32 {
        let (near_bound, far_bound) = (self.near_bound_ticks.max(1.0), self.far_bound_ticks.max(1.0));
        let span = (self.far - self.near).max(f32::MIN_POSITIVE);
        let along = ((distance - self.near) / span).clamp(0.0, 1.0);
        // NaN distances (never from a world) read as near: sent more, not less.
        if along.is_nan() { near_bound } else { near_bound + (far_bound - near_bound).max(0.0) * along }
    }
}

/// What the server knows of one object in a player's view.
///
/// 64 bytes, kept in the order of the view (ascending slot) from tick to tick: a view of
/// thousands of objects is read and written once a tick, so this is memory traffic, and
/// in the view's order it streams through the caches where a lookup by id missed them
/// at every object.
#[derive(Debug, Clone, Copy)]
struct Track {
    /// The object's id.
    id: u64,
    /// The newest state the client acknowledged (its tick [`NONE`] if there is none).
    acked_tick: u64,
    /// The newest state sent, acknowledged or not (its tick [`NONE`] if none).
    sent_tick: u64,
    acked_pos: QuantPos,
    sent_pos: QuantPos,
    /// Grows while the client lacks the current state (see the module docs).
    priority: f32,
    /// The object's slot when last in view.
    slot: u32,
    /// Whether the newest state sent differed from the one sent before it: the object
    /// was moving, and a client extrapolates it past that state.
    sent_moved: bool,
    /// The state acknowledged before the newest, as ticks before it (0: none) and its
    /// position less the newest's: small, so the track stays one cache line.
    prior_back: u8,
    prior_offset: [i16; 3],
}

/// The tick of a baseline that does not exist.
const NONE: u64 = u64::MAX;

impl Track {
    fn new(id: u64, slot: u32) -> Self {
        let zero = QuantPos::new(0, 0, 0);
        Track {
            id,
            acked_tick: NONE,
            sent_tick: NONE,
            acked_pos: zero,
            sent_pos: zero,
            priority: 0.0,
            slot,
            sent_moved: false,
            prior_back: 0,
            prior_offset: [0; 3],
        }
    }

    /// The acknowledged state, if the next record can still name it (not older than
    /// `floor`).
    fn acked(&self, floor: u64) -> Option<Baseline> {
        (self.acked_tick != NONE && self.acked_tick >= floor)
            .then_some(Baseline { tick: self.acked_tick, pos: self.acked_pos })
    }

    /// The state acknowledged before the baseline `acked`, if there is one.
    fn prior(&self, acked: Option<Baseline>) -> Option<Baseline> {
        let o = self.prior_offset.map(i32::from);
        let pos = QuantPos::new(
            self.acked_pos.x.wrapping_add(o[0]),
            self.acked_pos.y.wrapping_add(o[1]),
            self.acked_pos.z.wrapping_add(o[2]),
        );
        acked.filter(|_| self.prior_back > 0).map(|a| Baseline { tick: a.tick - u64::from(self.prior_back), pos })
    }

    fn sent(&self) -> Option<Baseline> {
        (self.sent_tick != NONE).then_some(Baseline { tick: self.sent_tick, pos: self.sent_pos })
    }

    /// Takes `pos`, carried by a datagram of `tick` the client acknowledged, as the
    /// baseline if it is newer than the one held.
    fn acknowledge(&mut self, tick: u64, pos: QuantPos) {
        if self.acked_tick == NONE || self.acked_tick < tick {
            // The baseline it replaces becomes the prior, if a record can still name
            // it together with a baseline and the offset fits.
            let offset = [
                i64::from(self.acked_pos.x) - i64::from(pos.x),
                i64::from(self.acked_pos.y) - i64::from(pos.y),
                i64::from(self.acked_pos.z) - i64::from(pos.z),
            ]
            .map(|d| i16::try_from(d).ok());
            let back = tick.checked_sub(self.acked_tick).filter(|&b| self.acked_tick != NONE && b < MAX_BACK);
            (self.prior_back, self.prior_offset) = match (back, offset) {
                (Some(b), [Some(x), Some(y), Some(z)]) => (b as u8, [x, y, z]),
                _ => (0, [0; 3]),
            };
            (self.acked_tick, self.acked_pos) = (tick, pos);
        }
    }
}

/// Most datagrams a replica keeps in flight: a client that stops acknowledging costs
/// the server this much and no more (the oldest flight goes first).
pub const MAX_FLIGHTS: usize = 64;

/// Most states a replica's flights hold together (the oldest flight goes first).
pub const MAX_FLIGHT_STATES: usize = 4096;

/// What packing and sealing one build's records did.
#[derive(Debug)]
pub struct Sealed {
    /// Records of other objects packed (`records[..packed]`).
    pub packed: usize,
    /// Sequence number of the first datagram.
    pub first: u64,
    /// Bytes the datagrams took (0 if sealing failed).
    pub spent: f32,
    /// Whether sealing succeeded; if not, `out` holds nothing to send.
    pub sealed: Result<(), myriad_protocol::SealError>,
}

/// Packs `own` (in every datagram) and `records` (ids increasing) into at most
/// `datagrams` delta updates under `header`, `ends` getting where each datagram's
/// records end, and seals them into `out`: the last step of the host replica's build.
pub fn pack_and_seal(
    header: &UpdateHeader,
    own: Option<&DeltaRecord>,
    records: &[DeltaRecord],
    datagrams: usize,
    sealer: &mut Sealer,
    out: &mut DatagramBatch,
    ends: &mut Vec<usize>,
) -> Sealed {
    out.clear();
    let packed = pack_deltas(header, own, records, datagrams, out, ends);
    seal(packed, sealer, out)
}

/// Seals `out`, a build's datagrams, which hold `packed` of its records: the step after
/// packing, wherever the packing was done (here, or on a device).
pub(crate) fn seal(packed: usize, sealer: &mut Sealer, out: &mut DatagramBatch) -> Sealed {
    let first = sealer.next_sequence();
    let sealed = sealer.seal_batch(out);
    let spent = if sealed.is_ok() { out.total_bytes() as f32 } else { 0.0 };
    Sealed { packed, first, spent, sealed }
}

/// What packing one build's chosen records did (here by [`pack_and_seal`], or elsewhere:
/// [`Subscriber::seal_packed`](crate::Subscriber::seal_packed)).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Packing {
    /// Records of other objects chosen.
    pub chosen: usize,
    /// Of them, packed (the first `packed`; the rest wait for a later tick).
    pub packed: usize,
    /// Records packed relative to a state the client acknowledged, the own object's
    /// included (once).
    pub relative: usize,
}

impl Packing {
    /// What packing the first `packed` of `records`, and `own` in every datagram, did.
    pub(crate) fn of(own: Option<&DeltaRecord>, records: &[DeltaRecord], packed: usize) -> Packing {
        let relative =
            usize::from(own.is_some_and(is_relative)) + records[..packed].iter().filter(|r| is_relative(r)).count();
        Packing { chosen: records.len(), packed, relative }
    }
}

impl Sealed {
    /// Adds what packing did to `report`, if sealing succeeded: the records packed, the
    /// chosen ones that did not fit deferred, and how many went relative to a state the
    /// client acknowledged (the own object's included).
    pub(crate) fn count(&self, report: &mut ReplicaReport, packing: Packing) {
        if self.sealed.is_ok() {
            report.packed = packing.packed;
            report.deferred += packing.chosen.saturating_sub(packing.packed);
            report.relative = packing.relative;
        }
    }
}

/// One sent datagram awaiting acknowledgement.
#[derive(Debug, Default)]
struct Flight {
    sequence: u64,
    tick: u64,
    /// `(slot, id, position)` of each record it carried.
    states: Vec<(u32, u64, QuantPos)>,
}

/// One player's replication state; see the module docs.
#[derive(Debug, Default)]
pub struct Replica {
    /// The objects in view last tick, ascending by slot.
    tracks: Vec<Track>,
    /// The player's own object.
    own: Option<Track>,
    flights: VecDeque<Flight>,
    /// Emptied flights, to reuse their memory.
    spare: Vec<Flight>,
    /// Acknowledgements not applied yet.
    acks: Option<AckField>,
    /// Unspent budget carried to the next tick.
    credit: f32,
    /// One past the tick of the newest datagram the client acknowledged (0: none yet):
    /// how fresh the link is, whatever the objects it carried.
    heard: u64,
}

/// An object in view this tick.
#[derive(Debug, Clone, Copy)]
pub struct Candidate {
    /// The object's slot: what orders a view. It increases along the candidates and
    /// stays with the object from tick to tick (the AOI lists' dynamic slots).
    pub slot: u32,
    /// The object's id.
    pub id: u64,
    /// Its shape.
    pub kind: ShapeKind,
    /// Its position, quantized.
    pub pos: QuantPos,
    /// Its distance from the player, world units.
    pub distance: f32,
}

/// What one [`Replica::build`] did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ReplicaReport {
    /// Objects in view (own excluded, duplicates dropped).
    pub in_view: usize,
    /// Candidates dropped because their slot did not increase along the view (a
    /// duplicate, or a list out of order).
    pub out_of_order: usize,
    /// Records of other objects sent.
    pub packed: usize,
    /// Objects that wanted sending but did not fit this tick.
    pub deferred: usize,
    /// Records sent relative to a baseline (`Delta` or `Same`), own included.
    pub relative: usize,
    /// Objects sent over the budget because they were starving.
    pub starving: usize,
}

/// Per-thread working memory of [`Replica::build`].
#[derive(Default)]
pub struct ReplicaScratch {
    /// This tick's tracks, in the view's order (swapped with the replica's at the end,
    /// so the memory passes from player to player).
    next: Vec<Track>,
    /// The candidate of each of `next`.
    candidate_of: Vec<u32>,
    /// Indices into `next` of tracks new this tick by slot, and into the old tracks of
    /// ones no candidate took by slot: matched by id (an object whose slot changed).
    unmatched: Vec<u32>,
    orphans: Vec<u32>,
    /// `(old slot, id, new slot)` of the objects matched by id.
    moved: Vec<(u32, u64, u32)>,
    /// The objects due.
    wanted: Vec<Due>,
    /// `(record, track index, candidate index)` of what this tick sends.
    chosen: Vec<(DeltaRecord, u32, u32)>,
    records: Vec<DeltaRecord>,
    ends: Vec<usize>,
}

/// An object due this tick, and how it ranks.
#[derive(Debug, Clone, Copy)]
struct Due {
    /// Its place in the order, smallest first ([`Due::rank`]).
    rank: u128,
    /// Index of its track.
    track: u32,
    /// Index of its candidate.
    candidate: u32,
    /// It waited `max_wait_ticks`: sent even over the budget.
    starving: bool,
    /// Not due, but near and not held by the client: offered after everything due, from
    /// what the budget would forfeit (not counted as deferred when it does not fit).
    eager: bool,
}

impl Due {
    /// The order of urgency as one integer, smallest first: everything due before the
    /// `eager` (not due), near objects and ones the client lacks (`first`), then by
    /// priority (higher first), then the nearer (so a
    /// player who just joined gets its surroundings first), then by id, a total order,
    /// so the choice is a function of the inputs alone. Both floats are at least zero
    /// (or NaN, which goes last), whose bit patterns order as the numbers do; an integer
    /// key compares in one instruction where four comparisons of fields took many.
    fn rank(eager: bool, first: bool, priority: f32, distance: f32, id: u64) -> u128 {
        const MAGNITUDE: u32 = 0x7fff_ffff;
        let priority = MAGNITUDE - (priority.to_bits() & MAGNITUDE);
        let distance = distance.to_bits() & MAGNITUDE;
        (u128::from(eager) << 127)
            | (u128::from(!first) << 126)
            | (u128::from(priority) << 95)
            | (u128::from(distance) << 64)
            | u128::from(id)
    }

    /// The order of [`Due::rank`], then by track (two tracks of one id come only from a
    /// broken source, but the device replica must still pick as the host does).
    fn urgency(a: &Self, b: &Self) -> std::cmp::Ordering {
        a.rank.cmp(&b.rank).then(a.track.cmp(&b.track))
    }
}

/// The budget and datagrams of one build, as objects are offered to them.
struct Filling {
    /// Bytes left (negative once starving objects went over).
    budget: f32,
    /// Datagrams opened.
    datagrams: usize,
    max_datagrams: usize,
    /// Bits of records in the open datagram.
    in_datagram: usize,
    /// Bits of records a datagram holds for sure.
    room: usize,
    /// What opening a datagram costs: its overhead and the own object's record.
    per_datagram: f32,
    /// What an eager record must leave of the budget: what carries over to the next
    /// tick at most, so that eager records spend only what would be forfeited.
    keep: f32,
}

impl Filling {
    /// Takes a record of `bits` if the budget pays for it (opening a datagram if needed
    /// and allowed; an `eager` one only from what the budget would forfeit), or over the
    /// budget if it is `starving`; `Some(over budget)` when taken.
    fn offer(&mut self, bits: usize, starving: bool, eager: bool) -> Option<bool> {
        let cost = bits as f32 / 8.0;
        let free = self.budget - if eager { self.keep } else { 0.0 };
        let mut fits = cost <= free || starving;
        if fits && self.in_datagram + bits > self.room {
            // Another datagram, if allowed and paid for.
            fits = self.datagrams < self.max_datagrams && (cost + self.per_datagram <= free || starving);
            if fits {
                self.datagrams += 1;
                self.in_datagram = 0;
                self.budget -= self.per_datagram;
            }
        }
        if !fits {
            return None;
        }
        let over_budget = cost > self.budget;
        self.budget -= cost;
        self.in_datagram += bits;
        Some(over_budget)
    }
}

/// Bits an id code is charged when a record is weighed against the budget: its real
/// size depends on its neighbours in id order, known only once the tick's records are
/// chosen. Views of thousands of objects in worlds of hundreds of thousands leave gaps
/// near 2^10, which the code order `pack_deltas` picks writes in 11 to 13 bits.
const ID_CHARGE_BITS: u32 = 16;

/// What a record is charged in bits: its own with the back written out, and
/// [`ID_CHARGE_BITS`] for its id.
fn charge_bits(record: &DeltaRecord, origin: QuantPos) -> usize {
    record.bits(origin, 0).map_or(MAX_RECORD_LEN * 8, |b| (b + ID_CHARGE_BITS) as usize)
}

/// The smallest a record can be charged (a `Same` record): below it, no budget pays for
/// anything.
const MIN_COST: f32 = (3 + 7 + ID_CHARGE_BITS) as f32 / 8.0;

/// Objects due taken from the order at a time: more than a usual budget holds, so that
/// one slice mostly suffices.
const ORDER_SLICE: usize = 64;

/// Slack on the starvation test: a priority is a running sum of one rate, and thirty
/// additions of 1/3 in `f32` fall short of 30 × 1/3 by a few ulps; the test counts
/// whole ticks, so a thousandth of one is far below anything that matters.
const WAIT_SLACK: f32 = 1.0e-3;

impl Replica {
    /// Notes an acknowledgement from the client; applied at the next build.
    pub fn acknowledge(&mut self, acks: AckField) {
        self.acks = Some(self.acks.map_or(acks, |a| a.merge(acks)));
    }

    /// Builds and seals this tick's datagrams into `out`: `own` is the player's own
    /// object (in every datagram), `candidates` the objects in view by ascending slot
    /// (the own object is skipped, and so is a candidate whose slot does not exceed the
    /// one before it), `origin` the AOI centre. Returns what it did; `out` is empty if
    /// sealing failed.
    #[allow(clippy::too_many_arguments)]
    pub fn build(
        &mut self,
        config: &ReplicationConfig,
        tick: TickInfo,
        origin: QuantPos,
        own: Option<(u64, ShapeKind, QuantPos)>,
        candidates: &[Candidate],
        max_datagrams: usize,
        sealer: &mut Sealer,
        out: &mut DatagramBatch,
        scratch: &mut ReplicaScratch,
    ) -> Result<ReplicaReport, myriad_protocol::SealError> {
        let now = tick.tick;
        // Baselines older than this cannot be named by a record of this tick.
        let floor = now.saturating_sub(MAX_BACK - 1);
        let mut report = ReplicaReport::default();
        if let Some((id, _, _)) = own
            && self.own.is_none_or(|t| t.id != id)
        {
            self.own = Some(Track::new(id, u32::MAX));
        }
        report.out_of_order = self.match_view(own.map(|o| o.0), candidates, scratch);
        let ReplicaScratch { next, candidate_of, moved, wanted, chosen, records, ends, .. } = scratch;
        if !moved.is_empty() {
            // States in flight name objects by slot: the moved ones' follow them (rare,
            // so a pass over the flights costs nothing that matters).
            for s in self.flights.iter_mut().flat_map(|f| f.states.iter_mut()) {
                if let Some(m) = moved.iter().find(|m| (m.0, m.1) == (s.0, s.1)) {
                    s.0 = m.2;
                }
            }
        }
        // On this tick's tracks, which the match just wrote (a search in last tick's,
        // cold in memory, missed the cache at every step).
        self.apply_acks(now, next);
        // Eager records go only over a link that acknowledged a datagram within
        // `resend_ticks`: the link's age, not the object's baseline's, which is old for
        // an object that rested long before it moved (such an object then waited for
        // its bound, and a client drew its first steps between states ticks apart).
        let fresh_link = self.heard != 0 && self.heard + config.resend_ticks > now;

        // Own object first: it is in every datagram whatever the budget.
        let own_record = own.zip(self.own).map(|((id, kind, pos), t)| {
            let acked = t.acked(floor);
            DeltaRecord::choose(id, kind, pos, now, acked, t.prior(acked))
        });
        report.in_view = next.len();

        // Priorities, in the view's order: both arrays stream.
        wanted.clear();
        for (k, (t, &j)) in next.iter_mut().zip(candidate_of.iter()).enumerate() {
            let c = &candidates[j as usize];
            let (acked, sent) = (t.acked(floor), t.sent());
            // The client holds the current state if its baseline is that state and no
            // other was sent since: an object that moved away and back (a jitter) is
            // drawn from the state it moved to until it gets the current one.
            let holds = acked.is_some_and(|b| b.pos == c.pos) && sent.is_none_or(|s| s.pos == c.pos);
            let sending = sent.is_some_and(|s| s.pos == c.pos && now.saturating_sub(s.tick) < config.resend_ticks);
            // Sent moving last tick and still there since: it stopped, and the client,
            // holding two states apart, would carry it on past the stop. The same state
            // once more (now) shows it still; only near, where the error shows (beyond,
            // where the budget binds, these records pushed what waits over it).
            let stopped =
                sending && t.sent_moved && c.distance <= config.near && sent.is_some_and(|s| s.tick + 1 == now);
            let rate = if stopped {
                1.0
            } else if holds {
                1.0 / config.refresh_ticks.max(1.0)
            } else if sending {
                0.0
            } else if acked.is_none() && sent.is_none() {
                // New in view: the client has nothing of it, which is worse than old.
                1.0
            } else {
                1.0 / config.bound_ticks(c.distance)
            };
            t.priority += rate;
            // Sent when due: the bounds, not the budget, decide how often; the budget
            // decides what waits when more is due than it holds.
            if t.priority >= 1.0 {
                // Priority over this tick's rate: the ticks it has wanted sending.
                let starving = rate > 0.0 && t.priority / rate + WAIT_SLACK >= config.max_wait_ticks;
                // Near objects and objects the client lacks go first once due: their
                // bound is the tightest, and a far object that waits its turn is drawn
                // off by less. Nothing far starves: `max_wait_ticks` still holds.
                let first = c.distance <= config.near || acked.is_none();
                let rank = Due::rank(false, first, t.priority, c.distance, c.id);
                wanted.push(Due { rank, track: k as u32, candidate: j, starving, eager: false });
            } else if !holds && rate > 0.0 && c.distance <= config.near && acked.is_some() && fresh_link {
                // A near object the client does not hold, before its bound: what the
                // budget would forfeit goes to these (every tick where it can), so a
                // small view is sent whole each tick and drawn as exactly as full
                // states, and a view the budget binds loses nothing to them.
                let rank = Due::rank(true, true, t.priority, c.distance, c.id);
                wanted.push(Due { rank, track: k as u32, candidate: j, starving: false, eager: true });
            }
        }

        // Most urgent first, within the budget and the datagrams.
        let own_bits = own_record.map_or(0, |r| charge_bits(&r, origin));
        // Room for records in a datagram (bits), less the most a datagram can waste when
        // the next record does not fit.
        let room = (MAX_BODY - DELTA_HEADER_LEN - MAX_RECORD_LEN) * 8 - STREAM_PARAMS_BITS as usize - own_bits;
        let per_datagram = DATAGRAM_OVERHEAD as f32 + own_bits as f32 / 8.0;
        // A negative or NaN budget is none: only what starves (and the own object) is
        // sent. An infinite one holds everything the datagrams do.
        let per_tick = if config.budget_bytes_per_tick.is_nan() { 0.0 } else { config.budget_bytes_per_tick.max(0.0) };
        let mut fill = Filling {
            budget: per_tick + self.credit - per_datagram,
            datagrams: 1,
            max_datagrams: max_datagrams.max(1),
            in_datagram: 0,
            room,
            per_datagram,
            // An infinite budget keeps nothing back from eager records.
            keep: if per_tick.is_finite() { per_tick } else { 0.0 },
        };
        chosen.clear();
        // A budget holds a few dozen of the objects due where hundreds may be: the order
        // is taken a slice at a time (a partial selection of what is left, then a sort
        // of the slice), and once the budget cannot pay for the smallest record only the
        // starving can still go. The objects are offered in exactly the order a sort of
        // them all gives (a total order), at a fraction of its cost.
        let mut start = 0;
        while start < wanted.len() {
            let rest = &mut wanted[start..];
            let exhausted = fill.budget < MIN_COST;
            let take = if exhausted {
                // Only the starving can still go: they alone, in their order.
                let mut n = 0;
                for j in 0..rest.len() {
                    if rest[j].starving {
                        rest.swap(n, j);
                        n += 1;
                    }
                }
                report.deferred += rest[n..].iter().filter(|d| !d.eager).count();
                n
            } else {
                let n = ORDER_SLICE.min(rest.len());
                if n < rest.len() {
                    rest.select_nth_unstable_by(n, Due::urgency);
                }
                n
            };
            rest[..take].sort_unstable_by(Due::urgency);
            for d in &rest[..take] {
                let c = &candidates[d.candidate as usize];
                let t = &next[d.track as usize];
                let acked = t.acked(floor);
                let record = DeltaRecord::choose(c.id, c.kind, c.pos, now, acked, t.prior(acked));
                match fill.offer(charge_bits(&record, origin), d.starving, d.eager) {
                    Some(over_budget) => {
                        report.starving += usize::from(over_budget);
                        chosen.push((record, d.track, d.candidate));
                    }
                    None => report.deferred += usize::from(!d.eager),
                }
            }
            start = if exhausted { wanted.len() } else { start + take };
        }

        // Write, ids increasing, and remember what went in which datagram. Distinct
        // slots should hold distinct ids; a source where they do not must not make a
        // datagram whose ids fail to increase, so a repeated id goes once.
        chosen.sort_unstable_by_key(|c| (c.0.id, c.1));
        let before = chosen.len();
        chosen.dedup_by_key(|c| c.0.id);
        report.deferred += before - chosen.len();
        records.clear();
        records.extend(chosen.iter().map(|c| c.0));
        let header = UpdateHeader { tick: now, dilation_permille: tick.dilation_permille, origin };
        let done = pack_and_seal(&header, own_record.as_ref(), records, fill.datagrams, sealer, out, ends);
        // What the datagrams took, not what the records were charged, is what this tick
        // spent; what is left (never more than a tick's worth) carries over, and an
        // overdraft is forgiven.
        self.credit = (per_tick + self.credit - done.spent).clamp(0.0, per_tick);
        done.count(&mut report, Packing::of(own_record.as_ref(), records, done.packed));
        let Sealed { first, sealed, .. } = done;
        if sealed.is_ok() {
            let mut start = 0;
            for (d, &end) in ends.iter().enumerate() {
                let mut f = self.spare.pop().unwrap_or_default();
                f.sequence = first + d as u64;
                f.tick = now;
                f.states.clear();
                f.states.extend(own.map(|(id, _, pos)| (u32::MAX, id, pos)));
                for &(_, i, j) in &chosen[start..end] {
                    let c = &candidates[j as usize];
                    let t = &mut next[i as usize];
                    t.sent_moved = t.sent_tick != NONE && t.sent_pos != c.pos;
                    (t.sent_tick, t.sent_pos, t.priority) = (now, c.pos, 0.0);
                    f.states.push((c.slot, c.id, c.pos));
                }
                start = end;
                self.push_flight(f);
            }
        } else {
            out.clear();
        }
        // This tick's tracks become the replica's; the old ones are scratch now.
        std::mem::swap(&mut self.tracks, next);
        sealed.map(|()| report)
    }

    /// Keeps `f` in flight, dropping the oldest flights first while the replica holds
    /// [`MAX_FLIGHTS`] of them or their states would pass [`MAX_FLIGHT_STATES`].
    fn push_flight(&mut self, f: Flight) {
        let mut states: usize = self.flights.iter().map(|f| f.states.len()).sum();
        while self.flights.len() >= MAX_FLIGHTS || states + f.states.len() > MAX_FLIGHT_STATES {
            let Some(mut old) = self.flights.pop_front() else { break };
            states -= old.states.len();
            old.states.clear();
            self.spare.push(old);
        }
        self.flights.push_back(f);
    }

    /// Takes the acknowledgements not applied yet (the device replica applies them).
    pub fn take_acks(&mut self) -> Option<AckField> {
        self.acks.take()
    }

    /// Matches this tick's view against last tick's tracks into `scratch.next` (one
    /// track per candidate taken, in the view's order, with its candidate in
    /// `scratch.candidate_of`); returns the candidates dropped as out of order.
    ///
    /// Both are in ascending slot order, so this is a merge; an object is the same if
    /// slot and id agree. Objects whose slot changed (a removal moved them) are matched
    /// by id among what the merge left over: few, so sorting them costs little.
    fn match_view(&self, own: Option<u64>, candidates: &[Candidate], scratch: &mut ReplicaScratch) -> usize {
        let ReplicaScratch { next, candidate_of, unmatched, orphans, moved, .. } = scratch;
        let old = &self.tracks;
        next.clear();
        candidate_of.clear();
        unmatched.clear();
        orphans.clear();
        moved.clear();
        let (mut i, mut last, mut out_of_order) = (0, None, 0);
        for (j, c) in candidates.iter().enumerate() {
            if own == Some(c.id) {
                continue;
            }
            if last.is_some_and(|s| c.slot <= s) {
                out_of_order += 1;
                continue;
            }
            last = Some(c.slot);
            while i < old.len() && old[i].slot < c.slot {
                orphans.push(i as u32);
                i += 1;
            }
            candidate_of.push(j as u32);
            if i < old.len() && old[i].slot == c.slot {
                i += 1;
                if old[i - 1].id == c.id {
                    next.push(old[i - 1]);
                    continue;
                }
                orphans.push(i as u32 - 1);
            }
            unmatched.push(next.len() as u32);
            next.push(Track::new(c.id, c.slot));
        }
        if unmatched.is_empty() {
            return out_of_order;
        }
        orphans.extend(i as u32..old.len() as u32);
        if orphans.is_empty() {
            return out_of_order;
        }
        // By id, then index: a total order, which the device replica follows too.
        unmatched.sort_unstable_by_key(|&k| (next[k as usize].id, k));
        orphans.sort_unstable_by_key(|&k| (old[k as usize].id, k));
        let mut o = orphans.iter().peekable();
        for &k in unmatched.iter() {
            let id = next[k as usize].id;
            while o.next_if(|&&x| old[x as usize].id < id).is_some() {}
            if let Some(&&x) = o.peek()
                && old[x as usize].id == id
            {
                let slot = next[k as usize].slot;
                moved.push((old[x as usize].slot, id, slot));
                next[k as usize] = Track { slot, ..old[x as usize] };
                o.next();
            }
        }
        out_of_order
    }

    /// Applies the acknowledgements that arrived to `tracks` (this tick's, by ascending
    /// slot) and the own object's: each state of an acknowledged flight becomes its
    /// object's baseline if newer; flights acknowledged, or too old to be baselines or
    /// to be acknowledged, are dropped.
    fn apply_acks(&mut self, now: u64, tracks: &mut [Track]) {
        let acks = self.acks.take();
        let floor = now.saturating_sub(MAX_BACK - 1);
        // Each flight once, in order, back to the back if it stays: no allocation.
        for _ in 0..self.flights.len() {
            let Some(mut f) = self.flights.pop_front() else { break };
            let acked = acks.is_some_and(|a| a.contains(f.sequence));
            if acked {
                self.heard = self.heard.max(f.tick + 1);
                for &(slot, id, pos) in &f.states {
                    let track = match &mut self.own {
                        Some(t) if t.id == id => Some(t),
                        _ => tracks.binary_search_by_key(&slot, |t| t.slot).ok().map(|k| &mut tracks[k]),
                    };
                    // Not found: an object that left the view.
                    if let Some(t) = track.filter(|t| t.id == id) {
                        t.acknowledge(f.tick, pos);
                    }
                }
            }
            let unackable = acks.is_some_and(|a| a.newest().saturating_sub(f.sequence) > ACK_BITS);
            if acked || unackable || f.tick < floor {
                f.states.clear();
                self.spare.push(f);
            } else {
                self.flights.push_back(f);
            }
        }
        // A baseline the next record could not name any more is no baseline: `acked`
        // reads such a track's as none (and the next acknowledgement replaces it).
    }
}

/// Whether a record is relative to a state the client acknowledged.
pub(crate) fn is_relative(r: &DeltaRecord) -> bool {
    !matches!(r.state, myriad_protocol::RecordState::Absolute { .. })
}

#[cfg(test)]
#[path = "replica_tests.rs"]
mod tests;
