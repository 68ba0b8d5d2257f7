//! A live run replays bit for bit: two zones on threads take a gateway's players (joins,
//! changing actions, a walk across the cut, leaves) at whatever tick their intents
//! arrive; each zone logs what it took and stores a checkpoint and a log segment every
//! 20 ticks, as a zone process does. Replayed from tick 0 or from a checkpoint in the
//! middle (the book restored), the world ends in the live run's hash; replayed without
//! the intents, it does not.

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;

use myriad_core::{Action, ActionScript, ObjectKind, ScenarioSpec, Shape, Vec3, World};
use myriad_physics::{Backend, TickConstants};
use myriad_zone::checkpoint::{CheckpointStore, MemoryCheckpoints};
use myriad_zone::replay::{load, replay};
use myriad_zone::supervisor::assemble;
use myriad_zone::{ClusterKey, GatewayConfig, MemoryFabric, Zone, ZoneConfig, ZoneId, ZoneLayout, ZonesBackend};

mod common;

/// The gateway of the test.
const GW: u16 = 2;

const TICKS: u64 = 260;
const EVERY: u64 = 20;
const EPOCH: u64 = 1;

fn small_world() -> World {
    ScenarioSpec { max_height: 2.0, ..ScenarioSpec::custom(5).counts(80, 0, 0).map_size(64.0, 65) }.build().unwrap()
}

/// What a zone process does at a checkpoint: the objects, then the log since the last.
fn checkpoint(zone: &mut Zone, store: &mut MemoryCheckpoints) {
    let t = zone.tick();
    store.put(zone.id(), t, EPOCH, &zone.stepped_cuts(), &zone.advanced()).unwrap();
    if let Some((from, segment)) = zone.checkpoint_log(EPOCH) {
        store.put_log(zone.id(), from, &segment).unwrap();
    }
}

#[test]
fn a_live_run_with_players_replays_to_its_hash() {
    let world = small_world();
    let layout = ZoneLayout::for_count(&world.bounds, 2, myriad_zone::pair_reach(&world), 2.0).unwrap();
    let shared = Arc::new(layout.clone());
    let key = ClusterKey::random();
    let store = MemoryCheckpoints::new(key.clone());
    let (fabrics, link) = MemoryFabric::mesh_with_gateway(2, GW);
    let k = TickConstants::default();
    let cut = layout.region(ZoneId(0)).max_x;
    let finished = AtomicUsize::new(0);

    let taken = std::thread::scope(|s| {
        let zones: Vec<_> = fabrics
            .into_iter()
            .enumerate()
            .map(|(i, fabric)| {
                let (layout, key, world, k, mut store) = (shared.clone(), key.clone(), &world, &k, store.clone());
                let finished = &finished;
                s.spawn(move || {
                    let id = ZoneId(i as u16);
                    let cfg = ZoneConfig { id, run: EPOCH, key, wait: Duration::from_secs(5), live: true };
                    let mut zone = Zone::new(cfg, layout, world, common::cpu(id).unwrap(), Box::new(fabric)).unwrap();
                    while zone.tick() < TICKS {
                        if zone.tick().is_multiple_of(EVERY) {
                            checkpoint(&mut zone, &mut store);
                        }
                        zone.step(&[], k).unwrap();
                        std::thread::sleep(Duration::from_millis(1));
                    }
                    checkpoint(&mut zone, &mut store);
                    finished.fetch_add(1, Ordering::SeqCst);
                    zone.stats().messages.1
                })
            })
            .collect();
        s.spawn(|| {
            let cfg = GatewayConfig {
                gateway: GW,
                key: key.clone(),
                zones: 2,
                wait: Duration::from_secs(2),
                refresh: 30,
                interest: None,
            };
            let mut backend = ZonesBackend::new(cfg, Box::new(link)).unwrap();
            let mut gw = world.clone();
            backend.prepare(&mut gw);
            let shape = Shape::Capsule { radius: 0.4, half_height: 0.5 };
            let mut players = Vec::new();
            // The players play until the zones reach their last tick: the end holds them.
            for step in 0u32.. {
                if finished.load(Ordering::SeqCst) == 2 {
                    break;
                }
                backend.step(&mut gw, &k).unwrap();
                // A player joins every 10 worlds, a few units before the cut, and walks
                // right, left or stands; some leave again.
                if step % 10 == 0 && players.len() < 8 {
                    let z = 4.0 + 6.0 * players.len() as f32;
                    let at = Vec3::new(cut - 3.0, 0.0, z);
                    let at = Vec3::new(at.x, gw.terrain.height_at(at.x, at.z) + 1.2, at.z);
                    players.push(gw.dynamics.spawn(shape, at, ObjectKind::User).unwrap());
                }
                for (i, p) in players.iter().enumerate() {
                    let bits =
                        [Action::RIGHT, Action::LEFT, 0, Action::RIGHT | Action::JUMP][(i + step as usize / 7) % 4];
                    gw.dynamics.set_action(*p, Action::from_bits(bits).unwrap());
                }
                if step == 100 {
                    gw.dynamics.despawn(players.remove(0));
                }
                std::thread::sleep(Duration::from_millis(2));
            }
            drop(backend);
        });
        zones.into_iter().map(|h| h.join().unwrap()).sum::<u64>()
    });

    let mut store = store;
    let live = assemble(&mut store, 2, TICKS, None).unwrap().0;
    let script = ActionScript::default();
    let backend = |z: ZoneId| common::cpu(z);
    let replayed = |store: &mut MemoryCheckpoints, from: u64, strip: bool| {
        let (epoch, mut inputs) = load(store, &key, 2, from, TICKS).unwrap();
        assert_eq!(epoch, EPOCH);
        if strip {
            inputs.iter_mut().for_each(|z| z.entries.clear());
        }
        let intents: usize = inputs.iter().map(|z| z.entries.len()).sum();
        (replay(&world, layout.clone(), &script, &k, &backend, inputs, &key, from, TICKS).unwrap(), intents)
    };
    let (whole, intents) = replayed(&mut store, 0, false);
    assert!(intents > 10 && taken >= intents as u64, "{intents} intents messages logged, {taken} messages taken");
    assert_eq!(whole.state_hash, live, "replayed from tick 0, the world ends as the live run did");
    assert!(whole.objects.len() > world.dynamics.len(), "players are in the world at its end");
    let (middle, _) = replayed(&mut store, 120, false);
    assert_eq!(middle.state_hash, live, "from a checkpoint in the middle too: the book was restored");
    let (without, _) = replayed(&mut store, 0, true);
    assert_ne!(without.state_hash, live, "without the intents the run is another");
}

