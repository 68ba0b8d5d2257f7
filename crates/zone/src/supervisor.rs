//! The supervisor: starts a cluster's epoch, watches heartbeats, and on a fault (a zone
//! silent for `dead_after`, a zone stalled, a zone process that exited) halts every
//! zone, lets dead ones come back, and starts a new epoch from the latest checkpoint
//! that every zone stored with the same cuts. At the run's last tick it reassembles the
//! world from the zones' results and reports its state hash.
//!
//! With [`SupervisorConfig::rebalance`] it also moves the cuts while the cluster runs:
//! from the load the heartbeats report, it announces cut moves on the cuts subject and
//! rolls the cluster back when a zone steps on other cuts than announced
//! ([`crate::rebalance::announce`]).

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use futures_util::StreamExt;
use myriad_core::{ObjectState, hash_state};

use crate::checkpoint::CheckpointStore;
use crate::error::ZoneError;
use crate::layout::{ZoneId, ZoneLayout};
use crate::nats::{NatsLink, control_subject, cuts_subject, heartbeat_subject, heartbeats_subject};
use crate::rebalance::announce::{Announcement, Announcer, LiveOptions, ZoneBeat};
use crate::rebalance::{CutMove, Cuts};
use crate::wire::{ClusterKey, Load, Message, ZoneState, decode, encode_control, encode_cut_move};

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
    /// The layout the zones start the run on (tick 0).
    pub layout: ZoneLayout,
    /// Move the cuts while the cluster runs (`None`: they stay).
    pub rebalance: Option<LiveOptions>,
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
    /// The slowest zone's tick and every zone's load, about twice a second while an
    /// epoch runs.
    Progress {
        /// The epoch.
        epoch: u64,
        /// The lowest tick any zone reported.
        tick: u64,
        /// Each zone's last heartbeat of this epoch (its tick and load), by zone
        /// (`None`: not heard in it).
        beats: Vec<Option<ZoneBeat>>,
    },
    /// A cut move was announced, every zone applied one, or one was refused (a zone that
    /// steps on other cuts than announced is a [`Event::Fault`]).
    Cuts {
        /// The epoch.
        epoch: u64,
        /// What happened: [`Announcement::Send`] (announced), [`Announcement::Applied`]
        /// or [`Announcement::Refused`].
        what: Announcement,
    },
    /// Every zone reached the last tick.
    Done {
        /// The reassembled world's state hash.
        state_hash: u64,
    },
}

/// Reassembles the world at `tick` from every zone's checkpoint and hashes it; the zones'
/// checkpoints must hold the same cuts.
pub fn assemble(
    store: &mut dyn CheckpointStore,
    zones: usize,
    tick: u64,
    objects: Option<usize>,
) -> Result<(u64, Vec<ObjectState>), ZoneError> {
    match assemble_with_cuts(store, zones, tick, objects)? {
        Some((hash, all, _)) => Ok((hash, all)),
        None => Err(ZoneError::Checkpoint(format!(
            "tick {tick}: the zones' checkpoints hold different cuts or come from different epochs"
        ))),
    }
}

/// [`assemble`], with the cuts every zone's checkpoint holds; `None` when they differ (a
/// zone missed a cut move) or when the checkpoints were written by different epochs (a
/// fault came while the zones were writing this tick again after a rollback, and live
/// intents may have made the two epochs' states of it differ): either way the world of
/// `tick` is not one world.
pub fn assemble_with_cuts(
    store: &mut dyn CheckpointStore,
    zones: usize,
    tick: u64,
    objects: Option<usize>,
) -> Result<Option<(u64, Vec<ObjectState>, Cuts)>, ZoneError> {
    let mut all = Vec::with_capacity(objects.unwrap_or(0));
    let mut first: Option<(Cuts, u64)> = None;
    for z in 0..zones {
        let snap = store.get(ZoneId(z as u16), tick)?;
        let (cuts, run) = first.get_or_insert_with(|| (snap.cuts.clone(), snap.run));
        if *cuts != snap.cuts || *run != snap.run {
            return Ok(None);
        }
        all.extend(snap.objects);
    }
    let cuts = first.map(|(c, _)| c);
    all.sort_unstable_by_key(|o| o.id);
    if let Some(w) = all.windows(2).find(|w| w[0].id == w[1].id) {
        return Err(ZoneError::Checkpoint(format!("tick {tick}: object {} stored by two zones", w[0].id.0)));
    }
    if let Some(n) = objects.filter(|n| *n != all.len()) {
        return Err(ZoneError::Checkpoint(format!("tick {tick}: {} objects reassembled, {n} expected", all.len())));
    }
    Ok(Some((hash_state(all.iter().copied(), tick, all.len()), all, cuts.unwrap_or_default())))
}

