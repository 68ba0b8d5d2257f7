use std::sync::LazyLock;

use super::*;
use crate::wire::{Message, Prediction, decode};
use myriad_core::terrain::TerrainPlacement;
use myriad_core::{Action, Terrain, Vec3};

const RUN: u64 = 4;
const G: u16 = 1;

fn key() -> ClusterKey {
    ClusterKey::new(&[3; 32]).unwrap()
}

fn bounds() -> Aabb {
    Aabb::new(Vec3::ZERO, Vec3::new(100.0, 20.0, 100.0))
}

/// Hills under `bounds()`, up to 12 units high.
static HILLS: LazyLock<Terrain> = LazyLock::new(|| {
    let at = TerrainPlacement { origin_x: 0.0, origin_z: 0.0, extent_x: 100.0, extent_z: 100.0, base_y: 0.0 };
    Terrain::generate(5, 33, 33, 12.0, at).unwrap()
});
static BOUNDS: LazyLock<Aabb> = LazyLock::new(bounds);

/// The zone's world: the hills and the bounds.
fn ground() -> GroundWorld<'static> {
    GroundWorld { terrain: &HILLS, bounds: &BOUNDS }
}

fn object(id: u32, x: f32, z: f32) -> ObjectState {
    crate::test_objects::npc_at(id, Vec3::new(x, 1.0, z))
}

/// Gateway `G`'s subscription to the cells of the first three columns (x < 30) of a
/// 10 × 10 grid.
fn subscription(incarnation: u64, version: u64, confirmed: Option<u64>) -> Subscription {
    let grid = CellGrid::new(&bounds(), 10.0).unwrap();
    let mut cells = CellSet::new(grid.len());
    for row in 0..10 {
        for col in 0..3 {
            cells.insert(row * 10 + col);
        }
    }
    Subscription {
        incarnation,
        gateway: G,
        version,
        confirmed: confirmed.map(|c| (RUN, c)),
        resyncs: 0,
        cell: 10.0,
        cols: 10,
        rows: 10,
        cells: cells.to_bytes(10, 10),
        ground: 0,
    }
}

/// One tick's views: (base, ids sent whole, ids moved, ids gone) per gateway.
#[allow(clippy::type_complexity)]
fn publish(
    subs: &mut Subscribers,
    tick: u64,
    owned: &[ObjectState],
) -> Vec<(u16, Option<u64>, Vec<u32>, Vec<u32>, Vec<u32>)> {
    let mut out = Vec::new();
    subs.publish(&key(), (RUN, tick, ZoneId(0)), owned.iter().copied(), ground(), 1 << 20, |g, bytes| {
        let Ok(Message::View(v)) = decode(&key(), &bytes) else { panic!("a view") };
        assert_eq!((v.run, v.tick, v.gateway, v.parts), (RUN, tick, g, 1));
        let ids = |v: &[EntityId]| v.iter().map(|id| id.0).collect::<Vec<_>>();
        // Moves and nudges alike: both carry a new position.
        let mut moved: Vec<EntityId> = v.moves.iter().map(|m| m.0).chain(v.nudges.iter().map(|n| n.id)).collect();
        moved.sort_unstable();
        out.push((g, v.base, v.objects.iter().map(|o| o.id.0).collect(), ids(&moved), ids(&v.gone)));
        Ok(())
    })
    .unwrap();
    out
}

