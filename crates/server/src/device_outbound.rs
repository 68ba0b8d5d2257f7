//! The device implementation of [`Outbound`]: the CUDA backend answers the AOI boxes and
//! selects each player's records on the device (`myriad_cuda`'s interest selection, the
//! host interest manager's rule), so only the chosen slots come back, never the AOI
//! lists; the host packs and seals them in parallel over players
//! ([`InterestManager::pack_selected`]) and tells the device what it packed, which
//! becomes the staleness of the next tick.
//!
//! The payloads are byte for byte those of [`CpuOutbound`] for the same world, tick and
//! history (the GPU suite's `device_outbound` test). With another backend, a budget
//! larger than the device selection holds, or after a device error, it serves the tick
//! through a [`CpuOutbound`] (a device error is logged and counted as
//! `myriad_outbound_errors_total{reason="device_select"}`); players then start their
//! rotation afresh.

use std::time::Instant;

use myriad_core::{Aabb, Vec3, World};
use myriad_cuda::CudaBackend;
use myriad_cuda::backend::{InterestQuery, MAX_SELECTED, NO_PREVIOUS};
use myriad_interest::{InterestConfig, InterestManager, Selection, TickInfo};
use myriad_physics::Backend;
use myriad_protocol::MAX_COMPACT_RECORDS;

use crate::outbound::{CpuOutbound, Outbound, OutboundReport, Recipient, WorldObjects, aim};

/// Interest selection on the device, packing and sealing on the host.
#[derive(Debug)]
pub struct DeviceOutbound {
    interest: InterestManager,
    half: Vec3,
    fallback: CpuOutbound,
    /// Each session's index in the last device selection (empty after a host tick).
    last: foldhash::HashMap<u64, u32>,
    boxes: Vec<Aabb>,
    own: Vec<u32>,
    centres: Vec<[f32; 3]>,
    prev: Vec<u32>,
    packed: Vec<u32>,
}

impl DeviceOutbound {
    /// AOI boxes of edge `aoi_size` centred on each player, at most `max_datagrams`
    /// update datagrams per player and tick.
    pub fn new(aoi_size: f32, max_datagrams: usize) -> Self {
        DeviceOutbound {
            interest: InterestManager::new(InterestConfig { max_datagrams, ..Default::default() }),
            half: Vec3::splat(aoi_size / 2.0),
            fallback: CpuOutbound::new(aoi_size, max_datagrams),
            last: foldhash::HashMap::default(),
            boxes: Vec::new(),
            own: Vec::new(),
            centres: Vec::new(),
            prev: Vec::new(),
            packed: Vec::new(),
        }
    }

    /// Slots the device may choose for one player: a view that fits can hold
    /// `MAX_COMPACT_RECORDS` a datagram when the player has no own object.
    fn selection_room(&self) -> usize {
        self.interest.config().max_datagrams.max(1) * MAX_COMPACT_RECORDS
    }

    /// Whether the device selection can hold this budget.
    fn budget_fits(&self) -> bool {
        self.selection_room() <= MAX_SELECTED
    }

    /// Serves the tick on the host; the device's staleness is then out of date.
    fn on_host(
        &mut self,
        backend: &mut dyn Backend,
        world: &World,
        tick: TickInfo,
        recipients: &mut [Recipient<'_>],
    ) -> OutboundReport {
        self.last.clear();
        self.fallback.build(backend, world, tick, recipients)
    }
}

impl Outbound for DeviceOutbound {
    fn description(&self) -> String {
        let max = self.interest.config().max_datagrams;
        if self.budget_fits() {
            format!("device interest selection, host packing and sealing ({max} datagrams a player at most)")
        } else {
            format!(
                "host interest management: {max} datagrams a player is over the device selection's {MAX_SELECTED} records"
            )
        }
    }

    fn build(
        &mut self,
        backend: &mut dyn Backend,
        world: &World,
        tick: TickInfo,
        recipients: &mut [Recipient<'_>],
    ) -> OutboundReport {
        if !self.budget_fits() {
            return self.on_host(backend, world, tick, recipients);
        }
        let Some(cuda) = backend.as_any_mut().downcast_mut::<CudaBackend>() else {
            return self.on_host(backend, world, tick, recipients);
        };
        let mut report = OutboundReport::default();
        if recipients.is_empty() {
            self.last.clear();
            return report;
        }
        aim(recipients, self.half, &mut self.boxes);
        self.own.clear();
        self.centres.clear();
        self.prev.clear();
        for r in recipients.iter() {
            self.own.push(r.object);
            self.centres.push(r.centre.to_array());
            self.prev.push(self.last.get(&r.session_id).copied().unwrap_or(NO_PREVIOUS));
        }
        let config = *self.interest.config();
        let query = InterestQuery {
            tick: tick.tick,
            boxes: &self.boxes,
            own: &self.own,
            centres: &self.centres,
            prev: &self.prev,
            max_datagrams: config.max_datagrams.max(1) as u32,
            near_slots: config.near_slots() as u32,
            rotation_slots: config.rotation_slots() as u32,
            capacity: self.selection_room() as u32,
        };
        let t = Instant::now();
        let selections = match cuda.select_interest(world, &query) {
            Ok(s) => s,
            Err(e) => {
                tracing::error!(error = %e, "device interest selection failed; this tick is built on the host");
                metrics::counter!("myriad_outbound_errors_total", "reason" => "device_select").increment(1);
                return self.on_host(backend, world, tick, recipients);
            }
        };
        report.aoi_ms = t.elapsed().as_secs_f64() * 1e3;
        let chosen = |i: usize| {
            selections.get(i).map(|s| Selection {
                slots: s.slots,
                in_view: s.in_view as usize,
                over_budget: s.over_budget,
            })
        };
        report.add_interest(&self.interest.pack_selected(tick, &WorldObjects(world), chosen, recipients));
        self.packed.clear();
        self.packed.extend(recipients.iter().map(|r| r.view.report().packed as u32));
        self.last.clear();
        match cuda.stamp_interest(&self.packed) {
            Ok(()) => self.last.extend(recipients.iter().enumerate().map(|(i, r)| (r.session_id, i as u32))),
            Err(e) => {
                // The next tick then starts every player afresh.
                tracing::error!(error = %e, "marking the sent records on the device failed");
                metrics::counter!("myriad_outbound_errors_total", "reason" => "device_stamp").increment(1);
            }
        }
        report
    }
}
