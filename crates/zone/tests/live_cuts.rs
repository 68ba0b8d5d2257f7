//! Cut moves from the fabric, as a live cluster's zones take them (in memory, without
//! processes): the supervisor's signed move reaches every zone, which follows it at its
//! tick, and the world ends in one process's hash; moves that are forged, invalid, late,
//! of another epoch or in conflict with the one held are refused and counted and change
//! nothing; a checkpoint records the cuts, zones restarted from it resume on the moved
//! cuts, and a replay of the logs applies the move at its tick and ends in the live hash.

use std::sync::Arc;
use std::sync::mpsc::{Receiver, Sender, channel};
use std::time::{Duration, Instant};

use myriad_core::{ActionScript, ScenarioSpec, World};
use myriad_physics::TickConstants;
use myriad_zone::checkpoint::{CheckpointStore, MemoryCheckpoints};
use myriad_zone::rebalance::CutMove;
use myriad_zone::replay::{is_cut_move, load, replay};
use myriad_zone::supervisor::{assemble, assemble_with_cuts};
use myriad_zone::wire::encode_cut_move;
use myriad_zone::{
    ClusterKey, Fabric, MemoryFabric, Zone, ZoneConfig, ZoneError, ZoneId, ZoneLayout, ZoneStats, pair_reach,
};

mod common;
use common::{cpu, single};

const EPOCH: u64 = 7;
const EVERY: u64 = 30;
/// The tick the good move applies at.
const APPLY: u64 = 40;

/// A zone's fabric with a supervisor's channel beside it: what the test sends there is
/// received before anything else waiting (as a zone's NATS subscription to the cuts
/// subject delivers it among the borders).
struct WithSupervisor {
    inner: MemoryFabric,
    supervisor: Receiver<Vec<u8>>,
}

impl Fabric for WithSupervisor {
    fn send(&mut self, to: ZoneId, bytes: Vec<u8>) -> Result<(), ZoneError> {
        self.inner.send(to, bytes)
    }
    fn publish_states(&mut self, bytes: Vec<u8>) -> Result<(), ZoneError> {
        self.inner.publish_states(bytes)
    }
    fn send_view(&mut self, gateway: u16, bytes: Vec<u8>) -> Result<(), ZoneError> {
        self.inner.send_view(gateway, bytes)
    }
    fn recv(&mut self, deadline: Instant) -> Result<Option<Vec<u8>>, ZoneError> {
        match self.supervisor.try_recv() {
            Ok(b) => Ok(Some(b)),
            Err(_) => self.inner.recv(deadline),
        }
    }
    fn max_message(&self) -> usize {
        self.inner.max_message()
    }
    fn bytes(&self) -> (u64, u64) {
        self.inner.bytes()
    }
}

/// How a zone thread makes its zone, given its fabric.
type MakeZone<'a> = Box<dyn FnOnce(Box<dyn Fabric>) -> Zone + Send + 'a>;

/// A small dense world: strips of objects lie between a cut and its moved place.
fn world() -> World {
    ScenarioSpec::custom(5).counts(600, 60, 60).map_size(96.0, 33).build().unwrap()
}

fn layout(world: &World) -> ZoneLayout {
    ZoneLayout::for_count(&world.bounds, 4, pair_reach(world), 2.0).unwrap()
}

/// The good move: the x cut 6 units up, the z cut 6 down, at tick [`APPLY`].
fn good_move(l: &ZoneLayout) -> CutMove {
    let (xs, zs) = l.cuts();
    CutMove {
        decided_at: 10,
        apply_at: APPLY,
        xs: vec![xs[0], xs[1] + 6.0, xs[2]],
        zs: vec![zs[0], zs[1] - 6.0, zs[2]],
    }
}

