//! The `cpu` backend's AOI query on a reference scenario, as the server asks it: one box
//! of edge AOI per player, centred on objects spread over the world.
//!
//! `cargo run --release -p myriad-physics --example aoi_query -- SCENARIO AOI`
//! (defaults: scenario 2, AOI 100) prints the medians of 20 rounds: the grid's build
//! after the objects moved (one query), then every player's query on the built grid.

use std::time::Instant;

use myriad_core::{Aabb, ScenarioSpec, Vec3};
use myriad_physics::{AoiResults, BackendKind, TickConstants, create_cpu_backend};

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let scenario: u8 = args.next().map(|s| s.parse()).transpose()?.unwrap_or(2);
    let aoi: f32 = args.next().map(|s| s.parse()).transpose()?.unwrap_or(100.0);
    let spec = ScenarioSpec::reference(scenario, 1)?;
    let mut world = spec.build()?;
    let mut backend = create_cpu_backend(BackendKind::Cpu)?;
    backend.step(&mut world, &TickConstants::new(&Default::default(), 1.0))?;
    let n = world.dynamics.len();
    let players = spec.users as usize;
    let boxes: Vec<Aabb> = (0..players)
        .map(|i| Aabb::from_center_half(world.dynamics.positions()[(i * 7919) % n], Vec3::splat(aoi / 2.0)))
        .collect();
    let (id, at) = (world.dynamics.ids()[0], world.dynamics.positions()[0]);
    let mut out = AoiResults::default();
    let (mut build, mut query) = (Vec::new(), Vec::new());
    for _ in 0..20 {
        // Moving an object (in place) makes the grid stale, as a step does.
        world.dynamics.teleport(id, at);
        let t = Instant::now();
        backend.query_aoi(&world, &boxes[..1], &mut out)?;
        build.push(t.elapsed().as_secs_f64() * 1e3);
        let t = Instant::now();
        backend.query_aoi(&world, &boxes, &mut out)?;
        query.push(t.elapsed().as_secs_f64() * 1e3);
    }
    println!(
        "scenario {scenario}, {n} objects, {players} players, AOI {aoi}: build {:.2} ms, queries {:.2} ms ({} objects a list), {} threads",
        median(build),
        median(query),
        out.objects.len() / players.max(1),
        rayon::current_num_threads()
    );
    Ok(())
}
