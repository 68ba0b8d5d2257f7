//! A second configuration of protocol version 3's replication (deltas against
//! acknowledged states, the priority accumulator and a byte budget:
//! `myriad_interest::replica`) run beside the live server on the sampled players of the
//! quality probe, on the same world and ticks: another budget or near bound, or a
//! simulated lossy link, compared with what the live players got.
//!
//! Each sampled player gets a [`Replica`] on the server side and a client that opens
//! its datagrams, resolves their records against the states it holds
//! ([`Baselines`]), feeds a [`WorldMirror`] (the same interpolation as the live
//! mirrors) and acknowledges every datagram whose records all applied, before the next
//! tick, or over a simulated [`Link`] that loses and delays datagrams both ways (whole
//! ticks, seeded; `myriad relay` does the same to real datagrams between bots and a
//! server). The candidates are the objects whose
//! centre lies in the player's AOI cube, as the quality probe's truth; the AOI query of
//! the server may also hold objects whose box only overlaps the cube.
//!
//! *Staleness* here is the age of the information a client has ([`InformationAge`]): 0
//! while the state it holds is the object's current (quantized) position, else the time
//! since the object moved away from it. Deltas send an unchanged object only now and
//! then, so the age of its newest state says nothing of how current it is; the live
//! protocol is measured the same way beside it.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use myriad_client::{Interpolation, Quality, QualitySummary, WorldMirror};
use myriad_core::rng::Stream;
use myriad_interest::{Replica, ReplicaScratch, ReplicationConfig, TickInfo, replica::Candidate};
use myriad_protocol::{
    AckField, AckTracker, Baselines, DatagramBatch, DeltaUpdate, Direction, Opener, QuantPos, Sealer, ShapeKind,
};

/// A simulated network between a shadow's server and client: each datagram (and each
/// acknowledgement the client sends, one a tick) is lost with probability `loss`, else
/// arrives `delay_ms ± jitter_ms` later (uniform, rounded to whole ticks), so datagrams
/// also overtake each other.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize)]
pub(super) struct Link {
    /// Probability a datagram is lost, each way.
    pub loss: f64,
    /// One-way delay, ms.
    pub delay_ms: f64,
    /// Spread of the delay either side, ms.
    pub jitter_ms: f64,
}

impl Link {
    /// Ticks a datagram sent now takes, or `None` if it is lost.
    fn travel(&self, rng: &mut Stream, tick_rate_hz: f64) -> Option<u64> {
        if f64::from(rng.unit()) < self.loss {
            return None;
        }
        let ms = self.delay_ms + self.jitter_ms * (2.0 * f64::from(rng.unit()) - 1.0);
        Some((ms.max(0.0) * tick_rate_hz / 1000.0).round() as u64)
    }
}

/// One sampled player's version 3 link.
pub(super) struct Shadow {
    replica: Replica,
    sealer: Sealer,
    opener: Opener,
    baselines: Baselines,
    acks: AckTracker,
    mirror: WorldMirror,
    out: DatagramBatch,
    scratch: ReplicaScratch,
    candidates: Vec<Candidate>,
    link: Link,
    rng: Stream,
    tick_rate_hz: f64,
    /// Datagrams on their way to the client: (arrival tick, bytes).
    to_client: Vec<(u64, Vec<u8>)>,
    /// Acknowledgements on their way to the server: (arrival tick, field).
    to_server: Vec<(u64, AckField)>,
}

/// What the shadows did over the measured ticks.
#[derive(Debug, Clone, Default)]
pub(super) struct ShadowTotals {
    /// Bytes of sealed datagrams, over all sampled players.
    pub bytes: u64,
    /// Datagrams.
    pub datagrams: u64,
    /// Records of other objects sent.
    pub records: u64,
    /// Records relative to a baseline (own included).
    pub relative: u64,
    /// Records a client could not resolve (must stay 0).
    pub unresolved: u64,
    /// Player-ticks measured.
    pub player_ticks: u64,
}

