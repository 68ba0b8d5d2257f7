//! Building what each player is sent: the AOI query, interest selection, packing and
//! sealing, behind one trait.
//!
//! [`Outbound::build`] gets the physics backend, the world after the step and one
//! [`Recipient`] per active player, and leaves each recipient's sealed datagrams in its
//! [`Subscriber`]. It hands every recipient to a [`Ready`] once, as soon as the
//! recipient's datagrams are final: the tick sends them from there, on several lanes
//! (sockets) at once, so an implementation that builds in chunks overlaps the sending of
//! one chunk with the building of the next.
//!
//! Two implementations, which send the same bytes:
//! - [`HostOutbound`] (`host.rs`): the backend answers the AOI boxes (on the device for
//!   `cuda`), the [`InterestManager`](myriad_interest::InterestManager) builds protocol
//!   version 3's delta updates through each player's replica and seals them in parallel
//!   over players;
//! - [`DeviceOutbound`] (`device.rs`, a CUDA backend's, the default there): every
//!   player's replica lives on the device, which chooses the records; the host packs and
//!   seals them.
//!
//! Either way every recipient is ready at the end.

mod chunks;
mod device;
mod host;

use std::borrow::{Borrow, BorrowMut};
use std::net::SocketAddr;
use std::ops::AddAssign;
use std::time::Duration;

use myriad_core::{Aabb, Vec3, World};
use myriad_cuda::replica::DeviceReplicas;
use myriad_interest::{Subscriber, TickInfo, TickReport};
use myriad_physics::Backend;
use rayon::prelude::*;

use crate::config::{OutboundKind, ServerConfig};
use crate::transport::lane_share;
pub use chunks::ChunkPlan;
pub use device::DeviceOutbound;
pub use host::HostOutbound;

/// The outbound for the config's AOI size and what each player is sent
/// ([`ServerConfig::interest`]): on the device when the backend brought its
/// `replicas` (a CUDA backend) and the config does not ask for the host
/// ([`OutboundKind`]).
pub fn create(config: &ServerConfig, replicas: Option<DeviceReplicas>) -> Box<dyn Outbound> {
    match (config.outbound, replicas) {
        (OutboundKind::Auto, Some(replicas)) => {
            Box::new(DeviceOutbound::new(replicas, config.aoi_size, config.interest()))
        }
        _ => Box::new(HostOutbound::new(config.aoi_size, config.interest())),
    }
}

/// Points each recipient's view at its object and centre, and collects their AOI boxes
/// (half extents `half`) into `boxes`. In parallel: each recipient's subscriber is a
/// cache miss, 10,000 of them a tick.
fn aim(recipients: &mut [Recipient<'_>], half: Vec3, boxes: &mut Vec<Aabb>) {
    recipients
        .par_iter_mut()
        .map(|r| {
            r.view.object = r.object;
            r.view.centre = r.centre.to_array();
            Aabb::from_center_half(r.centre, half)
        })
        .collect_into_vec(boxes);
}

/// Leaves every recipient without datagrams this tick (a build that failed).
fn clear_all(recipients: &mut [Recipient<'_>]) {
    for r in recipients {
        r.view.clear_datagrams();
    }
}

/// One active player as the outbound sees it.
#[derive(Debug)]
pub struct Recipient<'a> {
    /// The player's session (a stable key for per-player state kept elsewhere).
    pub session_id: u64,
    /// Slot of the player's own object in the world's dynamics.
    pub object: u32,
    /// Centre of the player's area of interest (its object's position).
    pub centre: Vec3,
    /// Where the player's datagrams go (`None`: nowhere yet; nothing is sent).
    pub addr: Option<SocketAddr>,
    /// The player's interest state, sealer and this tick's datagrams.
    pub view: &'a mut Subscriber,
}

/// `v` emptied, as a vector of `U` in the same memory when the layouts agree (one type
/// under two lifetimes, or `Option<Recipient>` and `Recipient`): the standard library
/// collects a vector's `into_iter().map(..)` in place then. What lets a tick keep its
/// recipients' memory for the next, whose recipients borrow the sessions anew.
pub(crate) fn recycle<T, U>(mut v: Vec<T>) -> Vec<U> {
    v.clear();
    v.into_iter().map(|_| unreachable!("the vector was emptied")).collect()
}

impl Borrow<Subscriber> for Recipient<'_> {
    fn borrow(&self) -> &Subscriber {
        self.view
    }
}

