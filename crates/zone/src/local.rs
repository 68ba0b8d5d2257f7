//! K zones of one world on threads of this process, over any fabric: what
//! `myriad sim --zones K` runs (with [`MemoryFabric`](crate::MemoryFabric)s, or
//! [`NatsFabric`](crate::NatsFabric)s with `--nats`), and what the equality tests check
//! against one process.

use std::sync::Arc;
use std::sync::mpsc::{Receiver, Sender, channel};
use std::time::{Duration, Instant};

use myriad_core::{ActionScript, ObjectState, World, hash_state};
use myriad_physics::{Backend, TickConstants};

use crate::error::ZoneError;
use crate::fabric::Fabric;
use crate::layout::{ZoneId, ZoneLayout};
use crate::rebalance::{Coordinator, Decision, LoadReport, RebalanceLog, RebalanceOptions};
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
    /// Cut moves every zone applied (0 without [`RunOptions::rebalance`]).
    pub cut_moves: u64,
    /// The rebalancing's moves, refusals, load samples and final cuts (with
    /// [`RunOptions::rebalance`]).
    pub rebalance: Option<RebalanceLog>,
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
    /// Watch the zones' load and move the cuts (see [`crate::rebalance`]); `None`: fixed
    /// cuts, no reports.
    pub rebalance: Option<RebalanceOptions>,
}

impl RunOptions {
    /// `ticks` ticks with a fresh random key and run id, and a wait of `wait`.
    pub fn new(ticks: u64, wait: Duration) -> RunOptions {
        let mut run = [0u8; 8];
        ring::rand::SecureRandom::fill(&ring::rand::SystemRandom::new(), &mut run).expect("random run id");
        RunOptions { ticks, wait, key: ClusterKey::random(), run: u64::from_le_bytes(run), rebalance: None }
    }
}

/// Runs `world` split by `layout` for `opts.ticks` ticks, one thread per zone, each with
/// the backend `backend(zone)` and the fabric `fabrics[zone]`, and reassembles the
/// result.
///
/// With [`RunOptions::rebalance`], a coordinator thread gathers every zone's
/// [`LoadReport`] at each report tick `t`, decides, and sends every zone the same
/// [`Decision`]: a zone does not step `t + delay` before it has the decision of `t`, and
/// switches layouts just before that step, so all switch at one tick.
pub fn run_zoned(
    world: &World,
    layout: ZoneLayout,
    script: &ActionScript,
    k: &TickConstants,
    backend: &(dyn Fn(ZoneId) -> Result<Box<dyn Backend>, ZoneError> + Sync),
    fabrics: Vec<Box<dyn Fabric>>,
    opts: &RunOptions,
) -> Result<ZonedRun, ZoneError> {
    let ticks = opts.ticks;
    if fabrics.len() != layout.len() {
        return Err(ZoneError::Layout(format!("{} fabrics for {} zones", fabrics.len(), layout.len())));
    }
    let layout = Arc::new(layout);
    let end = world.tick + ticks;
    let coordinator = match &opts.rebalance {
        Some(r) => Some(Coordinator::new(r.clone(), layout.clone(), end)?),
        None => None,
    };
    // Reports (and ends) of every zone to the coordinator; decisions back, one channel
    // a zone.
    let (report_tx, report_rx) = channel::<Report>();
    let (decision_txs, decision_rxs): (Vec<_>, Vec<_>) = (0..layout.len()).map(|_| channel::<Decision>()).unzip();
    let (results, log) = std::thread::scope(|s| {
        let coord = coordinator.map(|c| s.spawn(move || coordinate(c, report_rx, decision_txs)));
        let handles: Vec<_> = fabrics
            .into_iter()
            .zip(decision_rxs)
            .enumerate()
            .map(|(i, (fabric, decisions))| {
                let layout = layout.clone();
                let reports = opts.rebalance.as_ref().map(|r| (r, ZoneEnd::new(ZoneId(i as u16), report_tx.clone())));
                s.spawn(move || {
                    let id = ZoneId(i as u16);
                    let zone = Zone::new(zone_config(opts, id), layout, world, backend(id)?, fabric)?;
                    run_zone(zone, world, script, k, end, reports, &decisions)
                })
            })
            .collect();
        drop(report_tx);
        let results: Vec<Result<Outcome, ZoneError>> =
            handles.into_iter().map(|h| h.join().expect("a zone thread panicked")).collect();
        let log = coord.map(|c| c.join().expect("the coordinator panicked"));
        (results, log)
    });
    reassemble(results, Some(world.dynamics.len()), end, log.transpose()?)
}

