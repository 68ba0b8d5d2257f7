//! A world split into K zones ends in the same state hash as one process: scenarios 1 and
//! 2, the clustered scenario and a pile on the cuts, K = 2, 4 and 9, on the `cpu`
//! backend, over the in-process fabric (`tests/nats.rs` repeats some over NATS; the GPU
//! suite repeats them on `cuda`).

use std::time::Duration;

use myriad_core::{ActionScript, ObjectKind, ScenarioSpec, Shape, Vec3, World};
use myriad_physics::TickConstants;
use myriad_zone::{RunOptions, ZoneLayout, pair_reach, run_zoned};

mod common;
use common::{clustered, cpu, memory, single};

fn zoned(world: &World, k: u16, ticks: u64, script: &ActionScript) -> myriad_zone::ZonedRun {
    let layout = ZoneLayout::for_count(&world.bounds, k, pair_reach(world), 2.0).unwrap();
    let fabrics = memory(layout.len());
    let opts = RunOptions::new(ticks, Duration::from_secs(120));
    run_zoned(world, layout, script, &TickConstants::default(), &cpu, fabrics, &opts).unwrap()
}

fn check(name: &str, world: &World, ticks: u64, script: &ActionScript) {
    let want = single(world, ticks, script);
    for k in [2, 4, 9] {
        let run = zoned(world, k, ticks, script);
        let handoffs: u64 = run.stats.iter().map(|s| s.handoffs_in).sum();
        let ghosts: u64 = run.stats.iter().map(|s| s.ghosts_in).sum();
        assert_eq!(run.objects.len(), world.dynamics.len());
        assert_eq!(run.state_hash, want, "{name}, {k} zones: {handoffs} hand-offs, {ghosts} ghost records");
        assert!(ghosts > 0, "{name}, {k} zones: objects near the cuts were exchanged");
        assert_eq!(run.stats.iter().map(|s| s.rejected_total()).sum::<u64>(), 0);
        assert_eq!(run.actions, script.entries().iter().filter(|a| a.tick < ticks).count());
        eprintln!("{name}, {k} zones: equal over {ticks} ticks; {handoffs} hand-offs, {ghosts} ghost records");
    }
}

#[test]
fn scenario_one_with_walking_players() {
    let world = ScenarioSpec::reference(1, 3).unwrap().build().unwrap();
    let script = ActionScript::walkers(&world, 1_000, 300, 9);
    check("scenario 1", &world, 300, &script);
}

#[test]
fn scenario_two() {
    let world = ScenarioSpec::reference(2, 5).unwrap().build().unwrap();
    check("scenario 2", &world, 120, &ActionScript::default());
}

#[test]
fn clustered_scenario() {
    let world = clustered(11, 20_000, 2_000, 15_000);
    let script = ActionScript::walkers(&world, 2_000, 200, 4);
    check("clustered", &world, 200, &script);
}

/// Piles of objects dropped on every point where cuts of a 2 × 1, 2 × 2 or 3 × 3 grid
/// meet, so that hand-offs and contacts across two and four zones happen every tick.
#[test]
fn piles_on_the_cuts() {
    let mut world = ScenarioSpec::custom(21).counts(500, 50, 300).build().unwrap();
    let (lo, size) = (world.bounds.min, world.bounds.size());
    let mut corners = Vec::new();
    for f in [1.0 / 3.0, 0.5, 2.0 / 3.0] {
        for g in [1.0 / 3.0, 0.5, 2.0 / 3.0] {
            corners.push((lo.x + size.x * f, lo.z + size.z * g));
        }
    }
    let shapes = [
        Shape::Sphere { radius: 0.5 },
        Shape::Box { half: Vec3::new(0.4, 0.3, 0.6) },
        Shape::Capsule { radius: 0.3, half_height: 0.5 },
    ];
    for (c, (x, z)) in corners.iter().enumerate() {
        let ground = world.terrain.height_at(*x, *z);
        for i in 0..120 {
            let (dx, dz) = ((i % 5) as f32 * 0.7 - 1.4, ((i / 5) % 5) as f32 * 0.7 - 1.4);
            let p = Vec3::new(x + dx, ground + 1.0 + (i / 25) as f32 * 1.1, z + dz);
            world.dynamics.spawn(shapes[(i + c) % 3], p, ObjectKind::Npc).unwrap();
        }
    }
    check("piles on the cuts", &world, 240, &ActionScript::default());
}

/// The control: without ghosts (reach 0) the zones miss pairs across the cuts and the
/// hash differs, so the equalities above are not vacuous.
#[test]
fn without_reach_the_hash_differs() {
    let world = clustered(11, 5_000, 0, 1_000);
    let want = single(&world, 100, &ActionScript::default());
    let layout = ZoneLayout::for_count(&world.bounds, 4, 0.0, 2.0).unwrap();
    let fabrics = memory(4);
    let opts = RunOptions::new(100, Duration::from_secs(60));
    let run =
        run_zoned(&world, layout, &ActionScript::default(), &TickConstants::default(), &cpu, fabrics, &opts).unwrap();
    assert_ne!(run.state_hash, want);
}