impl BorrowMut<Subscriber> for Recipient<'_> {
    fn borrow_mut(&mut self) -> &mut Subscriber {
        self.view
    }
}

/// What one build did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct OutboundReport {
    /// State records packed, over all recipients.
    pub records: usize,
    /// Of those, records relative to a state the player acknowledged.
    pub relative: usize,
    /// Time of the backend's AOI query in ms (part of the `packets` stage), lists copied
    /// back to the host included.
    pub aoi_ms: f64,
    /// Recipients whose sealing failed (nothing is sent to them this tick).
    pub seal_failures: usize,
}

/// Sums the reports of builds that served parts of one tick's players.
impl AddAssign for OutboundReport {
    fn add_assign(&mut self, other: OutboundReport) {
        self.records += other.records;
        self.relative += other.relative;
        self.aoi_ms += other.aoi_ms;
        self.seal_failures += other.seal_failures;
    }
}

impl OutboundReport {
    /// Takes the interest manager's counts of a build (and counts its seal failures).
    fn add_interest(&mut self, r: &TickReport) {
        if r.seal_failures > 0 {
            metrics::counter!("myriad_seal_failures_total").increment(r.seal_failures as u64);
        }
        // What the players' budgets held back, and what went over them to keep the
        // staleness bound: an operator's signal that `send_budget_kbps` is too small.
        metrics::counter!("myriad_records_deferred_total").increment(r.deferred as u64);
        metrics::counter!("myriad_records_over_budget_total").increment(r.starving as u64);
        self.records = r.records;
        self.relative = r.relative;
        self.seal_failures = r.seal_failures;
    }
}

/// Builds every active player's sealed updates for a tick; see the module docs.
pub trait Outbound: Send {
    /// A human-readable description (for the start-up log).
    fn description(&self) -> String;

    /// Fills each recipient's datagrams for this tick and hands every recipient to
    /// `job.ready` exactly once, as soon as its datagrams are final. Errors are logged
    /// and counted by the implementation; recipients it could not serve get no datagrams
    /// (and are still handed over).
    fn build(&mut self, job: &mut Job<'_>, recipients: &mut [Recipient<'_>]) -> OutboundReport;

    /// Adds `took`, a span of the tick's host work timed elsewhere (the receive's
    /// phases), under `span` to the profile this outbound keeps, if any: the device
    /// outbound's, under `MYRIAD_CUDA_PROFILE=1`, prints it with its kernels.
    fn profile(&self, span: &'static str, took: Duration) {
        let _ = (span, took);
    }

    /// Forgets what that profile gathered so far: a measurement that starts after its
    /// warm-up (and, in `myriad bench`, after its players were made active) profiles only
    /// the ticks it measures.
    fn restart_profile(&self) {}
}

/// What an [`Outbound::build`] works with besides its recipients.
pub struct Job<'a> {
    /// The physics backend (the host outbound asks it the AOI query).
    pub backend: &'a mut dyn Backend,
    /// The world after the tick's step.
    pub world: &'a World,
    /// The tick being built.
    pub tick: TickInfo,
    /// Where recipients go once their datagrams are final.
    pub ready: &'a dyn Ready,
}

/// Where an [`Outbound`] hands recipients whose datagrams are final: on
/// [`lanes`](Ready::lanes) lanes, which threads use at once, each lane by one thread at a
/// time at best (the tick sends each lane's players on a socket of its own).
pub trait Ready: Sync {
    /// How many lanes there are (at least one).
    fn lanes(&self) -> usize;