/// The world of the zones' outcomes at `tick`: checked for duplicates (and for
/// `expected` objects, when the count is known), hashed, with the zones' counters and
/// the rebalancing's log (`log`, when the run rebalanced).
pub(crate) fn reassemble(
    results: Vec<Result<Outcome, ZoneError>>,
    expected: Option<usize>,
    end: u64,
    log: Option<RebalanceLog>,
) -> Result<ZonedRun, ZoneError> {
    // A zone that failed makes its neighbours stall, and zones waiting for a decision
    // fail when the coordinator gives up: report the cause, not its echoes.
    let echo = |e: &ZoneError| matches!(e, ZoneError::Stalled { .. } | ZoneError::CoordinatorGone);
    if let Some(e) = results.iter().position(|r| matches!(r, Err(e) if !echo(e))) {
        return Err(results.into_iter().nth(e).expect("index").expect_err("an error"));
    }
    let mut objects = Vec::with_capacity(expected.unwrap_or(0));
    let (mut actions, mut stats, mut static_prims) = (0, Vec::new(), Vec::new());
    let (mut first, mut last): (Option<Instant>, Option<Instant>) = (None, None);
    for r in results {
        let o = r?;
        first = Some(first.map_or(o.first, |x| x.min(o.first)));
        last = Some(last.map_or(o.last, |x| x.max(o.last)));
        objects.extend(o.objects);
        actions += o.actions;
        stats.push(o.stats);
        static_prims.push(o.static_prims);
    }
    objects.sort_unstable_by_key(|o| o.id);
    if let Some(w) = objects.windows(2).find(|w| w[0].id == w[1].id) {
        return Err(ZoneError::Duplicate(w[0].id, end));
    }
    if let Some(n) = expected.filter(|n| *n != objects.len()) {
        return Err(ZoneError::Layout(format!("{} objects came back of {n}", objects.len())));
    }
    // Every zone switched at every move, or the zones did not follow one layout.
    let cut_moves = stats.first().map_or(0, |s: &ZoneStats| s.cut_moves);
    if stats.iter().any(|s| s.cut_moves != cut_moves) || log.as_ref().is_some_and(|l| l.moves.len() as u64 != cut_moves)
    {
        return Err(ZoneError::Layout("the zones did not follow the same cut moves".into()));
    }
    let state_hash = hash_state(objects.iter().copied(), end, objects.len());
    let ticks_ms = match (first, last) {
        (Some(f), Some(l)) => (l - f).as_secs_f64() * 1e3,
        _ => 0.0,
    };
    Ok(ZonedRun { state_hash, tick: end, objects, actions, stats, static_prims, ticks_ms, cut_moves, rebalance: log })
}

/// What a zone thread hands back.
#[derive(Debug)]
pub(crate) struct Outcome {
    pub objects: Vec<ObjectState>,
    pub actions: usize,
    pub stats: ZoneStats,
    pub static_prims: usize,
    pub first: Instant,
    pub last: Instant,
}

/// A zone thread's message to the coordinator.
enum Report {
    /// Its load at a report tick.
    Load(Box<LoadReport>),
    /// It ended: `true` after its last tick, `false` on an error (it reports no more).
    End(ZoneId, bool),
}

/// Tells the coordinator that a zone ended, however it ends (errors and panics too), so
/// that it never waits for a report that will not come.
struct ZoneEnd {
    zone: ZoneId,
    tx: Sender<Report>,
    ok: bool,
}

impl ZoneEnd {
    fn new(zone: ZoneId, tx: Sender<Report>) -> ZoneEnd {
        ZoneEnd { zone, tx, ok: false }
    }
}

