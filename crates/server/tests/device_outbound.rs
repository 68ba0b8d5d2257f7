//! The device outbound's payloads are byte for byte the host outbound's: same world,
//! same ticks, same players (some joining, leaving, missing a tick or changing order),
//! with views that fit the budget, views over it (the rotation by staleness) and views
//! with extended records (objects over 512 units from the player).
//!
//! Needs a CUDA device: without one it skips, unless `MYRIAD_REQUIRE_CUDA=1` (the GPU
//! suite, `scripts/gpu-run.sh`), which makes a missing device a failure.

use std::sync::Mutex;

use myriad_core::{PhysicsConfig, ScenarioSpec, World};
use myriad_cuda::CudaBackend;
use myriad_interest::{Subscriber, TickInfo};
use myriad_physics::{Backend, BackendKind, TickConstants};
use myriad_protocol::{Direction, Sealer};
use myriad_server::outbound::{DeviceOutbound, HostOutbound, Job, Outbound, Ready, Recipient};

/// Whether the run must fail instead of skipping when no GPU is usable.
fn cuda_required() -> bool {
    std::env::var("MYRIAD_REQUIRE_CUDA").is_ok_and(|v| v == "1")
}

/// One player as both outbounds see it: the same session, twice.
struct Player {
    session_id: u64,
    slot: u32,
    host: Subscriber,
    device: Subscriber,
}

fn sealer(session_id: u64) -> Sealer {
    let mut key = [0u8; 32];
    key[..8].copy_from_slice(&session_id.to_le_bytes());
    Sealer::new(session_id, Direction::ServerToClient, &key)
}

impl Player {
    fn new(session_id: u64, slot: u32) -> Player {
        Player {
            session_id,
            slot,
            host: Subscriber::new(slot, [0.0; 3], sealer(session_id)),
            device: Subscriber::new(slot, [0.0; 3], sealer(session_id)),
        }
    }
}

/// A [`Ready`] that keeps what it was handed: each session and its datagrams then.
#[derive(Default)]
struct Handed(Mutex<Vec<(u64, Vec<Vec<u8>>)>>);

impl Ready for Handed {
    fn lanes(&self) -> usize {
        3
    }

