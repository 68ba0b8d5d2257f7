//! End-to-end tests: build, seal, then open with the client half of each session and
//! check what each player actually receives.

use std::collections::{HashMap, HashSet};

use myriad_interest::*;
use myriad_protocol::{ClientSession, SealLease, ServerMessage, ServerSession, SessionKeys, ShapeKind, StateRecord};

/// A tiny deterministic generator (xorshift64*), so failures reproduce.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
    fn f(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (self.next() >> 40) as f32 / (1u64 << 24) as f32 * (hi - lo)
    }
}

struct World {
    ids: Vec<u64>,
    kinds: Vec<ShapeKind>,
    positions: Vec<[f32; 3]>,
}

impl World {
    fn new(n: usize, rng: &mut Rng, id_offset: u64) -> Self {
        Self {
            ids: (0..n as u64).map(|i| id_offset + i * 3).collect(),
            kinds: (0..n).map(|i| [ShapeKind::Sphere, ShapeKind::Box, ShapeKind::Capsule][i % 3]).collect(),
            positions: (0..n).map(|_| [rng.f(-100.0, 100.0), rng.f(0.0, 20.0), rng.f(-100.0, 100.0)]).collect(),
        }
    }
    fn soa(&self) -> SoaObjects<'_> {
        SoaObjects { ids: &self.ids, kinds: &self.kinds, positions: &self.positions }
    }
}

fn keys(i: u64) -> SessionKeys {
    SessionKeys { session_id: i, client_to_server: [i as u8; 32], server_to_client: [(i as u8) ^ 0x55; 32] }
}

/// Opens every datagram of `sub` with `client`; returns the records in order and the
/// ticks of the updates.
fn receive(sub: &Subscriber, client: &mut ClientSession) -> (Vec<StateRecord>, Vec<u64>) {
    let mut records = Vec::new();
    let mut ticks = Vec::new();
    for d in sub.datagrams().iter() {
        assert!(d.len() <= myriad_protocol::MAX_DATAGRAM);
        let mut d = d.to_vec();
        match client.open(&mut d).expect("sealed datagram opens").message {
            ServerMessage::StateUpdate(u) => {
                ticks.push(u.header.tick);
                records.extend(u.records);
            }
            other => panic!("unexpected {other:?}"),
        }
    }
    (records, ticks)
}

fn subscriber(i: u64, object: u32, centre: [f32; 3]) -> (Subscriber, ClientSession) {
    let k = keys(i);
    (Subscriber::new(object, centre, ServerSession::new(&k).sealer), ClientSession::new(&k))
}

#[test]
fn small_views_are_sent_whole_with_own_object_first() {
    let mut rng = Rng(1);
    let world = World::new(500, &mut rng, 1 << 40);
    let (mut sub, mut client) = subscriber(1, 10, world.positions[10]);
    // The own object also appears in its own AOI list, as a physics query returns it.
    let list: Vec<u32> = (0..150).collect();
    let offsets = [0, list.len() as u32];
    let manager = InterestManager::new(InterestConfig::default());
    let tick = TickInfo { tick: 5, dilation_permille: 1000 };
    let report = manager
        .build(tick, &world.soa(), AoiLists { offsets: &offsets, objects: &list }, std::slice::from_mut(&mut sub))
        .unwrap();
    let (records, ticks) = receive(&sub, &mut client);
    // 149 others and the own object, which leads each of the two datagrams.
    assert_eq!(records.len(), 151);
    assert_eq!(records[0].id, world.ids[10]);
    assert_eq!(records.iter().filter(|r| r.id == world.ids[10]).count(), 2);
    let got: HashSet<u64> = records.iter().map(|r| r.id).collect();
    assert_eq!(got, list.iter().map(|&s| world.ids[s as usize]).collect());
    assert!(ticks.iter().all(|&t| t == 5));
    assert_eq!(report.datagrams, 2);
    assert_eq!(report.records, 151);
    assert!(!sub.report().over_budget);
    // Positions arrive at 1/64 resolution.
    for r in &records {
        let slot = world.ids.iter().position(|&id| id == r.id).unwrap();
        let p = r.pos.to_f32();
        for (got, want) in p.iter().zip(world.positions[slot]) {
            assert!((got - want).abs() <= 1.0 / 128.0 + 1e-4);
        }
    }
}

