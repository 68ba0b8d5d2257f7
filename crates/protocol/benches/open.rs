//! Opening one tick's action datagrams, one per session, on one thread and on rayon's
//! pool: what the server's receive does with them (`crates/server/src/inbound.rs`:
//! verify in parallel, then commit in order). The batch sizes around the server's
//! threshold show where the pool starts to pay.
//!
//! Run: `cargo bench -p myriad-protocol --bench open` (`RAYON_NUM_THREADS` sets the
//! pool's size).

use std::hint::black_box;

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use myriad_protocol::{AckField, ActionMask, ClientMessage, ClientSession, PlayerInput, ServerSession, SessionKeys};
use rayon::prelude::*;

/// What the server's `inbound::OPEN_CHUNK` is: datagrams per rayon task.
const CHUNK: usize = 16;

/// `n` sessions, each with one sealed action datagram (55 bytes: 21 of body).
fn sessions(n: usize) -> (Vec<ServerSession>, Vec<Vec<u8>>) {
    (0..n as u64)
        .map(|i| {
            let keys = SessionKeys { session_id: i + 1, client_to_server: [i as u8; 32], server_to_client: [2; 32] };
            let mut client = ClientSession::new(&keys);
            let input = PlayerInput { mask: ActionMask::new(ActionMask::FORWARD).unwrap(), client_frame: 1 };
            // A client in play acknowledges what it received: a full field, as most are.
            let acks = AckField::new(1_000 + i, u64::MAX);
            let mut d = Vec::new();
            client.seal(&ClientMessage::Action { input, acks }, &mut d).expect("seal");
            (ServerSession::new(&keys), d)
        })
        .unzip()
}

/// Verifies every datagram, in parallel or not, as the server's receive does before it
/// commits in order; returns how many verified. Verifying leaves the openers' windows
/// as they were, so the same datagrams verify again next time.
fn verify_all(servers: &[ServerSession], sealed: &[Vec<u8>], scratch: &mut [Vec<u8>], parallel: bool) -> usize {
    for (s, d) in scratch.iter_mut().zip(sealed) {
        s.copy_from_slice(d);
    }
    let verify = |(s, d): (&ServerSession, &mut Vec<u8>)| s.opener.verify(d, ClientMessage::decode_body).is_ok();
    if parallel {
        servers.par_iter().zip(scratch.par_iter_mut()).with_min_len(CHUNK).map(verify).filter(|&ok| ok).count()
    } else {
        servers.iter().zip(scratch.iter_mut()).map(verify).filter(|&ok| ok).count()
    }
}

fn bench(c: &mut Criterion) {
    eprintln!("rayon pool: {} threads", rayon::current_num_threads());
    let mut g = c.benchmark_group("verify_actions");
    for n in [16, 64, 128, 256, 512, 1024, 3333] {
        let (servers, sealed) = sessions(n);
        let mut scratch = sealed.clone();
        g.throughput(Throughput::Elements(n as u64));
        for (name, parallel) in [("sequential", false), ("parallel", true)] {
            g.bench_with_input(BenchmarkId::new(name, n), &n, |b, _| {
                b.iter(|| black_box(verify_all(&servers, &sealed, &mut scratch, parallel)))
            });
        }
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
