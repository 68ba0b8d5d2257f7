//! What a player actually gets in the server tick: the staleness of the states its
//! client holds and the error of what the client draws, against the server's world in
//! the same process.
//!
//! # How
//!
//! A seeded sample of bots (at most [`QualityConfig::players`]) each keep a client
//! [`WorldMirror`], fed every update the bot opens ([`TickBench::tick_with`]). The bench
//! runs unpaced, so the mirrors live on the server's clock: the update of tick `T`
//! "arrives" at `T / tick rate` seconds (loopback, no delay), and the mirror's clock
//! estimate and render time follow from that as in a real client.
//!
//! Every [`QualityConfig::every`] ticks, after the tick (untimed, outside the server's
//! stages), the probe takes the *truth*: for each sampled player, the position of every
//! dynamic object whose centre lies in the player's AOI cube (the player's own object
//! left out). At once it records each object's *staleness*: the age of the newest state
//! the mirror holds of it, `(T − its tick) / rate` (an object of which the mirror holds
//! nothing counts as missing). The truth of tick `T` is then kept until the mirror's
//! render time reaches `T` (the render delay later), when the probe records each
//! object's *error*: the distance between the mirror's position at render tick `T`
//! (interpolated, extrapolated within the cap, or held: [`WorldMirror::sample`]) and the
//! true position at `T`. Both are split into objects within
//! [`NEAR`](myriad_client::quality::NEAR) units of the player
//! and the whole AOI. Memory is bounded: the sample's mirrors and at most a few ticks'
//! truths.
//!
//! Protocol version 3 sends an unchanged object only to confirm it now and then, so the
//! age of the newest state says little of how current a client is; the probe also
//! records each object's *information age* (`shadow.rs`'s [`InformationAge`]: 0 while the
//! client holds the object's current quantized position, else the time since the object
//! moved away from it), looked at every tick.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use myriad_client::{Interpolation, Quality, QualitySummary, WorldMirror};
use myriad_core::World;
use myriad_core::rng::Stream;
use myriad_interest::ReplicationConfig;
use myriad_protocol::{ShapeKind, StateRecord};
use myriad_server::tick_bench::TickBench;
use myriad_server::world::wire_kind;
use rayon::prelude::*;

use super::shadow::{InformationAge, Link, Shadow, ShadowRow, ShadowTotals};

/// What to sample.
#[derive(Debug, Clone, Copy)]
pub struct QualityConfig {
    /// Players sampled at most (0: none).
    pub players: usize,
    /// Ticks between two truths (at least 1).
    pub every: u64,
    /// Seed of the sample's choice.
    pub seed: u64,
    /// The server's AOI edge, world units.
    pub aoi_size: f32,
    /// The server's tick rate, Hz.
    pub tick_rate_hz: u16,
    /// The mirrors' render delay and extrapolation cap.
    pub interpolation: Interpolation,
    /// Also run a second configuration of protocol 3's replication beside the live one
    /// on the sampled players (`shadow.rs`), with this configuration, datagram cap and
    /// simulated link.
    pub shadow: Option<(ReplicationConfig, usize, Link)>,
}

/// A truth older than this many render delays without being compared (a mirror that
/// never got an update) is dropped.
const TRUTH_PATIENCE_TICKS: u64 = 60;

/// One sampled player.
struct Watched {
    entity: u64,
    mirror: WorldMirror,
    /// The information age of the live mirror.
    live_age: InformationAge,
    /// A second configuration beside the live one, and its mirror's information age.
    shadow: Option<(Shadow, InformationAge)>,
}

/// One object of a player's AOI at a truth's tick.
#[derive(Debug, Clone, Copy)]
struct Seen {
    /// Its slot in the world (what orders a view).
    slot: u32,
    id: u64,
    kind: ShapeKind,
    distance: f32,
    position: [f32; 3],
}

/// The truth of one tick: per sampled player, its AOI's objects (none once compared).
struct Truth {
    tick: u64,
    players: Vec<Option<Vec<Seen>>>,
}

/// The measurement; see the module docs.
pub struct QualityProbe {
    watched: Vec<Watched>,
    /// Bot number → index in `watched`.
    by_bot: Vec<Option<u32>>,
    config: QualityConfig,
    /// The instant of tick 0 on the mirrors' clock.
    base: Instant,
    pending: VecDeque<Truth>,
    quality: Quality,
    measuring: bool,
    /// With shadows: what they sent and their figures (`shadow.rs`).
    shadow_totals: ShadowTotals,
    shadow_quality: Quality,
    /// The live mirrors' information age (and error, again, beside it).
    live_information: Quality,
}

