//! The zones over a real NATS server: equal to one process, and a stalled neighbour is
//! detected. Needs `NATS_URL` (CI sets it; these machines run NATS at
//! 127.0.0.1:4222); skips with a message without it, fails under `MYRIAD_REQUIRE_NATS=1`.

use std::time::{Duration, Instant};

use myriad_core::{ActionScript, ScenarioSpec};
use myriad_physics::TickConstants;
use myriad_zone::{
    Fabric, NatsFabric, RunOptions, Zone, ZoneConfig, ZoneError, ZoneId, ZoneLayout, pair_reach, run_zoned,
};

mod common;
use common::{clustered, cpu, single};
use myriad_testenv::nats_url;
use myriad_zone::fabric_auth::NatsAuth;

fn cluster(name: &str) -> String {
    let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos();
    format!("test-{name}-{}-{nanos}", std::process::id())
}

#[test]
fn nine_zones_over_nats_equal_one_process() {
    let Some(url) = nats_url() else { return };
    let world = clustered(2, 8_000, 800, 3_000);
    let script = ActionScript::walkers(&world, 800, 150, 3);
    let layout = ZoneLayout::for_count(&world.bounds, 9, pair_reach(&world), 2.0).unwrap();
    let name = cluster("nine");
    let fabrics = (0..9)
        .map(|z| {
            NatsFabric::connect(&url, &name, ZoneId(z), &NatsAuth::default()).map(|f| Box::new(f) as Box<dyn Fabric>)
        })
        .collect::<Result<Vec<_>, _>>()
        .unwrap();
    let opts = RunOptions::new(150, Duration::from_secs(60));
    let run = run_zoned(&world, layout, &script, &TickConstants::default(), &cpu, fabrics, &opts).unwrap();
    assert_eq!(run.state_hash, single(&world, 150, &script));
    assert!(run.stats.iter().all(|s| s.bytes.0 > 0 && s.bytes.1 > 0));
}

/// A neighbour that never speaks is reported as stalled after the configured wait, with
/// its id, instead of blocking forever.
#[test]
fn a_silent_neighbour_is_a_stall() {
    let Some(url) = nats_url() else { return };
    let world = ScenarioSpec::reference(1, 1).unwrap().build().unwrap();
    let layout = std::sync::Arc::new(ZoneLayout::for_count(&world.bounds, 2, pair_reach(&world), 2.0).unwrap());
    let name = cluster("stall");
    let fabric = NatsFabric::connect(&url, &name, ZoneId(0), &NatsAuth::default()).unwrap();
    let cfg = ZoneConfig {
        id: ZoneId(0),
        run: 1,
        key: myriad_zone::ClusterKey::random(),
        wait: Duration::from_millis(300),
        live: false,
    };
    let mut zone = Zone::new(cfg, layout, &world, cpu(ZoneId(0)).unwrap(), Box::new(fabric)).unwrap();
    let start = Instant::now();
    match zone.step(&[], &TickConstants::default()) {
        Err(ZoneError::Stalled { missing, tick: 0, .. }) => assert_eq!(missing, [ZoneId(1)]),
        other => panic!("expected a stall, got {other:?}"),
    }
    assert!(start.elapsed() >= Duration::from_millis(300));
}