#[test]
fn over_budget_sends_own_then_the_nearest() {
    let mut rng = Rng(2);
    let world = World::new(1000, &mut rng, 0);
    let centre = [0.0, 10.0, 0.0];
    let (mut sub, mut client) = subscriber(2, 999, centre);
    let list: Vec<u32> = (0..400).collect();
    let offsets = [0, 400];
    let config = InterestConfig { max_datagrams: 1, near_share: 0.5 };
    let manager = InterestManager::new(config);
    manager
        .build(
            TickInfo { tick: 1, dilation_permille: 1000 },
            &world.soa(),
            AoiLists { offsets: &offsets, objects: &list },
            std::slice::from_mut(&mut sub),
        )
        .unwrap();
    let (records, _) = receive(&sub, &mut client);
    assert_eq!(sub.datagrams().len(), 1);
    assert_eq!(records.len(), config.capacity() + 1, "the own object and a full datagram of others");
    assert_eq!(records[0].id, world.ids[999]);
    let dist = |slot: usize| {
        let p = world.positions[slot];
        (p[0] - centre[0]).powi(2) + (p[1] - centre[1]).powi(2) + (p[2] - centre[2]).powi(2)
    };
    let mut by_dist: Vec<usize> = (0..400).collect();
    by_dist.sort_by(|&a, &b| dist(a).total_cmp(&dist(b)));
    let k = config.near_slots();
    // The K nearest come right after the own object (in no particular order: they
    // all fit, so ordering them would be wasted work).
    let expected: HashSet<u64> = by_dist[..k].iter().map(|&s| world.ids[s]).collect();
    let near: HashSet<u64> = records[1..=k].iter().map(|r| r.id).collect();
    assert_eq!(near, expected);
    assert!(sub.report().over_budget);
}

#[test]
fn every_object_in_view_is_refreshed_within_the_bound() {
    let mut rng = Rng(3);
    let world = World::new(2000, &mut rng, 5);
    let config = InterestConfig { max_datagrams: 1, near_share: 0.5 };
    let manager = InterestManager::new(config);
    let players = 8usize;
    let mut subs = Vec::new();
    let mut clients = Vec::new();
    for p in 0..players {
        let (s, c) = subscriber(p as u64 + 10, 1900 + p as u32, [rng.f(-50.0, 50.0), 5.0, rng.f(-50.0, 50.0)]);
        subs.push(s);
        clients.push(c);
    }
    // Each player's view: a churning set of 150..=320 objects out of 600.
    let mut views: Vec<Vec<u32>> = (0..players).map(|_| (0..250).collect()).collect();
    let mut last_event: Vec<HashMap<u64, u64>> = vec![HashMap::new(); players];
    let mut max_in_view = 0usize;
    let mut checks = Vec::new();
    for tick in 1..=120u64 {
        for v in views.iter_mut() {
            // Drop a few, add a few.
            for _ in 0..rng.below(12) {
                if v.len() > 150 {
                    let i = rng.below(v.len() as u64) as usize;
                    v.swap_remove(i);
                }
            }
            for _ in 0..rng.below(12) {
                let s = rng.below(600) as u32;
                if v.len() < 320 && !v.contains(&s) {
                    v.push(s);
                }
            }
            max_in_view = max_in_view.max(v.len());
        }
        let mut offsets = vec![0u32];
        let mut objects = Vec::new();
        for v in &views {
            objects.extend_from_slice(v);
            offsets.push(objects.len() as u32);
        }
        manager
            .build(
                TickInfo { tick, dilation_permille: 1000 },
                &world.soa(),
                AoiLists { offsets: &offsets, objects: &objects },
                &mut subs,
            )
            .unwrap();
        for p in 0..players {
            let (records, _) = receive(&subs[p], &mut clients[p]);
            assert_eq!(records[0].id, world.ids[1900 + p], "own object first");
            let in_view: HashSet<u64> = views[p].iter().map(|&s| world.ids[s as usize]).collect();
            // Entrants count from the tick before they entered.
            let events = &mut last_event[p];
            events.retain(|id, _| in_view.contains(id));
            for &id in &in_view {
                events.entry(id).or_insert(tick - 1);
            }
            for r in &records[1..] {
                assert!(in_view.contains(&r.id), "sent an object not in view");
                events.insert(r.id, tick);
            }
            for (&id, &t) in events.iter() {
                checks.push((tick - t, id));
            }
        }
    }
    let bound = config.refresh_bound(max_in_view);
    assert!(bound > 1, "the scenario must actually be over budget");
    let worst = checks.iter().map(|c| c.0).max().unwrap();
    assert!(worst <= bound, "an object waited {worst} ticks, bound {bound}");
    // And the bound is not vacuous: some object did wait more than one tick.
    assert!(worst > 1);
}

