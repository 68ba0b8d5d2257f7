use std::collections::HashMap;

use myriad_protocol::{Direction, Opener, PacketKind, RecordState, SessionKeys, UpdateReceiver};

use super::*;

const OWN: u64 = 1;

/// A client as the protocol asks: opens each datagram, resolves its records against
/// what it holds, and acknowledges a datagram only when every record applied.
struct Client {
    opener: Opener,
    receiver: UpdateReceiver,
    /// Newest state per object: (tick, position).
    held: HashMap<u64, (u64, QuantPos)>,
    unresolved: usize,
    bytes: usize,
}

impl Client {
    fn new(keys: &SessionKeys) -> Self {
        Self {
            opener: Opener::new(keys.session_id, Direction::ServerToClient, &keys.server_to_client),
            receiver: UpdateReceiver::default(),
            held: HashMap::new(),
            unresolved: 0,
            bytes: 0,
        }
    }

    fn receive(&mut self, datagram: &[u8]) {
        self.bytes += datagram.len();
        let mut d = datagram.to_vec();
        let opened = self
            .opener
            .open_with(&mut d, |kind, body| {
                assert_eq!(kind, PacketKind::StateUpdate);
                myriad_protocol::DeltaUpdate::decode_body(body)
            })
            .expect("a datagram the server sealed opens");
        let (sequence, update) = (opened.header.sequence, opened.message);
        let mut states = Vec::new();
        let failed = self.receiver.receive_update(sequence, &update, &mut states);
        for s in states {
            let e = self.held.entry(s.id).or_insert((0, s.pos));
            if update.header.tick >= e.0 {
                *e = (update.header.tick, s.pos);
            }
        }
        self.unresolved += failed;
    }
}

fn keys() -> SessionKeys {
    SessionKeys { session_id: 9, client_to_server: [1; 32], server_to_client: [2; 32] }
}

/// Objects `n` walking along x at 0.17 units a tick from `distance(i)` units away, ids
/// `id(i)`.
fn walkers(tick: u64, n: u64, id: impl Fn(u64) -> u64, distance: impl Fn(u64) -> f32) -> Vec<Candidate> {
    (0..n)
        .map(|i| {
            let d = distance(i);
            let x = d + tick as f32 * 0.17;
            Candidate {
                slot: i as u32,
                id: id(i),
                kind: ShapeKind::Sphere,
                pos: QuantPos::from_f32([x, 0.0, 0.0]),
                distance: d,
            }
        })
        .collect()
}

/// Objects on a line along x, `moving` of them walking at 0.17 units a tick.
fn world(tick: u64, n: u64, moving: u64) -> Vec<Candidate> {
    (0..n)
        .map(|i| {
            let x = i as f32 * 1.5 + if i < moving { tick as f32 * 0.17 } else { 0.0 };
            Candidate {
                slot: i as u32,
                id: 100 + i * 7,
                kind: ShapeKind::Sphere,
                pos: QuantPos::from_f32([x, 0.0, 0.0]),
                distance: x,
            }
        })
        .collect()
}

struct Run {
    replica: Replica,
    sealer: Sealer,
    client: Client,
    scratch: ReplicaScratch,
    out: DatagramBatch,
    config: ReplicationConfig,
}

impl Run {
    fn new(config: ReplicationConfig) -> Self {
        let k = keys();
        Self {
            replica: Replica::default(),
            sealer: Sealer::new(k.session_id, Direction::ServerToClient, &k.server_to_client),
            client: Client::new(&k),
            scratch: ReplicaScratch::default(),
            out: DatagramBatch::new(),
            config,
        }
    }

    /// One tick: build, deliver what `deliver(tick, i)` lets through, then the client's
    /// acknowledgement (if `ack`).
    fn tick(
        &mut self,
        tick: u64,
        view: &[Candidate],
        deliver: impl Fn(u64, usize) -> bool,
        ack: bool,
    ) -> ReplicaReport {
        let own = Some((OWN, ShapeKind::Capsule, QuantPos::new(0, 0, 0)));
        let report = self
            .replica
            .build(
                &self.config,
                TickInfo { tick, dilation_permille: 1000 },
                QuantPos::new(0, 0, 0),
                own,
                view,
                2,
                &mut self.sealer,
                &mut self.out,
                &mut self.scratch,
            )
            .unwrap();
        for (i, d) in self.out.iter().enumerate() {
            if deliver(tick, i) {
                self.client.receive(d);
            }
        }
        if ack && let Some(f) = self.client.receiver.acks() {
            self.replica.acknowledge(f);
        }
        report
    }
}

