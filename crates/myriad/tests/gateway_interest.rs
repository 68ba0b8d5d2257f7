//! States by interest give every player exactly what the whole mirror gives: the real
//! server tick (sessions, interest management, packing, sealing; the scripted harness,
//! in memory) over a gateway's zones backend, with four zones on threads, players
//! walking across both cuts among moving NPCs; once with the mirror, once with
//! subscriptions. The clients' records, hashed, are equal; the gateway took a fraction
//! of the mirror's objects.
//!
//! The zones and the gateway go in lockstep (the test releases the zones for one tick
//! after each gateway step and waits for them), so that both runs see the same zones'
//! tick at every gateway tick: the only difference between them is what the zones send.

use std::sync::mpsc::{Receiver, Sender, channel};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use myriad_core::{Aabb, Action, ActionScript, ObjectKind, ScenarioSpec, ScriptedAction, Vec3, World};
use myriad_physics::{AoiResults, Backend, BackendKind, PhysicsError, StepReport, TickConstants, create_cpu_backend};
use myriad_server::ServerConfig;
use myriad_server::scripted::ScriptedRun;
use myriad_zone::gateway::GatewayStats;
use myriad_zone::subscription::InterestConfig;
use myriad_zone::{
    ClusterKey, GatewayConfig, MemoryFabric, ZoneConfig, ZoneId, ZoneLayout, ZoneStats, ZonesBackend, pair_reach,
};

const GW: u16 = 1;
const TICKS: u64 = 160;
const AOI: f32 = 20.0;

/// The gateway's backend, stepping the zones one tick after each of its steps.
struct Lockstep {
    inner: ZonesBackend,
    go: Vec<Sender<()>>,
    done: Receiver<()>,
    /// The gateway's counters after each step.
    stats: Arc<Mutex<Vec<GatewayStats>>>,
}

impl Backend for Lockstep {
    fn kind(&self) -> BackendKind {
        self.inner.kind()
    }
    fn description(&self) -> String {
        self.inner.description()
    }
    fn step(&mut self, world: &mut World, k: &TickConstants) -> Result<StepReport, PhysicsError> {
        let report = self.inner.step(world, k);
        self.stats.lock().unwrap().push(self.inner.stats().clone());
        for g in &self.go {
            g.send(()).unwrap();
        }
        for _ in &self.go {
            self.done.recv().unwrap();
        }
        report
    }
    fn query_aoi(&mut self, world: &World, boxes: &[Aabb], out: &mut AoiResults) -> Result<(), PhysicsError> {
        self.inner.query_aoi(world, boxes, out)
    }
}

fn world() -> World {
    ScenarioSpec { max_height: 2.0, ..ScenarioSpec::custom(5).counts(500, 0, 0).map_size(128.0, 65) }.build().unwrap()
}

struct Outcome {
    run: ScriptedRun,
    gateway: GatewayStats,
    /// The gateway's counters after each step.
    history: Vec<GatewayStats>,
    zones: Vec<ZoneStats>,
    players: Vec<(Vec3, Vec3)>,
}

/// Players of a run: where each starts (x, z), and its script, given the zones' layout
/// and the players' ids.
type Players = dyn Fn(&ZoneLayout) -> Vec<(f32, f32)>;
type Script = dyn Fn(&[myriad_core::EntityId]) -> ActionScript;

/// The players of the equality test: on both sides of both cuts, walking across them
/// and back among the NPCs.
fn across_the_cuts(layout: &ZoneLayout) -> Vec<(f32, f32)> {
    let cut = layout.region(ZoneId(0)).max_x;
    (0..8).map(|i| (cut - 4.0 + (i % 4) as f32 * 2.5, cut - 5.0 + (i / 4) as f32 * 8.0 + (i % 3) as f32)).collect()
}

