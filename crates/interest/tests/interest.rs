//! End-to-end tests of protocol 3: the manager builds and seals every player's
//! datagrams; each player's client opens them with its session (`ClientSession::open`),
//! resolves their records against the states it holds (`Baselines::resolve_update`),
//! acknowledges the datagrams whose every record resolved (`AckTracker`), and the server
//! hands that acknowledgement to the player's subscriber (`Subscriber::acknowledge`)
//! before the next build. What is checked is what each client ends up holding.

use std::borrow::{Borrow, BorrowMut};
use std::collections::{HashMap, HashSet};

use myriad_interest::replica::DATAGRAM_OVERHEAD;
use myriad_interest::*;
use myriad_protocol::delta::MAX_RECORD_LEN;
use myriad_protocol::{
    ClientSession, DELTA_HEADER_LEN, DeltaRecord, MAX_BODY, MAX_DATAGRAM, QuantPos, RecordState, ServerMessage,
    ServerSession, SessionKeys, ShapeKind, UpdateHeader, UpdateReceiver,
};

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
    /// Where the client should hold object `slot`: its position, quantized.
    fn truth(&self, slot: u32) -> QuantPos {
        QuantPos::from_f32(self.positions[slot as usize])
    }
}

fn keys(i: u64) -> SessionKeys {
    SessionKeys { session_id: i, client_to_server: [i as u8; 32], server_to_client: [(i as u8) ^ 0x55; 32] }
}

/// The views as the AOI query's CSR lists: `(offsets, objects)`.
fn csr(views: &[Vec<u32>]) -> (Vec<u32>, Vec<u32>) {
    let mut offsets = vec![0u32];
    let mut objects = Vec::new();
    for v in views {
        objects.extend_from_slice(v);
        offsets.push(objects.len() as u32);
    }
    (offsets, objects)
}

/// The newest state a client received of an object.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Held {
    /// Tick of the update that carried it.
    tick: u64,
    kind: ShapeKind,
    pos: QuantPos,
}

/// A player's client as protocol 3 asks: opens each datagram with its session, resolves
/// the records against the states it holds, and acknowledges a datagram only when every
/// record of it resolved.
struct Client {
    session: ClientSession,
    receiver: UpdateReceiver,
    held: HashMap<u64, Held>,
    /// Records whose baseline the client did not hold (never, if the server is right).
    unresolved: usize,
}

impl Client {
    fn new(keys: &SessionKeys) -> Self {
        Self {
            session: ClientSession::new(keys),
            receiver: UpdateReceiver::default(),
            held: HashMap::new(),
            unresolved: 0,
        }
    }

    /// Opens and applies one datagram; returns its header and records as sent.
    fn receive(&mut self, datagram: &[u8]) -> (UpdateHeader, Vec<DeltaRecord>) {
        assert!(datagram.len() <= MAX_DATAGRAM);
        let mut d = datagram.to_vec();
        let opened = self.session.open(&mut d).expect("a sealed datagram opens");
        let ServerMessage::StateUpdate(update) = opened.message else { panic!("expected a state update") };
        let mut states = Vec::new();
        let failed = self.receiver.receive_update(opened.header.sequence, &update, &mut states);
        for s in states {
            let held = Held { tick: update.header.tick, kind: s.kind, pos: s.pos };
            let e = self.held.entry(s.id).or_insert(held);
            if held.tick >= e.tick {
                *e = held;
            }
        }
        self.unresolved += failed;
        (update.header, update.records)
    }

    /// Receives the datagrams of `sub`'s last build that `deliver(i)` lets through.
    fn receive_from(
        &mut self,
        sub: &Subscriber,
        deliver: impl Fn(usize) -> bool,
    ) -> Vec<(UpdateHeader, Vec<DeltaRecord>)> {
        sub.datagrams().iter().enumerate().filter(|&(i, _)| deliver(i)).map(|(_, d)| self.receive(d)).collect()
    }

    /// What the client's next action or keep-alive carries, handed to the server.
    fn acknowledge(&self, sub: &mut Subscriber) {
        if let Some(field) = self.receiver.acks() {
            sub.acknowledge(field);
        }
    }
}

/// A subscriber and its client, sharing one session's keys.
struct Player {
    sub: Subscriber,
    client: Client,
}

/// So the players themselves can be the manager's subscribers.
impl Borrow<Subscriber> for Player {
    fn borrow(&self) -> &Subscriber {
        &self.sub
    }
}

