//! Building what each player is sent: the AOI query, interest selection, packing and
//! sealing, behind one trait.
//!
//! [`Outbound::build`] gets the physics backend, the world after the step and one
//! [`Recipient`] per active player, and leaves each recipient's sealed datagrams in its
//! [`Subscriber`]. It hands every recipient to a [`Ready`] once, as soon as the
//! recipient's datagrams are final: the tick sends them from there, on several lanes
//! (sockets) at once, so an implementation that builds in chunks overlaps the sending of
//! one chunk with the building of the next. [`CpuOutbound`] is the implementation on the
//! host: the backend answers the AOI boxes, [`InterestManager`] selects, packs and seals
//! in parallel over players, and every recipient is ready at the end.
//!
//! [`DeviceOutbound`](crate::device_outbound::DeviceOutbound) is the implementation on
//! the device: it receives the backend as `&mut dyn Backend` and reaches the CUDA
//! backend's device buffers through [`Backend::as_any_mut`]. Each recipient also brings
//! its sealer, from which it leases a key and a range of sequence numbers to seal on the
//! device without ever reusing a nonce.
//!
//! [`OutboundKind`] picks one: `auto` (the default) is the device outbound on a CUDA
//! backend and the host one otherwise.

use std::borrow::{Borrow, BorrowMut};
use std::net::SocketAddr;
use std::time::Instant;

use myriad_core::{Aabb, Vec3, World};
use myriad_interest::{AoiLists, InterestConfig, InterestManager, ObjectSource, Subscriber, TickInfo, TickReport};
use myriad_physics::{AoiResults, Backend};
use myriad_protocol::ShapeKind as WireKind;
use rayon::prelude::*;

use crate::world::wire_kind;

/// Which [`Outbound`] the tick uses (config key `outbound`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum OutboundKind {
    /// The device outbound on a CUDA backend, the host one otherwise.
    #[default]
    Auto,
    /// [`CpuOutbound`] whatever the backend.
    Host,
}