#[test]
fn a_still_world_costs_only_refreshes_once_acknowledged() {
    let mut run = Run::new(ReplicationConfig { budget_bytes_per_tick: 10_000.0, ..Default::default() });
    let view = world(0, 50, 0);
    let first = run.tick(1, &view, |_, _| true, true);
    assert_eq!(first.packed, 50, "everything new goes at once");
    assert_eq!(first.relative, 0);
    // Acknowledged: nothing but the own object until the refresh bound.
    let mut sizes = Vec::new();
    for t in 2..=30 {
        let r = run.tick(t, &view, |_, _| true, true);
        sizes.push((r.packed, run.out.total_bytes()));
    }
    let quiet = &sizes[..20];
    assert!(quiet.iter().all(|&(p, _)| p == 0), "{sizes:?}");
    // Own object relative to its acknowledged state: the stream's 12 bits of parameters,
    // the own id's code (id 1 at order 1: 2 bits) and a `Same` record with the usual
    // back (4 bits): 3 bytes.
    assert!(quiet.iter().all(|&(_, b)| b == DATAGRAM_OVERHEAD + 3), "{sizes:?}");
    // Then a `Same` record confirms each object, about 3 bytes apiece.
    let refreshed: usize = sizes.iter().map(|s| s.0).sum();
    assert_eq!(refreshed, 50, "{sizes:?}");
    assert_eq!(run.client.unresolved, 0);
}

#[test]
fn deltas_follow_acknowledgements_and_loss_only_delays() {
    let config = ReplicationConfig { budget_bytes_per_tick: 600.0, ..Default::default() };
    let mut run = Run::new(config);
    // A deterministic 20 % loss, and acknowledgements lost on every third tick.
    let lose = |tick: u64, i: usize| (tick * 7 + i as u64 * 13).is_multiple_of(5);
    let mut relative = 0;
    for t in 1..=200 {
        let view = world(t, 120, 80);
        let r = run.tick(t, &view, |tick, i| !lose(tick, i), t % 3 != 0);
        relative += r.relative;
    }
    assert_eq!(run.client.unresolved, 0, "the server used only states the client holds");
    assert!(relative > 1000, "deltas were used: {relative}");
    // Then a clean link: everything converges to the truth.
    for t in 201..=240 {
        run.tick(t, &world(t, 120, 80), |_, _| true, true);
    }
    let truth = world(240, 120, 80);
    for c in &truth {
        let held = run.client.held.get(&c.id).expect("every object reached the client");
        let age = 240 - held.0;
        assert!(held.1 == c.pos || age <= config.far_bound_ticks as u64, "object {} {age} ticks old", c.id);
    }
    // Within 3 ticks for the near ones.
    for c in truth.iter().filter(|c| c.distance <= config.near) {
        let held = run.client.held[&c.id];
        assert!(held.1 == c.pos || 240 - held.0 < 3 + 1, "near object {} held {held:?}", c.id);
    }
}

#[test]
fn the_budget_holds_on_average_and_nothing_starves() {
    let budget = 300.0;
    let mut run = Run::new(ReplicationConfig { budget_bytes_per_tick: budget, ..Default::default() });
    let mut last_sent: HashMap<u64, u64> = HashMap::new();
    let mut worst = 0;
    let ticks = 300;
    for t in 1..=ticks {
        let view = world(t, 400, 400);
        run.tick(t, &view, |_, _| true, true);
        for (&id, &(tick, _)) in &run.client.held {
            let last = last_sent.entry(id).or_insert(tick);
            if tick == t {
                worst = worst.max(t - *last);
                *last = t;
            }
        }
    }
    let per_tick = run.client.bytes as f32 / ticks as f32;
    assert!(per_tick <= budget * 1.05, "{per_tick} bytes a tick");
    // 400 moving objects do not fit 300 bytes a tick: the starving ones still come,
    // within twice the far bound and a little.
    assert!(worst <= 2 * 24 + 5, "an object waited {worst} ticks");
    assert_eq!(run.client.held.len(), 401);
}