fn there_and_back(ids: &[myriad_core::EntityId]) -> ActionScript {
    let mut script = Vec::new();
    for (i, &entity) in ids.iter().enumerate() {
        let (there, back) = match i % 4 {
            0 => (Action::RIGHT, Action::LEFT),
            1 => (Action::LEFT, Action::RIGHT),
            2 => (Action::FORWARD, Action::BACK),
            _ => (Action::BACK | Action::RIGHT, Action::FORWARD),
        };
        for (tick, bits) in [(2, there), (70 + i as u64, back), (130, 0)] {
            script.push(ScriptedAction { tick, entity, action: Action::from_bits(bits).unwrap() });
        }
    }
    ActionScript::new(script)
}

/// One run: mirror (`interest` none) or by interest.
fn run(interest: Option<InterestConfig>) -> Outcome {
    run_with(world(), None, interest, AOI, TICKS, &across_the_cuts, &there_and_back)
}

fn run_with(
    world: World,
    inner_cuts: Option<f32>,
    interest: Option<InterestConfig>,
    aoi: f32,
    ticks: u64,
    players: &Players,
    script: &Script,
) -> Outcome {
    let mut layout = ZoneLayout::for_count(&world.bounds, 4, pair_reach(&world), 2.0).unwrap();
    if let Some(c) = inner_cuts {
        let (xs, zs) = layout.cuts();
        layout = layout.with_cuts(&[xs[0], c, xs[2]], &[zs[0], c, zs[2]]).unwrap();
    }
    let layout = Arc::new(layout);
    let key = ClusterKey::random();
    let (fabrics, mut links) = MemoryFabric::mesh_with_gateways(4, &[GW]);
    let k = TickConstants::default();
    let (done_tx, done) = channel();
    let mut go = Vec::new();
    std::thread::scope(|s| {
        let zones: Vec<_> = fabrics
            .into_iter()
            .enumerate()
            .map(|(i, fabric)| {
                let (layout, key, world, k, done_tx) = (layout.clone(), key.clone(), &world, &k, done_tx.clone());
                let (tx, rx) = channel::<()>();
                go.push(tx);
                s.spawn(move || {
                    let id = ZoneId(i as u16);
                    let cfg = ZoneConfig { id, run: 1, key, wait: Duration::from_secs(10), live: true };
                    let backend = create_cpu_backend(BackendKind::Cpu).unwrap();
                    let mut zone = myriad_zone::Zone::new(cfg, layout, world, backend, Box::new(fabric)).unwrap();
                    zone.set_mirror(interest.is_none());
                    while rx.recv().is_ok() {
                        zone.step(&[], k).unwrap();
                        done_tx.send(()).unwrap();
                    }
                    zone.stats().clone()
                })
            })
            .collect();
        let cfg = GatewayConfig {
            gateway: GW,
            key: key.clone(),
            zones: 4,
            wait: Duration::from_millis(300),
            refresh: 30,
            interest,
        };
        // One incarnation for both runs: the players' ids follow from it.
        let inner = ZonesBackend::with_incarnation(cfg, Box::new(links.pop().unwrap()), 1_764_000_000_000).unwrap();
        let mut gw = world.clone();
        inner.prepare(&mut gw);
        let mut ids = Vec::new();
        for (x, z) in players(&layout) {
            let at = Vec3::new(x, gw.terrain.height_at(x, z) + 1.2, z);
            let id = gw.dynamics.spawn(myriad_server::PLAYER_SHAPE, at, ObjectKind::User).unwrap();
            ids.push((id, at));
        }
        let script = script(&ids.iter().map(|(id, _)| *id).collect::<Vec<_>>());
        let stats = Arc::new(Mutex::new(Vec::new()));
        let backend = Lockstep { inner, go: std::mem::take(&mut go), done, stats: stats.clone() };
        let config = ServerConfig { aoi_size: aoi, ..ServerConfig::default() };
        let run = myriad_server::scripted::run(config, gw, Box::new(backend), &script, ticks).unwrap();
        let players = ids
            .iter()
            .map(|(id, at)| (*at, run.world.dynamics.positions()[run.world.dynamics.slot(*id).expect("in the world")]))
            .collect();
        // The backend (and with it the zones' release channels) is gone: the zones end.
        let zones = zones.into_iter().map(|h| h.join().unwrap()).collect();
        let history = std::mem::take(&mut *stats.lock().unwrap());
        let gateway = history.last().cloned().unwrap_or_default();
        Outcome { run, gateway, history, zones, players }
    })
}

