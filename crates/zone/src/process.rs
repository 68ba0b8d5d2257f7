//! A zone as a process of a cluster: it waits for the supervisor's start, resumes from a
//! checkpoint, steps, stores a checkpoint every `checkpoint_every` ticks, and on a
//! stall or a halt goes back to waiting — never exits for a neighbour's fault.
//!
//! At every checkpoint it also stores the segment of its intent log since the last one
//! ([`crate::replay`]), so that a live run can be replayed. A checkpoint records the cuts
//! its objects were stepped with, and a start names the cuts to start on: a zone
//! restarted after a cut move resumes on the moved cuts. Its heartbeat carries its step
//! time, its owned objects, the digest of its cuts and the cut move it holds, for the
//! supervisor's rebalancing ([`crate::rebalance::announce`]).
//!
//! States, as its heartbeat reports them: `Waiting` (for a start), `Running`, `Stalled`
//! (a neighbour did not answer within `stall`), `Done` (reached the last tick; the
//! result is stored as the checkpoint of that tick).

use std::sync::Arc;
use std::time::{Duration, Instant};

use myriad_core::{ActionScript, World};
use myriad_physics::{Backend, TickConstants};

use crate::checkpoint::CheckpointStore;
use crate::error::ZoneError;
use crate::fabric::Fabric;
use crate::layout::{ZoneId, ZoneLayout};
use crate::nats::{Beat, Heartbeat};
use crate::rebalance::Cuts;
use crate::wire::{ClusterKey, Load, Message, ZoneState, decode};
use crate::zone::{TickEnd, Zone, ZoneConfig};

/// How a zone process runs.
#[derive(Clone, Debug)]
pub struct ProcessConfig {
    /// This zone.
    pub zone: ZoneId,
    /// The cluster's key.
    pub key: ClusterKey,
    /// The last tick: at it the zone stores its result and reports `Done`.
    pub ticks: u64,
    /// Ticks between checkpoints (30 = one second at 30 Hz).
    pub checkpoint_every: u64,
    /// How long to wait for a neighbour before reporting a stall.
    pub stall: Duration,
    /// The tick period, or zero to step as fast as the neighbours allow.
    pub period: Duration,
    /// Whether the zone serves gateways (sends its views, or states, every tick).
    pub live: bool,
    /// Whether a live zone also publishes the whole mirror for every gateway
    /// ([`Zone::set_mirror`]); subscribed gateways get their views either way.
    pub mirror: bool,
    /// Checkpoints (and intent log segments) kept; at least [`KEEP`]: a replay can start
    /// from the oldest.
    pub keep: u64,
}

/// Checkpoints each zone keeps at least.
pub const KEEP: u64 = 3;

/// Messages kept while waiting for a start: border states of the coming epoch may
/// arrive before its start does. Bounded, oldest dropped.
const PENDING: usize = 4096;