/// The tick a new epoch starts from: the newest of `candidates` that every zone stored
/// with the same cuts in the same epoch, with those cuts and its state hash; tick 0 (the generated world on
/// `layout`'s cuts) when there is none.
fn start_point(
    cfg: &SupervisorConfig,
    store: &mut dyn CheckpointStore,
    candidates: &[u64],
) -> Result<(u64, Cuts, Option<u64>), ZoneError> {
    for &t in candidates.iter().filter(|t| **t > 0) {
        if store.latest_consistent(cfg.zones, &[t])?.is_none() {
            continue;
        }
        match assemble_with_cuts(store, cfg.zones, t, cfg.objects)? {
            Some((hash, _, cuts)) => return Ok((t, cuts, Some(hash))),
            None => tracing::warn!(tick = t, "the zones' checkpoints hold different cuts or epochs: an older one"),
        }
    }
    let (xs, zs) = cfg.layout.cuts();
    Ok((0, (xs.to_vec(), zs.to_vec()), None))
}

/// The latest heartbeat of a zone.
#[derive(Clone, Copy, Debug)]
struct Heard {
    at: Instant,
    run: u64,
    tick: u64,
    state: ZoneState,
    load: Load,
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
    let mut last: BTreeMap<ZoneId, Heard> = BTreeMap::new();
    let mut announcer = match &cfg.rebalance {
        Some(o) => Some(Announcer::new(o.clone(), Arc::new(cfg.layout.clone()), cfg.ticks)?),
        None => None,
    };
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
                Ok(Message::Heartbeat { run, tick, zone, state, load }) if (zone.0 as usize) < cfg.zones => {
                    // Heartbeats are signed but could be replayed: one that goes back in
                    // (epoch, tick) is an old one and is ignored. A restarted zone starts
                    // at epoch 0 and is heard again once it takes the halt.
                    let fresh = last.get(&zone).is_none_or(|b| (run, tick) >= (b.run, b.tick) || run == 0);
                    if fresh {
                        last.insert(zone, Heard { at: Instant::now(), run, tick, state, load });
                    }
                }
                Ok(_) | Err(_) => tracing::debug!("a message on the heartbeat subject was not a heartbeat"),
            }
        }
        let now = Instant::now();
        if halting {
            if epoch == 0 {
                // The first epoch follows whatever epochs zones already went through.
                epoch = last.values().map(|b| b.run).max().unwrap_or(0) + 1;
            }
            let ready = (0..cfg.zones).all(|z| {
                last.get(&ZoneId(z as u16))
                    .is_some_and(|b| b.run == epoch && b.state == ZoneState::Waiting && now - b.at < cfg.dead_after)
            });
            if ready {
                // The checkpoints zones may still hold, newest first.
                let every = cfg.checkpoint_every.max(1);
                let newest = last.values().map(|b| b.tick).max().unwrap_or(0).min(cfg.ticks) / every * every;
                let candidates: Vec<u64> =
                    (0..=crate::process::KEEP).filter_map(|i| newest.checked_sub(i * every)).collect();
                let (tick, cuts, state_hash) = start_point(cfg, store, &candidates)?;
                if let Some(a) = &mut announcer {
                    a.restart(tick, &cuts)?;
                }
                link.publish(
                    control_subject(&cfg.cluster),
                    encode_control(&cfg.key, &Message::Start { run: epoch, tick, cuts })?,
                )?;
                on_event(&Event::Started { epoch, tick, state_hash });
                halting = false;
                // Zones get a fresh deadline from the start.
                for b in last.values_mut() {
                    b.at = now;
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
                Some(b) if now - b.at > cfg.dead_after => {
                    fault.get_or_insert_with(|| format!("zone {} silent for {} ms", z.0, (now - b.at).as_millis()));
                }
                Some(b) if b.run == epoch && b.state == ZoneState::Stalled => {
                    fault.get_or_insert_with(|| format!("zone {} stalled at tick {}", z.0, b.tick));
                }
                None => {
                    fault.get_or_insert_with(|| format!("zone {} never heard", z.0));
                }
                _ => {}
            }
        }
        if fault.is_none()
            && let Some(a) = &mut announcer
        {
            fault = rebalance(cfg, link, a, &last, epoch, since.elapsed().as_secs_f64(), on_event)?;
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
            let tick = last.values().filter(|b| b.run == epoch).map(|b| b.tick).min().unwrap_or(0);
            on_event(&Event::Progress { epoch, tick, beats: epoch_beats(cfg, &last, epoch) });
        }
        let done = (0..cfg.zones).all(|z| {
            last.get(&ZoneId(z as u16))
                .is_some_and(|b| b.run == epoch && b.state == ZoneState::Done && b.tick == cfg.ticks)
        });
        if done {
            let (state_hash, _) = assemble(store, cfg.zones, cfg.ticks, cfg.objects)?;
            on_event(&Event::Done { state_hash });
            return Ok(state_hash);
        }
    }
}