#[test]
fn records_are_the_smallest_form() {
    // Near objects due every tick: each goes as a one-tick delta once acknowledged.
    let config = ReplicationConfig { budget_bytes_per_tick: 10_000.0, near_bound_ticks: 1.0, ..Default::default() };
    let mut run = Run::new(config);
    run.tick(1, &world(1, 10, 10), |_, _| true, true);
    run.tick(2, &world(2, 10, 10), |_, _| true, true);
    let mut d = run.out.get(0).unwrap().to_vec();
    let mut opener = Opener::new(9, Direction::ServerToClient, &keys().server_to_client);
    // The client's opener saw earlier numbers; a fresh one opens this one too.
    let update = opener.open_with(&mut d, |_, b| myriad_protocol::DeltaUpdate::decode_body(b)).unwrap().message;
    let deltas = update.records.iter().filter(|r| matches!(r.state, RecordState::Delta { back: 1, .. })).count();
    assert_eq!(deltas, 10, "{:?}", update.records);
    // With two acknowledged states, a steady move is predicted: a step or so off.
    run.tick(3, &world(3, 10, 10), |_, _| true, true);
    let mut d = run.out.get(0).unwrap().to_vec();
    let update = opener.open_with(&mut d, |_, b| myriad_protocol::DeltaUpdate::decode_body(b)).unwrap().message;
    let predicted = update.records.iter().filter(|r| match r.state {
        RecordState::Predicted { back: 1, prior: 1, d } => d.iter().all(|v| v.abs() <= 1),
        _ => false,
    });
    assert_eq!(predicted.count(), 10, "{:?}", update.records);
    assert_eq!(run.client.unresolved, 0);
}

#[test]
fn changing_objects_go_at_their_bound_and_near_ones_whenever_the_budget_has_room() {
    // A bound of 3 ticks at any distance; near is within 10 units.
    let config =
        ReplicationConfig { budget_bytes_per_tick: 10_000.0, near: 10.0, far_bound_ticks: 3.0, ..Default::default() };
    let sent = |distance: f32| {
        let mut run = Run::new(config);
        (1..=31)
            .map(|t| run.tick(t, &walkers(t, 10, |i| 100 + i, |_| distance), |_, _| true, true).packed)
            .sum::<usize>()
    };
    // Ten objects beyond `near`: new at tick 1, then every third tick.
    assert_eq!(sent(20.0), 10 + 10 * 10);
    // Near ones go every tick the budget has room for them (it has for all here).
    assert_eq!(sent(2.0), 10 * 31);
    // Unless the client acknowledges too slowly for a cheap record (every eighth tick):
    // then between its bound and every tick.
    let mut run = Run::new(config);
    let slow: usize =
        (1..=31).map(|t| run.tick(t, &walkers(t, 10, |i| 100 + i, |_| 2.0), |_, _| true, t % 8 == 0).packed).sum();
    assert!(slow > 10 + 10 * 10 && slow < 10 * 31, "{slow}");
    // A budget just above what the bound needs (90 bytes a tick: a datagram's overhead,
    // ten small records every third tick): eager records take only what it would
    // forfeit, so some go, and nothing due ever waits for them.
    let tight = ReplicationConfig { budget_bytes_per_tick: 90.0, ..config };
    let mut run = Run::new(tight);
    let (mut sent, mut deferred) = (0, 0);
    for t in 1..=31 {
        let r = run.tick(t, &walkers(t, 10, |i| 100 + i, |_| 2.0), |_, _| true, true);
        // (The first two ticks' absolute records are more than it holds.)
        (sent, deferred) = (sent + r.packed, deferred + if t > 2 { r.deferred } else { 0 });
    }
    assert!(sent > 10 + 10 * 10 && sent < 10 * 31, "{sent}");
    assert_eq!(deferred, 0);
}

