//! Per-player update selection, packing and sealing, parallel over players.

use std::borrow::BorrowMut;
use std::cell::RefCell;

use myriad_protocol::update::record_len;
use myriad_protocol::{
    COMPACT_RECORD_LEN, DatagramBatch, Direction, EXTENDED_RECORD_LEN, MAX_BODY, MAX_DATAGRAM, MIN_DATAGRAM,
    PacketKind, QuantPos, SealLease, Sealer, ShapeKind, StateRecord, UPDATE_HEADER_LEN, UpdateHeader,
    pack_updates_pinned, peek_header,
};
use rayon::prelude::*;
use thiserror::Error;

use crate::config::{InterestConfig, TickInfo};
use crate::source::{AoiLists, ObjectSource};
use crate::stale::StaleTable;

/// Errors of [`InterestManager::build`]. Bad data inside a list (slots out of range,
/// offsets out of order) is skipped and counted instead, so one broken list cannot stop
/// the tick.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
pub enum InterestError {
    /// The AOI result has a different number of lists than there are subscribers.
    #[error("{lists} AOI lists for {subscribers} subscribers")]
    LengthMismatch {
        /// Lists in the AOI result.
        lists: usize,
        /// Subscribers passed.
        subscribers: usize,
    },
}

/// One player as interest management sees it. The server owns these, keeps them in the
/// same order as the AOI queries, and updates `object` and `centre` before each tick.
#[derive(Debug)]
pub struct Subscriber {
    /// Slot of the player's own object, always sent first (skipped if invalid).
    pub object: u32,
    /// Centre of the player's area of interest; the origin of its updates.
    pub centre: [f32; 3],
    /// Seals this player's datagrams (the server half of its session).
    pub sealer: Sealer,
    /// Where a selection made outside [`InterestManager::build`] (a device's) keeps this
    /// player's staleness: the tick of that selection and the player's index in it, which
    /// the next tick's selection reads it through. [`InterestManager::build`] clears it.
    pub selected: Option<(u64, u32)>,
    /// `(object id, staleness key)` of the objects in view, in no order, kept while the
    /// player is over budget.
    rotation: Vec<(u64, u64)>,
    /// The tick `rotation` was written at: it is read only by the next tick's build, so a
    /// player who missed a tick (or was served by a device selection) starts afresh, as
    /// the device selection does.
    rotation_tick: Option<u64>,
    /// This tick's sealed datagrams.
    datagrams: DatagramBatch,
    /// What the last build did for this player.
    report: SubscriberReport,
}

impl Subscriber {
    /// A subscriber with no rotation history.
    pub fn new(object: u32, centre: [f32; 3], sealer: Sealer) -> Self {
        Self {
            object,
            centre,
            sealer,
            selected: None,
            rotation: Vec::new(),
            rotation_tick: None,
            datagrams: DatagramBatch::new(),
            report: SubscriberReport::default(),
        }
    }

    /// The sealed datagrams of the last [`InterestManager::build`], ready to send.
    pub fn datagrams(&self) -> &DatagramBatch {
        &self.datagrams
    }

    /// What the last build did for this player.
    pub fn report(&self) -> SubscriberReport {
        self.report
    }

    /// Drops the datagrams of the last build: a tick that could not serve this player
    /// sends it nothing rather than the last tick's datagrams again.
    pub fn clear_datagrams(&mut self) {
        self.datagrams.clear();
        self.report = SubscriberReport::default();
    }
}

/// Counters of one subscriber's last build.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct SubscriberReport {
    /// Objects in view after dropping invalid and duplicate slots (own excluded).
    pub in_view: usize,
    /// Records sent (own included).
    pub records: usize,
    /// Records of other objects packed (own excluded), counted before sealing.
    pub packed: usize,
    /// Datagrams produced.
    pub datagrams: usize,
    /// Bytes produced, sealed.
    pub bytes: usize,
    /// Whether the view did not fit the budget and rotation was used.
    pub over_budget: bool,
    /// Invalid slots or broken list bounds that were skipped.
    pub skipped: usize,
    /// Whether sealing failed (sequence numbers exhausted): nothing was sent.
    pub seal_failed: bool,
}

