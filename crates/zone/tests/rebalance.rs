//! Boundaries that follow the load end in one process's state hash: runs whose cuts move
//! (decided from object counts, or forced) on scenario 1, scenario 2, the clustered
//! scenario, a custom world and the moving crowd, K = 2, 4 and 9; a cut moved through a crowd; a cut
//! moved at a tick where objects cross it on their own; random layouts and random moves.

use std::time::Duration;

use myriad_core::{ActionScript, MovingCrowd, ObjectKind, ScenarioSpec, Shape, Vec3, World};
use myriad_physics::{BackendKind, TickConstants, create_cpu_backend};
use myriad_zone::rebalance::{CountOptions, ForcedMove, Policy, RebalanceOptions};
use myriad_zone::{ZoneLayout, ZonedRun, pair_reach, run_zoned};
use proptest::prelude::*;

mod common;
use common::{clustered, cpu, memory, single};

fn zoned(world: &World, k: u16, ticks: u64, script: &ActionScript, rebalance: RebalanceOptions) -> ZonedRun {
    let layout = ZoneLayout::for_count(&world.bounds, k, pair_reach(world), 2.0).unwrap();
    let fabrics = memory(layout.len());
    let mut opts = myriad_zone::RunOptions::new(ticks, Duration::from_secs(120));
    opts.rebalance = Some(rebalance);
    run_zoned(world, layout, script, &TickConstants::default(), &cpu, fabrics, &opts).unwrap()
}

/// Quick decisions for short runs: every 10 ticks, a cut rests 20.
fn counts() -> RebalanceOptions {
    let c = CountOptions { cooldown: 20, ..CountOptions::default() };
    RebalanceOptions { every: 10, delay: 2, policy: Policy::Counts(c), ..RebalanceOptions::default() }
}

fn forced(moves: Vec<ForcedMove>, every: u64, delay: u64) -> RebalanceOptions {
    RebalanceOptions { every, delay, policy: Policy::Forced(moves), ..RebalanceOptions::default() }
}

/// Runs `world` in 2, 4 and 9 zones with `rebalance` and checks the hash against one
/// process's; returns the cut moves of each run.
fn check(name: &str, world: &World, ticks: u64, script: &ActionScript, rebalance: &RebalanceOptions) -> Vec<u64> {
    let want = single(world, ticks, script);
    let mut moves = Vec::new();
    for k in [2, 4, 9] {
        let run = zoned(world, k, ticks, script, rebalance.clone());
        let log = run.rebalance.as_ref().unwrap();
        assert_eq!(run.objects.len(), world.dynamics.len());
        assert_eq!(run.state_hash, want, "{name}, {k} zones, {} cut moves: {:?}", run.cut_moves, log.moves);
        assert_eq!(run.cut_moves, log.moves.len() as u64);
        assert!(run.stats.iter().all(|s| s.cut_moves == run.cut_moves), "every zone switched at every move");
        assert!(log.refused.is_empty(), "{:?}", log.refused);
        // Samples every `every` ticks, the end included, each summing to the world.
        assert_eq!(log.samples.len() as u64, ticks / rebalance.every + 1);
        assert!(log.samples.iter().all(|s| s.owned.iter().sum::<usize>() == world.dynamics.len()));
        eprintln!("{name}, {k} zones: equal over {ticks} ticks with {} cut moves; cuts {:?}", run.cut_moves, log.cuts);
        moves.push(run.cut_moves);
    }
    moves
}

#[test]
fn scenario_one_rebalanced() {
    let world = ScenarioSpec::reference(1, 3).unwrap().build().unwrap();
    let script = ActionScript::walkers(&world, 1_000, 30, 9);
    check("scenario 1", &world, 30, &script, &counts());
}

#[test]
fn clustered_rebalanced_moves_cuts() {
    let world = clustered(11, 3_000, 300, 1_000);
    let script = ActionScript::walkers(&world, 300, 60, 4);
    let moves = check("clustered", &world, 60, &script, &counts());
    // The hot spots happen to balance the two columns of 2 zones; rows and the 3 × 3
    // grid are not balanced.
    assert!(moves[1] > 0 && moves[2] > 0, "hot spots unbalance the 2 × 2 and 3 × 3 grids: {moves:?}");
}