/// Runs zone `cfg.zone` until its process is stopped. `world` is the generated world at
/// tick 0 (bounds, terrain, statics, and the objects for a start at tick 0).
#[allow(clippy::too_many_arguments)]
pub fn run_zone_process(
    cfg: &ProcessConfig,
    layout: Arc<ZoneLayout>,
    world: &World,
    script: &ActionScript,
    k: &TickConstants,
    backend: &dyn Fn() -> Result<Box<dyn Backend>, ZoneError>,
    mut fabric: Box<dyn Fabric>,
    store: &mut dyn CheckpointStore,
    heartbeat: &Heartbeat,
) -> Result<(), ZoneError> {
    // The newest epoch announced (by a halt or a start), and the last one started: a
    // start is taken once, and only if no newer halt was seen.
    let mut epoch = 0u64;
    let mut started = 0u64;
    let mut tick = 0u64;
    let mut state = ZoneState::Waiting;
    let mut load = Load::default();
    let mut pending: Vec<Vec<u8>> = Vec::new();
    let mut next: Option<(u64, u64, Cuts)> = None;
    loop {
        // Wait for a start of a newer epoch.
        let (run, from, cuts) = match next.take() {
            Some(s) => s,
            None => loop {
                heartbeat.set(Beat { run: epoch, tick, state, load });
                let Some(bytes) = fabric.recv(Instant::now() + Duration::from_millis(500))? else { continue };
                match decode(&cfg.key, &bytes) {
                    Ok(Message::Start { run, tick, cuts }) if run >= epoch && run > started => break (run, tick, cuts),
                    Ok(Message::Halt { run }) if run > epoch => {
                        epoch = run;
                        state = ZoneState::Waiting;
                        pending.clear();
                    }
                    // Border states and cut moves of the coming epoch may come before its
                    // start (the zone checks them once started; the supervisor's repeats
                    // of an older epoch's move are dropped here, not counted as refused).
                    Ok(Message::Border(_)) => hold(&mut pending, bytes),
                    Ok(Message::CutMove { run, .. }) if run >= epoch => hold(&mut pending, bytes),
                    _ => {}
                }
            },
        };
        epoch = run;
        started = run;
        tracing::info!(zone = cfg.zone.0, epoch, tick = from, "starting");
        let zcfg = ZoneConfig { id: cfg.zone, run, key: cfg.key.clone(), wait: cfg.stall, live: cfg.live };
        // The cuts the supervisor names: the checkpoint's (every zone's agree), or the
        // layout's own at tick 0.
        let moved = Arc::new(layout.with_cuts(&cuts.0, &cuts.1)?);
        let mut zone = if from == 0 {
            Zone::new(zcfg, moved, world, backend()?, fabric)?
        } else {
            let mut at = world.clone();
            at.tick = from;
            let snap = store.get(cfg.zone, from)?;
            if snap.cuts != cuts {
                return Err(ZoneError::Checkpoint(format!(
                    "a start from tick {from} with cuts {cuts:?}, but zone {}'s checkpoint holds {:?}",
                    cfg.zone.0, snap.cuts
                )));
            }
            Zone::resume(zcfg, moved, &at, snap.objects, backend()?, fabric)?
        };
        zone.set_mirror(cfg.mirror);
        for bytes in pending.drain(..) {
            // Controls seen here are older than this start: ignored.
            let _ = zone.offer(&bytes);
        }
        tick = zone.tick();
        state = ZoneState::Running;
        let mut step_ms = StepAverage::default();
        load = step_ms.load(&zone);
        heartbeat.set(Beat { run: epoch, tick, state, load });
        // The gauges describe the checkpoint from now on, not the abandoned epoch's last
        // tick, which a neighbour's first step of this epoch may reach: one tick's
        // gauges never come from two epochs.
        zone.stats().export(cfg.zone);
        let outcome = loop {
            let t = zone.tick();
            let every = cfg.checkpoint_every.max(1);
            if t.is_multiple_of(every) || t == cfg.ticks {
                // The intents taken since the last checkpoint, for a replay (their segment
                // starts at that checkpoint), stored first: a checkpoint that is there has
                // the log that leads to it.
                if let Some((from, segment)) = zone.checkpoint_log(epoch) {
                    store.put_log(cfg.zone, from, &segment)?;
                }
                store.put(cfg.zone, t, epoch, &zone.stepped_cuts(), &zone.advanced())?;
                // Keep the last `keep` checkpoints: zones drift apart by a few ticks at
                // most, so a tick that all of them stored is among them.
                if let Some(old) = (t / every * every).checked_sub(cfg.keep.max(KEEP) * every) {
                    store.forget(cfg.zone, old)?;
                }
            }
            if t >= cfg.ticks {
                break Ok(ZoneState::Done);
            }
            let stepped = Instant::now();
            match zone.step(script.at(t), k) {
                Ok(TickEnd::Stepped(_)) => {}
                Ok(TickEnd::Interrupted(Message::Start { run, tick, cuts })) if run > started => {
                    next = Some((run, tick, cuts));
                    break Ok(ZoneState::Waiting);
                }
                Ok(TickEnd::Interrupted(Message::Halt { run })) if run > epoch => {
                    epoch = run;
                    break Ok(ZoneState::Waiting);
                }
                // An older epoch's halt or start: the tick is tried again.
                Ok(TickEnd::Interrupted(_)) => continue,
                Err(ZoneError::Stalled { missing, .. }) => {
                    tracing::warn!(zone = cfg.zone.0, tick = t, ?missing, "neighbours silent: stalled");
                    break Ok(ZoneState::Stalled);
                }
                Err(e) => break Err(e),
            }
            tick = zone.tick();
            load = step_ms.load(&zone);
            heartbeat.set(Beat { run: epoch, tick, state, load });
            zone.stats().export(cfg.zone);
            if let Some(rest) = cfg.period.checked_sub(stepped.elapsed()) {
                std::thread::sleep(rest);
            }
        };
        tick = zone.tick();
        fabric = zone.into_fabric();
        state = outcome?;
        if state == ZoneState::Done {
            tracing::info!(zone = cfg.zone.0, epoch, tick, "done");
        }
    }
}

/// Keeps a message that came before its epoch's start (the oldest goes when full).
fn hold(pending: &mut Vec<Vec<u8>>, bytes: Vec<u8>) {
    if pending.len() == PENDING {
        pending.remove(0);
    }
    pending.push(bytes);
}

/// A zone's step time (its own work and the physics, not the wait), averaged over about
/// a second of ticks: what its heartbeat reports to the supervisor's policy.
#[derive(Debug, Default)]
struct StepAverage {
    /// The step and send time counted at the last sample.
    seen: Duration,
    /// The average, in ms (`None` before the first tick).
    ms: Option<f64>,
}

impl StepAverage {
    /// Ticks the average spans (about one second at 30 Hz).
    const SPAN: f64 = 30.0;

    /// Takes the zone's counters after a tick (or at its start), and says the load.
    fn load(&mut self, zone: &Zone) -> Load {
        let s = zone.stats();
        let total = s.step + s.send;
        if s.ticks > 0 {
            let last = total.saturating_sub(self.seen).as_secs_f64() * 1e3;
            self.ms = Some(self.ms.map_or(last, |m| m + (last - m) / Self::SPAN));
        }
        self.seen = total;
        Load {
            step_us: self.ms.map_or(0, |m| (m * 1e3).round().min(u32::MAX as f64) as u32),
            owned: u32::try_from(s.owned).unwrap_or(u32::MAX),
            cuts: zone.stepped_digest(),
            pending: zone.pending_cut_move(),
        }
    }
}
