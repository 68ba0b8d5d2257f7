//! Interest management at the reference's scenario sizes: one tick of every player's
//! update, protocol 3 (delta records against acknowledged states), built and sealed.
//!
//! Scenario 2: 55,000 dynamic objects, 5,000 players. Scenario 3: 260,000 objects,
//! 10,000 players. Objects are spread uniformly over a square map whose size gives an
//! average of 175 objects per 100 × 100 AOI; each player's AOI half-size is drawn so
//! that its expected occupancy is uniform in 50..=300. The AOI lists are computed once
//! (with a grid) before timing, by ascending slot as the physics backend would hand them
//! over. Every tick half the objects move a little, and every client acknowledges all it
//! received before the next tick; 40 ticks warm up first (everything is new to the
//! clients at first).
//!
//! * `interest_tick`: `InterestManager::build`, the live path: gather each view through
//!   `ObjectSource`, run the player's replica, seal; with the server's default budget
//!   (`InterestConfig::default()`: two datagrams, 64 kbit/s at 30 Hz).
//! * `replica_tick`: the per-player `Replica` alone, same views, budget and
//!   acknowledgements, on candidates the bench gathers itself: the difference to
//!   `interest_tick` is the manager's share (its gather, prefetching and reports).
//!
//! Run: `cargo bench -p myriad-interest --bench interest`

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use myriad_interest::replica::Candidate;
use myriad_interest::{
    AoiLists, InterestConfig, InterestManager, Replica, ReplicaScratch, SoaObjects, Subscriber, TickInfo, TickReport,
};
use myriad_protocol::{AckField, DatagramBatch, QuantPos, Sealer, ServerSession, SessionKeys, ShapeKind};
use rayon::prelude::*;

struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }
    fn unit(&mut self) -> f32 {
        (self.next() >> 40) as f32 / (1u64 << 24) as f32
    }
}

struct Scenario {
    ids: Vec<u64>,
    kinds: Vec<ShapeKind>,
    positions: Vec<[f32; 3]>,
    offsets: Vec<u32>,
    objects: Vec<u32>,
    subscribers: Vec<Subscriber>,
}

fn scenario(objects: usize, players: usize, seed: u64) -> Scenario {
    let mut rng = Rng(seed);
    let density = 175.0 / (100.0 * 100.0);
    let side = (objects as f32 / density).sqrt();
    let positions: Vec<[f32; 3]> =
        (0..objects).map(|_| [rng.unit() * side, rng.unit() * 30.0, rng.unit() * side]).collect();
    // A 32-unit grid over x/z to find each AOI's objects.
    let cell = 32.0f32;
    let cells = (side / cell).ceil() as usize + 1;
    let mut grid: Vec<Vec<u32>> = vec![Vec::new(); cells * cells];
    let cell_of = |v: f32| ((v / cell) as usize).min(cells - 1);
    for (i, p) in positions.iter().enumerate() {
        grid[cell_of(p[2]) * cells + cell_of(p[0])].push(i as u32);
    }
    let mut offsets = vec![0u32];
    let mut list = Vec::new();
    let mut subscribers = Vec::with_capacity(players);
    // Players are the first `players` objects (ids are slots, as in the world).
    for p in 0..players {
        let c = positions[p];
        let want = 50.0 + rng.unit() * 250.0;
        let half = 50.0 * (want / 175.0).sqrt();
        let (x0, x1) = (cell_of((c[0] - half).max(0.0)), cell_of(c[0] + half));
        let (z0, z1) = (cell_of((c[2] - half).max(0.0)), cell_of(c[2] + half));
        let start = list.len();
        for cz in z0..=z1 {
            for cx in x0..=x1 {
                for &o in &grid[cz * cells + cx] {
                    let q = positions[o as usize];
                    if (q[0] - c[0]).abs() <= half && (q[2] - c[2]).abs() <= half {
                        list.push(o);
                    }
                }
            }
        }
        // By ascending slot, as the physics backends answer (a replica follows a view
        // in that order).
        list[start..].sort_unstable();
        offsets.push(list.len() as u32);
        let keys = SessionKeys { session_id: p as u64, client_to_server: [1; 32], server_to_client: [2; 32] };
        subscribers.push(Subscriber::new(p as u32, c, ServerSession::new(&keys).sealer));
    }
    Scenario {
        ids: (0..objects as u64).collect(),
        kinds: (0..objects).map(|i| [ShapeKind::Sphere, ShapeKind::Box, ShapeKind::Capsule][i % 3]).collect(),
        positions,
        offsets,
        objects: list,
        subscribers,
    }
}