    fn ready(&self, lane: usize, players: &[Recipient<'_>]) {
        assert!(lane < 64, "a lane for each thread at most");
        let mut handed = self.0.lock().unwrap();
        handed.extend(players.iter().map(|r| (r.session_id, r.view.datagrams().iter().map(<[u8]>::to_vec).collect())));
    }
}

/// Builds one tick with both outbounds for `players` (in this order) and checks that
/// every player got the same datagrams and report from both; returns (players over
/// budget, records sent).
fn compare(
    backend: &mut CudaBackend,
    world: &World,
    tick: TickInfo,
    host: &mut HostOutbound,
    device: &mut DeviceOutbound,
    players: &mut [&mut Player],
) -> (usize, usize) {
    let positions = world.dynamics.positions();
    let mut host_side: Vec<Recipient<'_>> = Vec::new();
    let mut device_side: Vec<Recipient<'_>> = Vec::new();
    for p in players.iter_mut() {
        let centre = positions[p.slot as usize];
        let (session_id, object, addr) = (p.session_id, p.slot, None);
        host_side.push(Recipient { session_id, object, centre, addr, view: &mut p.host });
        device_side.push(Recipient { session_id, object, centre, addr, view: &mut p.device });
    }
    // Every recipient is handed over once, with its datagrams final by then.
    let (host_ready, device_ready) = (Handed::default(), Handed::default());
    let h = host.build(&mut Job { backend: &mut *backend, world, tick, ready: &host_ready }, &mut host_side);
    let d = device.build(&mut Job { backend, world, tick, ready: &device_ready }, &mut device_side);
    for (side, ready, recipients) in [("host", host_ready, &host_side), ("device", device_ready, &device_side)] {
        let mut handed = ready.0.into_inner().unwrap();
        handed.sort_unstable();
        let mut now: Vec<(u64, Vec<Vec<u8>>)> = recipients
            .iter()
            .map(|r| (r.session_id, r.view.datagrams().iter().map(<[u8]>::to_vec).collect()))
            .collect();
        now.sort_unstable();
        assert_eq!(handed, now, "tick {}: {side} outbound's hand-over", tick.tick);
    }
    assert_eq!(h.records, d.records, "tick {}: records", tick.tick);
    let mut over = 0;
    for (a, b) in host_side.iter().zip(&device_side) {
        let (ra, rb) = (a.view.report(), b.view.report());
        assert_eq!(ra, rb, "tick {}, session {}: reports", tick.tick, a.session_id);
        let da: Vec<&[u8]> = a.view.datagrams().iter().collect();
        let db: Vec<&[u8]> = b.view.datagrams().iter().collect();
        assert!(!da.is_empty(), "tick {}, session {}: no datagram", tick.tick, a.session_id);
        assert_eq!(da, db, "tick {}, session {}: payloads differ", tick.tick, a.session_id);
        over += usize::from(ra.over_budget);
    }
    (over, h.records)
}

/// Runs `ticks` ticks of `world` with players at `slots`, building both outbounds with
/// AOI edge `aoi` (the device's in chunks of `chunk` players, `None`: its default); on
/// some ticks players leave, come back, join or change order.
fn run(
    world: &mut World,
    backend: &mut CudaBackend,
    aoi: f32,
    slots: &[u32],
    ticks: u64,
    chunk: Option<usize>,
) -> (usize, usize) {
    let k = TickConstants::new(&PhysicsConfig::default(), 1.0);
    let mut host = HostOutbound::new(aoi, 2);
    // The device interest of the backend that steps the world, as the factory hands it
    // out beside the backend.
    let mut device = DeviceOutbound::new(backend.device_interest(), aoi, 2);
    if let Some(chunk) = chunk {
        device = device.with_chunk(chunk);
    }
    let mut players: Vec<Player> = slots.iter().enumerate().map(|(i, &s)| Player::new(1000 + i as u64, s)).collect();
    let (mut over, mut records) = (0, 0);
    for t in 0..ticks {
        backend.step(world, &k).expect("step");
        let tick = TickInfo { tick: world.tick, dilation_permille: 1000 };
        let n = players.len();
        let mut order: Vec<&mut Player> = players.iter_mut().collect();
        match t % 4 {
            // Every third player misses this tick (starts afresh on the next).
            1 => order = order.into_iter().enumerate().filter(|(i, _)| i % 3 != 0).map(|(_, p)| p).collect(),
            // Reversed: each player's index in the device selection changes.
            2 => order.reverse(),
            _ => {}
        }
        let (o, r) = compare(backend, world, tick, &mut host, &mut device, &mut order);
        over += o;
        records += r;
        if t == ticks / 2 {
            // One leaves for good, one joins.
            players.remove(n / 2);
            let slot = slots[0] + 1;
            players.push(Player::new(5000 + t, slot));
        }
    }
    (over, records)
}

#[test]
fn device_outbound_payloads_equal_the_host_outbound() {
    let mut backend = match CudaBackend::new(BackendKind::Cuda) {
        Ok(b) => b,
        Err(e) => {
            assert!(!cuda_required(), "MYRIAD_REQUIRE_CUDA=1 but cuda is unavailable: {e}");
            eprintln!("skipping device_outbound_payloads_equal_the_host_outbound: {e}");
            return;
        }
    };
    let mut world = ScenarioSpec::reference(2, 7).expect("scenario 2").build().expect("world");
    let n = world.dynamics.len() as u32;
    // Players spread over the world's slots.
    let many: Vec<u32> = (0..400).map(|i| i * (n / 400)).collect();
    // AOI 100: most views over budget, so staleness decides half of every update; in
    // chunks of 64 players (the last one shorter), as a tick of thousands is cut.
    let (over, records) = run(&mut world, &mut backend, 100.0, &many, 12, Some(64));
    eprintln!("AOI 100: {over} player-ticks over budget, {records} records");
    assert!(over > 1000, "too few views over budget to test the rotation: {over}");
    // AOI 14: views that fit; one chunk.
    let (over, records) = run(&mut world, &mut backend, 14.0, &many, 6, None);
    eprintln!("AOI 14: {over} player-ticks over budget, {records} records");
    // AOI 1,100 on a few players: objects beyond 512 units take extended records; chunks
    // of three.
    let few: Vec<u32> = many.iter().step_by(40).copied().collect();
    let (over, records) = run(&mut world, &mut backend, 1100.0, &few, 6, Some(3));
    eprintln!("AOI 1100: {over} player-ticks over budget, {records} records");
    assert!(over > 0);
}