#[test]
fn an_object_that_stops_is_sent_once_more_where_it_stopped() {
    let config = ReplicationConfig { budget_bytes_per_tick: 10_000.0, near_bound_ticks: 1.0, ..Default::default() };
    let mut run = Run::new(config);
    let mut packed = Vec::new();
    for t in 1..=20 {
        // Ten walkers, still from tick 10 on.
        packed.push(run.tick(t, &world(t.min(10), 10, 10), |_, _| true, true).packed);
    }
    // New at 1, then every tick while they move (a bound of one tick), once more at 11
    // where they stopped, then nothing: the client holds two equal states.
    assert_eq!(packed[..11], [10; 11], "{packed:?}");
    assert!(packed[11..].iter().all(|&p| p == 0), "{packed:?}");
    assert!(run.client.held.iter().filter(|(id, _)| **id != OWN).all(|(_, held)| held.0 == 11));
    assert_eq!(run.client.unresolved, 0);
    // Beyond `near` a stop is not worth a record of its own (where the budget binds it
    // would push over it what waits): the same walkers, near only within 5 units.
    let mut run = Run::new(ReplicationConfig { near: 5.0, far_bound_ticks: 1.0, ..config });
    let packed: Vec<usize> =
        (1..=20).map(|t| run.tick(t, &world(t.min(10), 10, 10), |_, _| true, true).packed).collect();
    // Walkers 0, 1 and 2 stop within 5 units (x = 1.5 i + 1.7): they alone go again at 11.
    assert_eq!(packed[..10], [10; 10], "{packed:?}");
    assert_eq!(packed[10], 3, "{packed:?}");
}

#[test]
fn a_near_object_that_jitters_is_sent_each_time_it_moves() {
    // An object that jumps between two places every tick, its client acknowledging every
    // third tick: its baseline is often where it is now, but the client's newest state
    // is the other place, so it goes every tick as a walker would (from tick 4, the first
    // build with a baseline: an eager record is relative).
    let config = ReplicationConfig { budget_bytes_per_tick: 10_000.0, ..Default::default() };
    let mut run = Run::new(config);
    let at = |t: u64| {
        let x = 2.0 + (t % 2) as f32 * 0.5;
        [Candidate { slot: 0, id: 100, kind: ShapeKind::Sphere, pos: QuantPos::from_f32([x, 0.0, 0.0]), distance: x }]
    };
    let packed: Vec<usize> = (1..=30).map(|t| run.tick(t, &at(t), |_, _| true, t % 3 == 0).packed).collect();
    assert!(packed[3..].iter().all(|&p| p == 1), "{packed:?}");
    assert_eq!(run.client.held[&100], (30, at(30)[0].pos));
    assert_eq!(run.client.unresolved, 0);
}

#[test]
fn a_near_object_that_rested_long_is_sent_the_tick_it_moves() {
    // Still until tick 40, then walking; the client acknowledges every third tick, so its
    // baseline is the refresh of tick 27 when it starts. A fresh link gets the first
    // step at once, however old the baseline, so the client does not draw it gliding
    // from a state ticks old.
    let config = ReplicationConfig { budget_bytes_per_tick: 10_000.0, ..Default::default() };
    let view = |t: u64| walkers(t.saturating_sub(40), 1, |_| 100, |_| 2.0);
    let mut run = Run::new(config);
    let packed: Vec<usize> = (1..=50).map(|t| run.tick(t, &view(t), |_, _| true, t % 3 == 0).packed).collect();
    let sent: Vec<usize> = (1..=50).filter(|&t| packed[t - 1] == 1).collect();
    assert_eq!(sent, [1, 27, 41, 42, 43, 44, 45, 46, 47, 48, 49, 50], "{packed:?}");
    // A link that has acknowledged nothing for longer than `resend_ticks` gets it at its
    // bound instead (a record against an old baseline is larger, and may be lost too):
    // acknowledged once, at tick 30, it moves from 41 and goes every third tick.
    let mut run = Run::new(config);
    let packed: Vec<usize> = (1..=50).map(|t| run.tick(t, &view(t), |_, _| true, t == 30).packed).collect();
    let moving: Vec<usize> = (41..=50).filter(|&t| packed[t - 1] == 1).collect();
    assert_eq!(moving, [42, 45, 48], "{packed:?}");
}

#[test]
fn a_budget_too_small_for_anything_still_sends_the_starving() {
    // Less than a datagram's own overhead: only objects past twice their bound go.
    let config = ReplicationConfig { budget_bytes_per_tick: 40.0, ..Default::default() };
    let mut run = Run::new(config);
    let mut first_seen: HashMap<u64, u64> = HashMap::new();
    let mut starving = 0;
    for t in 1..=120 {
        let r = run.tick(t, &world(t, 30, 30), |_, _| true, true);
        starving += r.starving;
        for &id in run.client.held.keys() {
            first_seen.entry(id).or_insert(t);
        }
    }
    assert_eq!(first_seen.len(), 31, "every object came");
    assert!(starving > 0);
    // New objects are due at once and go over the budget once they have waited
    // `max_wait_ticks` (30), a few a tick as the budget's deficit allows.
    assert!(first_seen.values().all(|&t| t <= 30 + 2), "{first_seen:?}");
}