#[test]
fn broken_inputs_are_skipped_not_fatal() {
    let mut rng = Rng(4);
    let world = World::new(100, &mut rng, 0);
    let (s0, _) = subscriber(20, 0, [0.0; 3]);
    let (s1, mut c1) = subscriber(21, 500, [0.0; 3]); // own slot invalid
    let (s2, _) = subscriber(22, 2, [0.0; 3]);
    let mut subs = vec![s0, s1, s2];
    let manager = InterestManager::default();
    let objects = [1, 2, 7000, 3, 3, 4];
    // List 0 is out of order (5 > 2), list 1 has an invalid slot and a duplicate.
    let offsets = [5, 2, 6, 6];
    let report = manager
        .build(TickInfo::default(), &world.soa(), AoiLists { offsets: &offsets, objects: &objects }, &mut subs)
        .unwrap();
    assert_eq!(report.subscribers, 3);
    assert_eq!(subs[0].report().skipped, 1);
    assert_eq!(subs[0].report().records, 1, "own object only");
    assert_eq!(subs[1].report().skipped, 1);
    let (records, _) = receive(&subs[1], &mut c1);
    // Slots 3, 3 and 4; no own object. A duplicate slot costs one record when the view
    // fits (the physics query never returns duplicates; only the over-budget path,
    // which sorts by id anyway, removes them).
    assert_eq!(records.len(), 3);
    assert_eq!(records[0].id, world.ids[3]);
    assert_eq!(subs[2].report().records, 1);
    assert_eq!(
        manager.build(TickInfo::default(), &world.soa(), AoiLists { offsets: &[0, 1], objects: &[1] }, &mut subs),
        Err(InterestError::LengthMismatch { lists: 1, subscribers: 3 })
    );
}

#[test]
fn far_objects_and_huge_ids_use_extended_records_within_budget() {
    let world = World {
        ids: vec![1, u64::MAX, 1 << 50, 77],
        kinds: vec![ShapeKind::Box; 4],
        positions: vec![[0.0; 3], [5000.0, 0.0, 0.0], [-1e6, 3.0, 2.0], [1.0, 1.0, 1.0]],
    };
    let (mut sub, mut client) = subscriber(30, 0, [0.0; 3]);
    InterestManager::default()
        .build(
            TickInfo::default(),
            &world.soa(),
            AoiLists { offsets: &[0, 4], objects: &[0, 1, 2, 3] },
            std::slice::from_mut(&mut sub),
        )
        .unwrap();
    let (records, _) = receive(&sub, &mut client);
    let got: Vec<(u64, [f32; 3])> = records.iter().map(|r| (r.id, r.pos.to_f32())).collect();
    assert_eq!(
        got,
        vec![(1, [0.0; 3]), (u64::MAX, [5000.0, 0.0, 0.0]), (1 << 50, [-1e6, 3.0, 2.0]), (77, [1.0, 1.0, 1.0])]
    );
}