impl QualityProbe {
    /// A probe over a seeded sample of `bench`'s players; it records nothing until
    /// [`QualityProbe::start_measuring`] (the mirrors fill during the warm-up).
    pub fn new(bench: &TickBench, config: QualityConfig) -> Self {
        let players = bench.players();
        let base = Instant::now();
        // A partial Fisher–Yates shuffle: the first `n` of a seeded permutation.
        let mut order: Vec<usize> = (0..players).collect();
        let mut rng = Stream::new(config.seed, 0x7175_616c);
        let n = config.players.min(players);
        for i in 0..n {
            let j = i + rng.below((players - i) as u32) as usize;
            order.swap(i, j);
        }
        let mut by_bot = vec![None; players];
        let mut watched = Vec::with_capacity(n);
        for &bot in &order[..n] {
            let Some(entity) = bench.bot_entity(bot) else { continue };
            let mut mirror = WorldMirror::new(Duration::from_secs(1)).with_interpolation(config.interpolation);
            mirror.set_timing(config.tick_rate_hz, 1000, base);
            by_bot[bot] = Some(watched.len() as u32);
            let shadow = config
                .shadow
                .map(|(_, _, link)| Shadow::new(entity ^ 0x5eed, config.interpolation, config.tick_rate_hz, base, link))
                .map(|s| (s, InformationAge::default()));
            watched.push(Watched { entity, mirror, live_age: InformationAge::default(), shadow });
        }
        Self {
            watched,
            by_bot,
            config,
            base,
            pending: VecDeque::new(),
            quality: Quality::new(),
            measuring: false,
            shadow_totals: ShadowTotals::default(),
            shadow_quality: Quality::new(),
            live_information: Quality::new(),
        }
    }

    /// Players sampled.
    pub fn players(&self) -> usize {
        self.watched.len()
    }

    /// Records from now on.
    pub fn start_measuring(&mut self) {
        self.measuring = true;
    }

    /// The mirrors' instant of server tick `tick`.
    fn instant(&self, tick: u64) -> Instant {
        self.base + Duration::from_secs_f64(tick as f64 / f64::from(self.config.tick_rate_hz.max(1)))
    }

    /// Bot `bot` opened the update of `tick` and resolved `records`: its mirror takes
    /// them, if it is sampled.
    pub fn on_update(&mut self, bot: usize, tick: u64, records: &[StateRecord]) {
        let Some(&Some(at)) = self.by_bot.get(bot) else { return };
        let now = self.instant(tick);
        self.watched[at as usize].mirror.apply(tick, records.iter().copied(), now);
    }

    /// After the server's tick (the bots drained it): a truth every `every` ticks, with
    /// the staleness at once, and the errors of the truths the render time reached.
    pub fn after_tick(&mut self, world: &World) {
        if self.watched.is_empty() {
            return;
        }
        let tick = world.tick;
        let now = self.instant(tick);
        let sample = self.measuring && tick.is_multiple_of(self.config.every.max(1));
        // Every tick: the information age needs to see each change.
        let truth = self.truth(world);
        self.tick_shadows(world, tick, now, &truth);
        self.observe_information(tick, &truth);
        if !self.measuring {
            return;
        }
        if sample {
            self.record_staleness(tick, &truth);
            self.pending.push_back(Truth { tick, players: truth.into_iter().map(Some).collect() });
            for w in &mut self.watched {
                w.mirror.forget_older_than(Duration::from_secs(10), now);
            }
        }
        for truth in &mut self.pending {
            for (w, seen) in self.watched.iter().zip(&mut truth.players) {
                if w.mirror.render_tick(now).is_some_and(|r| r >= truth.tick as f64) {
                    let Some(seen) = seen.take() else { continue };
                    for s in seen {
                        if let Some(e) = error(&w.mirror, &s, truth.tick) {
                            self.quality.record_error(s.distance, e);
                            self.live_information.record_error(s.distance, e);
                        }
                        if let Some(e) = w.shadow.as_ref().and_then(|sh| error(sh.0.mirror(), &s, truth.tick)) {
                            self.shadow_quality.record_error(s.distance, e);
                        }
                    }
                }
            }
        }
        self.pending.retain(|t| t.players.iter().any(Option::is_some) && t.tick + TRUTH_PATIENCE_TICKS > tick);
    }