#[test]
fn a_crowded_view_within_a_budget_reaches_every_object() {
    // About scenario 2 at AOI 100: 510 objects, the nearest within 30 units, all moving.
    let config = ReplicationConfig { budget_bytes_per_tick: 32_000.0 / 30.0, ..Default::default() };
    let mut run = Run::new(config);
    let view = |t: u64| walkers(t, 510, |i| 1000 + i * 97, |i| (i as f32 / 510.0).sqrt() * 86.0);
    let mut deferred = 0;
    for t in 1..=40 {
        deferred += run.tick(t, &view(t), |_, _| true, true).deferred;
    }
    assert_eq!(run.client.held.len(), 511, "deferred {deferred}");
}

#[test]
fn near_objects_keep_their_bound_when_the_budget_is_short() {
    // 60 near objects and 600 far ones, all moving: the budget holds the near ones every
    // third tick, not the far ones every 24th.
    let config = ReplicationConfig { budget_bytes_per_tick: 220.0, ..Default::default() };
    let mut run = Run::new(config);
    let view = |t: u64| {
        walkers(t, 660, |i| 10 + i * 5, |i| if i < 60 { 5.0 + i as f32 * 0.4 } else { 70.0 + i as f32 * 0.05 })
    };
    let (mut near_worst, mut far_worst) = (0, 0);
    for t in 1..=150 {
        let v = view(t);
        run.tick(t, &v, |_, _| true, true);
        if t > 60 {
            for c in &v {
                let age = t - run.client.held.get(&c.id).map_or(0, |h| h.0);
                if c.distance <= config.near {
                    near_worst = near_worst.max(age)
                } else {
                    far_worst = far_worst.max(age)
                }
            }
        }
    }
    // Sent every third tick, a near object's held state is at most two ticks old.
    assert!(near_worst < config.near_bound_ticks as u64, "a near object's state got {near_worst} ticks old");
    assert!(far_worst <= config.max_wait_ticks as u64 + 3, "a far object waited {far_worst} ticks");
}

#[test]
fn a_player_who_just_joined_gets_its_surroundings_first() {
    // 400 objects the client lacks, ids rising as the distance falls: what a small budget
    // holds on the first tick is the nearest, not the lowest ids.
    let config = ReplicationConfig { budget_bytes_per_tick: 4_000.0 / 30.0, ..Default::default() };
    let mut run = Run::new(config);
    let view = walkers(1, 400, |i| 10 + i, |i| 200.0 - i as f32 * 0.5);
    let r = run.tick(1, &view, |_, _| true, true);
    assert!(r.packed > 0 && r.deferred > 300, "{r:?}");
    let mut sent: Vec<&Candidate> = view.iter().filter(|c| run.client.held.contains_key(&c.id)).collect();
    sent.sort_by(|a, b| a.distance.total_cmp(&b.distance));
    let nearest_unsent = view.iter().filter(|c| !run.client.held.contains_key(&c.id)).map(|c| c.distance);
    let farthest_sent = sent.last().map_or(0.0, |c| c.distance);
    assert!(nearest_unsent.into_iter().all(|d| d >= farthest_sent), "a nearer object waited for a farther one");
}

#[test]
fn a_budget_that_is_not_a_positive_number_sends_only_the_own_object_and_the_starving() {
    let mut unlimited = Run::new(ReplicationConfig { budget_bytes_per_tick: f32::INFINITY, ..Default::default() });
    assert_eq!(unlimited.tick(1, &world(1, 10, 10), |_, _| true, true).packed, 10, "an infinite budget holds all");
    for budget in [-5.0, f32::NAN, f32::NEG_INFINITY] {
        let mut run = Run::new(ReplicationConfig { budget_bytes_per_tick: budget, ..Default::default() });
        let mut first = None;
        for t in 1..=40 {
            let r = run.tick(t, &world(t, 10, 10), |_, _| true, true);
            if r.packed > 0 && first.is_none() {
                first = Some((t, r.starving));
            }
        }
        // Nothing fits a budget of nothing; the objects go once they starve, on the
        // tick `max_wait_ticks` allows, and the own object every tick.
        assert_eq!(first, Some((30, 10)), "budget {budget}");
        assert!(run.client.held.contains_key(&OWN));
    }
}