/// Sums over all subscribers of one tick.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct TickReport {
    /// Subscribers processed.
    pub subscribers: usize,
    /// Records sent.
    pub records: usize,
    /// Datagrams produced.
    pub datagrams: usize,
    /// Bytes produced.
    pub bytes: usize,
    /// Subscribers over budget.
    pub over_budget: usize,
    /// Invalid slots skipped.
    pub skipped: usize,
    /// Subscribers whose sealing failed.
    pub seal_failures: usize,
}

impl TickReport {
    fn add(mut self, s: &SubscriberReport) -> Self {
        self.subscribers += 1;
        self.records += s.records;
        self.datagrams += s.datagrams;
        self.bytes += s.bytes;
        self.over_budget += usize::from(s.over_budget);
        self.skipped += s.skipped;
        self.seal_failures += usize::from(s.seal_failed);
        self
    }

    /// The sums of two reports (of two parts of the subscribers, built apart).
    pub fn merge(mut self, o: Self) -> Self {
        self.subscribers += o.subscribers;
        self.records += o.records;
        self.datagrams += o.datagrams;
        self.bytes += o.bytes;
        self.over_budget += o.over_budget;
        self.skipped += o.skipped;
        self.seal_failures += o.seal_failures;
        self
    }
}

/// Builds every player's updates for a tick.
#[derive(Debug, Clone, Default)]
pub struct InterestManager {
    config: InterestConfig,
}

/// Per-thread working memory, reused across subscribers and ticks.
#[derive(Default)]
struct Scratch {
    /// Candidates (own excluded), in list order.
    cands: Vec<Candidate>,
    /// The subscriber's stored keys, loaded for lookups; taking a key marks its id
    /// seen, which drops duplicate slots.
    stored: StaleTable,
    /// Indices into `cands`, for the partial selections.
    order: Vec<u32>,
    /// The records to pack, in priority order.
    records: Vec<StateRecord>,
}

/// An object in view. Its position is quantized only when it is sent (or when the
/// whole view might fit): an over-budget view sends a fraction of its candidates.
#[derive(Clone, Copy)]
struct Candidate {
    id: u64,
    kind: ShapeKind,
    pos: [f32; 3],
    dist2: f32,
    key: u64,
}

impl Candidate {
    #[inline]
    fn record(&self) -> StateRecord {
        StateRecord { id: self.id, kind: self.kind, pos: QuantPos::from_f32(self.pos) }
    }
}

thread_local! {
    static SCRATCH: RefCell<Scratch> = RefCell::new(Scratch::default());
}

impl InterestManager {
    /// A manager with `config`.
    pub fn new(config: InterestConfig) -> Self {
        Self { config }
    }

    /// The configuration.
    pub fn config(&self) -> &InterestConfig {
        &self.config
    }

    /// Builds and seals this tick's updates for every subscriber; subscriber `i` sees
    /// AOI list `i`. Afterwards each [`Subscriber::datagrams`] holds what to send to
    /// that player.
    pub fn build<O, S>(
        &self,
        tick: TickInfo,
        objects: &O,
        aoi: AoiLists<'_>,
        subscribers: &mut [S],
    ) -> Result<TickReport, InterestError>
    where
        O: ObjectSource,
        S: BorrowMut<Subscriber> + Send,
    {
        if aoi.len() != subscribers.len() {
            return Err(InterestError::LengthMismatch { lists: aoi.len(), subscribers: subscribers.len() });
        }
        let config = self.config;
        Ok(subscribers
            .par_iter_mut()
            .enumerate()
            .fold(TickReport::default, |acc, (i, s)| {
                let s = s.borrow_mut();
                SCRATCH.with_borrow_mut(|scratch| {
                    build_one(&config, tick, objects, aoi.get(i), s, scratch);
                });
                acc.add(&s.report)
            })
            .reduce(TickReport::default, TickReport::merge))
    }
}

