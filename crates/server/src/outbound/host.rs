//! The host implementation of [`Outbound`]: the backend answers the AOI boxes, then the
//! [`InterestManager`] builds and seals each player's delta updates in parallel over
//! players; every recipient is ready at the end.

use std::time::Instant;

use myriad_core::{Aabb, Vec3, World};
use myriad_interest::{AoiLists, InterestConfig, InterestManager, ObjectSource};
use myriad_physics::AoiResults;
use myriad_protocol::ShapeKind as WireKind;

use super::{Job, Outbound, OutboundReport, Recipient, aim, clear_all, spread_over_lanes};
use crate::world::wire_kind;

/// The host implementation: backend AOI query, then [`InterestManager`].
#[derive(Debug)]
pub struct HostOutbound {
    /// The interest manager of every player.
    interest: InterestManager,
    /// Half extents of each player's AOI box.
    half: Vec3,
    boxes: Vec<Aabb>,
    aoi: AoiResults,
}

impl HostOutbound {
    /// AOI boxes of edge `aoi_size` centred on each player, each player sent what
    /// `config` allows.
    pub fn new(aoi_size: f32, config: InterestConfig) -> Self {
        HostOutbound {
            interest: InterestManager::new(config),
            half: Vec3::splat(aoi_size / 2.0),
            boxes: Vec::new(),
            aoi: AoiResults::default(),
        }
    }
}

/// Reads the world's dynamics for interest management.
struct WorldObjects<'a>(&'a World);

impl ObjectSource for WorldObjects<'_> {
    fn get(&self, slot: u32) -> Option<(u64, WireKind, [f32; 3])> {
        let d = &self.0.dynamics;
        let i = slot as usize;
        Some((u64::from(d.ids().get(i)?.0), wire_kind(*d.shapes().get(i)?), d.positions().get(i)?.to_array()))
    }
}

impl Outbound for HostOutbound {
    fn description(&self) -> String {
        let c = self.interest.config();
        format!(
            "host interest management, protocol 3 ({:.0} bytes a player a tick, {} datagrams at most)",
            c.replication.budget_bytes_per_tick, c.max_datagrams
        )
    }

    fn build(&mut self, job: &mut Job<'_>, recipients: &mut [Recipient<'_>]) -> OutboundReport {
        let report = self.build_all(job, recipients);
        spread_over_lanes(recipients, job.ready);
        report
    }
}

impl HostOutbound {
    /// [`Outbound::build`] without the hand-over: every recipient is ready at the end.
    fn build_all(&mut self, job: &mut Job<'_>, recipients: &mut [Recipient<'_>]) -> OutboundReport {
        let mut report = OutboundReport::default();
        if recipients.is_empty() {
            return report;
        }
        aim(recipients, self.half, &mut self.boxes);
        let t = Instant::now();
        let queried = job.backend.query_aoi(job.world, &self.boxes, &mut self.aoi);
        report.aoi_ms = t.elapsed().as_secs_f64() * 1e3;
        if let Err(e) = queried {
            tracing::error!(error = %e, "AOI query failed");
            metrics::counter!("myriad_outbound_errors_total", "reason" => "aoi_query").increment(1);
            clear_all(recipients);
            return report;
        }
        let lists = AoiLists { offsets: &self.aoi.offsets, objects: &self.aoi.objects };
        match self.interest.build(job.tick, &WorldObjects(job.world), lists, recipients) {
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