#[test]
fn datagrams_sealed_elsewhere_are_adopted_as_the_manager_would_send_them() {
    let mut rng = Rng(9);
    let world = World::new(600, &mut rng, 1 << 33);
    let list: Vec<u32> = (0..600).collect();
    let offsets = [0, 600, 600, 600];
    let manager = InterestManager::new(InterestConfig { max_datagrams: 2, ..Default::default() });
    let tick = TickInfo { tick: 8, dilation_permille: 900 };
    let mut built = vec![subscriber(3, 7, world.positions[7]).0];
    manager.build(tick, &world.soa(), AoiLists { offsets: &offsets[..2], objects: &list }, &mut built).unwrap();
    assert!(built[0].report().over_budget && built[0].datagrams().len() == 2);

    // The same bodies, sealed elsewhere (as a device would) under a lease of a twin
    // session's sealer: three numbers leased, two used.
    let (mut twin, mut client) = subscriber(3, 7, world.positions[7]);
    let mut keep = ClientSession::new(&keys(3));
    let mut device = ServerSession::new(&keys(3)).sealer;
    let sealed: Vec<Vec<u8>> = built[0]
        .datagrams()
        .iter()
        .map(|d| {
            let mut d = d.to_vec();
            keep.open(&mut d).unwrap();
            // The clear frame again: version and kind, the body, room for the tag.
            d[2..myriad_protocol::HEADER_LEN].fill(0);
            device.seal_in_place(&mut d).unwrap();
            d
        })
        .collect();
    let first = built[0].report();
    fn with(datagrams: Vec<&[u8]>, in_view: usize) -> Packed<Vec<&[u8]>> {
        Packed { datagrams, in_view, over_budget: true, pinned: true, packed: 0 }
    }
    let packed = |datagrams| with(datagrams, first.in_view);
    let mut leases = [Some(twin.sealer.lease(3).unwrap())];
    let report = manager.adopt_sealed(
        |_| Some(Packed { packed: first.packed, ..packed(sealed.iter().map(Vec::as_slice).collect()) }),
        std::slice::from_mut(&mut twin),
        &mut leases,
    );
    assert_eq!(twin.datagrams().iter().collect::<Vec<_>>(), built[0].datagrams().iter().collect::<Vec<_>>());
    assert_eq!(twin.report(), first);
    assert_eq!(report.records, first.records);
    assert_eq!(twin.sealer.next_sequence(), 2, "the unused number goes back");
    assert!(leases[0].is_none());
    let (records, ticks) = receive(&twin, &mut client);
    assert_eq!(records.len(), first.records);
    assert_eq!(ticks, [8, 8]);

    // Refused: a datagram under another number than the lease's next, one too short to
    // be an update, another session's, nothing to trust. Nothing is sent, one skip each,
    // and the leases' numbers stay used. Without a lease: a seal failure.
    let mut subs: Vec<Subscriber> = (0..5).map(|_| subscriber(3, 7, world.positions[7]).0).collect();
    let mut leases: Vec<Option<SealLease>> = subs.iter_mut().map(|s| Some(s.sealer.lease(2).unwrap())).collect();
    leases[4] = None;
    let short = sealed[0][..myriad_protocol::MIN_DATAGRAM + 4].to_vec();
    let mut other = sealed[0].clone();
    other[2] ^= 1;
    let report = manager.adopt_sealed(
        |i| match i {
            0 => Some(packed(vec![&sealed[1][..]])),
            1 => Some(packed(vec![&short[..]])),
            2 => Some(packed(vec![&other[..]])),
            3 => None,
            _ => Some(packed(vec![&sealed[0][..]])),
        },
        &mut subs,
        &mut leases,
    );
    assert_eq!((report.skipped, report.seal_failures, report.datagrams, report.subscribers), (4, 1, 0, 5));
    assert!(subs.iter().all(|s| s.datagrams().is_empty()));
    assert!(subs[..4].iter().all(|s| s.sealer.next_sequence() == 2));
}