/// Each zone's latest heartbeat of `epoch`, by zone (`None`: not heard in it): what the
/// rebalancing looks at and the progress reports.
fn epoch_beats(cfg: &SupervisorConfig, last: &BTreeMap<ZoneId, Heard>, epoch: u64) -> Vec<Option<ZoneBeat>> {
    (0..cfg.zones)
        .map(|z| {
            let b = last.get(&ZoneId(z as u16)).filter(|b| b.run == epoch)?;
            Some(ZoneBeat { tick: b.tick, state: b.state, load: b.load })
        })
        .collect()
}

/// One look of the rebalancing at the epoch's heartbeats: publishes what the announcer
/// sends, reports the rest, and returns a fault when a zone steps on other cuts than
/// announced.
fn rebalance(
    cfg: &SupervisorConfig,
    link: &NatsLink,
    a: &mut Announcer,
    last: &BTreeMap<ZoneId, Heard>,
    epoch: u64,
    now: f64,
    on_event: &mut dyn FnMut(&Event),
) -> Result<Option<String>, ZoneError> {
    let beats = epoch_beats(cfg, last, epoch);
    let mut fault = None;
    for what in a.observe(now, &beats) {
        match what {
            Announcement::Send { ref cut, first } => {
                link.publish(cuts_subject(&cfg.cluster), encode_cut_move(&cfg.key, epoch, cut)?)?;
                if first {
                    tracing::info!(epoch, apply_at = cut.apply_at, xs = ?cut.xs, zs = ?cut.zs, "cut move announced");
                    on_event(&Event::Cuts { epoch, what });
                }
            }
            Announcement::Diverged(reason) => fault = Some(reason),
            what @ (Announcement::Applied(_) | Announcement::Refused { .. }) => on_event(&Event::Cuts { epoch, what }),
        }
    }
    a.export(&beats);
    Ok(fault)
}

