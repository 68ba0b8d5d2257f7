//! The device implementation of [`Outbound`]: the CUDA backend answers the AOI boxes,
//! selects each player's records by the host interest manager's rule and packs them into
//! state update bodies, all on the device (`myriad_cuda`'s interest updates), so only the
//! finished bodies come back, never the AOI lists; the host frames and seals them in
//! parallel over players ([`InterestManager::seal_packed`]). What was packed becomes the
//! staleness of the next tick on the device.
//!
//! The datagrams are byte for byte those of [`CpuOutbound`] for the same world, tick and
//! history (the GPU suite's `device_outbound` test). With another backend, a budget
//! larger than the device selection holds, or after a device error, it serves the tick
//! through a [`CpuOutbound`] (a device error is logged and counted as
//! `myriad_outbound_errors_total{reason="device_select"}`); players then start their
//! rotation afresh.

use std::time::Instant;

use myriad_core::{Aabb, Vec3, World};
use myriad_cuda::CudaBackend;
use myriad_cuda::backend::{InterestQuery, MAX_PACK_DATAGRAMS, MAX_SELECTED, NO_PREVIOUS};
use myriad_interest::{InterestConfig, InterestManager, Packed, TickInfo};
use myriad_physics::Backend;
use myriad_protocol::MAX_COMPACT_RECORDS;
use rayon::prelude::*;

use crate::outbound::{CpuOutbound, Outbound, OutboundReport, Recipient};

/// Interest selection and packing on the device, sealing on the host.
#[derive(Debug)]
pub struct DeviceOutbound {
    interest: InterestManager,
    half: Vec3,
    fallback: CpuOutbound,
    /// Each session's index in the last device selection (empty after a host tick).
    last: foldhash::HashMap<u64, u32>,
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
        }
    }

    /// Slots the device may choose for one player: a view that fits can hold
    /// `MAX_COMPACT_RECORDS` a datagram when the player has no own object.
    fn selection_room(&self) -> usize {
        self.interest.config().max_datagrams.max(1) * MAX_COMPACT_RECORDS
    }

    /// Whether the device selection and packing can hold this budget.
    fn budget_fits(&self) -> bool {
        self.selection_room() <= MAX_SELECTED && self.interest.config().max_datagrams <= MAX_PACK_DATAGRAMS
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
            format!("device interest selection and packing, host sealing ({max} datagrams a player at most)")
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
        // In parallel: each recipient and its previous index are cache misses. The views'
        // object and centre are the host interest manager's; the device takes them here.
        let (half, last) = (self.half, &self.last);
        let ((boxes, own), (centres, prev)): ((Vec<_>, Vec<_>), (Vec<_>, Vec<_>)) = recipients
            .par_iter()
            .map(|r| {
                let prev = last.get(&r.session_id).copied().unwrap_or(NO_PREVIOUS);
                ((Aabb::from_center_half(r.centre, half), r.object), (r.centre.to_array(), prev))
            })
            .unzip();
        let config = *self.interest.config();
        let query = InterestQuery {
            tick: tick.tick,
            dilation_permille: tick.dilation_permille,
            boxes: &boxes,
            own: &own,
            centres: &centres,
            prev: &prev,
            max_datagrams: config.max_datagrams.max(1) as u32,
            near_slots: config.near_slots() as u32,
            rotation_slots: config.rotation_slots() as u32,
            capacity: self.selection_room() as u32,
        };
        let t = Instant::now();
        let payloads = match cuda.interest_updates(world, &query) {
            Ok(p) => p,
            Err(e) => {
                tracing::error!(error = %e, "device interest updates failed; this tick is built on the host");
                metrics::counter!("myriad_outbound_errors_total", "reason" => "device_select").increment(1);
                return self.on_host(backend, world, tick, recipients);
            }
        };
        report.aoi_ms = t.elapsed().as_secs_f64() * 1e3;
        let packed = |i: usize| {
            payloads.get(i).map(|p| Packed {
                bodies: p.bodies(),
                in_view: p.in_view as usize,
                over_budget: p.over_budget,
                pinned: p.pinned,
                packed: p.packed as usize,
            })
        };
        let sealed = self.interest.seal_packed(packed, recipients);
        if sealed.skipped > 0 {
            // The device's counts disagreed with its bytes: those players get nothing
            // this tick (their staleness says they were sent; they are again soon).
            tracing::error!(players = sealed.skipped, "device update bodies refused");
            metrics::counter!("myriad_outbound_errors_total", "reason" => "device_bodies")
                .increment(sealed.skipped as u64);
        }
        report.add_interest(&sealed);
        self.last.clear();
        self.last.extend(recipients.iter().enumerate().map(|(i, r)| (r.session_id, i as u32)));
        report
    }
}
