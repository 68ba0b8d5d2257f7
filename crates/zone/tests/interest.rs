//! States by interest, in memory: four zones on threads and a gateway that subscribes to
//! what its players see, in lockstep (the zones step one tick after each gateway step).
//! After every step the gateway's world holds exactly the zones' objects (id, kind,
//! shape, extents, position; its own players whole) of the objects it holds, and every
//! object that touches a player's AOI box; it holds far fewer than the world. That stays
//! true through a lost view (the chain of views breaks, the gateway asks for views
//! relative to its confirmation), a rollback of every zone (a new run: whole views
//! again) and a restart of the gateway (a new incarnation: whole views); bad
//! subscriptions are refused and counted, and change nothing.

use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::AtomicU32;
use std::sync::atomic::Ordering::SeqCst;
use std::sync::mpsc::{Receiver, Sender, channel};
use std::time::{Duration, Instant};

use myriad_core::{Action, EntityId, ObjectKind, ObjectState, ScenarioSpec, Shape, Vec3, World};
use myriad_physics::{Backend, TickConstants};
use myriad_zone::fabric::GatewayPort;
use myriad_zone::subscription::InterestConfig;
use myriad_zone::wire::{HEADER_LEN, Message, Subscription, TAG_LEN, decode, encode_subscription, sign};
use myriad_zone::{
    ClusterKey, GatewayConfig, GatewayLink, MemoryFabric, Zone, ZoneConfig, ZoneId, ZoneLayout, ZoneStats,
    ZonesBackend, pair_reach,
};

mod common;

const GW: u16 = 5;
const AOI_HALF: f32 = 8.0;

enum Cmd {
    Step,
    /// Every zone starts run `r` from its own objects (a rollback to the current tick).
    Restart(u64),
}

struct Zones {
    go: Vec<Sender<Cmd>>,
    back: Receiver<(usize, Vec<ObjectState>)>,
    /// Each zone's objects after its last step.
    now: Vec<Vec<ObjectState>>,
}

impl Zones {
    fn order(&mut self, cmd: impl Fn() -> Cmd) {
        for g in &self.go {
            g.send(cmd()).unwrap();
        }
        for _ in 0..self.go.len() {
            let (z, objects) = self.back.recv().unwrap();
            self.now[z] = objects;
        }
    }
}

fn world() -> World {
    ScenarioSpec { max_height: 2.0, ..ScenarioSpec::custom(9).counts(600, 0, 0).map_size(128.0, 65) }.build().unwrap()
}

fn interest(world: &World) -> InterestConfig {
    InterestConfig {
        aoi_half: AOI_HALF,
        cell: 8.0,
        margin: InterestConfig::margin_for(3, 2.0, pair_reach(world) / 2.0),
        linger: 10,
    }
}

/// A gateway's link that loses the next `lose` views it receives (then counts down).
struct Lossy {
    link: Box<dyn GatewayLink>,
    key: ClusterKey,
    lose: Arc<AtomicU32>,
}

impl GatewayLink for Lossy {
    fn send_intents(&mut self, bytes: Vec<u8>) -> Result<(), myriad_zone::ZoneError> {
        self.link.send_intents(bytes)
    }

    fn send_subscription(&mut self, bytes: Vec<u8>) -> Result<(), myriad_zone::ZoneError> {
        self.link.send_subscription(bytes)
    }

    fn recv_states(&mut self, deadline: Instant) -> Result<Option<Vec<u8>>, myriad_zone::ZoneError> {
        loop {
            let got = self.link.recv_states(deadline)?;
            let view = got.as_ref().is_some_and(|b| matches!(decode(&self.key, b), Ok(Message::View(_))));
            if view && self.lose.fetch_update(SeqCst, SeqCst, |n| n.checked_sub(1)).is_ok() {
                continue;
            }
            return Ok(got);
        }
    }
}

fn gateway(key: &ClusterKey, world: &World, port: &GatewayPort, lose: &Arc<AtomicU32>) -> ZonesBackend {
    let cfg = GatewayConfig {
        gateway: GW,
        key: key.clone(),
        zones: 4,
        wait: Duration::from_millis(200),
        refresh: 30,
        interest: Some(interest(world)),
    };
    let link = Lossy { link: Box::new(port.attach(GW)), key: key.clone(), lose: lose.clone() };
    ZonesBackend::new(cfg, Box::new(link)).unwrap()
}

/// Spawns walking players at `spots` in the gateway's world.
fn players(gw: &mut World, spots: &[(f32, f32, u8)]) -> Vec<EntityId> {
    spots
        .iter()
        .map(|&(x, z, action)| {
            let at = Vec3::new(x, gw.terrain.height_at(x, z) + 1.2, z);
            let shape = Shape::Capsule { radius: 0.4, half_height: 0.5 };
            let id = gw.dynamics.spawn(shape, at, ObjectKind::User).unwrap();
            gw.dynamics.set_action(id, Action::from_bits(action).unwrap());
            id
        })
        .collect()
}