/// CPU seconds (user + system) this process has used, from `/proc/self/stat` (Linux;
/// `None` elsewhere). Wall time on a shared machine depends on what else runs; CPU
/// time per tick does not, much.
fn process_cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15.
    let rest = &stat[stat.rfind(')')? + 2..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let utime: f64 = fields.get(11)?.parse().ok()?;
    let stime: f64 = fields.get(12)?.parse().ok()?;
    // USER_HZ is 100 on Linux for every architecture's user-space ABI.
    Some((utime + stime) / 100.0)
}

/// Moves half the objects 0.17 units along x (back, one tick in seven), as a tick of the
/// physics would.
fn step(tick: u64, positions: &mut [[f32; 3]]) {
    for (i, p) in positions.iter_mut().enumerate().filter(|(i, _)| i % 2 == 0) {
        p[0] += 0.17 * if (i / 2 + tick as usize).is_multiple_of(7) { -1.0 } else { 1.0 };
    }
}

/// What a client that received all `sent` datagrams numbered up to `next - 1`
/// acknowledges.
fn all_received(sent: u64, next: u64) -> Option<AckField> {
    let bits = (1u64 << sent.saturating_sub(1).min(63)) - 1;
    (sent > 0).then(|| AckField::new(next - 1, bits).expect("valid field"))
}

/// The live path: `InterestManager::build` for every player (gather, replica, sealing),
/// half the objects moving each tick, every client acknowledging all it got before the
/// next tick, as the server hands acknowledgements over from the clients' actions.
fn bench(c: &mut Criterion) {
    let mut group = c.benchmark_group("interest_tick");
    group.sample_size(10);
    let config = InterestConfig::default();
    for (name, objects, players) in
        [("scenario2_5k_players", 55_000, 5_000), ("scenario3_10k_players", 260_000, 10_000)]
    {
        let mut s = scenario(objects, players, 42);
        let manager = InterestManager::new(config);
        let mut positions = s.positions.clone();
        let (ids, kinds, offsets, list) = (&s.ids, &s.kinds, &s.offsets, &s.objects);
        let subscribers = &mut s.subscribers;
        let mut tick = 0u64;
        let mut run = |tick: u64, positions: &mut Vec<[f32; 3]>| -> TickReport {
            step(tick, positions);
            let soa = SoaObjects { ids, kinds, positions };
            let aoi = AoiLists { offsets, objects: list };
            for (sub, p) in subscribers.iter_mut().zip(positions.iter()) {
                sub.centre = *p;
            }
            let report = manager
                .build(TickInfo { tick, dilation_permille: 1000 }, &soa, aoi, subscribers)
                .expect("lists match subscribers");
            subscribers.par_iter_mut().for_each(|sub| {
                if let Some(acks) = all_received(sub.datagrams().len() as u64, sub.sealer.next_sequence()) {
                    sub.acknowledge(acks);
                }
            });
            report
        };
        // Warm up: everything is new to the clients over the first ticks.
        let mut report = TickReport::default();
        for _ in 0..40 {
            tick += 1;
            report = run(tick, &mut positions);
        }
        eprintln!(
            "{name}: {} AOI entries ({:.0} per player); a warm tick: {} records ({} relative), {} datagrams, \
             {:.0} bytes a player, {} deferred, {} starving",
            list.len(),
            list.len() as f64 / players as f64,
            report.records,
            report.relative,
            report.datagrams,
            report.bytes as f64 / players as f64,
            report.deferred,
            report.starving
        );
        if let Some(before) = process_cpu_seconds() {
            let ticks = 20;
            let wall = std::time::Instant::now();
            for _ in 0..ticks {
                tick += 1;
                black_box(run(tick, &mut positions));
            }
            let wall = wall.elapsed().as_secs_f64();
            if let Some(after) = process_cpu_seconds() {
                eprintln!(
                    "{name}: {:.1} ms of CPU per tick ({:.1} ms wall, {} rayon threads, {ticks} ticks)",
                    (after - before) * 1000.0 / ticks as f64,
                    wall * 1000.0 / ticks as f64,
                    rayon::current_num_threads()
                );
            }
        }
        group.bench_function(name, |b| {
            b.iter(|| {
                tick += 1;
                black_box(run(tick, &mut positions))
            })
        });
    }
    group.finish();
}