    /// Every sampled player's AOI objects at the world's tick (own object left out).
    fn truth(&self, world: &World) -> Vec<Vec<Seen>> {
        let d = &world.dynamics;
        let half = self.config.aoi_size / 2.0;
        self.watched
            .par_iter()
            .map(|w| {
                let centre = u32::try_from(w.entity)
                    .ok()
                    .and_then(|id| d.slot(myriad_core::world::EntityId(id)))
                    .map(|slot| d.positions()[slot]);
                let Some(centre) = centre else { return Vec::new() };
                d.ids()
                    .iter()
                    .zip(d.positions())
                    .zip(d.shapes())
                    .enumerate()
                    .filter(|(_, ((id, p), _))| {
                        let o = **p - centre;
                        u64::from(id.0) != w.entity && o.x.abs() <= half && o.y.abs() <= half && o.z.abs() <= half
                    })
                    .map(|(slot, ((id, p), shape))| Seen {
                        slot: slot as u32,
                        id: u64::from(id.0),
                        kind: wire_kind(*shape),
                        distance: p.distance(centre),
                        position: p.to_array(),
                    })
                    .collect()
            })
            .collect()
    }

    /// Each shadow's tick on the world of `tick` (its player's AOI objects `truth`).
    fn tick_shadows(&mut self, world: &World, tick: u64, now: Instant, truth: &[Vec<Seen>]) {
        let Some((config, max_datagrams, _)) = self.config.shadow else { return };
        let d = &world.dynamics;
        let measuring = self.measuring;
        let totals: Vec<ShadowTotals> = self
            .watched
            .par_iter_mut()
            .zip(truth)
            .filter_map(|(w, seen)| {
                let (shadow, _) = w.shadow.as_mut()?;
                let slot = u32::try_from(w.entity).ok().and_then(|id| d.slot(myriad_core::world::EntityId(id)))?;
                let centre = d.positions()[slot].to_array();
                let own = (w.entity, wire_kind(d.shapes()[slot]), centre);
                let view = seen.iter().map(|s| (s.slot, s.id, s.kind, s.position, s.distance));
                let mut t = ShadowTotals::default();
                shadow.tick(&config, max_datagrams, tick, centre, own, view, now, measuring.then_some(&mut t));
                Some(t)
            })
            .collect();
        for t in totals {
            self.shadow_totals.add(&t);
        }
    }

    /// Every mirror's information age, looked at every tick, recorded on sample ticks.
    fn observe_information(&mut self, tick: u64, truth: &[Vec<Seen>]) {
        let record = self.measuring && tick.is_multiple_of(self.config.every.max(1));
        let rate = f64::from(self.config.tick_rate_hz.max(1));
        for (w, seen) in self.watched.iter_mut().zip(truth) {
            let objects = || seen.iter().map(|s| (s.id, s.distance, s.position));
            w.live_age.observe(&w.mirror, tick, rate, objects(), record.then_some(&mut self.live_information));
            if let Some((shadow, age)) = &mut w.shadow {
                age.observe(shadow.mirror(), tick, rate, objects(), record.then_some(&mut self.shadow_quality));
            }
        }
    }

    /// The second configuration beside the live one, if shadows ran.
    pub fn shadow_row(&self) -> Option<ShadowRow> {
        let (config, _, link) = self.config.shadow?;
        let rate = f64::from(self.config.tick_rate_hz.max(1));
        Some(ShadowRow::new(
            &config,
            link,
            rate,
            &self.shadow_totals,
            self.shadow_quality.summary(),
            self.live_information.summary(),
        ))
    }

    /// The age of the newest state each mirror holds of its AOI's objects at `tick`.
    fn record_staleness(&mut self, tick: u64, truth: &[Vec<Seen>]) {
        let rate = f64::from(self.config.tick_rate_hz.max(1));
        for (w, seen) in self.watched.iter().zip(truth) {
            for s in seen {
                match w.mirror.get(s.id) {
                    Some(o) => {
                        let age = tick.saturating_sub(o.tick) as f64 / rate;
                        self.quality.record_staleness(s.distance, Duration::from_secs_f64(age));
                    }
                    None => self.quality.record_missing(s.distance),
                }
            }
        }
    }

    /// Percentiles of what was recorded.
    pub fn summary(&self) -> QualitySummary {
        self.quality.summary()
    }

    /// Percentiles of the live mirrors' information age (as staleness) and error.
    pub fn information_summary(&self) -> QualitySummary {
        self.live_information.summary()
    }
}

/// The distance between what `mirror` draws of `s` at render tick `tick` and the truth.
fn error(mirror: &WorldMirror, s: &Seen, tick: u64) -> Option<f32> {
    let drawn = mirror.sample(s.id, tick as f64)?;
    let d: [f32; 3] = std::array::from_fn(|i| drawn.position[i] - s.position[i]);
    Some((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt())
}

#[cfg(test)]
#[path = "quality_tests.rs"]
mod tests;