#[test]
fn a_view_is_whole_then_only_what_changed_and_what_left_since_its_base() {
    let player = player_ids(G).start + 5;
    let mut world = vec![object(1, 5.0, 5.0), object(2, 25.0, 50.0), object(3, 50.0, 50.0), object(player, 90.0, 90.0)];
    let mut subs = Subscribers::default();
    assert!(publish(&mut subs, 1, &world).is_empty(), "nothing for nobody");
    subs.offer(subscription(10, 1, None), RUN, 1, &bounds()).unwrap();
    // Whole: the objects in the cells, and the gateway's own player wherever it is.
    assert_eq!(publish(&mut subs, 2, &world), [(G, None, vec![1, 2, player], vec![], vec![])]);
    subs.offer(subscription(10, 1, Some(2)), RUN, 2, &bounds()).unwrap();
    // At rest: nothing.
    assert_eq!(publish(&mut subs, 3, &world), [(G, Some(2), vec![], vec![], vec![])]);
    // One moves inside the cells (a move), one leaves them (gone), one enters (whole).
    world[0].pos.x = 6.0;
    world[1].pos.x = 35.0;
    world[2].pos.x = 29.0;
    // Relative to the last view sent (a chain): each change once.
    assert_eq!(publish(&mut subs, 4, &world), [(G, Some(3), vec![3], vec![1], vec![2])]);
    assert_eq!(publish(&mut subs, 5, &world), [(G, Some(4), vec![], vec![], vec![])]);
    // The gateway lost a view of the chain: the views are relative to its confirmation,
    // with every change since (gone ids kept until it confirms past them), until it
    // confirms one of them; then the chain goes on.
    let mut resync = subscription(10, 1, Some(2));
    resync.resyncs = 1;
    subs.offer(resync.clone(), RUN, 5, &bounds()).unwrap();
    assert_eq!(publish(&mut subs, 6, &world), [(G, Some(2), vec![3], vec![1], vec![2])]);
    assert_eq!(publish(&mut subs, 7, &world), [(G, Some(2), vec![3], vec![1], vec![2])]);
    resync.confirmed = Some((RUN, 6));
    subs.offer(resync.clone(), RUN, 7, &bounds()).unwrap();
    assert_eq!(publish(&mut subs, 8, &world), [(G, Some(7), vec![], vec![], vec![])]);
    // Told again (the same count): nothing new to do.
    subs.offer(resync, RUN, 8, &bounds()).unwrap();
    assert_eq!(publish(&mut subs, 9, &world), [(G, Some(8), vec![], vec![], vec![])]);
    // A confirmation more than CHAIN_LAG ticks behind: the gateway takes only its newest
    // tick, so views go relative to the confirmation.
    let behind = 9 + CHAIN_LAG + 1;
    world[0].pos.x = 7.0;
    assert_eq!(publish(&mut subs, behind, &world), [(G, Some(6), vec![], vec![1], vec![])]);
    let mut caught_up = subscription(10, 1, Some(behind));
    caught_up.resyncs = 1;
    subs.offer(caught_up, RUN, behind, &bounds()).unwrap();
    // The gateway's own player comes whole when it changes.
    world[3].pos.x = 91.0;
    assert_eq!(publish(&mut subs, behind + 1, &world), [(G, Some(behind), vec![player], vec![], vec![])]);
    // Handed to another zone: gone from this one.
    world.remove(0);
    assert_eq!(publish(&mut subs, behind + 2, &world), [(G, Some(behind + 1), vec![], vec![], vec![1])]);
    let t = behind + 2;
    // A gateway that dropped what it held (it confirms nothing now): whole again, until
    // it confirms one of them; then a chain.
    subs.offer(subscription(10, 1, None), RUN, t, &bounds()).unwrap();
    assert_eq!(publish(&mut subs, t + 1, &world), [(G, None, vec![3, player], vec![], vec![])]);
    assert_eq!(publish(&mut subs, t + 2, &world), [(G, None, vec![3, player], vec![], vec![])]);
    subs.offer(subscription(10, 1, Some(t + 1)), RUN, t + 2, &bounds()).unwrap();
    assert_eq!(publish(&mut subs, t + 3, &world), [(G, Some(t + 2), vec![], vec![], vec![])]);
    // A new subscriber's whole view is followed by a chain even before it confirms.
    let mut fresh = Subscribers::default();
    fresh.offer(subscription(10, 1, None), RUN, t, &bounds()).unwrap();
    assert_eq!(publish(&mut fresh, t + 1, &world), [(G, None, vec![3, player], vec![], vec![])]);
    assert_eq!(publish(&mut fresh, t + 2, &world), [(G, Some(t + 1), vec![], vec![], vec![])]);
    // A confirmation of another run (the gateway followed a rollback): whole again,
    // however recent the last view.
    let u = t + 3;
    let mut other = subscription(10, 3, Some(t));
    other.confirmed = Some((RUN + 1, t));
    subs.offer(other, RUN, u, &bounds()).unwrap();
    assert_eq!(publish(&mut subs, u + 1, &world), [(G, None, vec![3, player], vec![], vec![])]);
    // A restarted gateway (a newer incarnation) starts whole too; an older one is refused.
    subs.offer(subscription(11, 1, Some(u + 1)), RUN, u + 1, &bounds()).unwrap();
    assert_eq!(publish(&mut subs, u + 2, &world), [(G, None, vec![3, player], vec![], vec![])]);
    let stale = subs.offer(subscription(10, 9, Some(u)), RUN, u + 2, &bounds());
    assert_eq!(stale, Err(SubscriptionError::Stale { incarnation: 10, version: 9 }));
    // A subscriber silent for longer than EXPIRE_TICKS (last heard at u + 1) is dropped.
    assert_eq!(publish(&mut subs, u + 1 + EXPIRE_TICKS, &world).len(), 1);
    assert!(publish(&mut subs, u + 2 + EXPIRE_TICKS, &world).is_empty());
    assert!(subs.is_empty());
}