/// One player's protocol 3 state in the replica bench.
struct Player {
    replica: Replica,
    sealer: Sealer,
    out: DatagramBatch,
}

thread_local! {
    /// Per-thread working memory, as the live interest manager keeps it: hot in cache
    /// from one player to the next.
    static SCRATCH: std::cell::RefCell<(ReplicaScratch, Vec<Candidate>)> = Default::default();
}

/// The per-player replica (`replica.rs`) alone on the same views, moves and
/// acknowledgements as `interest_tick`, candidates gathered here: the CPU a tick of it
/// costs without the manager around it.
fn replica(c: &mut Criterion) {
    let mut group = c.benchmark_group("replica_tick");
    group.sample_size(10);
    let InterestConfig { max_datagrams, replication: config } = InterestConfig::default();
    for (name, objects, players) in
        [("scenario2_5k_players", 55_000, 5_000), ("scenario3_10k_players", 260_000, 10_000)]
    {
        let mut s = scenario(objects, players, 42);
        let mut ps: Vec<Player> = s
            .subscribers
            .drain(..)
            .map(|sub| Player { replica: Replica::default(), sealer: sub.sealer, out: DatagramBatch::new() })
            .collect();
        let mut tick = 0u64;
        let run = |tick: u64, positions: &mut Vec<[f32; 3]>, ps: &mut Vec<Player>| -> usize {
            step(tick, positions);
            let (offsets, list, kinds, positions) = (&s.offsets, &s.objects, &s.kinds, &*positions);
            ps.par_iter_mut()
                .enumerate()
                .map(|(i, p)| {
                    SCRATCH.with_borrow_mut(|(scratch, candidates)| {
                        let centre = positions[i];
                        let own = (i as u64, kinds[i], QuantPos::from_f32(centre));
                        candidates.clear();
                        candidates.extend(list[offsets[i] as usize..offsets[i + 1] as usize].iter().map(|&o| {
                            let q = positions[o as usize];
                            let d = [q[0] - centre[0], q[1] - centre[1], q[2] - centre[2]];
                            Candidate {
                                slot: o,
                                id: u64::from(o),
                                kind: kinds[o as usize],
                                pos: QuantPos::from_f32(q),
                                distance: (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt(),
                            }
                        }));
                        let first = p.sealer.next_sequence();
                        let r = p
                            .replica
                            .build(
                                &config,
                                TickInfo { tick, dilation_permille: 1000 },
                                QuantPos::from_f32(centre),
                                Some(own),
                                candidates,
                                max_datagrams,
                                &mut p.sealer,
                                &mut p.out,
                                scratch,
                            )
                            .expect("sequence numbers last");
                        // The client got them all.
                        let next = p.sealer.next_sequence();
                        if let Some(acks) = all_received(next - first, next) {
                            p.replica.acknowledge(acks);
                        }
                        black_box(r.packed);
                        p.out.total_bytes()
                    })
                })
                .sum()
        };
        let mut positions = s.positions.clone();
        // Warm up: everything new goes out over the first ticks.
        let mut bytes = 0;
        for _ in 0..40 {
            tick += 1;
            bytes = run(tick, &mut positions, &mut ps);
        }
        let before = process_cpu_seconds();
        let wall = std::time::Instant::now();
        let ticks = 20;
        for _ in 0..ticks {
            tick += 1;
            bytes = run(tick, &mut positions, &mut ps);
        }
        if let (Some(before), Some(after)) = (before, process_cpu_seconds()) {
            eprintln!(
                "{name} (replica alone): {:.1} ms of CPU per tick ({:.1} ms wall, {} rayon threads), {:.0} bytes a player a tick",
                (after - before) * 1000.0 / ticks as f64,
                wall.elapsed().as_secs_f64() * 1000.0 / ticks as f64,
                rayon::current_num_threads(),
                bytes as f64 / players as f64
            );
        }
        group.bench_function(name, |b| {
            b.iter(|| {
                tick += 1;
                black_box(run(tick, &mut positions, &mut ps))
            })
        });
    }
    group.finish();
}

criterion_group!(benches, bench, replica);
criterion_main!(benches);