#[test]
fn the_rank_orders_as_its_fields() {
    let r = |first, priority, distance, id| Due::rank(false, first, priority, distance, id);
    // First before not, then higher priority, then nearer, then the smaller id.
    assert!(r(true, 0.5, 90.0, 9) < r(false, 40.0, 1.0, 1));
    assert!(r(true, 2.0, 90.0, 9) < r(true, 1.5, 1.0, 1));
    assert!(r(true, 2.0, 1.0, 9) < r(true, 2.0, 1.5, 1));
    assert!(r(true, 2.0, 1.0, 1) < r(true, 2.0, 1.0, 2));
    assert!(r(false, 1.0, f32::MAX, 1) < r(false, 1.0, f32::NAN, 0), "a NaN distance goes last");
    assert!(r(false, 1.0e9, 0.0, u64::MAX) < r(false, 1.0, 0.0, 0));
    // Everything due before anything eager.
    assert!(r(false, 1.0, f32::NAN, u64::MAX) < Due::rank(true, true, 0.9, 0.0, 0));
}

#[test]
fn an_object_whose_slot_changed_keeps_its_baseline() {
    // Every moving object due every tick; from tick 5 the first one sits in a later
    // slot (a removal elsewhere moved it), so the merge by slot misses it.
    let config = ReplicationConfig { budget_bytes_per_tick: 10_000.0, near_bound_ticks: 1.0, ..Default::default() };
    let mut run = Run::new(config);
    let view = |t: u64| {
        let mut v = world(t, 10, 10);
        if t >= 5 {
            v[0].slot = 50;
            v.rotate_left(1);
        }
        v
    };
    for t in 1..=4 {
        run.tick(t, &view(t), |_, _| true, true);
    }
    for t in 5..=7 {
        let r = run.tick(t, &view(t), |_, _| true, true);
        assert_eq!((r.packed, r.out_of_order), (10, 0));
        assert_eq!(r.relative, 11, "tick {t}: every record relative to an acknowledged state, the moved one's too");
    }
    assert_eq!(run.client.unresolved, 0);
}

#[test]
fn candidates_out_of_slot_order_are_dropped_and_counted() {
    let mut run = Run::new(ReplicationConfig { budget_bytes_per_tick: 10_000.0, ..Default::default() });
    let mut view = world(1, 10, 0);
    // Slots 0, 1, 2, 4, 3, …: the 3 after the 4 is out of order; slot 0 again at the end.
    view.swap(3, 4);
    view.push(view[0]);
    let r = run.tick(1, &view, |_, _| true, true);
    assert_eq!((r.in_view, r.out_of_order, r.packed), (9, 2, 9));
    assert_eq!(run.client.unresolved, 0);
}

#[test]
fn one_id_in_two_slots_goes_once() {
    // A broken source: two slots claim one id. The datagram's ids must still increase
    // (the client would refuse it whole otherwise: `Client::receive` expects it opens).
    let mut run = Run::new(ReplicationConfig { budget_bytes_per_tick: 10_000.0, ..Default::default() });
    let mut view = world(1, 10, 0);
    view[5].id = view[4].id;
    let r = run.tick(1, &view, |_, _| true, true);
    assert_eq!((r.in_view, r.packed), (10, 9));
    assert_eq!(run.client.held.len(), 10, "nine objects and the own one");
}

#[test]
fn an_object_back_in_view_is_relative_to_what_the_client_acknowledged() {
    // Ten still objects go at tick 1; object 3 leaves the view at tick 2 and is back at
    // tick 3, when the acknowledgement of tick 1 arrives: the client holds its state,
    // so it is not sent again (it would go absolute if the track had started afresh).
    let mut run = Run::new(ReplicationConfig { budget_bytes_per_tick: 10_000.0, ..Default::default() });
    let all = world(1, 10, 0);
    let without: Vec<Candidate> = all.iter().filter(|c| c.slot != 3).copied().collect();
    assert_eq!(run.tick(1, &all, |_, _| true, false).packed, 10);
    assert_eq!(run.tick(2, &without, |_, _| true, true).packed, 0);
    let back = run.tick(3, &all, |_, _| true, true);
    assert_eq!((back.in_view, back.packed), (10, 0));
    assert_eq!(run.client.held.len(), 11);
    assert_eq!(run.client.unresolved, 0);
}