#[test]
fn damaged_or_missing_logs_are_refused() {
    let world = small_world();
    let layout = Arc::new(ZoneLayout::for_count(&world.bounds, 2, myriad_zone::pair_reach(&world), 2.0).unwrap());
    let key = ClusterKey::random();
    let mut store = MemoryCheckpoints::new(key.clone());
    let k = TickConstants::default();
    let fabrics = common::memory(2);
    std::thread::scope(|s| {
        for (i, fabric) in fabrics.into_iter().enumerate() {
            let (layout, key, world, k, mut store) = (layout.clone(), key.clone(), &world, &k, store.clone());
            s.spawn(move || {
                let id = ZoneId(i as u16);
                let cfg = ZoneConfig { id, run: EPOCH, key, wait: Duration::from_secs(5), live: false };
                let mut zone = Zone::new(cfg, layout, world, common::cpu(id).unwrap(), fabric).unwrap();
                while zone.tick() < 2 * EVERY {
                    if zone.tick().is_multiple_of(EVERY) {
                        checkpoint(&mut zone, &mut store);
                    }
                    zone.step(&[], k).unwrap();
                }
                checkpoint(&mut zone, &mut store);
            });
        }
    });
    assert!(load(&mut store, &key, 2, 0, 2 * EVERY).is_ok());
    assert!(load(&mut store, &ClusterKey::random(), 2, 0, 2 * EVERY).is_err(), "another cluster's key");
    let mut seg = store.get_log(ZoneId(1), EVERY).unwrap();
    let n = seg.len();
    seg[n / 2] ^= 0x10;
    store.put_log(ZoneId(1), EVERY, &seg).unwrap();
    let e = load(&mut store, &key, 2, 0, 2 * EVERY).unwrap_err().to_string();
    assert!(e.contains("intent log"), "{e}");
    // Zone 0's first segment stored as zone 1's: refused by its header.
    let other = store.get_log(ZoneId(0), 0).unwrap();
    store.put_log(ZoneId(1), 0, &other).unwrap();
    let other = store.get_log(ZoneId(0), EVERY).unwrap();
    store.put_log(ZoneId(1), EVERY, &other).unwrap();
    let e = load(&mut store, &key, 2, 0, 2 * EVERY).unwrap_err().to_string();
    assert!(e.contains("zone 0's"), "{e}");
    store.forget(ZoneId(1), EVERY).unwrap();
    assert!(load(&mut store, &key, 2, EVERY, 2 * EVERY).is_err(), "a forgotten checkpoint takes its log");
    // Without players, a stored run replays to its hash too.
    let live = assemble(&mut store, 2, 2 * EVERY, None).unwrap().0;
    assert_eq!(live, common::single(&world, 2 * EVERY, &ActionScript::default()));
}
