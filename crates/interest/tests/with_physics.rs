//! Interest management fed by a real physics backend's AOI query, as the server wires
//! them: world → `Backend::query_aoi` (one box per player) → `InterestManager::build` →
//! sealed datagrams → each player's client opens them, resolves the records against
//! what it holds and acknowledges them → `Subscriber::acknowledge` → the next tick.

use std::collections::{HashMap, HashSet};

use myriad_core::{Aabb, EntityId, ObjectKind as Who, ScenarioSpec, ShapeKind, Vec3, World};
use myriad_interest::{AoiLists, InterestConfig, InterestManager, SoaObjects, Subscriber, TickInfo};
use myriad_physics::{AoiResults, BackendKind, TickConstants, create_cpu_backend};
use myriad_protocol::{
    AckTracker, Baselines, ClientSession, QuantPos, ServerMessage, ServerSession, SessionKeys, ShapeKind as WireKind,
};

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

/// A player's client: what it holds of each object, `(tick, kind, position)`.
struct Client {
    session: ClientSession,
    baselines: Baselines,
    acks: AckTracker,
    held: HashMap<u64, (u64, WireKind, QuantPos)>,
}

/// The world as the server hands it to the manager this tick.
struct Snapshot {
    ids: Vec<u64>,
    kinds: Vec<WireKind>,
    positions: Vec<[f32; 3]>,
}

impl Snapshot {
    fn of(world: &World) -> Self {
        let d = &world.dynamics;
        Self {
            ids: d.ids().iter().map(|id| u64::from(id.0)).collect(),
            kinds: d.shapes().iter().map(|s| kind(*s)).collect(),
            positions: d.positions().iter().map(|p| p.to_array()).collect(),
        }
    }
}