/// The gateway's world against the zones': every object it holds has the zones' state,
/// and every object touching a player's AOI box is there. Returns how many it holds.
fn check(gw: &World, backend: &ZonesBackend, zones: &[Vec<ObjectState>], mine: &[EntityId]) -> usize {
    let truth: HashMap<EntityId, ObjectState> = zones.iter().flatten().map(|o| (o.id, *o)).collect();
    let d = &gw.dynamics;
    let step = backend.stats().mirrors;
    for s in 0..d.len() {
        let o = d.state_of(s);
        match truth.get(&o.id) {
            // What a gateway shows of an object is exact (its own players whole).
            Some(t) => assert!(
                (t.pos, t.kind, t.shape, t.half) == (o.pos, o.kind, o.shape, o.half)
                    && (!mine.contains(&o.id) || t.prev == o.prev),
                "object {:?} differs from its zone's after {step} worlds",
                o.id
            ),
            None => assert!(mine.contains(&o.id), "object {:?} is in no zone after {step} worlds", o.id),
        }
    }
    for id in mine {
        let p = d.positions()[d.slot(*id).expect("a player is always in the gateway's world")];
        for t in truth.values() {
            let touches = (t.pos.x - p.x).abs() <= AOI_HALF + t.half.x && (t.pos.z - p.z).abs() <= AOI_HALF + t.half.z;
            assert!(!touches || d.slot(t.id).is_some(), "object {:?} near player {id:?} is missing", t.id);
        }
    }
    d.len()
}

/// Bad subscriptions, each refused by every zone with its own reason.
fn hostile(key: &ClusterKey, port: &GatewayPort) {
    let mut link = port.attach(GW + 1);
    let good = Subscription {
        incarnation: 1,
        gateway: GW + 1,
        version: 1,
        confirmed: None,
        resyncs: 0,
        cell: 8.0,
        cols: 16,
        rows: 16,
        cells: vec![0xff; 32],
        ground: 0,
    };
    let stranger = ClusterKey::new(b"another cluster's key, not ours").unwrap();
    let bytes = encode_subscription(key, &good).unwrap();
    // Too many cells: signed with the cluster's key, refused behind the tag.
    let mut huge = bytes[..HEADER_LEN].to_vec();
    huge[24..28].copy_from_slice(&[0xff, 0xff, 0xff, 0xff]);
    let bad = [
        encode_subscription(&stranger, &good).unwrap(),
        bytes[..40].to_vec(),
        sign(key, &huge),
        encode_subscription(key, &Subscription { gateway: 200, ..good.clone() }).unwrap(),
        encode_subscription(key, &Subscription { cell: 16.0, ..good.clone() }).unwrap(),
        // The zones are in run 2 when they read it.
        encode_subscription(key, &Subscription { confirmed: Some((2, 1 << 40)), ..good.clone() }).unwrap(),
    ];
    assert_eq!(bad[2].len(), HEADER_LEN + TAG_LEN);
    for b in bad {
        link.send_subscription(b).unwrap();
    }
}