impl InterestManager {
    /// Takes each subscriber's datagrams as selected, packed and sealed elsewhere (the
    /// device outbound of `myriad-server`, on `myriad-cuda`'s kernels, which apply
    /// [`build`](Self::build)'s rule and `pack_updates_pinned`'s packing, and seal under
    /// sequence numbers leased from the subscriber's sealer): `sealed(i)` gives subscriber
    /// `i`'s datagrams, `None` when there are none to trust, and `leases[i]` the lease
    /// they were sealed under (`None`: none could be taken, so the subscriber gets
    /// nothing and counts a seal failure, as when its own sealer runs out).
    ///
    /// Each datagram must be a state update of this subscriber's session with the
    /// lease's next number, of a length an update can have; then the lease's unused
    /// numbers go back to the sealer ([`Sealer::return_unused`]). A subscriber whose
    /// datagrams fail that check gets nothing this tick and counts one skipped, and its
    /// lease is dropped (its numbers may have been used). Staleness is kept by whoever
    /// selected, so the subscribers' own rotation state is dropped.
    ///
    /// On the calling thread: callers take shares of the subscribers on threads of their
    /// own.
    pub fn adopt_sealed<'b, S, F, B>(
        &self,
        sealed: F,
        subscribers: &mut [S],
        leases: &mut [Option<SealLease>],
    ) -> TickReport
    where
        S: BorrowMut<Subscriber>,
        F: Fn(usize) -> Option<Packed<B>>,
        B: IntoIterator<Item = &'b [u8]>,
    {
        subscribers.iter_mut().zip(leases.iter_mut()).enumerate().fold(TickReport::default(), |acc, (i, (s, lease))| {
            let sub = s.borrow_mut();
            sub.datagrams.clear();
            sub.rotation.clear();
            sub.rotation_tick = None;
            let mut report = SubscriberReport::default();
            match (lease.take(), sealed(i)) {
                (None, _) => report.seal_failed = true,
                (Some(_), None) => report.skipped = 1,
                (Some(lease), Some(p)) => {
                    report.in_view = p.in_view;
                    report.over_budget = p.over_budget;
                    if adopt(p.datagrams, &lease, &mut sub.datagrams) {
                        let used = sub.datagrams.len() as u64;
                        report.packed = p.packed;
                        report.records = p.packed + usize::from(p.pinned) * sub.datagrams.len();
                        report.datagrams = sub.datagrams.len();
                        report.bytes = sub.datagrams.total_bytes();
                        // The sealer has not moved since the lease (the outbound leased
                        // last); if it had, the numbers simply stay unused.
                        let _ = sub.sealer.return_unused(lease, used);
                    } else {
                        sub.datagrams.clear();
                        report.skipped = 1;
                    }
                }
            }
            sub.report = report;
            acc.add(&sub.report)
        })
    }
}

/// Copies `datagrams` into `out` if each is a state update sealed under `lease`'s next
/// number (at most its numbers) with a length an update can have; returns whether it
/// did.
fn adopt<'b>(datagrams: impl IntoIterator<Item = &'b [u8]>, lease: &SealLease, out: &mut DatagramBatch) -> bool {
    let mut numbers = lease.first_sequence()..lease.end_sequence();
    for d in datagrams {
        let ok = numbers.next().is_some_and(|number| {
            (MIN_DATAGRAM + UPDATE_HEADER_LEN..=MAX_DATAGRAM).contains(&d.len())
                && peek_header(d, Direction::ServerToClient).is_ok_and(|h| {
                    h.kind == PacketKind::StateUpdate && h.session_id == lease.session_id() && h.sequence == number
                })
        });
        if !ok {
            return false;
        }
        out.push(d);
    }
    true
}

/// One subscriber's sealed datagrams, made outside [`InterestManager::build`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Packed<B> {
    /// The sealed state update datagrams, in order.
    pub datagrams: B,
    /// Objects in view, own excluded.
    pub in_view: usize,
    /// Whether the view was over budget.
    pub over_budget: bool,
    /// Whether the subscriber's own object leads every datagram.
    pub pinned: bool,
    /// Records of other objects packed.
    pub packed: usize,
}

/// Whether `compact` compact and `extended` extended records fit `max_datagrams`
/// datagrams beside a pinned record of `pinned` bytes, whatever order they are packed in:
/// with compact records only, exactly; with extended ones, by a bound (a datagram that
/// closes wastes less than one extended record), so that the answer never depends on the
/// order of an AOI list (the device selection sees its lists unsorted).
fn fits_whatever_order(pinned: usize, compact: usize, extended: usize, max_datagrams: usize) -> bool {
    let area = MAX_BODY - UPDATE_HEADER_LEN - pinned;
    if extended == 0 {
        compact.div_ceil(area / COMPACT_RECORD_LEN) <= max_datagrams
    } else {
        compact * COMPACT_RECORD_LEN + extended * EXTENDED_RECORD_LEN
            <= max_datagrams * (area - (EXTENDED_RECORD_LEN - 1))
    }
}

