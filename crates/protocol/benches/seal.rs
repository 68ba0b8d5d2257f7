//! Per-core throughput of the protocol: packing delta state updates, sealing and opening
//! full-size datagrams. Single-threaded, so the figures are per core.
//!
//! The update is what a busy player's tick looks like in protocol version 3: mostly
//! small moves (`Delta`) and still objects (`Same`) against acknowledged baselines, and
//! some objects sent absolute (`Near`), enough records to fill two datagrams.
//!
//! Run: `cargo bench -p myriad-protocol --bench seal`

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use myriad_protocol::{
    ClientSession, DatagramBatch, DeltaRecord, QuantPos, RecordState, ServerSession, SessionKeys, ShapeKind,
    UpdateHeader, pack_deltas,
};

fn keys() -> SessionKeys {
    SessionKeys { session_id: 1, client_to_server: [1; 32], server_to_client: [2; 32] }
}

/// `n` records, ids 7 apart: in every ten, five `Delta`, three `Same` and two `Near`.
fn records(n: usize) -> Vec<DeltaRecord> {
    (0..n as u64)
        .map(|i| {
            let v = i as i32;
            let state = match i % 10 {
                0..5 => {
                    RecordState::Delta { back: 1 + (i % 3) as u8, d: [(v % 41 - 20) as i16, 0, (v % 23 - 11) as i16] }
                }
                5..8 => RecordState::Same { back: 1 + (i % 5) as u8 },
                _ => RecordState::Absolute {
                    kind: ShapeKind::Capsule,
                    pos: QuantPos::new((v * 37) % 6000, 300, -(v * 91) % 6000),
                },
            };
            DeltaRecord { id: 1000 + i * 7, state }
        })
        .collect()
}

/// CPU seconds (user + system) this process has used, from `/proc/self/stat` (Linux;
/// `None` elsewhere). On a shared machine wall time depends on the neighbours; CPU time
/// gives the per-core cost.
fn process_cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    let rest = &stat[stat.rfind(')')? + 2..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let utime: f64 = fields.get(11)?.parse().ok()?;
    let stime: f64 = fields.get(12)?.parse().ok()?;
    // USER_HZ is 100 on Linux.
    Some((utime + stime) / 100.0)
}

/// Runs `f` `n` times and prints its CPU cost per call and per byte.
fn cpu_cost(name: &str, n: u32, bytes_per_call: usize, mut f: impl FnMut()) {
    let Some(before) = process_cpu_seconds() else { return };
    for _ in 0..n {
        f();
    }
    let Some(after) = process_cpu_seconds() else { return };
    let per_call = (after - before) / f64::from(n);
    eprintln!(
        "{name}: {:.2} µs of CPU per call, {:.0} MB/s per core ({n} calls)",
        per_call * 1e6,
        bytes_per_call as f64 / per_call / 1e6
    );
}

