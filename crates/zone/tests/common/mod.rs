//! What the zone tests share: the backend, the single-process reference, small worlds.
#![allow(dead_code)]

use myriad_core::{ActionScript, ScenarioSpec, World};
use myriad_physics::{Backend, BackendKind, TickConstants, create_cpu_backend};
use myriad_zone::{Fabric, MemoryFabric, ZoneError, ZoneId};

/// The `cpu` backend for every zone.
pub fn cpu(_: ZoneId) -> Result<Box<dyn Backend>, ZoneError> {
    Ok(create_cpu_backend(BackendKind::Cpu)?)
}

/// The state hash of `world` after `ticks` ticks in one process, with `script`.
pub fn single(world: &World, ticks: u64, script: &ActionScript) -> u64 {
    let mut w = world.clone();
    let mut b = create_cpu_backend(BackendKind::Cpu).unwrap();
    let k = TickConstants::default();
    for _ in 0..ticks {
        script.apply(&mut w).unwrap();
        b.step(&mut w, &k).unwrap();
    }
    w.state_hash()
}

/// The clustered scenario with other counts.
pub fn clustered(seed: u64, dynamic: u32, users: u32, statics: u32) -> World {
    let mut spec = ScenarioSpec::clustered(seed);
    spec.dynamic = dynamic;
    spec.users = users;
    spec.static_objects = statics;
    spec.build().unwrap()
}

/// In-process fabrics for `n` zones.
pub fn memory(n: usize) -> Vec<Box<dyn Fabric>> {
    MemoryFabric::mesh(n).into_iter().map(|f| Box::new(f) as Box<dyn Fabric>).collect()
}
