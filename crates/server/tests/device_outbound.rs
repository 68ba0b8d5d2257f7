//! The device outbound's datagrams are byte for byte the host outbound's: same world,
//! same ticks, same players (some joining, leaving, missing a tick or changing order),
//! whose clients acknowledge what reaches them through a lossy, late link, with views
//! that fit the budget and views over it (objects deferred, objects starving).
//!
//! Needs a CUDA device: without one it skips, unless `MYRIAD_REQUIRE_CUDA=1` (the GPU
//! suite, `scripts/gpu-run.sh`), which makes a missing device a failure.

use std::sync::Mutex;

use myriad_core::{PhysicsConfig, ScenarioSpec, World};
use myriad_cuda::CudaBackend;
use myriad_interest::{InterestConfig, Subscriber, TickInfo};
use myriad_physics::{Backend, BackendKind, TickConstants};
use myriad_protocol::{AckTracker, Direction, Sealer};
use myriad_server::outbound::{ChunkPlan, DeviceOutbound, HostOutbound, Job, Outbound, Ready, Recipient};

/// Whether the run must fail instead of skipping when no GPU is usable.
fn cuda_required() -> bool {
    std::env::var("MYRIAD_REQUIRE_CUDA").is_ok_and(|v| v == "1")
}

/// One player as both outbounds see it: the same session twice, and its client.
struct Player {
    session_id: u64,
    slot: u32,
    host: Subscriber,
    device: Subscriber,
    /// Datagrams on their way to the client: (arrival tick, sequence number).
    on_the_way: Vec<(u64, u64)>,
    client: AckTracker,
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
            on_the_way: Vec::new(),
            client: AckTracker::default(),
        }
    }

    /// This tick's datagrams leave for the client: one in ten is lost, the rest arrive
    /// one or two ticks later; what arrived by `tick` is acknowledged to both sides.
    fn deliver(&mut self, tick: u64) {
        let sent = self.host.datagrams().len() as u64;
        let next = self.host.sealer.next_sequence();
        for sequence in next - sent..next {
            let h =
                (self.session_id ^ sequence.wrapping_mul(0x9e37_79b9_7f4a_7c15)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            if !(h >> 32).is_multiple_of(10) {
                self.on_the_way.push((tick + 1 + (h >> 40) % 2, sequence));
            }
        }
        let client = &mut self.client;
        self.on_the_way.retain(|&(at, sequence)| {
            if at <= tick {
                client.record(sequence);
            }
            at > tick
        });
        if let Some(field) = self.client.field() {
            self.host.acknowledge(field);
            self.device.acknowledge(field);
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

/// What a run covered: records sent, of them relative, objects deferred and starving.
#[derive(Debug, Default)]
struct Covered {
    records: usize,
    relative: usize,
    deferred: usize,
    starving: usize,
    /// The most objects one player had due in one build (packed or deferred: in a
    /// player's first build every object in view is due).
    most_due: usize,
    /// The most datagrams one player got in one build (the packing's split).
    most_datagrams: usize,
}

/// Builds one tick with both outbounds for `players` (in this order) and checks that
/// every player got the same datagrams and report from both.
fn compare(
    backend: &mut CudaBackend,
    world: &World,
    tick: TickInfo,
    host: &mut HostOutbound,
    device: &mut DeviceOutbound,
    players: &mut [&mut Player],
    covered: &mut Covered,
) {
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
    assert_eq!(
        (h.records, h.relative, h.seal_failures),
        (d.records, d.relative, d.seal_failures),
        "tick {}",
        tick.tick
    );
    for (a, b) in host_side.iter().zip(&device_side) {
        let (ra, rb) = (a.view.report(), b.view.report());
        assert_eq!(ra, rb, "tick {}, session {}: reports", tick.tick, a.session_id);
        let da: Vec<&[u8]> = a.view.datagrams().iter().collect();
        let db: Vec<&[u8]> = b.view.datagrams().iter().collect();
        assert!(!da.is_empty(), "tick {}, session {}: no datagram", tick.tick, a.session_id);
        assert_eq!(da, db, "tick {}, session {}: datagrams differ", tick.tick, a.session_id);
        covered.records += ra.records;
        covered.relative += ra.relative;
        covered.deferred += ra.deferred;
        covered.starving += ra.starving;
        covered.most_due = covered.most_due.max(ra.packed + ra.deferred);
        covered.most_datagrams = covered.most_datagrams.max(da.len());
    }
}

/// Runs `ticks` ticks of `world` with players at `slots`, building both outbounds with
/// AOI edge `aoi` and a budget of `kbps` (the device's players in chunks as `chunks` says);
/// on some ticks players miss the tick, change order, leave or join.
fn run(
    world: &mut World,
    backend: &mut CudaBackend,
    (aoi, kbps, chunks): (f32, f64, ChunkPlan),
    slots: &[u32],
    ticks: u64,
) -> Covered {
    let k = TickConstants::new(&PhysicsConfig::default(), 1.0);
    let config = InterestConfig::with_budget(2, kbps, 30.0);
    let mut host = HostOutbound::new(aoi, config);
    // The replicas of the backend that steps the world, as the factory hands them out
    // beside the backend.
    let mut device = DeviceOutbound::new(backend.device_replicas(), aoi, config).with_chunks(chunks);
    let mut players: Vec<Player> = slots.iter().enumerate().map(|(i, &s)| Player::new(1000 + i as u64, s)).collect();
    let mut covered = Covered::default();
    for t in 0..ticks {
        backend.step(world, &k).expect("step");
        let tick = TickInfo { tick: world.tick, dilation_permille: 1000 };
        let n = players.len();
        let mut order: Vec<&mut Player> = players.iter_mut().collect();
        match t % 4 {
            // Every third player misses this tick (and keeps its replica).
            1 => order = order.into_iter().enumerate().filter(|(i, _)| i % 3 != 0).map(|(_, p)| p).collect(),
            // Reversed: each player's place in the build changes.
            2 => order.reverse(),
            _ => {}
        }
        compare(backend, world, tick, &mut host, &mut device, &mut order, &mut covered);
        for p in order {
            p.deliver(tick.tick);
        }
        if t == ticks / 2 {
            // One leaves for good, one joins.
            players.remove(n / 2);
            let slot = slots[0] + 1;
            players.push(Player::new(5000 + t, slot));
        }
    }
    covered
}

#[test]
fn device_outbound_datagrams_equal_the_host_outbound() {
    let mut backend = match CudaBackend::new(BackendKind::Cuda) {
        Ok(b) => b,
        Err(e) => {
            assert!(!cuda_required(), "MYRIAD_REQUIRE_CUDA=1 but cuda is unavailable: {e}");
            eprintln!("skipping device_outbound_datagrams_equal_the_host_outbound: {e}");
            return;
        }
    };
    let mut world = ScenarioSpec::reference(2, 7).expect("scenario 2").build().expect("world");
    let n = world.dynamics.len() as u32;
    // Players spread over the world's slots.
    let many: Vec<u32> = (0..300).map(|i| i * (n / 300)).collect();
    // One chunk: the device chooses for every player, then the host seals them all.
    let one = || ChunkPlan::equal(1);
    // AOI 100 at the default budget: views of hundreds, deltas against what the clients
    // acknowledged, near objects first, far ones waiting their turn.
    let c = run(&mut world, &mut backend, (100.0, 256.0, one()), &many, 40);
    eprintln!("AOI 100, 256 kbit/s: {c:?}");
    assert!(c.relative > c.records / 2 && c.deferred > 0, "{c:?}");
    // A budget far too small: most objects wait, some starve and go over it, into a
    // second datagram (the packing's split).
    let c = run(&mut world, &mut backend, (100.0, 16.0, one()), &many, 40);
    eprintln!("AOI 100, 16 kbit/s: {c:?}");
    assert!(c.starving > 0 && c.most_datagrams > 1, "{c:?}");
    // AOI 14: views that fit.
    let c = run(&mut world, &mut backend, (14.0, 256.0, one()), &many, 20);
    eprintln!("AOI 14: {c:?}");
    assert!(c.records > 0, "{c:?}");
    // AOI 400: views of thousands, more objects due than `k_replica_rank` sorts in
    // shared memory (4,096), which the block then sorts in global memory.
    let few: Vec<u32> = (0..12).map(|i| i * (n / 12)).collect();
    let c = run(&mut world, &mut backend, (400.0, 256.0, one()), &few, 6);
    eprintln!("AOI 400: {c:?}");
    assert!(c.most_due > 4096, "{c:?}");
    // The device's build in three chunks of players (the host seals and sends one while
    // the device chooses for the next), fresh replicas at first: the same bytes.
    let c = run(&mut world, &mut backend, (100.0, 256.0, ChunkPlan::equal(3)), &many, 20);
    eprintln!("AOI 100, 256 kbit/s, three chunks: {c:?}");
    assert!(c.relative > c.records / 2 && c.deferred > 0, "{c:?}");
    // Chunks of unequal sizes (each half the one before: 155, 77, 39, 19, 10 players of
    // 300 at first), and chunks sized by the measured ratio of host to device, as `serve`
    // runs them: the same bytes.
    let c = run(&mut world, &mut backend, (100.0, 256.0, ChunkPlan::tapered(5, 0.5).with_min_chunk(1)), &many, 20);
    eprintln!("AOI 100, 256 kbit/s, five chunks tapered by half: {c:?}");
    assert!(c.relative > c.records / 2 && c.deferred > 0, "{c:?}");
    let c = run(&mut world, &mut backend, (100.0, 256.0, ChunkPlan::measured(4)), &many, 20);
    eprintln!("AOI 100, 256 kbit/s, four chunks by the measured ratio: {c:?}");
    assert!(c.relative > c.records / 2 && c.deferred > 0, "{c:?}");
}
