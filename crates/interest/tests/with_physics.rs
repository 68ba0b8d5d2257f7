//! Interest management fed by a real physics backend's AOI query, as the server wires
//! them: world → `Backend::query_aoi` (one box per player) → `InterestManager::build` →
//! sealed datagrams → each player's client opens and decodes them.

use std::collections::HashSet;

use myriad_core::{Aabb, ObjectKind as Who, ScenarioSpec, ShapeKind, Vec3};
use myriad_interest::{AoiLists, InterestConfig, InterestManager, SoaObjects, Subscriber, TickInfo};
use myriad_physics::{AoiResults, BackendKind, TickConstants, create_cpu_backend};
use myriad_protocol::{ClientSession, ServerMessage, ServerSession, SessionKeys, ShapeKind as WireKind};

fn keys(i: u64) -> SessionKeys {
    SessionKeys { session_id: i, client_to_server: [i as u8; 32], server_to_client: [(i as u8) ^ 0x5a; 32] }
}

fn kind(s: ShapeKind) -> WireKind {
    match s {
        ShapeKind::Sphere => WireKind::Sphere,
        ShapeKind::Box => WireKind::Box,
        ShapeKind::Capsule => WireKind::Capsule,
    }
}

#[test]
fn every_player_receives_exactly_its_area_of_interest() {
    let small = ScenarioSpec::custom(77).counts(3_000, 60, 30).map_size(256.0, 65);
    let start = ScenarioSpec { origin: Vec3::new(-10_000.0, 0.0, 25_000.0), max_height: 4.0, ..small }.build().unwrap();
    let half = Vec3::new(12.0, 50.0, 12.0); // the AOI box: small enough to fit the budget

    for backend_kind in BackendKind::ALL {
        let mut world = start.clone();
        let mut backend = create_cpu_backend(backend_kind).unwrap();
        for _ in 0..5 {
            backend.step(&mut world, &TickConstants::default()).unwrap();
        }
        let d = &world.dynamics;
        let players: Vec<usize> = (0..d.len()).filter(|&s| d.kinds()[s] == Who::User).collect();
        let boxes: Vec<Aabb> = players.iter().map(|&s| Aabb::from_center_half(d.positions()[s], half)).collect();
        let mut aoi = AoiResults::default();
        backend.query_aoi(&world, &boxes, &mut aoi).unwrap();

        let ids: Vec<u64> = d.ids().iter().map(|id| id.0 as u64).collect();
        let kinds: Vec<WireKind> = d.shapes().iter().map(|s| kind(*s)).collect();
        let positions: Vec<[f32; 3]> = d.positions().iter().map(|p| p.to_array()).collect();
        let objects = SoaObjects { ids: &ids, kinds: &kinds, positions: &positions };
        let mut subs: Vec<Subscriber> = players
            .iter()
            .enumerate()
            .map(|(i, &s)| Subscriber::new(s as u32, positions[s], ServerSession::new(&keys(i as u64)).sealer))
            .collect();
        let manager = InterestManager::new(InterestConfig::default());
        let lists = AoiLists { offsets: &aoi.offsets, objects: &aoi.objects };
        manager.build(TickInfo { tick: world.tick, dilation_permille: 1000 }, &objects, lists, &mut subs).unwrap();

        let mut seen_others = 0;
        for (i, (&slot, sub)) in players.iter().zip(&subs).enumerate() {
            let mut client = ClientSession::new(&keys(i as u64));
            let mut got = HashSet::new();
            for datagram in sub.datagrams().iter() {
                let mut bytes = datagram.to_vec();
                let ServerMessage::StateUpdate(update) = client.open(&mut bytes).unwrap().message else {
                    panic!("expected a state update");
                };
                assert_eq!(update.header.tick, world.tick);
                for r in update.records {
                    let s = d.slot(myriad_core::EntityId(r.id as u32)).expect("a known object");
                    assert_eq!(r.kind, kinds[s]);
                    let p = r.pos.to_f32();
                    for axis in 0..3 {
                        assert!(
                            (p[axis] - positions[s][axis]).abs() <= 1.0 / 128.0 + 1e-3,
                            "{p:?} vs {:?}",
                            positions[s]
                        );
                    }
                    got.insert(s as u32);
                }
            }
            // The view fits the default budget here, so it arrives whole: exactly the
            // objects whose boxes overlap the AOI box, the player's own included.
            let want: HashSet<u32> = aoi.get(i).iter().copied().collect();
            assert!(want.len() < 200, "the test needs views that fit the budget");
            assert!(got.contains(&(slot as u32)), "{backend_kind}: player {i} misses its own object");
            assert_eq!(got, want, "{backend_kind}: player {i}");
            seen_others += want.len() - 1;
        }
        assert!(seen_others > 100, "players must see each other, saw {seen_others}");
    }
}