/// Zones on threads from their starts (`zones`) to tick `until`, each storing a
/// checkpoint and its log segment every [`EVERY`] ticks (as a zone process does), with
/// `messages` waiting on every zone's supervisor channel; returns each zone's counters.
fn run(
    zones: Vec<MakeZone<'_>>,
    messages: &[Vec<u8>],
    script: &ActionScript,
    until: u64,
    store: &MemoryCheckpoints,
) -> Vec<ZoneStats> {
    let k = TickConstants::default();
    let n = zones.len();
    let (txs, rxs): (Vec<Sender<Vec<u8>>>, Vec<_>) = (0..n).map(|_| channel()).unzip();
    for tx in &txs {
        messages.iter().for_each(|m| tx.send(m.clone()).unwrap());
    }
    std::thread::scope(|s| {
        let handles: Vec<_> = zones
            .into_iter()
            .zip(MemoryFabric::mesh(n).into_iter().zip(rxs))
            .map(|(make, (inner, supervisor))| {
                let (k, mut store) = (&k, store.clone());
                s.spawn(move || {
                    let mut zone = make(Box::new(WithSupervisor { inner, supervisor }));
                    loop {
                        let t = zone.tick();
                        if t.is_multiple_of(EVERY) || t == until {
                            if let Some((from, segment)) = zone.checkpoint_log(EPOCH) {
                                store.put_log(zone.id(), from, &segment).unwrap();
                            }
                            store.put(zone.id(), t, EPOCH, &zone.stepped_cuts(), &zone.advanced()).unwrap();
                        }
                        if t >= until {
                            break zone.stats().clone();
                        }
                        zone.step(script.at(t), k).unwrap();
                    }
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    })
}

fn config(key: &ClusterKey, z: usize) -> ZoneConfig {
    ZoneConfig { id: ZoneId(z as u16), run: EPOCH, key: key.clone(), wait: Duration::from_secs(30), live: false }
}

/// Zones made from the generated world on `layout`.
fn fresh<'a>(world: &'a World, layout: &ZoneLayout, key: &'a ClusterKey) -> Vec<MakeZone<'a>> {
    let shared = Arc::new(layout.clone());
    (0..layout.len())
        .map(|z| {
            let l = shared.clone();
            Box::new(move |f: Box<dyn Fabric>| Zone::new(config(key, z), l, world, cpu(ZoneId(0)).unwrap(), f).unwrap())
                as MakeZone<'a>
        })
        .collect()
}

#[test]
fn a_move_from_the_fabric_applies_at_its_tick_and_bad_ones_are_refused_and_counted() {
    let world = world();
    let l = layout(&world);
    let key = ClusterKey::random();
    let script = ActionScript::walkers(&world, 60, 90, 4);
    let good = good_move(&l);
    let (xs, zs) = (good.xs.clone(), good.zs.clone());
    let stranger = ClusterKey::new(b"not the cluster's key at all!!").unwrap();
    let messages = vec![
        // Refused before the good one arrives: each for its own reason.
        encode_cut_move(&stranger, EPOCH, &good).unwrap(), // forged: tag
        encode_cut_move(&key, EPOCH + 1, &good).unwrap(),  // another epoch
        // For tick 0, which the zones are stepping when it arrives: late.
        encode_cut_move(&key, EPOCH, &CutMove { apply_at: 0, decided_at: 0, ..good.clone() }).unwrap(),
        // A zone 1.5 units wide: narrower than reach + max step.
        encode_cut_move(&key, EPOCH, &CutMove { xs: vec![xs[0], xs[0] + 1.5, xs[2]], ..good.clone() }).unwrap(),
        encode_cut_move(&key, EPOCH, &good).unwrap(),
        // A repeat is recognised; another move for the same tick conflicts.
        encode_cut_move(&key, EPOCH, &good).unwrap(),
        encode_cut_move(&key, EPOCH, &CutMove { xs: vec![xs[0], xs[1] + 1.0, xs[2]], ..good.clone() }).unwrap(),
    ];
    let store = MemoryCheckpoints::new(key.clone());
    let stats = run(fresh(&world, &l, &key), &messages, &script, 90, &store);
    let mut s = store;
    let (hash, objects, cuts) = assemble_with_cuts(&mut s, 4, 90, Some(world.dynamics.len())).unwrap().unwrap();
    assert_eq!(hash, single(&world, 90, &script), "one process's hash with the move");
    assert_eq!(cuts, (xs.clone(), zs.clone()), "every zone's checkpoint holds the moved cuts");
    assert_eq!(s.get(ZoneId(0), 30).unwrap().cuts, (l.cuts().0.to_vec(), l.cuts().1.to_vec()), "before: the old");
    for (z, st) in stats.iter().enumerate() {
        assert_eq!(st.cut_moves, 1, "zone {z} followed the move once: {st:?}");
        assert_eq!(st.cut_moves_refused, 4, "zone {z}: another epoch, late, invalid, conflict: {:?}", st.rejected);
        for reason in ["tag", "cut_run", "cut_late", "cut_invalid", "cut_conflict"] {
            assert_eq!(st.rejected.get(reason), Some(&1), "zone {z}: {reason} in {:?}", st.rejected);
        }
    }
    // The strips between the old cuts and the new changed hands at tick 40.
    let moved = layout(&world).with_cuts(&xs, &zs).unwrap();
    let old = &l;
    let strip = objects.iter().filter(|o| moved.zone_at(o.pos) != old.zone_at(o.pos)).count();
    assert!(strip > 10, "{strip} objects lie between the old cuts and the new");
    let handed: u64 = stats.iter().map(|s| s.handoffs_in).sum();
    assert!(handed as usize >= strip, "{handed} hand-offs for a strip of {strip}");
}

#[test]
fn zones_restarted_after_a_move_resume_on_its_cuts_and_a_replay_applies_it_at_its_tick() {
    let world = world();
    let l = layout(&world);
    let key = ClusterKey::random();
    let script = ActionScript::walkers(&world, 60, 150, 4);
    let good = good_move(&l);
    let store = MemoryCheckpoints::new(key.clone());
    run(fresh(&world, &l, &key), &[encode_cut_move(&key, EPOCH, &good).unwrap()], &script, 90, &store);
    let mut s = store.clone();
    let live = assemble(&mut s, 4, 90, None).unwrap().0;

    // Killed at tick 90 and restarted from the checkpoint: on the moved cuts.
    let mut at = world.clone();
    at.tick = 90;
    let restarted: Vec<MakeZone<'_>> = (0..4)
        .map(|z| {
            let snap = s.get(ZoneId(z as u16), 90).unwrap();
            let moved = Arc::new(l.with_cuts(&snap.cuts.0, &snap.cuts.1).unwrap());
            let (at, key) = (&at, &key);
            Box::new(move |f: Box<dyn Fabric>| {
                Zone::resume(config(key, z), moved, at, snap.objects, cpu(ZoneId(0)).unwrap(), f).unwrap()
            }) as MakeZone<'_>
        })
        .collect();
    run(restarted, &[], &script, 150, &store);
    let (end, _, cuts) = assemble_with_cuts(&mut s, 4, 150, Some(world.dynamics.len())).unwrap().unwrap();
    assert_eq!(end, single(&world, 150, &script), "resumed on the moved cuts: one process's hash");
    assert_eq!(cuts, (good.xs.clone(), good.zs.clone()));

    // The replay of ticks 0..90 and 30..90 applies the logged move at tick 40.
    let k = TickConstants::default();
    for from in [0, 30] {
        let (_, inputs) = load(&mut s, &key, 4, from, 90).unwrap();
        assert!(inputs.iter().all(|z| z.entries.iter().filter(|(t, m)| *t == APPLY && is_cut_move(m)).count() == 1));
        let r = replay(&world, l.clone(), &script, &k, &cpu, inputs, &key, from, 90).unwrap();
        assert_eq!(r.state_hash, live, "replayed from tick {from}");
        assert!(r.stats.iter().all(|s| s.cut_moves == 1), "every zone followed the logged move");
    }
    // From the restart's checkpoint: on its cuts, with nothing to move.
    let (_, inputs) = load(&mut s, &key, 4, 90, 150).unwrap();
    let r = replay(&world, l.clone(), &script, &k, &cpu, inputs, &key, 90, 150).unwrap();
    assert_eq!((r.state_hash, r.cut_moves), (end, 0));
    // A log whose move is at another tick than it names is refused, not followed there.
    let (_, mut inputs) = load(&mut s, &key, 4, 30, 90).unwrap();
    for (t, m) in inputs.iter_mut().flat_map(|z| z.entries.iter_mut()) {
        if is_cut_move(m) {
            *t += 1;
        }
    }
    let e = replay(&world, l.clone(), &script, &k, &cpu, inputs, &key, 30, 90).unwrap_err().to_string();
    assert!(e.contains("refused a cut move"), "{e}");
}
