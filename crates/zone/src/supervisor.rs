//! The supervisor: starts a cluster's epoch, watches heartbeats, and on a fault (a zone
//! silent for `dead_after`, a zone stalled, a zone process that exited) halts every
//! zone, lets dead ones come back, and starts a new epoch from the latest checkpoint
//! that every zone stored. At the run's last tick it reassembles the world from the
//! zones' results and reports its state hash.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use futures_util::StreamExt;
use myriad_core::{ObjectState, hash_state};

use crate::checkpoint::CheckpointStore;
use crate::error::ZoneError;
use crate::layout::ZoneId;
use crate::nats::{NatsLink, control_subject, heartbeat_subject, heartbeats_subject};
use crate::wire::{ClusterKey, Message, ZoneState, decode, encode_control};

/// How the supervisor watches.
#[derive(Clone, Debug)]
pub struct SupervisorConfig {
    /// The cluster's name (subjects).
    pub cluster: String,
    /// The cluster's key.
    pub key: ClusterKey,
    /// Zones in the cluster.
    pub zones: usize,
    /// The run's last tick.
    pub ticks: u64,
    /// Objects in the world (a result with another count is an error), or `None` when
    /// gateways' players join and leave (the count is not known in advance).
    pub objects: Option<usize>,
    /// A zone whose heartbeat is older than this is dead.
    pub dead_after: Duration,
    /// Ticks between the zones' checkpoints.
    pub checkpoint_every: u64,
}

/// What happened, for the log and the caller.
#[derive(Clone, Debug, PartialEq)]
pub enum Event {
    /// An epoch started from the checkpoint at `tick` (0: the generated world), whose
    /// reassembled state hash is `state_hash` (`None` at tick 0).
    Started {
        /// The epoch.
        epoch: u64,
        /// The checkpoint's tick.
        tick: u64,
        /// Its state hash.
        state_hash: Option<u64>,
    },
    /// A fault was seen; a rollback follows.
    Fault {
        /// The epoch it ended.
        epoch: u64,
        /// What happened.
        reason: String,
    },
    /// The slowest zone's tick, about twice a second while an epoch runs.
    Progress {
        /// The epoch.
        epoch: u64,
        /// The lowest tick any zone reported.
        tick: u64,
    },
    /// Every zone reached the last tick.
    Done {
        /// The reassembled world's state hash.
        state_hash: u64,
    },
}

/// Reassembles the world at `tick` from every zone's checkpoint and hashes it.
pub fn assemble(
    store: &mut dyn CheckpointStore,
    zones: usize,
    tick: u64,
    objects: Option<usize>,
) -> Result<(u64, Vec<ObjectState>), ZoneError> {
    let mut all = Vec::with_capacity(objects.unwrap_or(0));
    for z in 0..zones {
        all.extend(store.get(ZoneId(z as u16), tick)?);
    }
    all.sort_unstable_by_key(|o| o.id);
    if let Some(w) = all.windows(2).find(|w| w[0].id == w[1].id) {
        return Err(ZoneError::Checkpoint(format!("tick {tick}: object {} stored by two zones", w[0].id.0)));
    }
    if let Some(n) = objects.filter(|n| *n != all.len()) {
        return Err(ZoneError::Checkpoint(format!("tick {tick}: {} objects reassembled, {n} expected", all.len())));
    }
    Ok((hash_state(all.iter().copied(), tick, all.len()), all))
}