#[test]
fn every_client_receives_the_same_records_by_interest_as_with_the_mirror() {
    let w = world();
    let mirror = run(None);
    let cfg = InterestConfig {
        aoi_half: AOI / 2.0,
        cell: 16.0,
        margin: InterestConfig::margin_for(4, 2.0, pair_reach(&w) / 2.0),
        linger: 30,
    };
    let interest = run(Some(cfg));
    for o in [&mirror, &interest] {
        assert_eq!(o.run.rejected, 0);
        assert_eq!(o.run.updates_without_own, 0, "every update holds the player's own object");
        assert_eq!(o.run.unresolved, 0, "every delta record met the state it names");
        assert!(o.run.datagrams_opened >= (TICKS - 5) * 8, "every player got updates: {}", o.run.datagrams_opened);
        assert_eq!(o.gateway.duplicates, 0);
        assert_eq!(o.gateway.rejected.values().sum::<u64>(), 0, "{:?}", o.gateway.rejected);
        assert!(o.gateway.mirrors >= TICKS - 2, "a world at (nearly) every step: {:?}", o.gateway);
        assert!(o.gateway.player_handoffs >= 4, "players were handed between zones: {:?}", o.gateway);
    }
    // The players walked across the cuts (the hand-offs above) and back, and ended where
    // they did in the mirror's run.
    assert_eq!(
        mirror.players.iter().map(|p| p.1).collect::<Vec<_>>(),
        interest.players.iter().map(|p| p.1).collect::<Vec<_>>(),
        "the same world"
    );
    assert_eq!(mirror.run.datagrams_opened, interest.run.datagrams_opened);
    assert_eq!(
        mirror.run.records_hash, interest.run.records_hash,
        "every client received the same records by interest as with the mirror"
    );
    // What it cost: the mirror is every object every tick; by interest only what changed
    // in the players' cells.
    let (m, i) = (&mirror.gateway, &interest.gateway);
    assert!(m.zone_objects_in >= m.mirrors * w.dynamics.len() as u64, "{m:?}");
    assert!(
        i.zone_objects_in * 2 < m.zone_objects_in,
        "by interest {} records, mirror {}",
        i.zone_objects_in,
        m.zone_objects_in
    );
    assert!(i.zone_gone_in > 0, "objects left the subscription: {i:?}");
    assert!(i.subscriptions >= TICKS && i.subscription_cells > 0 && i.subscription_cells < 64, "{i:?}");
    for z in &interest.zones {
        assert_eq!(z.states_bytes, 0, "no mirror published");
        assert!(z.views.contains_key(&GW) && z.subscribers == 1, "{z:?}");
    }
    for z in &mirror.zones {
        assert!(z.states_bytes > 0 && z.views.is_empty());
    }
}