impl OutboundKind {
    /// The outbound for `backend` with the configuration's AOI size, datagram budget and
    /// (on the device) run length.
    pub fn create(self, backend: &mut dyn Backend, config: &crate::ServerConfig) -> Box<dyn Outbound> {
        let on_device = backend.as_any_mut().is::<myriad_cuda::CudaBackend>();
        let (aoi, max_datagrams) = (config.aoi_size, config.max_datagrams_per_player);
        match self {
            OutboundKind::Auto if on_device => {
                let device = crate::device_outbound::DeviceOutbound::new(aoi, max_datagrams);
                Box::new(match config.outbound_chunk_players {
                    0 => device,
                    players => device.with_chunk(players),
                })
            }
            _ => Box::new(CpuOutbound::new(aoi, max_datagrams)),
        }
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
    /// Time of the host's AOI query in ms (part of the `packets` stage); 0 for the device
    /// outbound, whose query runs on the device inside [`Self::device_wait_ms`].
    pub aoi_ms: f64,
    /// Time the tick waited for the device in ms (part of the `packets` stage): queueing
    /// the work, with the AOI query's count, then the first pool thread's waits for
    /// chunks. 0 for the host outbound.
    pub device_wait_ms: f64,
    /// Recipients whose sealing failed (nothing is sent to them this tick).
    pub seal_failures: usize,
}

/// Points each recipient's view at its object and centre, and collects their AOI boxes
/// (half extents `half`) into `boxes`.
fn aim(recipients: &mut [Recipient<'_>], half: Vec3, boxes: &mut Vec<Aabb>) {
    boxes.clear();
    for r in recipients.iter_mut() {
        r.view.object = r.object;
        r.view.centre = r.centre.to_array();
        boxes.push(Aabb::from_center_half(r.centre, half));
    }
}

/// Leaves every recipient without datagrams this tick (a build that failed).
pub(crate) fn clear_all(recipients: &mut [Recipient<'_>]) {
    for r in recipients {
        r.view.clear_datagrams();
    }
}

impl OutboundReport {
    /// Takes the interest manager's counts of a build (and counts its seal failures).
    pub(crate) fn add_interest(&mut self, r: &TickReport) {
        if r.seal_failures > 0 {
            metrics::counter!("myriad_seal_failures_total").increment(r.seal_failures as u64);
        }
        self.records = r.records;
        self.seal_failures = r.seal_failures;
    }
}

/// Builds every active player's sealed updates for a tick; see the module docs.
pub trait Outbound: Send {
    /// A human-readable description (for the start-up log).
    fn description(&self) -> String;

    /// Fills each recipient's datagrams for this tick and hands every recipient to
    /// `ready` exactly once, as soon as its datagrams are final. Errors are logged and
    /// counted by the implementation; recipients it could not serve get no datagrams (and
    /// are still handed over).
    fn build(
        &mut self,
        backend: &mut dyn Backend,
        world: &World,
        tick: TickInfo,
        recipients: &mut [Recipient<'_>],
        ready: &dyn Ready,
    ) -> OutboundReport;
}

/// Where an [`Outbound`] hands recipients whose datagrams are final: on
/// [`lanes`](Ready::lanes) lanes, which threads use at once, each lane by one thread at a
/// time at best (the tick sends each lane's players on a socket of its own).
pub trait Ready: Sync {
    /// How many lanes there are (at least one).
    fn lanes(&self) -> usize;

    /// Hands over `players` on `lane` (any value: it is taken modulo the lanes).
    fn ready(&self, lane: usize, players: &[Recipient<'_>]);
}

/// Hands `recipients` to `ready` in parallel, a contiguous share per lane (on one lane
/// when they are too few to pay for waking the others: a player has a datagram or two).
pub(crate) fn hand_over(recipients: &[Recipient<'_>], ready: &dyn Ready) {
    if recipients.len() < crate::transport::PARALLEL_SEND_MIN {
        ready.ready(0, recipients);
        return;
    }
    let share = recipients.len().div_ceil(ready.lanes().max(1)).max(1);
    recipients.par_chunks(share).enumerate().for_each(|(lane, players)| ready.ready(lane, players));
}

/// The host implementation: backend AOI query, then [`InterestManager`].
#[derive(Debug)]
pub struct CpuOutbound {
    interest: InterestManager,
    half: Vec3,
    boxes: Vec<Aabb>,
    aoi: AoiResults,
}

impl CpuOutbound {
    /// AOI boxes of edge `aoi_size` centred on each player, at most `max_datagrams`
    /// update datagrams per player and tick.
    pub fn new(aoi_size: f32, max_datagrams: usize) -> Self {
        CpuOutbound {
            interest: InterestManager::new(InterestConfig { max_datagrams, ..Default::default() }),
            half: Vec3::splat(aoi_size / 2.0),
            boxes: Vec::new(),
            aoi: AoiResults::default(),
        }
    }
}

/// Reads the world's dynamics for interest management.
pub(crate) struct WorldObjects<'a>(pub(crate) &'a World);

impl ObjectSource for WorldObjects<'_> {
    fn get(&self, slot: u32) -> Option<(u64, WireKind, [f32; 3])> {
        let d = &self.0.dynamics;
        let i = slot as usize;
        Some((u64::from(d.ids().get(i)?.0), wire_kind(*d.shapes().get(i)?), d.positions().get(i)?.to_array()))
    }
}

impl Outbound for CpuOutbound {
    fn description(&self) -> String {
        format!("host interest management ({} datagrams a player at most)", self.interest.config().max_datagrams)
    }

    fn build(
        &mut self,
        backend: &mut dyn Backend,
        world: &World,
        tick: TickInfo,
        recipients: &mut [Recipient<'_>],
        ready: &dyn Ready,
    ) -> OutboundReport {
        let report = self.build_all(backend, world, tick, recipients);
        hand_over(recipients, ready);
        report
    }
}

impl CpuOutbound {
    /// [`Outbound::build`] without the hand-over: every recipient is ready at the end.
    fn build_all(
        &mut self,
        backend: &mut dyn Backend,
        world: &World,
        tick: TickInfo,
        recipients: &mut [Recipient<'_>],
    ) -> OutboundReport {
        let mut report = OutboundReport::default();
        if recipients.is_empty() {
            return report;
        }
        aim(recipients, self.half, &mut self.boxes);
        let t = Instant::now();
        let queried = backend.query_aoi(world, &self.boxes, &mut self.aoi);
        report.aoi_ms = t.elapsed().as_secs_f64() * 1e3;
        if let Err(e) = queried {
            tracing::error!(error = %e, "AOI query failed");
            metrics::counter!("myriad_outbound_errors_total", "reason" => "aoi_query").increment(1);
            clear_all(recipients);
            return report;
        }
        let lists = AoiLists { offsets: &self.aoi.offsets, objects: &self.aoi.objects };
        match self.interest.build(tick, &WorldObjects(world), lists, recipients) {
            Ok(r) => report.add_interest(&r),
            Err(e) => {
                tracing::error!(error = %e, "interest management failed");
                metrics::counter!("myriad_outbound_errors_total", "reason" => "interest").increment(1);
                clear_all(recipients);
            }
        }
        report
    }
}