#[test]
fn custom_world_rebalanced() {
    // A small map with a third of its objects in one corner.
    let mut world = ScenarioSpec::custom(5).counts(600, 60, 60).map_size(96.0, 33).build().unwrap();
    for i in 0..300 {
        let (x, z) = (4.0 + (i % 15) as f32 * 1.3, 4.0 + (i / 15) as f32 * 1.3);
        let y = world.terrain.height_at(x, z) + 1.0;
        world.dynamics.spawn(Shape::Sphere { radius: 0.5 }, Vec3::new(x, y, z), ObjectKind::Npc).unwrap();
    }
    let moves = check("custom", &world, 80, &ActionScript::default(), &counts());
    assert!(moves.iter().all(|m| *m > 0), "{moves:?}");
}

/// A small moving crowd: 600 users from 20 % of a 128-unit map toward +x.
fn small_crowd() -> (World, ActionScript, f32) {
    let mut c = MovingCrowd::new(7);
    c.base = c.base.counts(300, 0, 60).map_size(128.0, 65);
    c.crowd = 600;
    c.spread = 6.0;
    let (world, script) = c.build_with_script(400).unwrap();
    (world, script, 128.0)
}

fn crowd_mean_x(objects: impl Iterator<Item = (ObjectKind, Vec3)>) -> f32 {
    let xs: Vec<f32> = objects.filter(|(k, _)| *k == ObjectKind::User).map(|(_, p)| p.x).collect();
    xs.iter().sum::<f32>() / xs.len() as f32
}

#[test]
fn the_moving_crowd_crosses_the_cut_and_the_cuts_follow() {
    let (world, script, size) = small_crowd();
    let ticks = 400;
    let start =
        crowd_mean_x((0..world.dynamics.len()).map(|s| (world.dynamics.kinds()[s], world.dynamics.positions()[s])));
    let want = single(&world, ticks, &script);
    for k in [2, 4] {
        let rebalance = RebalanceOptions { every: 20, ..counts() };
        let run = zoned(&world, k, ticks, &script, rebalance);
        assert_eq!(run.state_hash, want, "{k} zones");
        let log = run.rebalance.unwrap();
        let end = crowd_mean_x(run.objects.iter().map(|o| (o.kind, o.pos)));
        eprintln!(
            "moving crowd, {k} zones: mean x {start:.1} -> {end:.1}; {} cut moves; cuts {:?}",
            run.cut_moves, log.cuts
        );
        assert!(start < size / 2.0 && end > size / 2.0, "the crowd crossed the middle: {start} -> {end}");
        assert!(run.cut_moves > 0);
        // The x cut followed the crowd: first left of the middle (toward where it
        // gathered), at the end right of where it was at its leftmost.
        let lowest = log.moves.iter().map(|m| m.xs[1]).fold(f32::INFINITY, f32::min);
        assert!(
            lowest < size / 2.0 && log.cuts.0[1] > lowest,
            "{:?}",
            log.moves.iter().map(|m| m.xs[1]).collect::<Vec<_>>()
        );
    }
}

