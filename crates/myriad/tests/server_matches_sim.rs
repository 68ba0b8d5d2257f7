//! The server's tick and `myriad sim` compute the same world: the server, fed a script of
//! actions as sealed datagrams through its real receive path (in memory, no sockets),
//! ends with the same state hash as the `myriad sim` command given the same scenario,
//! seed, tick count and script.
//!
//! This is the test that catches a server that counts ticks differently from the
//! simulation (NPC turns are drawn from the tick), applies actions a tick early or late,
//! or lets anything but the datagrams touch the world.

use std::process::Command;

use myriad_core::{ActionScript, ScenarioSpec, World};
use myriad_physics::{BackendKind, create_cpu_backend};
use myriad_server::ServerConfig;

/// `myriad sim` with a script; returns the state hash it printed.
fn sim_hash(world_args: &[&str], ticks: u64, script: &ActionScript) -> String {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("actions.txt");
    std::fs::write(&path, script.to_text()).unwrap();
    let ticks = ticks.to_string();
    let mut args = vec!["sim", "--json", "--backend", "cpu", "--ticks", &ticks, "--actions"];
    args.push(path.to_str().unwrap());
    args.extend_from_slice(world_args);
    let out = Command::new(env!("CARGO_BIN_EXE_myriad")).args(&args).env("RUST_LOG", "warn").output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["actions"].as_u64().unwrap() as usize, script.entries().len(), "sim applied every action");
    v["state_hash"].as_str().unwrap().to_string()
}

fn server_hash(world: World, ticks: u64, script: &ActionScript) -> String {
    let backend = create_cpu_backend(BackendKind::Cpu).unwrap();
    let run = myriad_server::scripted::run(ServerConfig::default(), world, backend, script, ticks).unwrap();
    assert_eq!(run.world.tick, ticks, "one tick of the world per server tick");
    assert_eq!(run.actions_applied as usize, script.entries().len(), "the server applied every action");
    assert_eq!(run.rejected, 0);
    assert_eq!(run.updates_without_own, 0);
    assert_eq!(run.unresolved, 0, "every delta record met the state it names");
    assert!(run.datagrams_opened >= ticks * script.entities().len() as u64, "every player got updates");
    format!("{:016x}", run.world.state_hash())
}

#[test]
fn scenario_1_with_walking_players() {
    // 130 ticks: past two NPC turn periods (60 ticks), so every NPC phase is exercised.
    let ticks = 130;
    let world = ScenarioSpec::reference(1, 1).unwrap().build().unwrap();
    let script = ActionScript::walkers(&world, 40, ticks, 5);
    assert!(script.entries().len() > 100);
    let args = ["--scenario", "1", "--seed", "1"];
    assert_eq!(sim_hash(&args, 0, &ActionScript::default()), format!("{:016x}", world.state_hash()), "same start");
    let sim = sim_hash(&args, ticks, &script);
    assert_eq!(server_hash(world, ticks, &script), sim);
}

#[test]
fn crowded_custom_world() {
    let ticks = 90;
    let args = [
        "--scenario",
        "custom",
        "--seed",
        "9",
        "--dynamic",
        "1500",
        "--static",
        "100",
        "--users",
        "150",
        "--world-size",
        "48",
        "--terrain-samples",
        "33",
    ];
    let mut spec = ScenarioSpec::custom(9);
    (spec.dynamic, spec.static_objects, spec.users, spec.world_size, spec.terrain_samples) = (1500, 100, 150, 48.0, 33);
    let world = spec.build().unwrap();
    let script = ActionScript::walkers(&world, 150, ticks, 11);
    assert_eq!(sim_hash(&args, 0, &ActionScript::default()), format!("{:016x}", world.state_hash()), "same start");
    let sim = sim_hash(&args, ticks, &script);
    assert_eq!(server_hash(world, ticks, &script), sim);
}