impl Drop for ZoneEnd {
    fn drop(&mut self) {
        // The coordinator may be gone already: nothing to tell then.
        let _ = self.tx.send(Report::End(self.zone, self.ok));
    }
}

fn zone_config(opts: &RunOptions, id: ZoneId) -> ZoneConfig {
    ZoneConfig { id, run: opts.run, key: opts.key.clone(), wait: opts.wait, live: false }
}

/// One zone's ticks up to `end`, reporting its load and following decisions when
/// `reports` is given.
fn run_zone(
    mut zone: Zone,
    world: &World,
    script: &ActionScript,
    k: &TickConstants,
    end: u64,
    mut reports: Option<(&RebalanceOptions, ZoneEnd)>,
    decisions: &Receiver<Decision>,
) -> Result<Outcome, ZoneError> {
    let mut actions = 0;
    let first = Instant::now();
    let mut since = (zone.stats().physics, zone.stats().step, zone.stats().ticks);
    loop {
        let t = zone.tick();
        if let Some((r, to)) = &reports {
            if r.reports_at(t) {
                let s = zone.stats();
                let positions = zone.advanced().into_iter().map(|o| o.pos);
                let mut report = LoadReport::of(zone.id(), t, positions, &world.bounds, r.bins);
                (report.physics, report.step, report.ticks) =
                    (s.physics - since.0, s.step - since.1, s.ticks - since.2);
                since = (s.physics, s.step, s.ticks);
                // A coordinator that is gone failed; the decision's wait below says so.
                let _ = to.tx.send(Report::Load(Box::new(report)));
            }
            if t >= r.delay && r.decides(t - r.delay, end) && t - r.delay >= world.tick {
                let d = decisions.recv().map_err(|_| ZoneError::CoordinatorGone)?;
                if d.apply_at != t {
                    return Err(ZoneError::Layout(format!("a decision for tick {} at tick {t}", d.apply_at)));
                }
                if let Some(layout) = d.layout {
                    zone.set_layout(layout)?;
                }
            }
        }
        if t >= end {
            break;
        }
        match zone.step(script.at(t), k)? {
            TickEnd::Stepped(applied) => actions += applied,
            // No supervisor runs these zones: a halt or start is another cluster's
            // (sharing the key), not this run's.
            TickEnd::Interrupted(m) => {
                return Err(ZoneError::Fabric(format!("a supervisor's message in a run without one: {m:?}")));
            }
        }
    }
    if let Some((_, to)) = &mut reports {
        to.ok = true;
    }
    let static_prims = zone.static_prims();
    Ok(Outcome {
        objects: zone.advanced(),
        actions,
        stats: zone.stats().clone(),
        static_prims,
        first,
        last: Instant::now(),
    })
}

/// The coordinator's thread: reports in, decisions out to every zone, until every zone
/// ended. A zone that failed ends it at once (its reports will not come): the others,
/// waiting for decisions, then fail too, and the run reports the first zone's error.
fn coordinate(
    mut c: Coordinator,
    reports: Receiver<Report>,
    decisions: Vec<Sender<Decision>>,
) -> Result<RebalanceLog, ZoneError> {
    let mut ended = 0;
    while let Ok(r) = reports.recv() {
        match r {
            Report::Load(r) => {
                if let Some(d) = c.offer(*r)? {
                    for tx in &decisions {
                        // A zone that ended needs no decision.
                        let _ = tx.send(d.clone());
                    }
                }
            }
            Report::End(_, true) => {
                ended += 1;
                if ended == decisions.len() {
                    break;
                }
            }
            Report::End(z, false) => {
                tracing::debug!(zone = z.0, "a zone failed: the coordinator stops");
                break;
            }
        }
    }
    Ok(c.finish())
}

/// The reach a world needs for its pairs: twice the largest horizontal half extent of
/// any dynamic object, plus a little slack against rounding at the edges.
pub fn pair_reach(world: &World) -> f32 {
    let h = world.dynamics.half_extents().iter().fold(0.0f32, |m, h| m.max(h.x).max(h.z));
    2.0 * h + 0.25
}