/// `large` with its corner of `small`'s size, at the common origin, replaced by `small`'s
/// contents: the terrain samples, the statics and the moving objects there are
/// `small`'s (ids kept, so its NPCs draw the same numbers), the rest `large`'s (ids moved
/// past `small`'s). Both maps must share their origin, sample spacing, heights and seed.
/// Players spread over the corner then see the same surroundings in either world, so
/// what a gateway takes in can be compared between the two sizes without the noise of
/// two different neighbourhoods.
fn with_corner_of(small: &World, large: World) -> World {
    let (ts, tl) = (&small.terrain, &large.terrain);
    let (ps, pl) = (ts.placement(), tl.placement());
    assert_eq!((ps.origin_x, ps.origin_z, ps.base_y), (pl.origin_x, pl.origin_z, pl.base_y), "one origin");
    assert_eq!(ts.max_height(), tl.max_height(), "the same heights");
    assert_eq!(small.seed, large.seed, "the same NPC draws");
    let spacing = |w: u32, e: f32| e / (w - 1) as f32;
    assert_eq!(spacing(ts.width(), ps.extent_x), spacing(tl.width(), pl.extent_x), "the same spacing");
    assert_eq!(spacing(ts.depth(), ps.extent_z), spacing(tl.depth(), pl.extent_z), "the same spacing");
    let (ws, wl) = (ts.width() as usize, tl.width() as usize);
    let mut samples = tl.samples().to_vec();
    for j in 0..ts.depth() as usize {
        samples[j * wl..j * wl + ws].copy_from_slice(&ts.samples()[j * ws..(j + 1) * ws]);
    }
    let terrain = myriad_core::Terrain::new(tl.width(), tl.depth(), samples, tl.max_height(), pl).unwrap();
    let corner = small.bounds;
    let inside = |p: Vec3| p.x < corner.max.x && p.z < corner.max.z;
    let mut world = World::new(large.bounds, terrain, large.seed).unwrap();
    let (sl, ss) = (&large.statics, &small.statics);
    world.statics = sl.subset(|_, o| !inside(sl.positions()[o.first as usize]));
    for o in ss.objects().iter().filter(|o| inside(ss.positions()[o.first as usize])) {
        let prims: Vec<_> = (o.first as usize..(o.first + o.count) as usize)
            .map(|i| {
                let shape = myriad_core::Shape::from_compact(ss.shapes()[i], ss.half_extents()[i], ss.radii()[i]);
                (shape, ss.positions()[i])
            })
            .collect();
        world.statics.add(o.kind, &prims).unwrap();
    }
    let (dl, ds) = (&large.dynamics, &small.dynamics);
    let past = ds.ids().iter().map(|i| i.0).max().unwrap_or(0) + 1;
    let theirs = (0..dl.len())
        .map(|s| dl.state_of(s))
        .filter(|o| !inside(o.pos))
        .map(|o| myriad_core::ObjectState { id: myriad_core::EntityId(o.id.0 + past), ..o });
    let mine = (0..ds.len()).map(|s| ds.state_of(s)).filter(|o| inside(o.pos));
    world.dynamics.insert_all(mine.chain(theirs).collect::<Vec<_>>().into_iter()).unwrap();
    world
}

/// A number from the environment, or `default`.
fn env_or<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default)
}