/// Piles of objects on the x cut of a 2 × 1 and 2 × 2 grid; the cut moves through the
/// pile (6 units right at tick 12, 12 left at tick 32) while it collapses.
#[test]
fn a_cut_moved_through_a_crowd() {
    let mut world = ScenarioSpec::custom(21).counts(300, 30, 100).map_size(96.0, 33).build().unwrap();
    let mid = world.bounds.min.x + world.bounds.size().x / 2.0;
    for (pile, z) in [30.0f32, 70.0].into_iter().enumerate() {
        let ground = world.terrain.height_at(mid, z);
        for i in 0..150 {
            let (dx, dz) = ((i % 5) as f32 * 0.7 - 1.4, ((i / 5) % 5) as f32 * 0.7 - 1.4);
            let p = Vec3::new(mid + dx, ground + 1.0 + (i / 25) as f32 * 1.1, z + dz);
            let shape = [Shape::Sphere { radius: 0.5 }, Shape::Box { half: Vec3::new(0.4, 0.3, 0.6) }][(i + pile) % 2];
            world.dynamics.spawn(shape, p, ObjectKind::Npc).unwrap();
        }
    }
    let want = single(&world, 60, &ActionScript::default());
    for k in [2u16, 4] {
        let l = ZoneLayout::for_count(&world.bounds, k, pair_reach(&world), 2.0).unwrap();
        let zs = l.cuts().1.to_vec();
        let moves = vec![
            ForcedMove { at: 10, xs: vec![0.0, mid + 6.0, 96.0], zs: zs.clone() },
            ForcedMove { at: 30, xs: vec![0.0, mid - 6.0, 96.0], zs },
        ];
        let run = zoned(&world, k, 60, &ActionScript::default(), forced(moves, 10, 2));
        assert_eq!(run.cut_moves, 2, "{k} zones");
        assert_eq!(run.state_hash, want, "{k} zones");
    }
}

/// Scenario 2 (55,000 objects, uniform, so the count policy has nothing to move): both
/// cuts of a 2 × 2 grid forced 40 units one way, then 60 back the other, thousands of
/// objects handed over at each move; the hash is one process's.
#[test]
fn scenario_two_with_cuts_forced_both_ways() {
    let world = ScenarioSpec::reference(2, 5).unwrap().build().unwrap();
    let ticks = 80;
    let want = single(&world, ticks, &ActionScript::default());
    let l = ZoneLayout::for_count(&world.bounds, 4, pair_reach(&world), 2.0).unwrap();
    let (xs, zs) = (l.cuts().0.to_vec(), l.cuts().1.to_vec());
    let shifted = |v: &[f32], d: f32| vec![v[0], v[1] + d, v[2]];
    let moves = vec![
        ForcedMove { at: 20, xs: shifted(&xs, 40.0), zs: shifted(&zs, -40.0) },
        ForcedMove { at: 50, xs: shifted(&xs, -20.0), zs: shifted(&zs, 20.0) },
    ];
    let run = zoned(&world, 4, ticks, &ActionScript::default(), forced(moves, 10, 2));
    assert_eq!(run.cut_moves, 2);
    let handed: u64 = run.stats.iter().map(|s| s.handoffs_in).sum();
    assert!(handed > 5_000, "the moves handed over whole strips: {handed} hand-offs");
    assert_eq!(run.state_hash, want);
}

/// A cut that moves at a tick where an object crosses it on its own: the tick is found
/// in one process's run, then the zones move the cut 2 units back at that tick, so the
/// crossing object and the objects of the strip are handed over in one exchange.
#[test]
fn a_cut_moved_at_the_tick_of_a_hand_off() {
    let (world, script, size) = small_crowd();
    let (every, delay) = (5, 1);
    let cut = size / 2.0;
    // One process: the first tick s = decision + delay at which an object's x goes from
    // below the cut (state at s - 1) to at or above it (state at s).
    let mut w = world.clone();
    let mut b = create_cpu_backend(BackendKind::Cpu).unwrap();
    let k = TickConstants::default();
    let mut before: Vec<f32> = w.dynamics.positions().iter().map(|p| p.x).collect();
    let mut at = None;
    for t in 0..400u64 {
        script.apply(&mut w).unwrap();
        b.step(&mut w, &k).unwrap();
        let now: Vec<f32> = w.dynamics.positions().iter().map(|p| p.x).collect();
        let s = t + 1;
        if s % every == delay && before.iter().zip(&now).any(|(a, b)| *a < cut && *b >= cut) {
            at = Some(s);
            break;
        }
        before = now;
    }
    let s = at.expect("the crowd reaches the cut");
    let ticks = s + 20;
    let want = single(&world, ticks, &script);
    for k in [2u16, 4] {
        let l = ZoneLayout::for_count(&world.bounds, k, pair_reach(&world), 2.0).unwrap();
        let moves = vec![ForcedMove { at: s - delay, xs: vec![0.0, cut - 2.0, size], zs: l.cuts().1.to_vec() }];
        let run = zoned(&world, k, ticks, &script, forced(moves, every, delay));
        assert_eq!(run.cut_moves, 1);
        assert_eq!(run.state_hash, want, "{k} zones, the cut moved at tick {s}");
    }
    eprintln!("an object crossed the cut at tick {s}, when the cut moved");
}