impl ShadowTotals {
    /// Adds another player's totals.
    pub fn add(&mut self, o: &ShadowTotals) {
        self.bytes += o.bytes;
        self.datagrams += o.datagrams;
        self.records += o.records;
        self.relative += o.relative;
        self.unresolved += o.unresolved;
        self.player_ticks += o.player_ticks;
    }
}

impl Shadow {
    /// A link with fresh keys, its mirror on the probe's clock.
    pub(super) fn new(
        key_seed: u64,
        interpolation: Interpolation,
        tick_rate_hz: u16,
        base: Instant,
        link: Link,
    ) -> Self {
        let mut key = [0u8; 32];
        for (i, b) in key.iter_mut().enumerate() {
            *b = (key_seed as u8).wrapping_add(i as u8).wrapping_mul(31);
        }
        let mut mirror = WorldMirror::new(Duration::from_secs(2)).with_interpolation(interpolation);
        mirror.set_timing(tick_rate_hz, 1000, base);
        Self {
            replica: Replica::default(),
            sealer: Sealer::new(key_seed, Direction::ServerToClient, &key),
            opener: Opener::new(key_seed, Direction::ServerToClient, &key),
            baselines: Baselines::default(),
            acks: AckTracker::default(),
            mirror,
            out: DatagramBatch::new(),
            scratch: ReplicaScratch::default(),
            candidates: Vec::new(),
            link,
            rng: Stream::new(key_seed, 0x6c69_6e6b),
            tick_rate_hz: f64::from(tick_rate_hz.max(1)),
            to_client: Vec::new(),
            to_server: Vec::new(),
        }
    }

    /// The mirror the client draws from.
    pub(super) fn mirror(&self) -> &WorldMirror {
        &self.mirror
    }

    /// One tick: the server builds this player's datagrams from `own` and `view`
    /// (`(slot, id, kind, position, distance)`, by ascending slot), the client takes them at `now` and
    /// acknowledges. Adds to `totals` when `measuring`.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn tick(
        &mut self,
        config: &ReplicationConfig,
        max_datagrams: usize,
        tick: u64,
        centre: [f32; 3],
        own: (u64, ShapeKind, [f32; 3]),
        view: impl Iterator<Item = (u32, u64, ShapeKind, [f32; 3], f32)>,
        now: Instant,
        totals: Option<&mut ShadowTotals>,
    ) {
        self.candidates.clear();
        self.candidates.extend(view.map(|(slot, id, kind, p, distance)| Candidate {
            slot,
            id,
            kind,
            pos: QuantPos::from_f32(p),
            distance,
        }));
        // Acknowledgements that arrived by now, then this tick's build.
        let arrived = self.to_server.iter().filter(|a| a.0 <= tick).map(|a| a.1).reduce(AckField::merge);
        self.to_server.retain(|a| a.0 > tick);
        if let Some(f) = arrived {
            self.replica.acknowledge(f);
        }
        let report = self.replica.build(
            config,
            TickInfo { tick, dilation_permille: 1000 },
            QuantPos::from_f32(centre),
            Some((own.0, own.1, QuantPos::from_f32(own.2))),
            &self.candidates,
            max_datagrams,
            &mut self.sealer,
            &mut self.out,
            &mut self.scratch,
        );
        let Ok(report) = report else { return };
        for d in self.out.iter() {
            if let Some(ticks) = self.link.travel(&mut self.rng, self.tick_rate_hz) {
                self.to_client.push((tick + ticks, d.to_vec()));
            }
        }
        // What reaches the client by now, in order of arrival.
        self.to_client.sort_by_key(|d| d.0);
        let due = self.to_client.partition_point(|d| d.0 <= tick);
        let mut unresolved = 0;
        for (_, mut d) in self.to_client.drain(..due) {
            let Ok(opened) = self.opener.open_with(&mut d, |_, body| DeltaUpdate::decode_body(body)) else {
                unresolved += 1;
                continue;
            };
            let update = opened.message;
            let mut states = Vec::with_capacity(update.records.len());
            let failed = self.baselines.resolve_update(&update, &mut states);
            unresolved += failed as u64;
            if failed == 0 {
                self.acks.record(opened.header.sequence);
            }
            self.mirror.apply(update.header.tick, states, now);
        }
        // The client's next datagram carries its acknowledgement.
        if let Some(f) = self.acks.field()
            && let Some(ticks) = self.link.travel(&mut self.rng, self.tick_rate_hz)
        {
            self.to_server.push((tick + ticks, f));
        }
        if let Some(t) = totals {
            t.bytes += self.out.total_bytes() as u64;
            t.datagrams += self.out.len() as u64;
            t.records += report.packed as u64;
            t.relative += report.relative as u64;
            t.unresolved += unresolved;
            t.player_ticks += 1;
        }
    }
}