impl BorrowMut<Subscriber> for Player {
    fn borrow_mut(&mut self) -> &mut Subscriber {
        &mut self.sub
    }
}

fn player(i: u64, object: u32, centre: [f32; 3]) -> Player {
    let k = keys(i);
    Player { sub: Subscriber::new(object, centre, ServerSession::new(&k).sealer), client: Client::new(&k) }
}

/// Receives everything of the last build and acknowledges it, as a client on a clean
/// link does; returns what was received.
fn deliver_all(players: &mut [Player]) -> Vec<Vec<(UpdateHeader, Vec<DeltaRecord>)>> {
    players
        .iter_mut()
        .map(|p| {
            let got = p.client.receive_from(&p.sub, |_| true);
            p.client.acknowledge(&mut p.sub);
            got
        })
        .collect()
}

/// One player's build of `tick` on `world` with AOI list `list`.
fn build_for(manager: &InterestManager, tick: u64, world: &World, list: &[u32], p: &mut Player) -> TickReport {
    let offsets = [0, list.len() as u32];
    manager
        .build(
            TickInfo { tick, dilation_permille: 1000 },
            &world.soa(),
            AoiLists { offsets: &offsets, objects: list },
            std::slice::from_mut(&mut p.sub),
        )
        .unwrap()
}