#[test]
fn every_player_comes_to_hold_exactly_its_area_of_interest() {
    let small = ScenarioSpec::custom(77).counts(3_000, 60, 30).map_size(256.0, 65);
    let start = ScenarioSpec { origin: Vec3::new(-10_000.0, 0.0, 25_000.0), max_height: 4.0, ..small }.build().unwrap();
    let half = Vec3::new(12.0, 50.0, 12.0);
    // The server's default: 64 kbit/s at 30 Hz, two datagrams a tick.
    let config = InterestConfig::default();
    let r = config.replication;
    // Once the world stands still, every object in a view reaches its client within
    // these many ticks: one new to the client starves after `max_wait_ticks` and goes
    // over the budget, one that changed goes within its bound (the far bound at most)
    // or starves a tick later than a new one (its priority, a sum of rates, rounds
    // below `max_wait_ticks` rates), and one the client holds is confirmed by a `Same`
    // record every `refresh_ticks`. An object that left a view before is sent no more.
    let settle =
        [r.max_wait_ticks + 1.0, r.far_bound_ticks, r.refresh_ticks].into_iter().fold(0.0, f32::max).ceil() as u64 + 1;
    let moving = 30u64;

    for backend_kind in BackendKind::ALL {
        let mut world = start.clone();
        let mut backend = create_cpu_backend(backend_kind).unwrap();
        let d = &world.dynamics;
        let players: Vec<EntityId> = (0..d.len()).filter(|&s| d.kinds()[s] == Who::User).map(|s| d.ids()[s]).collect();
        let mut subs: Vec<Subscriber> = (0..players.len())
            .map(|i| Subscriber::new(0, [0.0; 3], ServerSession::new(&keys(i as u64)).sealer))
            .collect();
        let mut clients: Vec<Client> = (0..players.len())
            .map(|i| Client {
                session: ClientSession::new(&keys(i as u64)),
                baselines: Baselines::default(),
                acks: AckTracker::default(),
                held: HashMap::new(),
            })
            .collect();
        let manager = InterestManager::new(config);
        let mut aoi = AoiResults::default();
        let (mut records, mut relative, mut deferred) = (0, 0, 0);
        // The physics runs (NPCs wander, everything falls and settles), then stops.
        for tick in 1..=moving + settle {
            if tick <= moving {
                backend.step(&mut world, &TickConstants::default()).unwrap();
            }
            let d = &world.dynamics;
            let now = Snapshot::of(&world);
            let slots: Vec<usize> = players.iter().map(|&id| d.slot(id).expect("players stay")).collect();
            let boxes: Vec<Aabb> = slots.iter().map(|&s| Aabb::from_center_half(d.positions()[s], half)).collect();
            backend.query_aoi(&world, &boxes, &mut aoi).unwrap();
            for (s, &slot) in subs.iter_mut().zip(&slots) {
                s.object = slot as u32;
                s.centre = now.positions[slot];
            }
            let objects = SoaObjects { ids: &now.ids, kinds: &now.kinds, positions: &now.positions };
            let lists = AoiLists { offsets: &aoi.offsets, objects: &aoi.objects };
            let report = manager.build(TickInfo { tick, dilation_permille: 1000 }, &objects, lists, &mut subs).unwrap();
            assert_eq!((report.skipped, report.seal_failures), (0, 0));
            (records, relative, deferred) =
                (records + report.records, relative + report.relative, deferred + report.deferred);

            for (i, (sub, client)) in subs.iter_mut().zip(&mut clients).enumerate() {
                let view: HashSet<u64> = aoi.get(i).iter().map(|&s| now.ids[s as usize]).collect();
                for datagram in sub.datagrams().iter() {
                    let mut bytes = datagram.to_vec();
                    let opened = client.session.open(&mut bytes).unwrap();
                    let ServerMessage::StateUpdate(update) = opened.message else { panic!("expected a state update") };
                    assert_eq!(update.header.tick, tick);
                    let mut states = Vec::new();
                    assert_eq!(client.baselines.resolve_update(&update, &mut states), 0, "{backend_kind}: player {i}");
                    client.acks.record(opened.header.sequence);
                    // Each state is the object's, in view, as the world has it this tick.
                    for s in states {
                        assert!(view.contains(&s.id), "{backend_kind}: player {i} sent object {} not in view", s.id);
                        let slot = d.slot(EntityId(s.id as u32)).expect("a known object");
                        assert_eq!((s.kind, s.pos), (now.kinds[slot], QuantPos::from_f32(now.positions[slot])));
                        client.held.insert(s.id, (tick, s.kind, s.pos));
                    }
                }
                if let Some(field) = client.acks.field() {
                    sub.acknowledge(field);
                }
            }
        }

        // Standing still for `settle` ticks, each client heard of exactly the objects
        // whose boxes overlap its player's AOI box, the player's own included, and holds
        // each at its position.
        let now = Snapshot::of(&world);
        let (mut seen_others, mut left) = (0, 0);
        for (i, client) in clients.iter().enumerate() {
            let want: HashMap<u64, (WireKind, QuantPos)> = aoi
                .get(i)
                .iter()
                .map(|&s| (now.ids[s as usize], (now.kinds[s as usize], QuantPos::from_f32(now.positions[s as usize]))))
                .collect();
            let heard: HashMap<u64, (WireKind, QuantPos)> = client
                .held
                .iter()
                .filter(|(_, h)| h.0 > moving)
                .map(|(&id, &(_, kind, pos))| (id, (kind, pos)))
                .collect();
            assert!(want.contains_key(&u64::from(players[i].0)), "{backend_kind}: player {i} misses its own object");
            assert_eq!(heard, want, "{backend_kind}: player {i}");
            seen_others += want.len() - 1;
            left += client.held.len() - heard.len();
        }
        assert!(seen_others > 100, "players must see each other, saw {seen_others}");
        // Not vacuous: objects left views (and their clients heard no more of them), the
        // views did not fit the budget at once, and deltas were used.
        assert!(left > 0 && deferred > 0, "{left} objects left views, {deferred} deferred");
        assert!(relative > records / 2, "{relative} of {records} records relative");
    }
}