/// Gateway `G`'s views of `tick`, decoded.
fn views(subs: &mut Subscribers, tick: u64, owned: &[ObjectState]) -> Vec<View> {
    let mut out = Vec::new();
    subs.publish(&key(), (RUN, tick, ZoneId(0)), owned.iter().copied(), ground(), 1 << 20, |_, bytes| {
        let Ok(Message::View(v)) = decode(&key(), &bytes) else { panic!("a view") };
        out.push(v);
        Ok(())
    })
    .unwrap();
    out
}

fn part(v: View) -> crate::gateway_view::Part {
    let View { base, objects, moves, nudges, gone, acts, .. } = v;
    crate::gateway_view::Part { base, objects, moves, nudges, gone, acts }
}

#[test]
fn small_moves_go_as_nudges_along_a_chain_and_after_a_lost_view_and_rebuild_exact_positions() {
    use crate::gateway_view::{Applicable, ZoneViews};
    let mut world: Vec<ObjectState> = (1..=20).map(|i| object(i, i as f32 + 0.37, 11.0 * i as f32 / 3.0)).collect();
    let mut subs = Subscribers::default();
    let mut gateway = ZoneViews::default();
    subs.offer(subscription(10, 1, None), RUN, 1, &bounds()).unwrap();
    let v = views(&mut subs, 2, &world).remove(0);
    assert_eq!(v.base, None);
    gateway.apply(0, vec![part(v)], ground());
    gateway.remember(2);
    subs.offer(subscription(10, 1, Some(2)), RUN, 2, &bounds()).unwrap();
    // Walk every object a little each tick, and one far (a move, not a nudge); the
    // gateway confirms two ticks late, as a live one may, and loses the view of tick 14.
    let (mut confirmed, mut taken, mut resyncs) = (2, 2, 0);
    let mut took = vec![2];
    for tick in 3..30u64 {
        for (i, o) in world.iter_mut().enumerate() {
            o.pos.x += 0.013 * (i as f32 - 9.5);
            o.pos.y -= 0.001;
        }
        world[3].pos.z = if tick % 2 == 0 { 5.0 } else { 95.0 };
        let v = views(&mut subs, tick, &world).remove(0);
        // A chain (the last view), but for the views after the gateway asked again,
        // until it confirms one of them.
        let resynced = (16..=18).contains(&tick);
        assert_eq!(v.base, Some(if resynced { confirmed } else { tick - 1 }), "tick {tick}");
        assert!(v.moves.iter().any(|m| m.0 == EntityId(4)), "a jump goes as a move");
        assert_eq!(v.nudges.len() + v.moves.len(), world.iter().filter(|o| o.pos.x < 30.0).count());
        assert!(v.nudges.len() >= 15, "small steps go as nudges: {} of them", v.nudges.len());
        // Steady walks are predicted along a chain: from its second step, and again from
        // the second view after the resync's.
        let predicted = v.nudges.iter().filter(|n| n.prediction.needs_before()).count();
        let chained = tick >= 4 && !(16..=19).contains(&tick);
        assert_eq!(predicted >= 15, chained, "tick {tick}: {predicted} predicted");
        let parts = vec![part(v)];
        match gateway.applicable(0, &parts, Some(taken)) {
            _ if tick == 14 => {}
            Applicable::Yes => {
                assert_eq!(gateway.apply(0, parts, ground()), 0);
                gateway.remember(tick);
                taken = tick;
                took.push(tick);
                let held = gateway.assemble();
                let want: Vec<[u32; 3]> = world
                    .iter()
                    .filter(|o| o.pos.x < 30.0)
                    .map(|o| [o.pos.x, o.pos.y, o.pos.z].map(f32::to_bits))
                    .collect();
                let got: Vec<[u32; 3]> =
                    held.iter().map(|(o, _)| [o.pos.x, o.pos.y, o.pos.z].map(f32::to_bits)).collect();
                assert_eq!(got, want, "tick {tick}: the gateway holds the zone's positions bit for bit");
            }
            // The chain broke at 14: refused until the view relative to the confirmation.
            Applicable::Ahead => {
                assert_eq!(tick, 15);
                resyncs += 1;
            }
            Applicable::Lost => panic!("tick {tick}: nudges from a base the gateway has"),
        }
        // The confirmation (a tick it took) reaches the zone two ticks later.
        confirmed = took.iter().copied().filter(|&t| t + 2 <= tick).max().unwrap_or(confirmed);
        let mut s = subscription(10, 1, Some(confirmed));
        s.resyncs = resyncs;
        subs.offer(s, RUN, tick, &bounds()).unwrap();
    }
    assert_eq!(taken, 29);
    // A base older than the window: moves only, whatever the step.
    let late = 29 + NUDGE_WINDOW;
    for o in &mut world {
        o.pos.y -= 0.001;
    }
    let v = views(&mut subs, late, &world).remove(0);
    assert!(v.nudges.is_empty() && !v.moves.is_empty());
    // Nudges from a base the gateway no longer keeps cannot be applied: only whole
    // views bring it back.
    let nudges = vec![Nudge { id: EntityId(1), prediction: Prediction::Off, bits: [1, 0, 0] }];
    let forged = part(View { base: Some(3), nudges, moves: vec![], ..v });
    assert_eq!(gateway.applicable(0, std::slice::from_ref(&forged), Some(28)), Applicable::Lost);
    assert_eq!(gateway.applicable(0, &[forged], Some(2)), Applicable::Ahead);
}