#[test]
fn a_gateway_holds_exactly_what_its_players_see_through_a_rollback_and_its_restart() {
    let world = world();
    let layout = Arc::new(ZoneLayout::for_count(&world.bounds, 4, pair_reach(&world), 2.0).unwrap());
    let key = ClusterKey::random();
    let (fabrics, port) = MemoryFabric::mesh_with_port(4);
    let k = TickConstants::default();
    let (back_tx, back) = channel();
    let stats: Vec<ZoneStats> = std::thread::scope(|s| {
        let mut go = Vec::new();
        let handles: Vec<_> = fabrics
            .into_iter()
            .enumerate()
            .map(|(i, fabric)| {
                let (layout, key, world, k, back_tx) = (layout.clone(), key.clone(), &world, &k, back_tx.clone());
                let (tx, rx) = channel::<Cmd>();
                go.push(tx);
                s.spawn(move || {
                    let id = ZoneId(i as u16);
                    let cfg = |run| ZoneConfig { id, run, key: key.clone(), wait: Duration::from_secs(10), live: true };
                    let mut zone =
                        Zone::new(cfg(1), layout.clone(), world, common::cpu(id).unwrap(), Box::new(fabric)).unwrap();
                    zone.set_mirror(false);
                    let mut stats = ZoneStats::default();
                    while let Ok(cmd) = rx.recv() {
                        if let Cmd::Restart(run) = cmd {
                            let (owned, tick) = (zone.advanced(), zone.tick());
                            stats = zone.stats().clone();
                            let mut at = world.clone();
                            at.tick = tick;
                            let fabric = zone.into_fabric();
                            zone = Zone::resume(cfg(run), layout.clone(), &at, owned, common::cpu(id).unwrap(), fabric)
                                .unwrap();
                            zone.set_mirror(false);
                        } else {
                            zone.step(&[], k).unwrap();
                        }
                        back_tx.send((i, zone.advanced())).unwrap();
                    }
                    // The rejections of both incarnations of the zone.
                    let mut last = zone.stats().clone();
                    for (reason, n) in stats.rejected {
                        *last.rejected.entry(reason).or_default() += n;
                    }
                    last
                })
            })
            .collect();
        let mut zones = Zones { go, back, now: vec![Vec::new(); 4] };

        // A gateway whose players stand and walk on both sides of both cuts (at 64).
        let lose = Arc::new(AtomicU32::new(0));
        let mut backend = gateway(&key, &world, &port, &lose);
        let mut gw = world.clone();
        backend.prepare(&mut gw);
        let (r, l, f) = (Action::RIGHT, Action::LEFT, Action::FORWARD);
        let mine = players(&mut gw, &[(60.0, 30.0, r), (68.0, 34.0, l), (40.0, 62.0, f), (90.0, 90.0, 0)]);
        let mut held = Vec::new();
        let mut run = |backend: &mut ZonesBackend, gw: &mut World, zones: &mut Zones, mine: &[EntityId], n: usize| {
            for _ in 0..n {
                let before = backend.stats().mirrors;
                backend.step(gw, &k).unwrap();
                if backend.stats().mirrors > before {
                    held.push(check(gw, backend, &zones.now, mine));
                }
                zones.order(|| Cmd::Step);
            }
        };
        run(&mut backend, &mut gw, &mut zones, &mine, 80);
        let first = backend.stats().clone();
        assert!(first.mirrors >= 75, "{first:?}");
        assert!(first.zone_gone_in > 0 && first.player_handoffs >= 2, "{first:?}");
        // Most moves came as nudges, and the world stayed exact (checked every step);
        // the views chained (each relative to the last), none lost.
        assert!(first.zone_nudges_in * 2 > first.zone_objects_in, "{first:?}");
        assert_eq!((first.resyncs, first.skipped), (0, 0), "{first:?}");

        // A view lost on the way: that tick never completes, the next does not apply
        // (its base is the lost tick), the gateway asks for views relative to its
        // confirmation and goes on, exact at every world it takes.
        lose.store(1, SeqCst);
        run(&mut backend, &mut gw, &mut zones, &mine, 20);
        let lossy = backend.stats().clone();
        assert_eq!(lossy.resyncs, 1, "{lossy:?}");
        assert!(lossy.rejected.get("base").is_some_and(|n| *n >= 1), "{lossy:?}");
        assert!(lossy.mirrors >= first.mirrors + 15, "{lossy:?}");
        let lost = lossy.rejected.clone();

        // A rollback of every zone: a new run, whose zones know no subscription yet.
        zones.order(|| Cmd::Restart(2));
        // Bad subscriptions, before the next tick.
        hostile(&key, &port);
        run(&mut backend, &mut gw, &mut zones, &mine, 40);
        let rolled = backend.stats().clone();
        assert_eq!(rolled.rollbacks, 1, "{rolled:?}");
        assert!(rolled.mirrors >= lossy.mirrors + 35, "views again after the rollback: {rolled:?}");
        assert_eq!(rolled.rejected, lost, "nothing refused after the loss: {rolled:?}");

        // The gateway restarts: its players leave with it, a new incarnation subscribes.
        drop(backend);
        std::thread::sleep(Duration::from_millis(1100));
        let mut backend = gateway(&key, &world, &port, &lose);
        let mut gw = world.clone();
        backend.prepare(&mut gw);
        let mine = players(&mut gw, &[(20.0, 100.0, r), (100.0, 20.0, l)]);
        run(&mut backend, &mut gw, &mut zones, &mine, 40);
        let restarted = backend.stats().clone();
        assert!(restarted.mirrors >= 35, "a restarted gateway gets whole views: {restarted:?}");
        for st in [&first, &restarted] {
            assert_eq!(st.duplicates, 0);
            assert_eq!(st.rejected.values().sum::<u64>(), 0, "{:?}", st.rejected);
        }
        let world_objects = world.dynamics.len();
        let most = *held.iter().max().unwrap();
        assert!(most * 2 < world_objects, "the gateway holds what its players see: {most} of {world_objects}");
        drop(zones);
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    for z in &stats {
        for reason in ["tag", "truncated", "cells", "subscription_stranger", "subscription_grid", "subscription_ahead"]
        {
            assert_eq!(z.rejected.get(reason), Some(&1), "zone refuses a {reason} subscription: {:?}", z.rejected);
        }
        assert!(z.views.contains_key(&GW), "{z:?}");
        assert!(z.publish > Duration::ZERO, "the views' time is counted: {z:?}");
    }
}