/// FNV-1a over bytes: a pinned hash needs a function that never changes.
fn fnv(hash: &mut u64, bytes: &[u8]) {
    for &b in bytes {
        *hash = (*hash ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3);
    }
}

/// Every byte every player is sent over 60 ticks of a moving, churning world is pinned:
/// small views sent whole, views over a two-datagram budget (nearest, then the stalest),
/// far objects and huge ids in extended records, a list with duplicates and invalid
/// slots, a player whose own object is invalid. The device outbound repeats these bytes
/// (the GPU suite's `device_outbound`), so a change here is a change of the wire's
/// contents, never an optimisation; update the hash only for a deliberate change of the
/// rule.
#[test]
fn the_datagrams_of_a_churning_world_are_pinned() {
    let mut rng = Rng(0x5eed);
    let mut world = World::new(3000, &mut rng, 1 << 20);
    for i in (0..3000).step_by(97) {
        world.ids[i] = u64::MAX - i as u64;
        world.positions[i][0] += 900.0;
    }
    let manager = InterestManager::new(InterestConfig { max_datagrams: 2, near_share: 0.5 });
    let sizes = [20usize, 60, 110, 200, 260, 400, 650, 900, 1500, 30, 700, 250];
    let mut subs = Vec::new();
    for (p, _) in sizes.iter().enumerate() {
        let object = if p == 11 { 99_999 } else { 2900 + p as u32 };
        subs.push(subscriber(p as u64 + 1, object, [0.0; 3]).0);
    }
    let mut views: Vec<Vec<u32>> = sizes.iter().map(|&n| (0..n).map(|_| rng.below(2900) as u32).collect()).collect();
    let mut hash = 0xcbf2_9ce4_8422_2325u64;
    let (mut over, mut under, mut skipped, mut extended) = (0, 0, 0, 0);
    for tick in 1..=60u64 {
        for p in &mut world.positions {
            p[0] += rng.f(-0.5, 0.5);
            p[2] += rng.f(-0.5, 0.5);
        }
        for (p, v) in views.iter_mut().enumerate() {
            for _ in 0..rng.below(v.len() as u64 / 8 + 2) {
                let i = rng.below(v.len() as u64) as usize;
                v[i] = rng.below(2900) as u32;
            }
            // Lists as an AOI query gives them (ascending, distinct), but for player 10's.
            if p != 10 {
                v.sort_unstable();
                v.dedup();
            } else {
                v.extend([v[0], v[1], 50_000, u32::MAX]);
            }
        }
        for (p, s) in subs.iter_mut().enumerate() {
            s.centre = world.positions[2900 + p];
        }
        let mut offsets = vec![0u32];
        let mut objects = Vec::new();
        for v in &views {
            objects.extend_from_slice(v);
            offsets.push(objects.len() as u32);
        }
        let report = manager
            .build(
                TickInfo { tick, dilation_permille: 1000 - tick as u16 },
                &world.soa(),
                AoiLists { offsets: &offsets, objects: &objects },
                &mut subs,
            )
            .unwrap();
        fnv(&mut hash, &(report.records as u64).to_le_bytes());
        fnv(&mut hash, &(report.over_budget as u64).to_le_bytes());
        over += report.over_budget;
        under += report.subscribers - report.over_budget;
        skipped += report.skipped;
        for s in &subs {
            for d in s.datagrams().iter() {
                fnv(&mut hash, d);
            }
            // Fewer records than a datagram of compact ones would hold: extended ones.
            extended += usize::from(s.report().over_budget && s.report().records < s.report().datagrams * 100);
        }
    }
    assert!(over >= 5 * 60 && under >= 2 * 60 && skipped >= 60 && extended > 0, "{over} {under} {skipped} {extended}");
    assert_eq!(hash, 0xba78_d559_7c51_75de, "datagrams hash {hash:#018x}");
}