/// Runs the cluster to its last tick. `restarted` is asked often which zones' processes
/// exited (and were restarted, if the caller manages them); `on_event` hears every
/// event. Returns the final state hash.
pub fn supervise(
    cfg: &SupervisorConfig,
    link: &NatsLink,
    store: &mut dyn CheckpointStore,
    restarted: &mut dyn FnMut() -> Vec<ZoneId>,
    on_event: &mut dyn FnMut(&Event),
) -> Result<u64, ZoneError> {
    let mut beats = link.subscribe(heartbeats_subject(&cfg.cluster))?;
    let mut last: BTreeMap<ZoneId, (Instant, u64, u64, ZoneState)> = BTreeMap::new();
    let mut epoch = 0u64;
    let mut halting = true;
    let mut last_halt = Instant::now() - Duration::from_secs(1);
    let since = Instant::now();
    let mut last_progress = Instant::now();
    loop {
        let next = link.rt.block_on(async { tokio::time::timeout(Duration::from_millis(100), beats.next()).await });
        if let Ok(Some(m)) = next {
            match decode(&cfg.key, &m.payload) {
                // A heartbeat counts only on its own zone's subject, which only that
                // zone's NATS user may publish on (on a locked-down server): another
                // zone, or anyone else, cannot replay it to hide the zone's death.
                Ok(Message::Heartbeat { zone, .. }) if m.subject.as_str() != heartbeat_subject(&cfg.cluster, zone) => {
                    tracing::warn!(subject = %m.subject, zone = zone.0, "a heartbeat on another zone's subject");
                    metrics::counter!("myriad_supervisor_rejected_total", "reason" => "heartbeat_subject").increment(1);
                }
                Ok(Message::Heartbeat { run, tick, zone, state }) if (zone.0 as usize) < cfg.zones => {
                    // Heartbeats are signed but could be replayed: one that goes back in
                    // (epoch, tick) is an old one and is ignored. A restarted zone starts
                    // at epoch 0 and is heard again once it takes the halt.
                    let fresh = last.get(&zone).is_none_or(|b| (run, tick) >= (b.1, b.2) || run == 0);
                    if fresh {
                        last.insert(zone, (Instant::now(), run, tick, state));
                    }
                }
                Ok(_) | Err(_) => tracing::debug!("a message on the heartbeat subject was not a heartbeat"),
            }
        }
        let now = Instant::now();
        if halting {
            if epoch == 0 {
                // The first epoch follows whatever epochs zones already went through.
                epoch = last.values().map(|b| b.1).max().unwrap_or(0) + 1;
            }
            let ready = (0..cfg.zones).all(|z| {
                last.get(&ZoneId(z as u16))
                    .is_some_and(|b| b.1 == epoch && b.3 == ZoneState::Waiting && now - b.0 < cfg.dead_after)
            });
            if ready {
                // The checkpoints zones may still hold, newest first.
                let every = cfg.checkpoint_every.max(1);
                let newest = last.values().map(|b| b.2).max().unwrap_or(0).min(cfg.ticks) / every * every;
                let candidates: Vec<u64> =
                    (0..=crate::process::KEEP).filter_map(|i| newest.checked_sub(i * every)).collect();
                let tick = store.latest_consistent(cfg.zones, &candidates)?.unwrap_or(0);
                let state_hash = if tick > 0 { Some(assemble(store, cfg.zones, tick, cfg.objects)?.0) } else { None };
                link.publish(
                    control_subject(&cfg.cluster),
                    encode_control(&cfg.key, &Message::Start { run: epoch, tick })?,
                )?;
                on_event(&Event::Started { epoch, tick, state_hash });
                halting = false;
                // Zones get a fresh deadline from the start.
                for b in last.values_mut() {
                    b.0 = now;
                }
            } else if now - last_halt > Duration::from_millis(300) && now - since > Duration::from_millis(300) {
                link.publish(control_subject(&cfg.cluster), encode_control(&cfg.key, &Message::Halt { run: epoch })?)?;
                last_halt = now;
            }
            continue;
        }
        let mut fault = restarted().first().map(|z| format!("zone {} exited", z.0));
        for z in (0..cfg.zones).map(|z| ZoneId(z as u16)) {
            match last.get(&z) {
                Some(b) if now - b.0 > cfg.dead_after => {
                    fault.get_or_insert_with(|| format!("zone {} silent for {} ms", z.0, (now - b.0).as_millis()));
                }
                Some(b) if b.1 == epoch && b.3 == ZoneState::Stalled => {
                    fault.get_or_insert_with(|| format!("zone {} stalled at tick {}", z.0, b.2));
                }
                None => {
                    fault.get_or_insert_with(|| format!("zone {} never heard", z.0));
                }
                _ => {}
            }
        }
        if let Some(reason) = fault {
            on_event(&Event::Fault { epoch, reason });
            epoch += 1;
            halting = true;
            last_halt = now - Duration::from_secs(1);
            continue;
        }
        if now - last_progress > Duration::from_millis(500) {
            last_progress = now;
            let tick = last.values().filter(|b| b.1 == epoch).map(|b| b.2).min().unwrap_or(0);
            on_event(&Event::Progress { epoch, tick });
        }
        let done = (0..cfg.zones).all(|z| {
            last.get(&ZoneId(z as u16)).is_some_and(|b| b.1 == epoch && b.3 == ZoneState::Done && b.2 == cfg.ticks)
        });
        if done {
            let (state_hash, _) = assemble(store, cfg.zones, cfg.ticks, cfg.objects)?;
            on_event(&Event::Done { state_hash });
            return Ok(state_hash);
        }
    }
}