fn bench(c: &mut Criterion) {
    let header = UpdateHeader { tick: 100, dilation_permille: 1000, origin: QuantPos::default() };
    // The player's own object (in every datagram, at its place in id order), and as many
    // other records as two datagrams then hold, so both are full.
    let own = DeltaRecord { id: 1703, state: RecordState::Delta { back: 1, d: [3, 0, -5] } };
    let mut batch = DatagramBatch::new();
    let mut ends = Vec::new();
    let all = records(2_000);
    let recs = all[..pack_deltas(&header, Some(&own), &all, 2, &mut batch, &mut ends)].to_vec();
    let datagram_bytes = batch.total_bytes() as u64;
    let n = recs.len();
    let mut server_small = ServerSession::new(&keys());
    eprintln!("{n} records and the own one in {} datagrams of {datagram_bytes} bytes in all", batch.len());

    // A small view's tick (AOI 14: about 40 records, one datagram), where what a
    // datagram costs whatever it holds weighs most.
    let small = records(40);
    // A build's last step on the host: `records` and the own one into at most
    // `datagrams` datagrams, sealed.
    let pack_and_seal = |records: &[DeltaRecord],
                         datagrams: usize,
                         session: &mut ServerSession,
                         batch: &mut DatagramBatch,
                         ends: &mut Vec<usize>| {
        batch.clear();
        pack_deltas(&header, Some(&own), black_box(records), datagrams, batch, ends);
        session.sealer.seal_batch(batch).expect("seal");
        batch.total_bytes()
    };
    let mut g = c.benchmark_group("protocol");
    g.bench_function("pack_and_seal_deltas_40_records", |b| {
        b.iter(|| black_box(pack_and_seal(&small, 1, &mut server_small, &mut batch, &mut ends)))
    });
    g.throughput(Throughput::Bytes(datagram_bytes));
    g.bench_function("pack_deltas_2_datagrams", |b| {
        b.iter(|| {
            batch.clear();
            black_box(pack_deltas(&header, Some(&own), black_box(&recs), 2, &mut batch, &mut ends))
        })
    });
    let mut server = ServerSession::new(&keys());
    g.bench_function("pack_and_seal_deltas_2_datagrams", |b| {
        b.iter(|| black_box(pack_and_seal(&recs, 2, &mut server, &mut batch, &mut ends)))
    });
    // Sealing and opening one full datagram: reseal a fresh copy each time so the replay
    // window accepts it.
    let mut client = ClientSession::new(&keys());
    batch.clear();
    pack_deltas(&header, Some(&own), &recs, 1, &mut batch, &mut ends);
    let one = batch.get(0).expect("one datagram").to_vec();
    eprintln!("a full datagram: {} bytes", one.len());
    g.throughput(Throughput::Bytes(one.len() as u64));
    let mut buf = one.clone();
    g.bench_function("seal_full_datagram", |b| {
        b.iter(|| {
            buf.copy_from_slice(&one);
            black_box(server.sealer.seal_in_place(&mut buf).expect("seal"))
        })
    });
    g.bench_function("seal_and_open_full_datagram", |b| {
        b.iter(|| {
            buf.copy_from_slice(&one);
            server.sealer.seal_in_place(&mut buf).expect("seal");
            black_box(client.opener.open_with(&mut buf, |_, body| Ok(body.len())).expect("open").message)
        })
    });
    // A tick of 50,000 such players on one core, each with its own session and batch:
    // what no single-player loop shows, every player's memory cold by its turn.
    let mut players: Vec<(ServerSession, DatagramBatch)> =
        (0..50_000).map(|_| (ServerSession::new(&keys()), DatagramBatch::new())).collect();
    g.sample_size(10);
    g.bench_function("pack_and_seal_40_records_50000_players", |b| {
        b.iter(|| {
            for (session, batch) in players.iter_mut() {
                pack_and_seal(&small, 1, session, batch, &mut ends);
            }
        })
    });
    g.finish();

    // The same operations timed by CPU time rather than wall time.
    let mut server = ServerSession::new(&keys());
    let mut client = ClientSession::new(&keys());
    cpu_cost("pack_deltas_2_datagrams", 200_000, datagram_bytes as usize, || {
        batch.clear();
        black_box(pack_deltas(&header, Some(&own), black_box(&recs), 2, &mut batch, &mut ends));
    });
    cpu_cost("pack_and_seal_deltas_2_datagrams", 50_000, datagram_bytes as usize, || {
        batch.clear();
        pack_deltas(&header, Some(&own), black_box(&recs), 2, &mut batch, &mut ends);
        server.sealer.seal_batch(&mut batch).expect("seal");
    });
    cpu_cost("seal_full_datagram", 100_000, one.len(), || {
        buf.copy_from_slice(&one);
        black_box(server.sealer.seal_in_place(&mut buf).expect("seal"));
    });
    cpu_cost("seal_and_open_full_datagram", 50_000, one.len(), || {
        buf.copy_from_slice(&one);
        server.sealer.seal_in_place(&mut buf).expect("seal");
        black_box(client.opener.open_with(&mut buf, |_, body| Ok(body.len())).expect("open"));
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
