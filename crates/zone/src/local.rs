//! K zones of one world on threads of this process, over any fabric: what
//! `myriad sim --zones K` runs (with [`MemoryFabric`](crate::MemoryFabric)s, or
//! [`NatsFabric`](crate::NatsFabric)s with `--nats`), and what the equality tests check
//! against one process.

use std::sync::Arc;
use std::time::{Duration, Instant};

use myriad_core::{ActionScript, ObjectState, World, hash_state};
use myriad_physics::{Backend, TickConstants};

use crate::error::ZoneError;
use crate::fabric::Fabric;
use crate::layout::{ZoneId, ZoneLayout};
use crate::stats::ZoneStats;
use crate::wire::ClusterKey;
use crate::zone::{TickEnd, Zone, ZoneConfig};

/// The outcome of a zoned run.
#[derive(Debug)]
pub struct ZonedRun {
    /// [`World::state_hash`] of the reassembled world: comparable with one process's.
    pub state_hash: u64,
    /// The tick reached.
    pub tick: u64,
    /// Every object's final state, by id.
    pub objects: Vec<ObjectState>,
    /// Scripted actions applied (each by the one zone that owned its object).
    pub actions: usize,
    /// Each zone's counters.
    pub stats: Vec<ZoneStats>,
    /// Static primitives each zone held.
    pub static_prims: Vec<usize>,
    /// Wall time of the ticks, from the first zone's first step to the last zone's last
    /// (world assembly and backend start-up excluded), in ms.
    pub ticks_ms: f64,
}

/// How a zoned run goes.
#[derive(Clone, Debug)]
pub struct RunOptions {
    /// Ticks to run.
    pub ticks: u64,
    /// How long a zone waits for a neighbour before declaring it stalled.
    pub wait: Duration,
    /// The key the zones sign with.
    pub key: ClusterKey,
    /// The run (epoch) written in every message.
    pub run: u64,
}

impl RunOptions {
    /// `ticks` ticks with a fresh random key and run id, and a wait of `wait`.
    pub fn new(ticks: u64, wait: Duration) -> RunOptions {
        let mut run = [0u8; 8];
        ring::rand::SecureRandom::fill(&ring::rand::SystemRandom::new(), &mut run).expect("random run id");
        RunOptions { ticks, wait, key: ClusterKey::random(), run: u64::from_le_bytes(run) }
    }
}

/// Runs `world` split by `layout` for `opts.ticks` ticks, one thread per zone, each with
/// the backend `backend(zone)` and the fabric `fabrics[zone]`, and reassembles the
/// result.
pub fn run_zoned(
    world: &World,
    layout: ZoneLayout,
    script: &ActionScript,
    k: &TickConstants,
    backend: &(dyn Fn(ZoneId) -> Result<Box<dyn Backend>, ZoneError> + Sync),
    fabrics: Vec<Box<dyn Fabric>>,
    opts: &RunOptions,
) -> Result<ZonedRun, ZoneError> {
    let (ticks, wait, run) = (opts.ticks, opts.wait, opts.run);
    if fabrics.len() != layout.len() {
        return Err(ZoneError::Layout(format!("{} fabrics for {} zones", fabrics.len(), layout.len())));
    }
    let layout = Arc::new(layout);
    let key = opts.key.clone();
    let results: Vec<Result<Outcome, ZoneError>> = std::thread::scope(|s| {
        let handles: Vec<_> = fabrics
            .into_iter()
            .enumerate()
            .map(|(i, fabric)| {
                let (layout, key) = (layout.clone(), key.clone());
                s.spawn(move || {
                    let id = ZoneId(i as u16);
                    let cfg = ZoneConfig { id, run, key, wait, live: false };
                    let mut zone = Zone::new(cfg, layout, world, backend(id)?, fabric)?;
                    let mut actions = 0;
                    let first = Instant::now();
                    for _ in 0..ticks {
                        let t = zone.tick();
                        match zone.step(script.at(t), k)? {
                            TickEnd::Stepped(applied) => actions += applied,
                            // No supervisor runs these zones: a halt or start is
                            // another cluster's (sharing the key), not this run's.
                            TickEnd::Interrupted(m) => {
                                return Err(ZoneError::Fabric(format!(
                                    "a supervisor's message in a run without one: {m:?}"
                                )));
                            }
                        }
                    }
                    let prims = zone.static_prims();
                    Ok((zone.advanced(), actions, zone.stats().clone(), prims, first, Instant::now()))
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().expect("a zone thread panicked")).collect()
    });
    reassemble(results, Some(world.dynamics.len()), world.tick + ticks)
}

/// What one zone thread returns: its advanced set, the scripted actions it applied, its
/// counters, its static primitives, and when its first and last ticks began and ended.
pub(crate) type Outcome = (Vec<ObjectState>, usize, ZoneStats, usize, Instant, Instant);

/// The world of the zones' outcomes at `tick`: checked for duplicates (and for
/// `expected` objects, when the count is known), hashed, with the zones' counters.
pub(crate) fn reassemble(
    results: Vec<Result<Outcome, ZoneError>>,
    expected: Option<usize>,
    tick: u64,
) -> Result<ZonedRun, ZoneError> {
    // A zone that failed makes its neighbours stall; report the cause, not the stalls.
    if let Some(e) = results.iter().position(|r| matches!(r, Err(e) if !matches!(e, ZoneError::Stalled { .. }))) {
        return Err(results.into_iter().nth(e).expect("index").expect_err("an error"));
    }
    let mut objects = Vec::with_capacity(expected.unwrap_or(0));
    let (mut actions, mut stats, mut static_prims) = (0, Vec::new(), Vec::new());
    let (mut first, mut last): (Option<Instant>, Option<Instant>) = (None, None);
    for r in results {
        let (o, a, s, p, f, l) = r?;
        first = Some(first.map_or(f, |x| x.min(f)));
        last = Some(last.map_or(l, |x| x.max(l)));
        objects.extend(o);
        actions += a;
        stats.push(s);
        static_prims.push(p);
    }
    objects.sort_unstable_by_key(|o| o.id);
    if let Some(w) = objects.windows(2).find(|w| w[0].id == w[1].id) {
        return Err(ZoneError::Duplicate(w[0].id, tick));
    }
    if let Some(n) = expected.filter(|n| *n != objects.len()) {
        return Err(ZoneError::Layout(format!("{} objects came back of {n}", objects.len())));
    }
    let state_hash = hash_state(objects.iter().copied(), tick, objects.len());
    let ticks_ms = match (first, last) {
        (Some(f), Some(l)) => (l - f).as_secs_f64() * 1e3,
        _ => 0.0,
    };
    Ok(ZonedRun { state_hash, tick, objects, actions, stats, static_prims, ticks_ms })
}

/// The reach a world needs for its pairs: twice the largest horizontal half extent of
/// any dynamic object, plus a little slack against rounding at the edges.
pub fn pair_reach(world: &World) -> f32 {
    let h = world.dynamics.half_extents().iter().fold(0.0f32, |m, h| m.max(h.x).max(h.z));
    2.0 * h + 0.25
}
