//! Per-core throughput of the protocol: packing state updates, sealing and opening
//! full-size datagrams. Single-threaded, so the figures are per core.
//!
//! Run: `cargo bench -p myriad-protocol --bench seal`

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use myriad_protocol::{
    ClientSession, DatagramBatch, MAX_COMPACT_RECORDS, QuantPos, ServerSession, SessionKeys, ShapeKind, StateRecord,
    UpdateHeader, pack_updates,
};

fn keys() -> SessionKeys {
    SessionKeys { session_id: 1, client_to_server: [1; 32], server_to_client: [2; 32] }
}

fn records(n: usize) -> Vec<StateRecord> {
    (0..n as u64)
        .map(|i| StateRecord {
            id: 1000 + i * 7,
            kind: ShapeKind::Capsule,
            pos: QuantPos::new((i as i32 * 37) % 6000, 300, -(i as i32 * 91) % 6000),
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
    let header = UpdateHeader { tick: 1, dilation_permille: 1000, origin: QuantPos::default() };
    let recs = records(MAX_COMPACT_RECORDS * 2);
    let mut batch = DatagramBatch::new();
    pack_updates(&header, &recs, 2, &mut batch);
    let datagram_bytes = batch.total_bytes() as u64;

    let mut g = c.benchmark_group("protocol");
    g.throughput(Throughput::Bytes(datagram_bytes));
    g.bench_function("pack_226_records", |b| {
        b.iter(|| {
            batch.clear();
            black_box(pack_updates(&header, black_box(&recs), 2, &mut batch))
        })
    });
    let mut server = ServerSession::new(&keys());
    g.bench_function("pack_and_seal_226_records", |b| {
        b.iter(|| {
            batch.clear();
            pack_updates(&header, black_box(&recs), 2, &mut batch);
            server.sealer.seal_batch(&mut batch).expect("seal");
            black_box(batch.total_bytes())
        })
    });
    // Opening: reseal a fresh copy each time so the replay window accepts it.
    let mut client = ClientSession::new(&keys());
    let mut plain = DatagramBatch::new();
    pack_updates(&header, &recs[..MAX_COMPACT_RECORDS], 1, &mut plain);
    let one = plain.get(0).expect("one datagram").to_vec();
    g.throughput(Throughput::Bytes(one.len() as u64));
    let mut buf = one.clone();
    g.bench_function("seal_1196_bytes", |b| {
        b.iter(|| {
            buf.copy_from_slice(&one);
            black_box(server.sealer.seal_in_place(&mut buf).expect("seal"))
        })
    });
    g.bench_function("seal_and_open_1196_bytes", |b| {
        b.iter(|| {
            buf.copy_from_slice(&one);
            server.sealer.seal_in_place(&mut buf).expect("seal");
            black_box(client.opener.open_with(&mut buf, |_, body| Ok(body.len())).expect("open").message)
        })
    });
    g.finish();

    // The same operations timed by CPU time rather than wall time.
    let mut server = ServerSession::new(&keys());
    let mut client = ClientSession::new(&keys());
    cpu_cost("pack_226_records", 200_000, datagram_bytes as usize, || {
        batch.clear();
        black_box(pack_updates(&header, black_box(&recs), 2, &mut batch));
    });
    cpu_cost("pack_and_seal_226_records", 50_000, datagram_bytes as usize, || {
        batch.clear();
        pack_updates(&header, black_box(&recs), 2, &mut batch);
        server.sealer.seal_batch(&mut batch).expect("seal");
    });
    cpu_cost("seal_1196_bytes", 100_000, one.len(), || {
        buf.copy_from_slice(&one);
        black_box(server.sealer.seal_in_place(&mut buf).expect("seal"));
    });
    cpu_cost("seal_and_open_1196_bytes", 50_000, one.len(), || {
        buf.copy_from_slice(&one);
        server.sealer.seal_in_place(&mut buf).expect("seal");
        black_box(client.opener.open_with(&mut buf, |_, body| Ok(body.len())).expect("open"));
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