#[test]
fn bad_subscriptions_are_refused_with_their_reason() {
    let mut subs = Subscribers::default();
    let s = subscription(10, 1, None);
    let refused = |s: Subscription, subs: &mut Subscribers| subs.offer(s, RUN, 20, &bounds()).unwrap_err().label();
    assert_eq!(refused(Subscription { gateway: MAX_GATEWAYS, ..s.clone() }, &mut subs), "subscription_stranger");
    let coarse = Subscription { cell: 20.0, ..s.clone() };
    assert_eq!(refused(coarse, &mut subs), "subscription_grid");
    assert_eq!(refused(subscription(10, 1, Some(21)), &mut subs), "subscription_ahead");
    assert!(subs.is_empty(), "nothing refused was kept");
    subs.offer(s, RUN, 20, &bounds()).unwrap();
    assert_eq!(subs.cells_of(G), Some(30));
}

/// The positions (as bits) and actions of `objects` with x below 30 (the subscription's
/// cells), ids ascending.
fn seen(objects: impl Iterator<Item = ObjectState>) -> Vec<(u32, [u32; 3], u8)> {
    objects.filter(|o| o.pos.x < 30.0).map(|o| (o.id.0, o.pos.to_array().map(f32::to_bits), o.action)).collect()
}

#[test]
fn walkers_on_the_hills_go_as_ground_nudges_with_their_actions_and_rebuild_exact_positions() {
    use crate::gateway_view::{Applicable, ZoneViews};
    use myriad_physics::TickConstants;
    use myriad_physics::integrate::{enforce_limits, integrate};
    let k = TickConstants::default();
    let ways = [Action::FORWARD, Action::FORWARD | Action::RIGHT, Action::RIGHT, Action::BACK | Action::LEFT, 0];
    // Twenty walkers on the terrain, stepped by the physics' own integration and limits
    // (no contacts), each changing its way every 7 ticks at its own phase.
    let mut objects: Vec<ObjectState> = (1..=20)
        .map(|i| {
            let (x, z) = (3.0 + i as f32 * 1.1, 10.0 + 3.7 * i as f32);
            let mut o = object(i, x, z);
            o.pos.y = HILLS.height_at(x, z) + o.half.y;
            o.prev = o.pos;
            o.flags = myriad_core::world::flags::ON_TERRAIN;
            o
        })
        .collect();
    let step = |objects: &mut Vec<ObjectState>, tick: u64| {
        for (i, o) in objects.iter_mut().enumerate() {
            if (tick + i as u64).is_multiple_of(7) {
                o.action = ways[(tick as usize + i) % ways.len()];
            }
            let (mut pos, mut prev) = (o.pos, o.prev);
            integrate(&mut pos, &mut prev, o.action, o.flags != 0, &k);
            o.flags = enforce_limits(&mut pos, &mut prev, o.half, &BOUNDS, &HILLS, &k);
            (o.pos, o.prev) = (pos, prev);
        }
    };
    for (name, fingerprint) in [("named", ground().fingerprint()), ("another world's", 7), ("none", 0)] {
        let mut world_now = objects.clone();
        let mut subs = Subscribers::default();
        let mut gateway = ZoneViews::default();
        let mut sub = subscription(10, 1, None);
        sub.ground = fingerprint;
        subs.offer(sub.clone(), RUN, 1, &bounds()).unwrap();
        gateway.apply(0, views(&mut subs, 2, &world_now).into_iter().map(part).collect(), ground());
        gateway.remember(2);
        let (mut on_ground, mut acts, mut nudges) = (0, 0, 0);
        for tick in 3..40u64 {
            step(&mut world_now, tick);
            let v = views(&mut subs, tick, &world_now);
            for v in &v {
                on_ground += v.nudges.iter().filter(|n| n.prediction == Prediction::Ground).count();
                nudges += v.nudges.len();
                acts += v.acts.len();
                // An act is sent only for an object whose action changed this tick (a
                // chain: each change once).
                for &(id, action) in &v.acts {
                    let o = world_now.iter().find(|o| o.id == id).unwrap();
                    assert_eq!(o.action, action);
                    assert_eq!((tick + u64::from(id.0) - 1) % 7, 0, "{name}: tick {tick}, act of {id:?}");
                }
            }
            let mut parts: Vec<_> = v.into_iter().map(part).collect();
            // On odd ticks the acts come in a part after the nudges that read them, as
            // a view cut in parts may send them.
            if tick % 2 == 1 {
                let acts = std::mem::take(&mut parts[0].acts);
                let base = parts[0].base;
                parts.push(crate::gateway_view::Part { base, acts, ..Default::default() });
            }
            assert_eq!(gateway.applicable(0, &parts, Some(tick - 1)), Applicable::Yes);
            assert_eq!(gateway.apply(0, parts, ground()), 0);
            gateway.remember(tick);
            let held = gateway.assemble();
            assert_eq!(seen(held.iter().map(|(o, _)| *o)), seen(world_now.iter().copied()), "{name}: tick {tick}");
            sub.confirmed = Some((RUN, tick));
            subs.offer(sub.clone(), RUN, tick, &bounds()).unwrap();
        }
        assert!(acts > 0, "{name}: the actions changed");
        if fingerprint == ground().fingerprint() {
            assert!(on_ground * 2 > nudges, "{name}: most walkers go as ground nudges ({on_ground} of {nudges})");
        } else {
            assert_eq!(on_ground, 0, "{name}: no ground nudges for a gateway on another ground");
        }
    }
    objects.clear();
}
