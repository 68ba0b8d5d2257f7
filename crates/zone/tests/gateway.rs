//! A gateway following zones on threads (in memory): a player's object joins through the
//! gateway, walks across the cut between two zones and changes owner, appears in every
//! world the gateway takes exactly once and without a gap, and leaves; a player still
//! connected when the gateway stops leaves with it.

use std::sync::Arc;
use std::time::Duration;

use myriad_core::{Action, ObjectKind, ScenarioSpec, Shape, Vec3, World};
use myriad_physics::{Backend, TickConstants};
use myriad_zone::gateway::player_ids;
use myriad_zone::{ClusterKey, GatewayConfig, MemoryFabric, Zone, ZoneConfig, ZoneId, ZoneLayout, ZonesBackend};

mod common;

/// The gateway of the test.
const GW: u16 = 3;

fn small_world() -> World {
    ScenarioSpec { max_height: 2.0, ..ScenarioSpec::custom(11).counts(60, 0, 0).map_size(64.0, 65) }.build().unwrap()
}

#[test]
fn a_player_joins_crosses_a_cut_without_a_gap_and_leaves() {
    let world = small_world();
    let layout = Arc::new(ZoneLayout::for_count(&world.bounds, 2, myriad_zone::pair_reach(&world), 2.0).unwrap());
    let key = ClusterKey::random();
    let (fabrics, link) = MemoryFabric::mesh_with_gateway(2, GW);
    let k = TickConstants::default();
    const ZONE_TICKS: u64 = 500;

    let cut = layout.region(ZoneId(0)).max_x;
    let (zones_out, gateway_out) = std::thread::scope(|s| {
        let zones: Vec<_> = fabrics
            .into_iter()
            .enumerate()
            .map(|(i, fabric)| {
                let (layout, key, world, k) = (layout.clone(), key.clone(), &world, &k);
                s.spawn(move || {
                    let id = ZoneId(i as u16);
                    let cfg = ZoneConfig { id, run: 1, key, wait: Duration::from_secs(5), live: true };
                    let mut zone = Zone::new(cfg, layout, world, common::cpu(id).unwrap(), Box::new(fabric)).unwrap();
                    for _ in 0..ZONE_TICKS {
                        zone.step(&[], k).unwrap();
                        // Paced, so the gateway follows tick by tick.
                        std::thread::sleep(Duration::from_millis(2));
                    }
                    (zone.advanced(), zone.stats().clone())
                })
            })
            .collect();

        let gateway = s.spawn(|| {
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
            backend.step(&mut gw, &k).unwrap();
            assert_eq!(
                gw.dynamics.len(),
                world.dynamics.len(),
                "the first world the gateway takes is the zones' whole world"
            );
            // A player logs in: the gateway's session code spawns its object, in the
            // gateway's id range, a few units before the cut, walking towards it.
            let at = Vec3::new(cut - 4.0, 0.0, 0.0);
            let at = Vec3::new(at.x, gw.terrain.height_at(at.x, at.z) + 1.2, at.z);
            let shape = Shape::Capsule { radius: 0.4, half_height: 0.5 };
            let player = gw.dynamics.spawn(shape, at, ObjectKind::User).unwrap();
            assert!(player_ids(3).contains(&player.0));
            gw.dynamics.set_action(player, Action::from_bits(Action::RIGHT).unwrap());
            // A second player stands still; it is still connected when the gateway stops.
            let at2 = Vec3::new(cut - 10.0, 0.0, 5.0);
            let at2 = Vec3::new(at2.x, gw.terrain.height_at(at2.x, at2.z) + 1.2, at2.z);
            let second = gw.dynamics.spawn(shape, at2, ObjectKind::User).unwrap();
            let mut xs = Vec::new();
            let mut crossed_at = None;
            for step in 0..400 {
                backend.step(&mut gw, &k).unwrap();
                let slot = gw.dynamics.slot(player).expect("the player's object is in every world the gateway shows");
                let x = gw.dynamics.positions()[slot].x;
                xs.push(x);
                if crossed_at.is_none() && x > cut + 2.0 {
                    crossed_at = Some(step);
                }
                if crossed_at.is_some_and(|c| step > c + 10) {
                    break;
                }
            }
            assert!(crossed_at.is_some(), "the player walked across the cut: {xs:?}");
            // Once adopted (a join takes a few of the zones' ticks, while the player stands
            // at its spawn point), every world moved it on: none without it, none that sent
            // it back, across the cut too.
            let moving = xs.iter().position(|x| *x > xs[0]).expect("it moved");
            assert!(moving < 30, "adopted after {moving} worlds");
            let stood = xs[moving..].windows(2).filter(|w| w[1] <= w[0]).count();
            assert!(stood <= 2, "the player stood still or went back in {stood} worlds: {xs:?}");
            // The player logs out.
            assert!(gw.dynamics.despawn(player));
            for _ in 0..20 {
                backend.step(&mut gw, &k).unwrap();
                assert!(gw.dynamics.slot(player).is_none(), "a player that left is not shown");
            }
            let shown = gw.dynamics.len();
            assert!(gw.dynamics.slot(second).is_some());
            let stats = backend.stats().clone();
            // The gateway stops: its remaining player leaves with it.
            drop(backend);
            (player, stats, shown)
        });
        let zones: Vec<_> = zones.into_iter().map(|h| h.join().unwrap()).collect();
        (zones, gateway.join().unwrap())
    });
    let (player, stats, shown) = gateway_out;
    assert_eq!(stats.duplicates, 0, "no object was claimed by two zones");
    assert!(stats.mirrors > 30, "{stats:?}");
    assert_eq!(stats.rejected.values().sum::<u64>(), 0, "{stats:?}");
    // What the gateway takes from the zones: today the whole world at every mirror.
    assert!(stats.zone_objects_in >= stats.mirrors * world.dynamics.len() as u64, "{stats:?}");
    assert!(stats.zone_bytes_in > 48 * stats.zone_objects_in, "48 bytes a record, plus headers: {stats:?}");
    assert_eq!(shown, world.dynamics.len() + 1, "the world and the second player");
    let (a, b) = (&zones_out[0], &zones_out[1]);
    assert!(a.1.states_bytes > 0 && b.1.states_bytes > 0, "live zones publish their states");
    assert!(a.1.states_bytes <= a.1.bytes.0, "the states are part of what a zone sends");
    assert_eq!(a.1.joins + b.1.joins, 2, "one zone adopted each player, once");
    assert_eq!(a.1.joins, 2, "zone 0 holds the spawn points");
    assert!(a.1.handoffs_out >= 1 && b.1.handoffs_in >= 1, "the player was handed from zone 0 to zone 1");
    assert_eq!(a.1.leaves + b.1.leaves, 2, "the owners removed both: one logged out, one left with its gateway");
    assert!(!a.0.iter().chain(&b.0).any(|o| o.id == player), "gone from every zone");
    assert_eq!(a.0.len() + b.0.len(), world.dynamics.len(), "the zones hold the world's objects once each");
}