/// Distance from `centre` as the manager computes it.
fn distance(p: [f32; 3], c: [f32; 3]) -> f32 {
    let d = [p[0] - c[0], p[1] - c[1], p[2] - c[2]];
    (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
}

#[test]
fn small_views_reach_the_client_whole_on_the_first_tick() {
    let mut rng = Rng(1);
    let world = World::new(500, &mut rng, 1 << 40);
    let mut p = player(1, 10, world.positions[10]);
    // The own object also appears in its own AOI list, as a physics query returns it.
    let list: Vec<u32> = (0..220).collect();
    // A budget far above what 220 objects cost: nothing waits.
    let manager = InterestManager::new(InterestConfig::with_budget(2, 10_000.0, 30.0));
    let build = |tick: u64, p: &mut Player| build_for(&manager, tick, &world, &list, p);
    let report = build(5, &mut p);
    let got = deliver_all(std::slice::from_mut(&mut p)).remove(0);
    let own = world.ids[10];
    // 219 absolute records do not fit one datagram: the own object is in each.
    assert!(got.len() >= 2, "{} datagrams", got.len());
    for (header, records) in &got {
        assert_eq!(header.tick, 5);
        assert_eq!(records.iter().filter(|r| r.id == own).count(), 1, "own object in every datagram");
        assert!(
            records.iter().all(|r| matches!(r.state, RecordState::Absolute { .. })),
            "the client holds nothing yet"
        );
    }
    let s = p.sub.report();
    assert_eq!((s.in_view, s.packed, s.deferred, s.starving, s.relative, s.skipped), (219, 219, 0, 0, 0, 0));
    assert_eq!(report.datagrams, got.len());
    assert_eq!(report.records, 219 + got.len());
    assert_eq!(report.records, got.iter().map(|g| g.1.len()).sum::<usize>());
    assert_eq!(report.bytes, p.sub.datagrams().total_bytes());
    // Every object in view, at its position to 1/64 unit, with its shape.
    assert_eq!(p.client.unresolved, 0);
    let held: HashSet<u64> = p.client.held.keys().copied().collect();
    assert_eq!(held, list.iter().map(|&s| world.ids[s as usize]).collect());
    for &slot in &list {
        let h = p.client.held[&world.ids[slot as usize]];
        assert_eq!((h.tick, h.kind, h.pos), (5, world.kinds[slot as usize], world.truth(slot)));
        for (got, want) in h.pos.to_f32().iter().zip(world.positions[slot as usize]) {
            assert!((got - want).abs() <= 1.0 / 128.0 + 1e-4);
        }
    }

    // Acknowledged and unchanged: the next tick is one datagram holding only the own
    // object, as a `Same` record against the state just acknowledged.
    let report = build(6, &mut p);
    let got = deliver_all(std::slice::from_mut(&mut p)).remove(0);
    assert_eq!((report.datagrams, report.records, report.relative), (1, 1, 1));
    assert_eq!(got[0].1, [DeltaRecord { id: own, state: RecordState::Same { back: 1 } }]);
}

/// Ticks an object has wanted sending without reaching the client, and the nearest and
/// farthest it was from its player meanwhile.
#[derive(Debug, Clone, Copy)]
struct Waiting {
    ticks: u64,
    nearest: f32,
    farthest: f32,
}

impl Waiting {
    fn new(d: f32) -> Self {
        Self { ticks: 0, nearest: d, farthest: d }
    }
    fn another(&mut self, d: f32) {
        self.ticks += 1;
        self.nearest = self.nearest.min(d);
        self.farthest = self.farthest.max(d);
    }
}

#[test]
fn over_budget_near_objects_go_first_and_the_budget_holds_on_average() {
    let mut rng = Rng(2);
    let mut world = World::new(1000, &mut rng, 0);
    let centre = [0.0, 10.0, 0.0];
    world.positions[999] = centre;
    let mut p = player(2, 999, centre);
    let list: Vec<u32> = (0..400).chain([999]).collect();
    let config = InterestConfig::with_budget(1, 36.0, 30.0);
    let r = config.replication;
    let budget = r.budget_bytes_per_tick;
    // A datagram with the own object always fits the budget, so only starving objects
    // ever overdraw it (see the bound below).
    assert!(budget >= (DATAGRAM_OVERHEAD + MAX_RECORD_LEN) as f32);
    // What a starving record may overdraw the budget by: its worst-case length (the id
    // written whole), and with more than one datagram allowed, a datagram it opens (its
    // overhead and the own object's record).
    let per_starving = MAX_RECORD_LEN + if config.max_datagrams > 1 { DATAGRAM_OVERHEAD + MAX_RECORD_LEN } else { 0 };
    let manager = InterestManager::new(config);
    let own = world.ids[999];
    let (mut bytes, mut overdraft, mut starving) = (0usize, 0usize, 0usize);
    let mut build = |tick: u64, world: &World, p: &mut Player| {
        build_for(&manager, tick, world, &list, p);
        let s = p.sub.report();
        bytes += s.bytes;
        starving += s.starving;
        overdraft += s.starving * per_starving;
        let got = deliver_all(std::slice::from_mut(p)).remove(0);
        assert_eq!(got.len(), 1, "max_datagrams is 1");
        for (_, records) in &got {
            assert_eq!(records.iter().filter(|r| r.id == own).count(), 1, "own object in every datagram");
        }
        s
    };

    // A player arrives: 400 objects new to its client do not fit the first tick's budget.
    let first = build(1, &world, &mut p);
    assert!(first.bytes as f32 <= budget, "{first:?}");
    assert!(first.deferred > 0 && first.packed > 0 && first.packed < 400, "{first:?}");
    // A still world. Every object new to the client gains 1 a tick and starves on its
    // `max_wait_ticks`-th, going over the budget as many a tick as the datagram holds (at
    // least `per_datagram`, charged at their longest): all are there by then.
    let per_datagram = (MAX_BODY - DELTA_HEADER_LEN - 2 * MAX_RECORD_LEN) / MAX_RECORD_LEN;
    let fill_bound = r.max_wait_ticks as u64 + 400u64.div_ceil(per_datagram as u64) - 1;
    let mut filled = None;
    for tick in 2..=60 {
        build(tick, &world, &mut p);
        if filled.is_none() && list.iter().all(|&s| p.client.held.contains_key(&world.ids[s as usize])) {
            filled = Some(tick);
        }
    }
    let filled = filled.expect("every object reached the client");
    assert!(filled <= fill_bound, "filled at tick {filled}, bound {fill_bound}");
    for &slot in &list {
        assert_eq!(p.client.held[&world.ids[slot as usize]].pos, world.truth(slot));
    }

    // Everything moves: 400 objects, a short budget. Near objects keep their bound; far
    // ones yield to them and wait longer than theirs, but not past the starvation bound.
    let heading: Vec<[f32; 2]> = (0..1000).map(|_| [rng.f(-0.07, 0.07), rng.f(-0.07, 0.07)]).collect();
    let mut waiting: HashMap<u32, Waiting> = HashMap::new();
    let (mut near_worst, mut far_worst, mut far_over_bound) = (0, 0, 0);
    let ticks = 61..=300u64;
    for tick in ticks.clone() {
        for (pos, h) in world.positions[..400].iter_mut().zip(&heading) {
            pos[0] += h[0];
            pos[2] += h[1];
        }
        build(tick, &world, &mut p);
        for &slot in &list[..400] {
            let d = distance(world.positions[slot as usize], centre);
            if p.client.held[&world.ids[slot as usize]].pos == world.truth(slot) {
                waiting.remove(&slot);
                continue;
            }
            let w = waiting.entry(slot).or_insert(Waiting::new(d));
            w.another(d);
            if w.farthest <= r.near {
                near_worst = near_worst.max(w.ticks);
            } else if w.nearest > r.far {
                far_worst = far_worst.max(w.ticks);
                far_over_bound += usize::from(w.ticks as f32 >= r.far_bound_ticks);
            }
        }
    }
    // A near object due after `near_bound_ticks` of wanting goes that tick.
    assert!(near_worst < r.near_bound_ticks as u64, "a near object waited {near_worst} ticks");
    // Far objects waited past their bound: the budget, not the bounds, held them back.
    assert!(far_over_bound > 0 && far_worst >= r.far_bound_ticks as u64, "{far_worst}");
    // An object that wanted sending for `max_wait_ticks` goes over the budget (a tick
    // later where its priority, a sum of rates, rounds below `max_wait_ticks` rates).
    assert!(far_worst <= r.max_wait_ticks as u64, "a far object waited {far_worst} ticks");
    assert_eq!(p.client.unresolved, 0);

    // The budget holds on average. Each tick may spend its budget and what earlier ticks
    // left unspent (never more than a tick's worth, never less than nothing: the first
    // tick starts with nothing), and every datagram and record is charged its worst
    // case, at least what it takes on the wire. Only a starving record may overdraw the
    // budget, by at most `per_starving`, and an overdraft is forgiven, not repaid. So
    // the bytes of T ticks stay within T budgets and the starving records' overdrafts.
    let ticks = *ticks.end() as f32;
    let per_tick = bytes as f32 / ticks;
    let bound = budget + overdraft as f32 / ticks;
    assert!(per_tick <= bound, "{per_tick} bytes a tick, bound {bound} ({starving} starving)");
    // Not vacuously: the budget was used (worst-case charges leave some unspent), and
    // the starving clause was in play.
    assert!(per_tick >= 0.8 * budget && starving > 0, "{per_tick} bytes a tick, {starving} starving");
}

/// How one churning run went.
#[derive(Debug, Default)]
struct Churn {
    /// Objects that, one tick, had waited the longest their bound allows.
    at_bound: usize,
    /// The longest an object waited (ticks it wanted sending, not received).
    worst_wait: u64,
    /// The longest an object new in view waited.
    worst_new: u64,
    deferred: usize,
    starving: usize,
    /// Records sent, and how many of them relative to an acknowledged state.
    records: usize,
    relative: usize,
}

/// Eight players with churning views (150 to 320 of 600 objects) on a world whose
/// objects random-walk and now and then jump, each player's AOI centred on its own
/// object; every client acknowledges. After each tick, every object in view is either
/// current at the client (received since it entered the view, at its present
/// position) or has wanted sending for fewer ticks than `allowed(farthest, nearest)`
/// (its distances meanwhile) allows; an object new in view for fewer than `allowed_new`.
fn churn(config: InterestConfig, seed: u64, allowed: impl Fn(f32, f32) -> u64, allowed_new: u64) -> Churn {
    let mut rng = Rng(seed);
    let mut world = World::new(2000, &mut rng, 5);
    let manager = InterestManager::new(config);
    let players = 8usize;
    let own = |p: usize| 1900 + p as u32;
    let mut ps: Vec<Player> =
        (0..players).map(|p| player(p as u64 + 10, own(p), world.positions[own(p) as usize])).collect();
    let mut views: Vec<Vec<u32>> = (0..players).map(|_| (0..250).collect()).collect();
    let mut entered: Vec<HashMap<u32, u64>> = vec![HashMap::new(); players];
    let mut waiting: Vec<HashMap<u32, Waiting>> = vec![HashMap::new(); players];
    let mut out = Churn::default();
    for tick in 1..=150u64 {
        for p in world.positions.iter_mut() {
            p[0] += rng.f(-0.1, 0.1);
            p[2] += rng.f(-0.1, 0.1);
        }
        for _ in 0..3 {
            world.positions[rng.below(600) as usize][0] += 5.0;
        }
        for v in views.iter_mut() {
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
        }
        for (p, player) in ps.iter_mut().enumerate() {
            player.sub.centre = world.positions[own(p) as usize];
        }
        let (offsets, objects) = csr(&views);
        let report = manager
            .build(
                TickInfo { tick, dilation_permille: 1000 },
                &world.soa(),
                AoiLists { offsets: &offsets, objects: &objects },
                &mut ps,
            )
            .unwrap();
        out.deferred += report.deferred;
        out.starving += report.starving;
        out.records += report.records;
        out.relative += report.relative;
        let got = deliver_all(&mut ps);
        for (p, player) in ps.iter().enumerate() {
            let view: HashSet<u64> = views[p].iter().map(|&s| world.ids[s as usize]).collect();
            let own_id = world.ids[own(p) as usize];
            for (_, records) in &got[p] {
                assert_eq!(records.iter().filter(|r| r.id == own_id).count(), 1, "own object in every datagram");
                assert!(records.iter().all(|r| r.id == own_id || view.contains(&r.id)), "sent an object not in view");
            }
            assert!(got[p].len() <= config.max_datagrams);
            entered[p].retain(|s, _| views[p].contains(s));
            waiting[p].retain(|s, _| views[p].contains(s));
            let centre = player.sub.centre;
            for &slot in &views[p] {
                let since = *entered[p].entry(slot).or_insert(tick);
                let d = distance(world.positions[slot as usize], centre);
                let held = player.client.held.get(&world.ids[slot as usize]).filter(|h| h.tick >= since);
                if held.is_some_and(|h| h.pos == world.truth(slot)) {
                    waiting[p].remove(&slot);
                    continue;
                }
                let w = waiting[p].entry(slot).or_insert(Waiting::new(d));
                w.another(d);
                let bound = if held.is_none() { allowed_new } else { allowed(w.farthest, w.nearest) };
                assert!(w.ticks < bound, "tick {tick}, player {p}: object {slot} waited {w:?}, bound {bound}");
                out.at_bound += usize::from(w.ticks + 1 == bound);
                out.worst_wait = out.worst_wait.max(w.ticks);
                if held.is_none() {
                    out.worst_new = out.worst_new.max(w.ticks);
                }
            }
        }
    }
    assert_eq!(ps.iter().map(|p| p.client.unresolved).sum::<usize>(), 0, "a record named a state the client lacks");
    // The acknowledgements were used: many records are relative to acknowledged states
    // (objects new in view, and ones that moved too far while they waited, are not).
    assert!(out.relative > out.records / 4, "{out:?}");
    out
}

#[test]
fn every_object_in_view_is_current_within_its_bound() {
    // A budget that holds everything due: an object new in view goes at once, and a
    // changing one once its priority, `1 / bound_ticks(d)` a tick, reaches 1: within
    // `bound_ticks` at the farthest it was meanwhile (near bound within `near`, growing
    // to the far bound at `far`).
    let generous = InterestConfig::with_budget(4, 1_000.0, 30.0);
    let r = generous.replication;
    let run = churn(generous, 3, |farthest, _| r.bound_ticks(farthest).ceil() as u64, 1);
    assert_eq!((run.deferred, run.starving), (0, 0), "{run:?}");
    // The bounds, not the budget, paced them: far objects did wait about the far bound.
    assert!(run.worst_wait + 1 >= r.far_bound_ticks as u64 && run.at_bound > 0, "{run:?}");

    // A budget the views do not fit: objects wait past their bound for it, but never
    // past the starvation bound. An object starves once its
    // priority is `max_wait_ticks` times this tick's rate; rates are `1 / bound_ticks`
    // at the distances it had, so an object that came nearer meanwhile waits up to
    // `bound(farthest) / bound(nearest)` times longer. New objects gain 1 a tick.
    let tight = InterestConfig::with_budget(2, 24.0, 30.0);
    let r = tight.replication;
    let starve = |farthest: f32, nearest: f32| {
        (r.max_wait_ticks * r.bound_ticks(farthest) / r.bound_ticks(nearest)).ceil() as u64 + 1
    };
    let run = churn(tight, 3, starve, r.max_wait_ticks as u64);
    assert!(run.deferred > 0 && run.starving > 0, "{run:?}");
    assert!(run.worst_wait > r.far_bound_ticks as u64, "the budget must actually hold objects back: {run:?}");
    assert!(run.at_bound > 0, "{run:?}");
}

#[test]
fn a_list_out_of_order_is_served_as_the_sorted_one() {
    // The replica follows views by ascending slot; a list in another order (with a
    // repeat) must reach the client as the same records as the sorted list.
    let mut rng = Rng(11);
    let mut world = World::new(60, &mut rng, 0);
    let manager = InterestManager::default();
    let (mut sorted, mut shuffled) = (player(30, 0, [0.0; 3]), player(31, 0, [0.0; 3]));
    for tick in 1..=8 {
        for (i, p) in world.positions.iter_mut().enumerate().filter(|(i, _)| i % 2 == 0) {
            p[0] += 0.05 * i as f32;
        }
        let list: Vec<u32> = (1..40).collect();
        let mut odd: Vec<u32> = list.iter().rev().copied().collect();
        odd.push(7);
        build_for(&manager, tick, &world, &list, &mut sorted);
        build_for(&manager, tick, &world, &odd, &mut shuffled);
        let (a, b) = (deliver_all(std::slice::from_mut(&mut sorted)), deliver_all(std::slice::from_mut(&mut shuffled)));
        assert_eq!(a, b, "tick {tick}");
        assert_eq!(sorted.sub.report().in_view, 39);
    }
}

#[test]
fn broken_inputs_are_skipped_not_fatal() {
    let mut rng = Rng(4);
    let world = World::new(100, &mut rng, 0);
    let mut ps = vec![
        player(20, 0, [0.0; 3]),
        player(21, 500, [0.0; 3]), // own slot invalid
        player(22, 2, [0.0; 3]),
    ];
    let manager = InterestManager::default();
    let objects = [1, 2, 7000, 3, 3, 4];
    // List 0 is out of order (5 > 2), list 1 has an invalid slot and a duplicate.
    let offsets = [5, 2, 6, 6];
    let report = manager
        .build(TickInfo::default(), &world.soa(), AoiLists { offsets: &offsets, objects: &objects }, &mut ps)
        .unwrap();
    assert_eq!((report.subscribers, report.skipped, report.seal_failures), (3, 2, 0));
    let got = deliver_all(&mut ps);
    // A broken list: the own object only.
    assert_eq!(ps[0].sub.report().skipped, 1);
    assert_eq!((ps[0].sub.report().records, ps[0].sub.report().in_view), (1, 0));
    assert_eq!(got[0].len(), 1);
    assert_eq!(got[0][0].1.iter().map(|r| r.id).collect::<Vec<_>>(), [world.ids[0]]);
    // Slots 3, 3 and 4, the invalid one skipped, the duplicate sent once; no own object.
    assert_eq!(ps[1].sub.report().skipped, 1);
    assert_eq!(ps[1].sub.report().in_view, 2);
    assert_eq!(got[1].iter().flat_map(|g| g.1.iter().map(|r| r.id)).collect::<Vec<_>>(), [world.ids[3], world.ids[4]]);
    assert_eq!(ps[2].sub.report().records, 1);
    assert!(ps.iter().all(|p| p.client.unresolved == 0));

    // Lists that do not match the subscribers: an error before anything is built.
    assert_eq!(
        manager.build(TickInfo::default(), &world.soa(), AoiLists { offsets: &[0, 1], objects: &[1] }, &mut ps),
        Err(InterestError::LengthMismatch { lists: 1, subscribers: 3 })
    );
    // The next tick with sound lists serves everyone, relative to what they acknowledged.
    let (offsets, objects) = csr(&[vec![1, 5], vec![3, 4], vec![]]);
    let report = manager
        .build(
            TickInfo { tick: 1, dilation_permille: 1000 },
            &world.soa(),
            AoiLists { offsets: &offsets, objects: &objects },
            &mut ps,
        )
        .unwrap();
    assert_eq!(report.skipped, 0);
    deliver_all(&mut ps);
    for (p, want) in ps.iter().zip([vec![0, 1, 5], vec![3, 4], vec![2]]) {
        let held: HashSet<u64> = p.client.held.keys().copied().collect();
        assert_eq!(held, want.iter().map(|&s| world.ids[s]).collect());
        assert_eq!(p.client.unresolved, 0);
    }
    // Player 1's objects did not change: the client holds them, so nothing is due.
    assert_eq!(ps[1].sub.report().records, 0);
}

#[test]
fn far_objects_and_huge_ids_are_delivered_exactly() {
    let mut world = World {
        ids: vec![1, u64::MAX, 1 << 50, 77, u64::MAX - 1, 2],
        kinds: vec![
            ShapeKind::Box,
            ShapeKind::Sphere,
            ShapeKind::Capsule,
            ShapeKind::Box,
            ShapeKind::Box,
            ShapeKind::Sphere,
        ],
        positions: vec![
            [0.0; 3],
            [5000.0, 0.0, 0.0],
            [-1e6, 3.0, 2.0],
            [1.0, 1.0, 1.0],
            [0.5, 700.0, -0.25],
            [3e5, -2e5, 1e5],
        ],
    };
    // Every change sent the tick it happens, so the client is current after each tick.
    let replication = ReplicationConfig {
        budget_bytes_per_tick: 10_000.0,
        near_bound_ticks: 1.0,
        far_bound_ticks: 1.0,
        ..ReplicationConfig::default()
    };
    let manager = InterestManager::new(InterestConfig { max_datagrams: 2, replication });
    let mut p = player(30, 0, [0.0; 3]);
    let mut forms = HashSet::new();
    for tick in 1..=40u64 {
        // Small moves (deltas) for most, a jump (absolute again) now and then.
        for (i, pos) in world.positions.iter_mut().enumerate().skip(1) {
            pos[i % 3] += if (tick + i as u64).is_multiple_of(9) { 3000.0 } else { 0.75 };
        }
        manager
            .build(
                TickInfo { tick, dilation_permille: 1000 },
                &world.soa(),
                AoiLists { offsets: &[0, 6], objects: &[0, 1, 2, 3, 4, 5] },
                std::slice::from_mut(&mut p.sub),
            )
            .unwrap();
        for (header, records) in deliver_all(std::slice::from_mut(&mut p)).remove(0) {
            for r in records {
                let form = match r.state {
                    RecordState::Absolute { pos, .. } if pos.offset_from(header.origin).is_some() => "near",
                    RecordState::Absolute { .. } => "far",
                    RecordState::Delta { .. } | RecordState::Predicted { .. } => "delta",
                    RecordState::Same { .. } => "same",
                };
                forms.insert((form, r.id));
            }
        }
        for slot in 0..6 {
            let h = p.client.held[&world.ids[slot]];
            assert_eq!((h.tick, h.kind, h.pos), (tick, world.kinds[slot], world.truth(slot as u32)), "tick {tick}");
        }
    }
    assert_eq!(p.client.unresolved, 0);
    // Huge ids and big id gaps went both absolute, far from the origin, and as deltas.
    for want in [("far", u64::MAX), ("delta", u64::MAX), ("far", 1 << 50), ("delta", 1 << 50), ("far", u64::MAX - 1)] {
        assert!(forms.contains(&want), "{want:?} in {forms:?}");
    }
    assert!(forms.contains(&("near", 77)) && forms.contains(&("same", 1)), "{forms:?}");
}

/// FNV-1a over bytes: a pinned hash needs a function that never changes.
fn fnv(hash: &mut u64, bytes: &[u8]) {
    for &b in bytes {
        *hash = (*hash ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3);
    }
}

/// Every record every player is sent over 60 ticks of a moving, churning world is
/// pinned, decoded: its update's tick, dilation and origin, then each record's id and
/// state (form, baseline distance, delta or absolute position). Small views and views
/// over the default budget (two datagrams, 64 kbit/s), far objects and huge ids, a list
/// with duplicates and invalid slots, a player whose own object is invalid. Every
/// client acknowledges what it resolved, but datagrams are lost and acknowledgements
/// with them on a fixed pattern, so the records are relative to older baselines too.
///
/// The hash pins protocol 3's choice of records: which objects each player's replica
/// sends each tick (priorities, bounds, budget, near objects first), in which form
/// against which acknowledged baseline, and how they are split into datagrams. A change
/// here is a change of what goes on the wire, never an optimisation; update the hash
/// only for a deliberate change of the rule.
#[test]
fn the_datagrams_of_a_churning_world_are_pinned() {
    let mut rng = Rng(0x5eed);
    let mut world = World::new(3000, &mut rng, 1 << 20);
    for i in (0..3000).step_by(97) {
        world.ids[i] = u64::MAX - i as u64;
        world.positions[i][0] += 900.0;
    }
    let manager = InterestManager::new(InterestConfig::default());
    let sizes = [20usize, 60, 110, 200, 260, 400, 650, 900, 1500, 30, 700, 250];
    let mut ps = Vec::new();
    // A second client per player opens every datagram, delivered or not, for the hash.
    let mut taps = Vec::new();
    for (p, _) in sizes.iter().enumerate() {
        let object = if p == 11 { 99_999 } else { 2900 + p as u32 };
        ps.push(player(p as u64 + 1, object, [0.0; 3]));
        taps.push(ClientSession::new(&keys(p as u64 + 1)));
    }
    let mut views: Vec<Vec<u32>> = sizes.iter().map(|&n| (0..n).map(|_| rng.below(2900) as u32).collect()).collect();
    let mut hash = 0xcbf2_9ce4_8422_2325u64;
    let (mut skipped, mut relative, mut deferred, mut lost) = (0, 0, 0, 0);
    let mut forms = [0usize; 5];
    let mut backs = HashSet::new();
    for tick in 1..=60u64 {
        // Two objects in three move; the others are still, and confirmed now and then.
        for (_, p) in world.positions.iter_mut().enumerate().filter(|(i, _)| !i.is_multiple_of(3)) {
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
        for (p, player) in ps.iter_mut().enumerate() {
            player.sub.centre = world.positions[2900 + p];
        }
        let (offsets, objects) = csr(&views);
        let report = manager
            .build(
                TickInfo { tick, dilation_permille: 1000 - tick as u16 },
                &world.soa(),
                AoiLists { offsets: &offsets, objects: &objects },
                &mut ps,
            )
            .unwrap();
        for v in [report.records, report.relative, report.datagrams, report.bytes, report.deferred, report.starving] {
            fnv(&mut hash, &(v as u64).to_le_bytes());
        }
        skipped += report.skipped;
        relative += report.relative;
        deferred += report.deferred;
        for (p, (player, tap)) in ps.iter_mut().zip(&mut taps).enumerate() {
            for d in player.sub.datagrams().iter() {
                let mut d = d.to_vec();
                let ServerMessage::StateUpdate(u) = tap.open(&mut d).unwrap().message else { panic!() };
                let h = u.header;
                fnv(&mut hash, &h.tick.to_le_bytes());
                fnv(&mut hash, &h.dilation_permille.to_le_bytes());
                for v in [h.origin.x, h.origin.y, h.origin.z, u.records.len() as i32] {
                    fnv(&mut hash, &v.to_le_bytes());
                }
                for r in &u.records {
                    fnv(&mut hash, &r.id.to_le_bytes());
                    match r.state {
                        RecordState::Delta { back, d } => {
                            forms[0] += 1;
                            backs.insert(back);
                            fnv(&mut hash, &[0, back]);
                            for v in d {
                                fnv(&mut hash, &v.to_le_bytes());
                            }
                        }
                        RecordState::Predicted { back, prior, d } => {
                            forms[4] += 1;
                            backs.insert(back);
                            fnv(&mut hash, &[4, back, prior]);
                            for v in d {
                                fnv(&mut hash, &v.to_le_bytes());
                            }
                        }
                        RecordState::Same { back } => {
                            forms[1] += 1;
                            backs.insert(back);
                            fnv(&mut hash, &[1, back]);
                        }
                        RecordState::Absolute { kind, pos } => {
                            let near = pos.offset_from(h.origin).is_some();
                            forms[2 + usize::from(!near)] += 1;
                            fnv(&mut hash, &[2 + u8::from(!near), kind as u8]);
                            for v in [pos.x, pos.y, pos.z] {
                                fnv(&mut hash, &v.to_le_bytes());
                            }
                        }
                    }
                }
            }
            // The link loses about one datagram in seven, and one acknowledgement in four.
            let p = p as u64;
            let delivered = |i: usize| !(tick * 3 + p * 5 + i as u64 * 11).is_multiple_of(7);
            lost += player.sub.datagrams().len() - (0..player.sub.datagrams().len()).filter(|&i| delivered(i)).count();
            player.client.receive_from(&player.sub, delivered);
            if !(tick + p).is_multiple_of(4) {
                player.client.acknowledge(&mut player.sub);
            }
        }
    }
    // Everything that makes the rule is exercised.
    assert!(skipped >= 60 && deferred > 0 && lost > 0, "{skipped} {deferred} {lost}");
    assert!(
        forms.iter().all(|&n| n > 0) && relative > 0,
        "records by form (delta, same, near, far, predicted): {forms:?}"
    );
    assert!(backs.iter().any(|&b| b > 1), "baselines older than a tick: {backs:?}");
    assert!(ps.iter().all(|p| p.client.unresolved == 0));
    assert_eq!(hash, 0x882e_1da1_93b9_4e17, "datagrams hash {hash:#018x}");
}