/// `n` random cuts strictly inside `(lo, hi)`, ascending, at least `gap` apart from each
/// other and the edges, drawn from `u` (shares in 0..1), or `None` when they do not fit.
fn cuts_from(u: &[f64], lo: f32, hi: f32, gap: f32) -> Option<Vec<f32>> {
    let n = u.len();
    let room = (hi - lo) as f64 - (n + 1) as f64 * gap as f64;
    if room <= 0.0 {
        return None;
    }
    let mut shares: Vec<f64> = u.to_vec();
    shares.sort_by(f64::total_cmp);
    let mut out = vec![lo];
    for (i, s) in shares.iter().enumerate() {
        out.push((lo as f64 + (i + 1) as f64 * gap as f64 + s * room) as f32);
    }
    out.push(hi);
    Some(out)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    /// Random grids, random moves (valid or not) and random points: a move either
    /// succeeds with every invariant or is refused; every point has one owner, inside its
    /// region; neighbours are symmetric and unchanged; zones are wider than the margin.
    #[test]
    fn random_cut_moves_keep_the_layouts_invariants(
        cols in 1u16..5, rows in 1u16..5,
        moves in prop::collection::vec((prop::collection::vec(0.0f64..1.0, 4), prop::collection::vec(0.0f64..1.0, 4), 0.0f32..6.0), 1..8),
        points in prop::collection::vec((-10.0f32..110.0, -10.0f32..90.0), 50),
    ) {
        let b = myriad_core::Aabb::new(Vec3::ZERO, Vec3::new(100.0, 10.0, 80.0));
        let mut l = ZoneLayout::grid(&b, cols, rows, 1.5, 2.0).unwrap();
        for (ux, uz, gap) in moves {
            let (xs, zs) = (cuts_from(&ux[..cols as usize - 1], 0.0, 100.0, gap), cuts_from(&uz[..rows as usize - 1], 0.0, 80.0, gap));
            let (Some(xs), Some(zs)) = (xs, zs) else { continue };
            let narrow = (cols > 1 || rows > 1) && xs.windows(2).chain(zs.windows(2)).any(|w| w[1] - w[0] <= l.margin());
            match l.with_cuts(&xs, &zs) {
                Ok(m) => {
                    prop_assert!(!narrow, "{:?} {:?} accepted", xs, zs);
                    prop_assert_eq!(m.shape(), l.shape());
                    for z in l.zones() {
                        prop_assert_eq!(m.neighbours(z), l.neighbours(z));
                    }
                    l = m;
                }
                Err(e) => prop_assert!(narrow, "{:?} {:?} refused: {}", xs, zs, e),
            }
            let (xs, zs) = l.cuts();
            prop_assert!((cols == 1 && rows == 1) || xs.windows(2).chain(zs.windows(2)).all(|w| w[1] - w[0] > l.margin()));
            for z in l.zones() {
                for n in l.neighbours(z) {
                    prop_assert!(l.neighbours(*n).contains(&z));
                }
            }
            for &(x, z) in &points {
                let p = Vec3::new(x, 0.0, z);
                let owner = l.zone_at(p);
                let owners = l.zones().filter(|q| { let r = l.region(*q); x >= r.min_x && x < r.max_x && z >= r.min_z && z < r.max_z }).count();
                let inside = (0.0..100.0).contains(&x) && (0.0..80.0).contains(&z);
                if inside {
                    prop_assert_eq!(owners, 1);
                    prop_assert_eq!(l.region(owner).distance(x, z), 0.0);
                }
                prop_assert!(l.sees(owner, p) && l.seers(p).any(|s| s == owner));
            }
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 6, ..ProptestConfig::default() })]

    /// A small world in zones with random forced moves at random ticks: every object
    /// comes back once, and the hash is one process's.
    #[test]
    fn random_forced_moves_lose_and_duplicate_nothing(
        k in prop::sample::select(vec![2u16, 4, 6]),
        moves in prop::collection::vec((0u64..8, prop::collection::vec(-1.0f32..1.0, 2), prop::collection::vec(-1.0f32..1.0, 2)), 1..6),
    ) {
        // Three hot spots on a 64-unit map: crowds near cuts wherever they move.
        let placement = myriad_core::Placement::Clustered { hotspots: 3, fraction: 0.8, spread: 4.0 };
        let spec = ScenarioSpec { placement, ..ScenarioSpec::clustered(5).counts(400, 40, 60).map_size(64.0, 33) };
        let world = spec.build().unwrap();
        let script = ActionScript::walkers(&world, 40, 40, 2);
        let l = ZoneLayout::for_count(&world.bounds, k, pair_reach(&world), 2.0).unwrap();
        // A chain of moves, each inner cut up to half a zone width either way from the
        // last proposal: some valid, some refused (too narrow, or jumping a zone).
        let (mut xs, mut zs) = (l.cuts().0.to_vec(), l.cuts().1.to_vec());
        let mut forced_moves = Vec::new();
        for (at, dx, dz) in &moves {
            for (cuts, d) in [(&mut xs, dx), (&mut zs, dz)] {
                let n = cuts.len();
                let half = 64.0 / (n - 1) as f32 / 2.0;
                for (c, d) in cuts[1..n - 1].iter_mut().zip(d) {
                    *c += d * half;
                }
            }
            forced_moves.push(ForcedMove { at: at * 5, xs: xs.clone(), zs: zs.clone() });
        }
        let mut opts = myriad_zone::RunOptions::new(40, Duration::from_secs(60));
        opts.rebalance = Some(forced(forced_moves.clone(), 5, 2));
        let run = run_zoned(&world, l, &script, &TickConstants::default(), &cpu, memory(k as usize), &opts).unwrap();
        let log = run.rebalance.as_ref().unwrap();
        prop_assert_eq!(run.objects.len(), world.dynamics.len());
        prop_assert!(run.objects.windows(2).all(|w| w[0].id < w[1].id));
        prop_assert_eq!(run.state_hash, single(&world, 40, &script));
        prop_assert_eq!(log.moves.len() + log.refused.len(), {
            let mut ats: Vec<u64> = forced_moves.iter().map(|m| m.at).filter(|at| at + 2 < 40).collect();
            ats.sort_unstable();
            ats.dedup();
            ats.len()
        });
    }
}

/// A zone that fails in a rebalancing run: its neighbours stall or lose their
/// coordinator, and the run reports the failing zone's error, not theirs.
#[test]
fn a_failing_zone_is_reported_not_its_echoes() {
    let world = ScenarioSpec::custom(5).counts(200, 20, 20).map_size(64.0, 33).build().unwrap();
    let layout = ZoneLayout::for_count(&world.bounds, 4, pair_reach(&world), 2.0).unwrap();
    let failing = |z: myriad_zone::ZoneId| {
        if z.0 == 1 { Err(myriad_zone::ZoneError::Checkpoint("no backend for zone 1".into())) } else { cpu(z) }
    };
    let mut opts = myriad_zone::RunOptions::new(40, Duration::from_secs(2));
    opts.rebalance = Some(counts());
    let e = run_zoned(&world, layout, &ActionScript::default(), &TickConstants::default(), &failing, memory(4), &opts)
        .unwrap_err();
    assert!(e.to_string().contains("no backend for zone 1"), "{e}");
}
