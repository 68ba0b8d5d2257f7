//! The device implementation of [`Outbound`]: every player's replica lives on the CUDA
//! backend's device ([`DeviceReplicas`]), which answers the AOI boxes, chooses each
//! player's records and packs them into delta update bodies there; the host frames and
//! seals the bodies in parallel over players (`Subscriber::seal_packed`) and hands what
//! sealing did back to the device.
//! The bytes are the host outbound's, byte for byte (`tests/device_outbound.rs`).

use std::time::{Duration, Instant};

use myriad_core::{Aabb, Vec3};
use myriad_cuda::replica::{Choices, DeviceReplicas, RCommit, ReplicaPlayer, chose_report};
use myriad_interest::{InterestConfig, Packing, TickReport};
use rayon::prelude::*;

use super::{Job, Outbound, OutboundReport, Recipient, aim, clear_all, spread_over_lanes};

/// The device implementation: see the module docs.
#[derive(Debug)]
pub struct DeviceOutbound {
    replicas: DeviceReplicas,
    config: InterestConfig,
    /// Half extents of each player's AOI box.
    half: Vec3,
    boxes: Vec<Aabb>,
    players: Vec<ReplicaPlayer>,
    commits: Vec<RCommit>,
}

impl DeviceOutbound {
    /// AOI boxes of edge `aoi_size` centred on each player, each player sent what
    /// `config` allows, chosen by `replicas` (a CUDA backend's).
    pub fn new(replicas: DeviceReplicas, aoi_size: f32, config: InterestConfig) -> Self {
        DeviceOutbound {
            replicas,
            config,
            half: Vec3::splat(aoi_size / 2.0),
            boxes: Vec::new(),
            players: Vec::new(),
            commits: Vec::new(),
        }
    }

    /// [`Outbound::build`] without the hand-over.
    fn build_all(&mut self, job: &mut Job<'_>, recipients: &mut [Recipient<'_>]) -> OutboundReport {
        let mut report = OutboundReport::default();
        let setting_up = Instant::now();
        aim(recipients, self.half, &mut self.boxes);
        recipients
            .par_iter_mut()
            .map(|r| ReplicaPlayer {
                key: r.session_id,
                own: r.object,
                centre: r.centre.to_array(),
                acks: r.view.take_acks(),
            })
            .collect_into_vec(&mut self.players);
        self.replicas.profile_host("host: outbound set-up", setting_up);
        let mdg = self.config.max_datagrams.max(1);
        let t = Instant::now();
        let chose =
            self.replicas.select(job.world, &self.boxes, &self.players, &self.config.replication, mdg, job.tick);
        report.aoi_ms = t.elapsed().as_secs_f64() * 1e3;
        if let Err(e) = chose {
            tracing::error!(error = %e, "device replicas failed");
            metrics::counter!("myriad_outbound_errors_total", "reason" => "device_replica").increment(1);
            clear_all(recipients);
            return report;
        }
        let n = recipients.len();
        self.commits.clear();
        self.commits.resize(n, RCommit::default());
        let sealing = Instant::now();
        let choices = self.replicas.choices();
        // The tick's report is summed here, over each player just sealed (its
        // subscriber is in cache), rather than by a serial pass after.
        let (faults, tick_report) = recipients
            .par_iter_mut()
            .zip(self.commits.par_iter_mut())
            .enumerate()
            .fold(
                || (0usize, TickReport::default()),
                |(faults, report), (i, (r, commit))| {
                    let ok = seal_one(&choices, i, r, commit);
                    (faults + usize::from(!ok), report.with(&r.view.report()))
                },
            )
            .reduce(|| (0, TickReport::default()), |a, b| (a.0 + b.0, a.1.merge(b.1)));
        self.replicas.profile_host("host: frame and seal", sealing);
        if faults > 0 {
            tracing::error!(players = faults, "the device packed bodies no datagram can carry");
            metrics::counter!("myriad_outbound_errors_total", "reason" => "device_record").increment(faults as u64);
        }
        let committing = Instant::now();
        let committed = self.replicas.commit(&self.commits);
        self.replicas.profile_host("host: replica commit", committing);
        if let Err(e) = committed {
            tracing::error!(error = %e, "device replicas failed to commit");
            metrics::counter!("myriad_outbound_errors_total", "reason" => "device_replica").increment(1);
        }
        report.add_interest(&tick_report);
        report
    }
}

/// Frames and seals player `i`'s bodies into its subscriber, and notes in `commit` what
/// that did; false if the device packed a body no datagram can carry (the player then
/// gets nothing this tick, and the device is told nothing was sealed).
fn seal_one(choices: &Choices<'_>, i: usize, r: &mut Recipient<'_>, commit: &mut RCommit) -> bool {
    let info = choices.info(i);
    let packed = choices.packed(i);
    let packing =
        Packing { chosen: info.count as usize, packed: packed.packed as usize, relative: packed.relative as usize };
    let bodies = choices.bodies(i);
    let datagrams = bodies.len() as u32;
    match r.view.seal_packed(bodies, info.has_own_record != 0, packing, chose_report(info)) {
        Ok(done) => {
            *commit = RCommit {
                first: done.first,
                spent: done.spent,
                ok: u32::from(done.sealed.is_ok()),
                packed: packed.packed,
                datagrams,
            };
            true
        }
        Err(_) => {
            *commit = RCommit::default();
            false
        }
    }
}

impl Outbound for DeviceOutbound {
    fn description(&self) -> String {
        let c = &self.config;
        format!(
            "device replicas, protocol 3 ({:.0} bytes a player a tick, {} datagrams at most)",
            c.replication.budget_bytes_per_tick, c.max_datagrams
        )
    }

    fn profile(&self, span: &'static str, took: Duration) {
        self.replicas.profile_span(span, took);
    }

    fn restart_profile(&self) {
        self.replicas.restart_profile();
    }

    fn build(&mut self, job: &mut Job<'_>, recipients: &mut [Recipient<'_>]) -> OutboundReport {
        let report = self.build_all(job, recipients);
        let sending = Instant::now();
        spread_over_lanes(recipients, job.ready);
        self.replicas.profile_host("host: hand to the lanes (sending)", sending);
        report
    }
}