/// A cut move as the cluster prints it.
pub fn cut_move_line(cut: &CutMove) -> String {
    format!("decided at tick {}, applied at tick {}: x {:?}, z {:?}", cut.decided_at, cut.apply_at, cut.xs, cut.zs)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::checkpoint::MemoryCheckpoints;
    use myriad_core::{Aabb, Vec3};

    fn object(id: u32) -> ObjectState {
        crate::test_objects::npc_at(id, Vec3::ONE)
    }

    /// Two zones of two objects, checkpoints every 30 ticks.
    fn two_zones(key: &ClusterKey, layout: ZoneLayout) -> SupervisorConfig {
        SupervisorConfig {
            cluster: "c".into(),
            key: key.clone(),
            zones: 2,
            ticks: 300,
            objects: Some(2),
            dead_after: Duration::from_secs(1),
            checkpoint_every: 30,
            layout,
            rebalance: None,
        }
    }

    /// A zone that missed a cut move stores its checkpoints on the old cuts: a rollback
    /// passes over the ticks whose checkpoints disagree, to the newest where all agree.
    #[test]
    fn a_rollback_starts_from_the_newest_checkpoint_whose_cuts_agree() {
        let key = ClusterKey::random();
        let layout = ZoneLayout::for_count(&Aabb::new(Vec3::ZERO, Vec3::splat(100.0)), 2, 1.5, 2.0).unwrap();
        let cfg = two_zones(&key, layout);
        let mut store = MemoryCheckpoints::new(key);
        let old = (vec![0.0, 50.0, 100.0], vec![0.0, 100.0]);
        let moved = (vec![0.0, 60.0, 100.0], vec![0.0, 100.0]);
        for (t, zone1_cuts) in [(30, &old), (60, &old), (90, &moved)] {
            store.put(ZoneId(0), t, 1, if t == 30 { &old } else { &moved }, &[object(1)]).unwrap();
            store.put(ZoneId(1), t, 1, zone1_cuts, &[object(2)]).unwrap();
        }
        // Tick 60: zone 1 still on the old cuts (it missed the move of tick 45).
        let (tick, cuts, hash) = start_point(&cfg, &mut store, &[60, 30, 0]).unwrap();
        assert_eq!((tick, &cuts), (30, &old));
        assert!(hash.is_some());
        assert!(assemble(&mut store, 2, 60, None).is_err(), "a world of two cuts is not one world");
        // Tick 90 agrees again (on the moved cuts) and is the newest: taken.
        assert_eq!(start_point(&cfg, &mut store, &[90, 60, 30]).unwrap().1, moved);
        // No checkpoint: the generated world on the layout's own cuts.
        let (tick, cuts, hash) = start_point(&cfg, &mut store, &[150, 120]).unwrap();
        assert_eq!((tick, cuts, hash), (0, old, None));
    }

    /// After a rollback the zones write their checkpoints of a tick again, in the new
    /// epoch; a fault while only some have leaves that tick with two epochs' states,
    /// which a rollback passes over.
    #[test]
    fn a_rollback_passes_over_a_tick_whose_checkpoints_come_from_two_epochs() {
        let key = ClusterKey::random();
        let layout = ZoneLayout::for_count(&Aabb::new(Vec3::ZERO, Vec3::splat(100.0)), 2, 1.5, 2.0).unwrap();
        let (xs, zs) = layout.cuts();
        let cuts = (xs.to_vec(), zs.to_vec());
        let cfg = two_zones(&key, layout);
        let mut store = MemoryCheckpoints::new(key);
        for t in [30, 60] {
            store.put(ZoneId(0), t, 1, &cuts, &[object(1)]).unwrap();
            store.put(ZoneId(1), t, 1, &cuts, &[object(2)]).unwrap();
        }
        // Epoch 2 restarted from 30 and zone 1 stored 60 again, with another history
        // (its object moved otherwise: live intents arrive at other ticks); zone 0's 60
        // is still epoch 1's. Nothing is missing or doubled: only the epochs tell.
        let elsewhere = crate::test_objects::npc_at(2, Vec3::splat(3.0));
        store.put(ZoneId(1), 60, 2, &cuts, &[elsewhere]).unwrap();
        let (tick, _, hash) = start_point(&cfg, &mut store, &[60, 30, 0]).unwrap();
        assert_eq!(tick, 30);
        assert!(hash.is_some());
        let err = assemble(&mut store, 2, 60, None).unwrap_err().to_string();
        assert!(err.contains("epochs"), "{err}");
        // Once zone 0 has stored it in epoch 2 too, tick 60 is one world again.
        store.put(ZoneId(0), 60, 2, &cuts, &[object(1)]).unwrap();
        assert_eq!(start_point(&cfg, &mut store, &[60, 30, 0]).unwrap().0, 60);
    }
}
