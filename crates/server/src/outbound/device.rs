//! The device implementation of [`Outbound`]: every player's replica lives on the CUDA
//! backend's device ([`DeviceReplicas`]), which answers the AOI boxes, chooses each
//! player's records and packs them into delta update bodies there; the host frames and
//! seals the bodies in parallel over players (`Subscriber::seal_packed`), sends them, and
//! hands what sealing did back to the device. With the players in chunks
//! ([`ChunkPlan`], `MYRIAD_REPLICA_CHUNKS` and `MYRIAD_REPLICA_TAPER`), the host seals
//! and sends a chunk while the device chooses for the next.
//! The bytes are the host outbound's, byte for byte (`tests/device_outbound.rs`).

use std::time::{Duration, Instant};

use myriad_core::{Aabb, Vec3};
use myriad_cuda::replica::{Choices, DeviceReplicas, RCommit, ReplicaPlayer, chose_report};
use myriad_interest::{InterestConfig, Packing, TickReport};
use rayon::prelude::*;

use super::chunks::ChunkPlan;
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
    /// How a build's players are split into chunks ([`ChunkPlan::from_env`] unless
    /// told), and this build's sizes.
    plan: ChunkPlan,
    chunks: Vec<usize>,
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
            plan: ChunkPlan::from_env(),
            chunks: Vec::new(),
        }
    }

    /// The same, each build's players in chunks as `plan` says: the host seals and
    /// sends a chunk's datagrams while the device chooses for the next.
    pub fn with_chunks(mut self, plan: ChunkPlan) -> Self {
        self.plan = plan;
        self
    }
}

/// A build that failed on the device: `recipients` get nothing this tick.
fn failed(e: &myriad_physics::PhysicsError, recipients: &mut [Recipient<'_>]) {
    tracing::error!(error = %e, "device replicas failed");
    metrics::counter!("myriad_outbound_errors_total", "reason" => "device_replica").increment(1);
    clear_all(recipients);
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

    /// Each chunk's players sealed and handed to `job.ready` as soon as the device has
    /// chosen for them.
    fn build(&mut self, job: &mut Job<'_>, recipients: &mut [Recipient<'_>]) -> OutboundReport {
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
        let replication = &self.config.replication;
        self.plan.sizes(self.players.len(), &mut self.chunks);
        let chose =
            self.replicas.select(job.world, &self.boxes, &self.players, replication, mdg, job.tick, &self.chunks);
        // The AOI query and the device's choice: the time the tick waits for the device.
        let mut waited = t.elapsed();
        if let Err(e) = chose {
            report.aoi_ms = waited.as_secs_f64() * 1e3;
            failed(&e, recipients);
            return report;
        }
        let n = recipients.len();
        self.commits.clear();
        self.commits.resize(n, RCommit::default());
        let (mut sealing, mut sending) = (Duration::ZERO, Duration::ZERO);
        let mut tick_report = TickReport::default();
        let (mut faults, mut handled) = (0, 0);
        loop {
            let waiting = Instant::now();
            let ready = self.replicas.ready();
            waited += waiting.elapsed();
            let range = match ready {
                Ok(Some(range)) => range,
                Ok(None) => break,
                Err(e) => {
                    // The chunks sent are sent; the rest get nothing, and the device
                    // starts everyone afresh (nothing is committed).
                    report.aoi_ms = waited.as_secs_f64() * 1e3;
                    failed(&e, &mut recipients[handled..]);
                    report.add_interest(&tick_report);
                    return report;
                }
            };
            handled = range.end;
            let started = Instant::now();
            let choices = self.replicas.choices();
            let first = range.start;
            let chunk = &mut recipients[range.clone()];
            // The tick's report is summed here, over each player just sealed (its
            // subscriber is in cache), rather than by a serial pass after.
            let (f, r) = chunk
                .par_iter_mut()
                .zip(self.commits[range].par_iter_mut())
                .enumerate()
                .fold(
                    || (0usize, TickReport::default()),
                    |(faults, report), (i, (r, commit))| {
                        let ok = seal_one(&choices, first + i, r, commit);
                        (faults + usize::from(!ok), report.with(&r.view.report()))
                    },
                )
                .reduce(|| (0, TickReport::default()), |a, b| (a.0 + b.0, a.1.merge(b.1)));
            faults += f;
            tick_report = tick_report.merge(r);
            let handing = Instant::now();
            sealing += handing - started;
            spread_over_lanes(chunk, job.ready);
            sending += handing.elapsed();
        }
        report.aoi_ms = waited.as_secs_f64() * 1e3;
        if let Some(device_ms) = self.replicas.choice_ms() {
            let host_ms = (sealing + sending).as_secs_f64() * 1e3;
            self.plan.observe(host_ms, device_ms);
            tracing::debug!(host_ms, device_ms, chunks = ?self.chunks, ratio = self.plan.ratio(), "device outbound chunks");
        }
        self.replicas.profile_span("host: frame and seal", sealing);
        self.replicas.profile_span("host: hand to the lanes (sending)", sending);
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