/// How many items ahead the loops prefetch: enough to cover a memory latency with the
/// work of a few candidates, few enough not to flood the CPU's fill buffers.
const AHEAD: usize = 8;

fn build_one<O: ObjectSource>(
    config: &InterestConfig,
    tick: TickInfo,
    objects: &O,
    list: Option<&[u32]>,
    sub: &mut Subscriber,
    scratch: &mut Scratch,
) {
    let Scratch { cands, stored, order, records } = scratch;
    sub.selected = None;
    cands.clear();
    records.clear();
    let mut report = SubscriberReport { skipped: usize::from(list.is_none()), ..SubscriberReport::default() };
    let origin = QuantPos::from_f32(sub.centre);
    if sub.rotation_tick.is_none_or(|t| t.checked_add(1) != Some(tick.tick)) {
        sub.rotation.clear();
    }

    // 1. Gather.
    let own = own_record(objects, sub);
    let c = sub.centre;
    let list = list.unwrap_or(&[]);
    for &slot in list.iter().take(AHEAD) {
        objects.prefetch(slot);
    }
    for (j, &slot) in list.iter().enumerate() {
        if let Some(&ahead) = list.get(j + AHEAD) {
            objects.prefetch(ahead);
        }
        match objects.get(slot) {
            Some((id, kind, p)) if own.is_none_or(|o| o.id != id) => {
                let d = [p[0] - c[0], p[1] - c[1], p[2] - c[2]];
                cands.push(Candidate { id, kind, pos: p, dist2: d[0] * d[0] + d[1] * d[1] + d[2] * d[2], key: 0 });
            }
            Some(_) => {}
            None => report.skipped += 1,
        }
    }
    let id_base = own.iter().map(|o| o.id).chain(cands.iter().map(|c| c.id)).min().unwrap_or(0);
    let size = |r: &StateRecord| record_len(r, id_base, origin);
    let own_size = own.as_ref().map_or(0, size);

    // 2. Everything fits? (Duplicates, if any, only make this estimate conservative.)
    // More candidates than compact records fit cannot fit with extended ones either
    // (`fits_whatever_order` says no to both), so such a view is not quantized here.
    let max_datagrams = config.max_datagrams.max(1);
    let compact_room = max_datagrams * ((MAX_BODY - UPDATE_HEADER_LEN - own_size) / COMPACT_RECORD_LEN);
    let fits = cands.len() <= compact_room && {
        records.extend(cands.iter().map(Candidate::record));
        let extended = records.iter().filter(|r| size(r) != COMPACT_RECORD_LEN).count();
        fits_whatever_order(own_size, records.len() - extended, extended, max_datagrams)
    };
    if fits {
        report.in_view = cands.len();
        sub.rotation.clear();
    } else {
        records.clear();
        report.over_budget = true;
        // 3a. Staleness keys. Objects absent from the stored list entered the view
        // this tick (key = now), unless there is no stored list: then everything was
        // sent last tick, or nothing ever was, and all share the key `now - 1`.
        let fresh_key = if sub.rotation.is_empty() { tick.tick.saturating_sub(1) } else { tick.tick };
        stored.reset(sub.rotation.len() + cands.len());
        for &(id, key) in &sub.rotation {
            stored.insert(id, key);
        }
        order.clear();
        for (i, c) in cands.iter_mut().enumerate() {
            if let Some(key) = stored.take(c.id, fresh_key) {
                c.key = key;
                order.push(i as u32);
            }
        }
        report.in_view = order.len();
        // 3b. The K nearest, by (distance, id): a total order, so the choice and the
        // order of the records are unique (the device selection makes the same ones).
        let nearer = |a: &u32, b: &u32| {
            let (a, b) = (&cands[*a as usize], &cands[*b as usize]);
            a.dist2.total_cmp(&b.dist2).then(a.id.cmp(&b.id))
        };
        let k = config.near_slots().min(order.len());
        if k < order.len() {
            order.select_nth_unstable_by(k, nearer);
        }
        let (near, rest) = order.split_at_mut(k);
        near.sort_unstable_by(nearer);
        // 3c. The stalest of the rest, by (key, id).
        let r = config.rotation_slots().min(rest.len());
        let stalest = |a: &u32, b: &u32| {
            let (a, b) = (&cands[*a as usize], &cands[*b as usize]);
            (a.key, a.id).cmp(&(b.key, b.id))
        };
        if r < rest.len() {
            rest.select_nth_unstable_by(r, stalest);
        }
        // Sorted, so that what an extended record pushes out is the least urgent.
        rest[..r].sort_unstable_by(stalest);
        records.extend(order[..k + r].iter().map(|&i| cands[i as usize].record()));
    }

    let packed = pack_and_seal(config, tick, own, records, sub, &mut report);
    if report.over_budget {
        // Stamp what was sent.
        for &i in order.iter().take(packed) {
            cands[i as usize].key = tick.tick;
        }
        sub.rotation.clear();
        sub.rotation.extend(order.iter().map(|&i| {
            let c = &cands[i as usize];
            (c.id, c.key)
        }));
    }
    sub.rotation_tick = Some(tick.tick);
    sub.report = report;
}

