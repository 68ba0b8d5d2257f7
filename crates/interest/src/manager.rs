//! Per-player update building and sealing, parallel over players: each subscriber's
//! [`Replica`] decides what its client is sent.

use std::borrow::BorrowMut;
use std::cell::RefCell;

use myriad_protocol::{AckField, BodyLengthError, DatagramBatch, QuantPos, Sealer, frame_delta_body};
use rayon::prelude::*;
use thiserror::Error;

use crate::config::{InterestConfig, TickInfo};
use crate::replica::{Candidate, Packing, Replica, ReplicaReport, ReplicaScratch, Sealed, seal};
use crate::source::{AoiLists, ObjectSource};

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
    /// Slot of the player's own object, in every datagram (skipped if invalid).
    pub object: u32,
    /// Centre of the player's area of interest; the origin of its updates.
    pub centre: [f32; 3],
    /// Seals this player's datagrams (the server half of its session).
    pub sealer: Sealer,
    /// What the player's client holds and what it is owed.
    replica: Replica,
    /// This tick's sealed datagrams.
    datagrams: DatagramBatch,
    /// What the last build did for this player.
    report: SubscriberReport,
}

impl Subscriber {
    /// A subscriber whose client holds nothing yet.
    pub fn new(object: u32, centre: [f32; 3], sealer: Sealer) -> Self {
        Self {
            object,
            centre,
            sealer,
            replica: Replica::default(),
            datagrams: DatagramBatch::new(),
            report: SubscriberReport::default(),
        }
    }

    /// Notes the client's acknowledgement of the datagrams it opened (from its actions
    /// and keep-alives); the next build sends relative to what it names.
    pub fn acknowledge(&mut self, acks: AckField) {
        self.replica.acknowledge(acks);
    }

    /// The sealed datagrams of the last [`InterestManager::build`], ready to send.
    pub fn datagrams(&self) -> &DatagramBatch {
        &self.datagrams
    }

    /// What the last build did for this player.
    pub fn report(&self) -> SubscriberReport {
        self.report
    }

    /// Takes the acknowledgements that arrived since the last build, for a replica kept
    /// elsewhere (the device's): this subscriber's own replica then never sees them.
    pub fn take_acks(&mut self) -> Option<AckField> {
        self.replica.take_acks()
    }

    /// Finishes a build whose records a replica kept elsewhere chose and packed (the
    /// device's, which follows [`Replica`]'s rules and `pack_deltas`'): frames and seals
    /// `bodies` (delta update bodies, in order) and takes the report of the build
    /// (`chose`: what the choosing counted; `packing`: what the packing did; `own`:
    /// whether the player's own object was in every datagram). Returns what sealing did,
    /// for that replica to commit, or the error of a body no datagram can carry (the
    /// player then gets nothing this tick).
    pub fn seal_packed<'b>(
        &mut self,
        bodies: impl IntoIterator<Item = &'b [u8]>,
        own: bool,
        packing: Packing,
        chose: ReplicaReport,
    ) -> Result<Sealed, BodyLengthError> {
        self.datagrams.clear();
        for body in bodies {
            if let Err(e) = frame_delta_body(body, &mut self.datagrams) {
                self.clear_datagrams();
                return Err(e);
            }
        }
        let done = seal(packing.packed, &mut self.sealer, &mut self.datagrams);
        let mut report = chose;
        done.count(&mut report, packing);
        self.take_report(own, done.sealed.as_ref().map(|_| report).map_err(|_| ()), 0);
        Ok(done)
    }

    /// Records the report of a build (`own`: whether the player's own object was in
    /// every datagram; `skipped`: slots of its list skipped).
    fn take_report(&mut self, own: bool, built: Result<ReplicaReport, ()>, skipped: usize) {
        let mut report = SubscriberReport { skipped, ..SubscriberReport::default() };
        match built {
            Ok(r) => {
                report.in_view = r.in_view;
                report.packed = r.packed;
                report.deferred = r.deferred;
                report.starving = r.starving;
                report.relative = r.relative;
                report.records = r.packed + usize::from(own) * self.datagrams.len();
            }
            Err(()) => {
                self.datagrams.clear();
                report.seal_failed = true;
            }
        }
        report.datagrams = self.datagrams.len();
        report.bytes = self.datagrams.total_bytes();
        self.report = report;
    }

    /// Drops the datagrams of the last build: a tick that could not serve this player
    /// sends it nothing rather than the last tick's datagrams again. What those
    /// datagrams carried stays in flight in the replica, so nothing is taken as received.
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
    /// Records sent (own included, once per datagram).
    pub records: usize,
    /// Records of other objects packed (own excluded), counted before sealing.
    pub packed: usize,
    /// Objects due that waited for a later tick (the budget or the datagrams were spent).
    pub deferred: usize,
    /// Objects sent over the budget because they had waited the longest allowed.
    pub starving: usize,
    /// Records sent relative to a state the client acknowledged (own included).
    pub relative: usize,
    /// Datagrams produced.
    pub datagrams: usize,
    /// Bytes produced, sealed.
    pub bytes: usize,
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
    /// Records sent relative to an acknowledged state.
    pub relative: usize,
    /// Datagrams produced.
    pub datagrams: usize,
    /// Bytes produced.
    pub bytes: usize,
    /// Objects due that waited for a later tick.
    pub deferred: usize,
    /// Objects sent over a budget because they were starving.
    pub starving: usize,
    /// Invalid slots skipped.
    pub skipped: usize,
    /// Subscribers whose sealing failed.
    pub seal_failures: usize,
}