/// How long a client has held a state that is no longer the object's: per object, the
/// state it held when last looked at and the first tick that state was seen out of date.
/// Looked at every tick, so the age counts from the tick the object moved away from what
/// the client holds, not from when the client got that state.
#[derive(Debug, Default)]
pub(super) struct InformationAge {
    wrong_since: HashMap<u64, (u64, u64)>,
}

impl InformationAge {
    /// Looks at what `mirror` holds of `seen` objects at `tick`; records their ages into
    /// `quality` when `record` (the probe's sample ticks).
    pub(super) fn observe(
        &mut self,
        mirror: &WorldMirror,
        tick: u64,
        rate: f64,
        seen: impl Iterator<Item = (u64, f32, [f32; 3])>,
        quality: Option<&mut Quality>,
    ) {
        let mut quality = quality;
        for (id, distance, truth) in seen {
            let age = match mirror.get(id) {
                Some(o) if QuantPos::from_f32(o.position) == QuantPos::from_f32(truth) => {
                    self.wrong_since.remove(&id);
                    Some(0)
                }
                Some(o) => {
                    let e = self.wrong_since.entry(id).or_insert((o.tick, tick));
                    if e.0 != o.tick {
                        *e = (o.tick, tick);
                    }
                    Some(tick - e.1.min(tick))
                }
                None => None,
            };
            if let Some(q) = quality.as_deref_mut() {
                match age {
                    Some(age) => q.record_staleness(distance, Duration::from_secs_f64(age as f64 / rate)),
                    None => q.record_missing(distance),
                }
            }
        }
    }
}

/// The shadow's row of the report: its configuration beside the live server's.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub(super) struct ShadowRow {
    /// The budget, kbit/s.
    pub budget_kbps: f64,
    /// The near bound, ticks.
    pub near_bound_ticks: f32,
    /// The simulated link.
    pub link: Link,
    /// Bytes per sampled player and second, protocol 3.
    pub bytes_per_player_s: f64,
    /// Share of records relative to a baseline.
    pub relative_share: f64,
    /// Records a client could not resolve.
    pub unresolved: u64,
    /// Protocol 2's information age and error.
    pub v2: super::QualityRowFigures,
    /// The live protocol's information age (same samples), and error.
    pub live: super::QualityRowFigures,
}

impl ShadowRow {
    pub(super) fn new(
        config: &ReplicationConfig,
        link: Link,
        tick_rate_hz: f64,
        totals: &ShadowTotals,
        v2: QualitySummary,
        live: QualitySummary,
    ) -> Self {
        let players_s = totals.player_ticks as f64 / tick_rate_hz;
        ShadowRow {
            budget_kbps: f64::from(config.budget_bytes_per_tick) * tick_rate_hz * 8.0 / 1000.0,
            near_bound_ticks: config.near_bound_ticks,
            link,
            bytes_per_player_s: totals.bytes as f64 / players_s.max(f64::MIN_POSITIVE),
            relative_share: totals.relative as f64 / (totals.records + totals.datagrams).max(1) as f64,
            unresolved: totals.unresolved,
            v2: v2.into(),
            live: live.into(),
        }
    }
}