/// The subscriber's own object as a record, if its slot is valid.
fn own_record<O: ObjectSource>(objects: &O, sub: &Subscriber) -> Option<StateRecord> {
    objects.get(sub.object).map(|(id, kind, p)| StateRecord { id, kind, pos: QuantPos::from_f32(p) })
}

/// Packs `records` after `own` into the subscriber's datagrams and seals them; fills the
/// report's counts and returns how many of `records` (a prefix) were packed.
fn pack_and_seal(
    config: &InterestConfig,
    tick: TickInfo,
    own: Option<StateRecord>,
    records: &[StateRecord],
    sub: &mut Subscriber,
    report: &mut SubscriberReport,
) -> usize {
    let origin = QuantPos::from_f32(sub.centre);
    let header = UpdateHeader { tick: tick.tick, dilation_permille: tick.dilation_permille, origin };
    sub.datagrams.clear();
    // The own object first in every datagram.
    let packed = pack_updates_pinned(&header, own.as_ref(), records, config.max_datagrams.max(1), &mut sub.datagrams);
    report.packed = packed;
    report.records = packed + usize::from(own.is_some()) * sub.datagrams.len();
    seal(sub, report);
    packed
}

/// Seals the subscriber's datagrams and counts them in the report (nothing is sent if
/// sealing fails).
fn seal(sub: &mut Subscriber, report: &mut SubscriberReport) {
    if sub.sealer.seal_batch(&mut sub.datagrams).is_err() {
        sub.datagrams.clear();
        report.seal_failed = true;
        report.records = 0;
    }
    report.datagrams = sub.datagrams.len();
    report.bytes = sub.datagrams.total_bytes();
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Datagrams first-fit packing in the given order needs (each datagram holding up to
    /// `area` bytes of records).
    fn greedy(area: usize, sizes: &[usize]) -> usize {
        let (mut datagrams, mut used) = (0, area);
        for &size in sizes {
            if used + size > area {
                datagrams += 1;
                used = 0;
            }
            used += size;
        }
        datagrams
    }

    #[test]
    fn what_fits_whatever_order_fits_in_every_order() {
        let mut x = 0x2545_f491_4f6c_dd1du64;
        for pinned in [0, COMPACT_RECORD_LEN, EXTENDED_RECORD_LEN] {
            let area = MAX_BODY - UPDATE_HEADER_LEN - pinned;
            for max in 1..4 {
                for extended in 0..60 {
                    for compact in (0..400).step_by(7) {
                        if !fits_whatever_order(pinned, compact, extended, max) {
                            continue;
                        }
                        let mut sizes = vec![COMPACT_RECORD_LEN; compact];
                        sizes.extend(std::iter::repeat_n(EXTENDED_RECORD_LEN, extended));
                        for _ in 0..4 {
                            // A random order (Fisher–Yates with xorshift).
                            for i in (1..sizes.len()).rev() {
                                x ^= x << 13;
                                x ^= x >> 7;
                                x ^= x << 17;
                                sizes.swap(i, (x % (i as u64 + 1)) as usize);
                            }
                            assert!(greedy(area, &sizes) <= max, "{compact} + {extended} in {max}");
                        }
                    }
                }
            }
        }
        // Exact with compact records: 112 beside a compact own object, not 113.
        assert!(fits_whatever_order(COMPACT_RECORD_LEN, 224, 0, 2));
        assert!(!fits_whatever_order(COMPACT_RECORD_LEN, 225, 0, 2));
    }
}