impl TickReport {
    /// This report with one more subscriber's counts.
    pub fn with(mut self, s: &SubscriberReport) -> Self {
        self.subscribers += 1;
        self.records += s.records;
        self.relative += s.relative;
        self.datagrams += s.datagrams;
        self.bytes += s.bytes;
        self.deferred += s.deferred;
        self.starving += s.starving;
        self.skipped += s.skipped;
        self.seal_failures += usize::from(s.seal_failed);
        self
    }

    /// The sums of two reports (of two parts of the subscribers, built apart).
    pub fn merge(mut self, o: Self) -> Self {
        self.subscribers += o.subscribers;
        self.records += o.records;
        self.relative += o.relative;
        self.datagrams += o.datagrams;
        self.bytes += o.bytes;
        self.deferred += o.deferred;
        self.starving += o.starving;
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
    /// A list put in ascending order, when it came otherwise.
    sorted: Vec<u32>,
    replica: ReplicaScratch,
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
                acc.with(&s.report)
            })
            .reduce(TickReport::default, TickReport::merge))
    }
}

/// How many items ahead the gather loop prefetches: enough to cover a memory latency
/// with the work of a few candidates, few enough not to flood the CPU's fill buffers.
const AHEAD: usize = 8;

fn build_one<O: ObjectSource>(
    config: &InterestConfig,
    tick: TickInfo,
    objects: &O,
    list: Option<&[u32]>,
    sub: &mut Subscriber,
    scratch: &mut Scratch,
) {
    let Scratch { cands, sorted, replica } = scratch;
    cands.clear();
    let mut skipped = usize::from(list.is_none());
    let own = objects.get(sub.object).map(|(id, kind, p)| (id, kind, QuantPos::from_f32(p)));
    let c = sub.centre;
    let mut list = list.unwrap_or(&[]);
    // The replica follows a view by ascending slot (the physics backends' AOI lists
    // are); any other list is put in that order here, duplicates dropped.
    if !list.is_sorted_by(|a, b| a < b) {
        sorted.clear();
        sorted.extend_from_slice(list);
        sorted.sort_unstable();
        sorted.dedup();
        list = sorted;
    }
    for &slot in list.iter().take(AHEAD) {
        objects.prefetch(slot);
    }
    for (j, &slot) in list.iter().enumerate() {
        if let Some(&ahead) = list.get(j + AHEAD) {
            objects.prefetch(ahead);
        }
        match objects.get(slot) {
            Some((id, kind, p)) if own.is_none_or(|o| o.0 != id) => {
                let d = [p[0] - c[0], p[1] - c[1], p[2] - c[2]];
                let distance = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                cands.push(Candidate { slot, id, kind, pos: QuantPos::from_f32(p), distance });
            }
            Some(_) => {}
            None => skipped += 1,
        }
    }
    let origin = QuantPos::from_f32(sub.centre);
    let built = sub.replica.build(
        &config.replication,
        tick,
        origin,
        own,
        cands,
        config.max_datagrams.max(1),
        &mut sub.sealer,
        &mut sub.datagrams,
        replica,
    );
    sub.take_report(own.is_some(), built.map_err(|_| ()), skipped);
}