/// Measures a gateway's bytes in from the zones against its bytes out to its players,
/// mirror and by interest, at scenario 2's density (55,000 dynamic objects a 1,024²
/// map) over `MYRIAD_MEASURE_SCALE` (1) times its area, with `MYRIAD_MEASURE_PLAYERS`
/// (100) players spread over the map (or over the square of side
/// `MYRIAD_MEASURE_SPREAD` at its corner: the same players, at the same places, in a
/// larger world; with `MYRIAD_MEASURE_CORNER=1` that corner is the 1,024² map's own,
/// [`with_corner_of`], and the zones' inner cuts where that map has them), each walking one way and turning every two
/// seconds, for `MYRIAD_MEASURE_TICKS` (120) ticks, the first 30 left out; cells of
/// `MYRIAD_MEASURE_CELL` (the AOI size), a margin for `MYRIAD_MEASURE_LAG` (8) ticks of
/// lag at the zones' max step (2). Prints one
/// line per mode (docs/zones.md, "States by interest", measured):
/// `cargo test -p myriad --test gateway_interest -- --ignored --nocapture`.
#[test]
#[ignore = "a measurement (minutes): run it by name with --ignored"]
fn measure_bytes_in_against_bytes_out() {
    let scale: f32 = env_or("MYRIAD_MEASURE_SCALE", 1.0);
    let count: usize = env_or("MYRIAD_MEASURE_PLAYERS", 100);
    let ticks: u64 = env_or("MYRIAD_MEASURE_TICKS", 120);
    let warm = 30usize;
    let side_of = |scale: f32| (1024.0 * scale.sqrt()).round();
    let side = side_of(scale);
    let build = |scale: f32| {
        let side = side_of(scale);
        let n = |base: f32| (base * scale).round() as u32;
        let spec = ScenarioSpec::reference(2, 1)
            .unwrap()
            .counts(n(55_000.0), n(5_000.0), n(15_000.0))
            .map_size(side, side as u32 + 1);
        spec.build().unwrap()
    };
    let mut world = build(scale);
    // With the 1,024² map's corner, the zones are cut where they are on that map (the
    // 2 x 2 grid's inner cuts at 512), so the players are split between the zones alike.
    let mut inner_cuts = None;
    if env_or("MYRIAD_MEASURE_CORNER", 0) == 1 && scale > 1.0 {
        let small = build(1.0);
        inner_cuts = Some((small.bounds.min.x + small.bounds.max.x) / 2.0);
        world = with_corner_of(&small, world);
    }
    let aoi = ServerConfig::default().aoi_size;
    let spread_side: f32 = env_or("MYRIAD_MEASURE_SPREAD", side);
    // Spread over the map (a fixed sequence, so both modes get the same players).
    let spread = move |_: &ZoneLayout| {
        let mut x = 0x9e37_79b9_u32;
        let mut next = move || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            0.05 + 0.9 * (x as f32 / u32::MAX as f32)
        };
        (0..count).map(|_| (next() * spread_side, next() * spread_side)).collect()
    };
    let walk = move |ids: &[myriad_core::EntityId]| {
        let ways = [Action::RIGHT, Action::FORWARD | Action::RIGHT, Action::FORWARD, Action::LEFT, Action::BACK];
        let mut script = Vec::new();
        for (i, &entity) in ids.iter().enumerate() {
            for (k, tick) in (1..ticks).step_by(60).enumerate() {
                let action = Action::from_bits(ways[(i * 7 + k * 3) % ways.len()]).unwrap();
                script.push(ScriptedAction { tick, entity, action });
            }
        }
        ActionScript::new(script)
    };
    let (cell, lag) = (env_or("MYRIAD_MEASURE_CELL", aoi), env_or("MYRIAD_MEASURE_LAG", 8));
    let interest = InterestConfig {
        aoi_half: aoi / 2.0,
        cell,
        margin: InterestConfig::margin_for(lag, 2.0, pair_reach(&world) / 2.0),
        linger: 30,
    };
    for (mode, cfg) in [("mirror", None), ("interest", Some(interest))] {
        let started = std::time::Instant::now();
        let o = run_with(world.clone(), inner_cuts, cfg, aoi, ticks, &spread, &walk);
        let h = &o.history;
        let window = (h.len() - warm) as f64;
        let (a, b) = (&h[warm - 1], &h[h.len() - 1]);
        let bytes_in = (b.zone_bytes_in - a.zone_bytes_in) as f64 / window;
        let objects_in = (b.zone_objects_in - a.zone_objects_in) as f64 / window;
        let bytes_out = o.run.bytes_out[warm..].iter().sum::<u64>() as f64 / (o.run.bytes_out.len() - warm) as f64;
        println!(
            "scale {scale} ({side} units, {} objects), {count} players, cell {cell}, lag {lag}, {mode}: \
             in {:.0} B/tick ({objects_in:.0} records), out {bytes_out:.0} B/tick, in/out {:.2}, cells {}, \
             held {} objects, wall {:.0} s",
            world.dynamics.len(),
            bytes_in,
            bytes_in / bytes_out,
            b.subscription_cells,
            b.held_objects,
            started.elapsed().as_secs_f64()
        );
        assert_eq!(o.run.updates_without_own, 0);
        assert_eq!(o.run.unresolved, 0);
        assert_eq!(b.duplicates, 0);
    }
}