    /// Hands over `players`, preferably on `lane` (any value: it is taken modulo the
    /// lanes); an implementation may send them on another lane that no thread is using.
    fn ready(&self, lane: usize, players: &[Recipient<'_>]);
}

/// Pieces each lane's share of a tick's recipients is cut into. One piece a lane left
/// the tick waiting on its slowest lane: at 50,000 players (16 lanes of 3,125 players)
/// handing over took 9.5 ms against the mean lane's 7.2 (lent H100, 2026-12-06), a lane
/// whose thread started late or lost its core finishing alone. Smaller pieces, each on
/// whichever lane is free, let the threads that finish early take the rest.
const PIECES_PER_LANE: usize = 4;

/// Hands `recipients` to `ready` in parallel, in contiguous pieces of a lane's share
/// ([`lane_share`]) over [`PIECES_PER_LANE`]: on one lane when they are too few to pay
/// for waking the others.
fn spread_over_lanes(recipients: &[Recipient<'_>], ready: &dyn Ready) {
    let lanes = ready.lanes();
    match lane_share(recipients.len(), lanes) {
        None => ready.ready(0, recipients),
        Some(share) => {
            let piece = share.div_ceil(PIECES_PER_LANE);
            recipients.par_chunks(piece).enumerate().for_each(|(k, players)| ready.ready(k % lanes, players));
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Mutex;

    use myriad_protocol::{Direction, Sealer};

    use super::*;

    /// A [`Ready`] of `lanes` lanes that notes each hand-over: its lane and sessions.
    struct Noted {
        lanes: usize,
        handed: Mutex<Vec<(usize, Vec<u64>)>>,
    }

    impl Ready for Noted {
        fn lanes(&self) -> usize {
            self.lanes
        }

        fn ready(&self, lane: usize, players: &[Recipient<'_>]) {
            self.handed.lock().unwrap().push((lane, players.iter().map(|r| r.session_id).collect()));
        }
    }

    fn subscribers(n: usize) -> Vec<Subscriber> {
        (0..n)
            .map(|i| Subscriber::new(i as u32, [0.0; 3], Sealer::new(i as u64, Direction::ServerToClient, &[7; 32])))
            .collect()
    }

    fn recipients(views: &mut [Subscriber]) -> Vec<Recipient<'_>> {
        views
            .iter_mut()
            .enumerate()
            .map(|(i, view)| Recipient { session_id: i as u64, object: i as u32, centre: Vec3::ZERO, addr: None, view })
            .collect()
    }

    #[test]
    fn every_recipient_is_handed_over_once_in_pieces_of_a_lanes_share() {
        let mut views = subscribers(1000);
        let all = recipients(&mut views);
        let ready = Noted { lanes: 4, handed: Mutex::default() };
        spread_over_lanes(&all, &ready);
        let mut handed = ready.handed.into_inner().unwrap();
        // Each lane's share of 250 in four pieces of 63 (the last piece shorter).
        assert_eq!(handed.len(), 16);
        assert!(handed.iter().all(|(lane, players)| *lane < 4 && players.len() <= 63));
        handed.sort_by_key(|(_, players)| players[0]);
        let order: Vec<u64> = handed.into_iter().flat_map(|(_, players)| players).collect();
        assert_eq!(order, (0..1000).collect::<Vec<u64>>(), "each once, each piece contiguous");

        // Too few to pay for waking the other lanes: one hand-over on lane 0.
        let few = Noted { lanes: 4, handed: Mutex::default() };
        spread_over_lanes(&all[..10], &few);
        assert_eq!(few.handed.into_inner().unwrap(), vec![(0, (0..10).collect::<Vec<u64>>())]);
    }

    #[test]
    fn recycled_recipients_keep_their_memory_from_tick_to_tick() {
        let mut store: Vec<Option<Recipient<'static>>> = Vec::with_capacity(64);
        let memory = store.as_ptr() as usize;
        for tick in 0..3 {
            let mut views = subscribers(40 + tick);
            let mut chosen: Vec<Option<Recipient<'_>>> = recycle(std::mem::take(&mut store));
            assert!(chosen.is_empty());
            chosen.extend(recipients(&mut views).into_iter().map(|r| (r.session_id % 3 != 0).then_some(r)));
            #[expect(clippy::filter_map_identity, reason = "`flatten` would not collect in place")]
            let gathered: Vec<Recipient<'_>> = chosen.into_iter().filter_map(|r| r).collect();
            assert_eq!(gathered.len(), (0..40 + tick).filter(|i| i % 3 != 0).count());
            assert_eq!(gathered.as_ptr() as usize, memory, "gathered in place");
            store = recycle(gathered);
            assert_eq!((store.as_ptr() as usize, store.capacity()), (memory, 64), "kept for the next tick");
        }
    }
}
