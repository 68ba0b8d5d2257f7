//! The device implementation of [`Outbound`]: every player's replica lives on the CUDA
//! backend's device ([`DeviceReplicas`]), which answers the AOI boxes and chooses each
//! player's records there; the host packs and seals them in parallel over players
//! (`Subscriber::seal_chosen`) and hands what the datagrams took back to the device.
//! The bytes are the host outbound's, byte for byte (`tests/device_outbound.rs`).

use std::cell::RefCell;
use std::time::Instant;

use myriad_core::{Aabb, Vec3};
use myriad_cuda::replica::{Choices, DeviceReplicas, RCommit, ReplicaPlayer, chose_report, delta_record};
use myriad_interest::{InterestConfig, TickReport};
use myriad_protocol::{DeltaRecord, QuantPos, UpdateHeader};
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
    ends: Vec<u32>,
}

/// Per-thread memory of the packing: records and datagram ends.
#[derive(Default)]
struct Scratch {
    records: Vec<DeltaRecord>,
    ends: Vec<usize>,
}

thread_local! {
    static SCRATCH: RefCell<Scratch> = RefCell::new(Scratch::default());
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
            ends: Vec::new(),
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
            self.replicas.select(job.world, &self.boxes, &self.players, &self.config.replication, mdg, job.tick.tick);
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
        self.ends.clear();
        self.ends.resize(n * mdg, 0);
        let packing = Instant::now();
        let choices = self.replicas.choices();
        let tick = job.tick;
        // The tick's report is summed here, over each player just sealed (its
        // subscriber is in cache), rather than by a serial pass after.
        let (faults, tick_report) = recipients
            .par_iter_mut()
            .zip(self.commits.par_iter_mut())
            .zip(self.ends.par_chunks_mut(mdg))
            .enumerate()
            .fold(
                || (0usize, TickReport::default()),
                |(faults, report), (i, ((r, commit), ends))| {
                    let ok = SCRATCH.with_borrow_mut(|s| seal_one(&choices, i, tick, r, commit, ends, s));
                    (faults + usize::from(!ok), report.with(&r.view.report()))
                },
            )
            .reduce(|| (0, TickReport::default()), |a, b| (a.0 + b.0, a.1.merge(b.1)));
        self.replicas.profile_host("host: pack and seal", packing);
        if faults > 0 {
            tracing::error!(players = faults, "the device chose records no datagram can carry");
            metrics::counter!("myriad_outbound_errors_total", "reason" => "device_record").increment(faults as u64);
        }
        let committing = Instant::now();
        let committed = self.replicas.commit(&self.commits, &self.ends);
        self.replicas.profile_host("host: replica commit", committing);
        if let Err(e) = committed {
            tracing::error!(error = %e, "device replicas failed to commit");
            metrics::counter!("myriad_outbound_errors_total", "reason" => "device_replica").increment(1);
        }
        report.add_interest(&tick_report);
        report
    }
}

/// Packs and seals player `i`'s choices into its subscriber, and notes in `commit` and
/// `ends` what that took; false if the device chose a record that is not one (the player
/// then gets nothing this tick, and the device is told nothing was sealed).
fn seal_one(
    choices: &Choices<'_>,
    i: usize,
    tick: myriad_interest::TickInfo,
    r: &mut Recipient<'_>,
    commit: &mut RCommit,
    ends: &mut [u32],
    scratch: &mut Scratch,
) -> bool {
    let info = choices.info(i);
    scratch.records.clear();
    let mut faulty = false;
    for rec in choices.records(i) {
        match delta_record(rec) {
            Some(d) => scratch.records.push(d),
            None => faulty = true,
        }
    }
    let own = if info.has_own_record != 0 { delta_record(&info.own_record) } else { None };
    faulty |= info.has_own_record != 0 && own.is_none();
    if faulty {
        r.view.clear_datagrams();
        *commit = RCommit::default();
        return false;
    }
    let header = UpdateHeader {
        tick: tick.tick,
        dilation_permille: tick.dilation_permille,
        origin: QuantPos::from_f32(r.centre.to_array()),
    };
    let chose = chose_report(info);
    let done =
        r.view.seal_chosen(&header, own.as_ref(), &scratch.records, info.datagrams as usize, chose, &mut scratch.ends);
    *commit = RCommit {
        first: done.first,
        spent: done.spent,
        ok: u32::from(done.sealed.is_ok()),
        packed: done.packed as u32,
        datagrams: scratch.ends.len().min(ends.len()) as u32,
    };
    for (e, &end) in ends.iter_mut().zip(&scratch.ends) {
        *e = end as u32;
    }
    true
}

impl Outbound for DeviceOutbound {
    fn description(&self) -> String {
        let c = &self.config;
        format!(
            "device replicas, protocol 3 ({:.0} bytes a player a tick, {} datagrams at most)",
            c.replication.budget_bytes_per_tick, c.max_datagrams
        )
    }

    fn build(&mut self, job: &mut Job<'_>, recipients: &mut [Recipient<'_>]) -> OutboundReport {
        let report = self.build_all(job, recipients);
        let sending = Instant::now();
        spread_over_lanes(recipients, job.ready);
        self.replicas.profile_host("host: hand to the lanes (sending)", sending);
        report
    }
}
