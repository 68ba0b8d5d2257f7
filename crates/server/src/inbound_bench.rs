//! A timing of the receive stage alone, for picking `PARALLEL_OPEN_MIN` on a given
//! machine: `N` players (default 3,333, scenario 3's actions a tick) each send one action
//! a tick through the in-memory transport (with acknowledgements, as protocol 3's
//! clients send them), gated inline, and the median receive is printed. Ignored by
//! default; it asserts nothing about time. Run:
//!
//! `N=3333 RAYON_NUM_THREADS=16 cargo test --release -p myriad-server --lib -- --ignored receive_timing --nocapture`
//! (`OBJECTS=1300000` adds scenario 4's objects to the world.)
//!
//! (`RAYON_NUM_THREADS=1` runs the parallel path on one worker: the cost of going
//! through the pool.)

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use myriad_protocol::{AckField, ActionMask, ClientMessage, ClientSession, PlayerInput, ServerInfo};
use myriad_store::{MapId, UserId};

use super::{PARALLEL_OPEN_MIN, ReceiveBuffers, receive};
use crate::gate::{Gate, ReceiveLimits};
use crate::session::{JoinContext, Sessions};
use crate::transport::MemoryTransport;

#[test]
#[ignore = "a timing, run by hand (module docs)"]
fn receive_timing() {
    let n: usize = std::env::var("N").ok().and_then(|v| v.parse().ok()).unwrap_or(3333);
    // Objects besides the players: the map from ids to slots that each action looks up
    // is as large as the world (`OBJECTS=1300000` for scenario 4's).
    let objects: u32 = std::env::var("OBJECTS").ok().and_then(|v| v.parse().ok()).unwrap_or(10);
    let mut world = myriad_core::ScenarioSpec::custom(11).counts(objects, 0, 0).map_size(1024.0, 33).build().unwrap();
    let mut sessions = Sessions::new(n, MapId(1));
    let ctx = JoinContext { tick: 0, dilation_permille: 1000 };
    let mut clients: Vec<ClientSession> = (0..n)
        .map(|u| {
            let (joined, _) = sessions.join(&mut world, UserId(u as i64 + 1), format!("u{u}"), None, ctx).unwrap();
            ClientSession::new(&joined.keys)
        })
        .collect();
    let net = MemoryTransport::new("127.0.0.1:7777".parse().unwrap());
    let mut transport = net.clone();
    let mut gate = Gate::new(ReceiveLimits { per_session: 8, other_address: 2, time: Duration::from_secs(10) });
    let mut buffers = ReceiveBuffers::default();
    let info = ServerInfo { tick_rate_hz: 30, dilation_permille: 1000 };
    let mut times = Vec::new();
    let mut phases: [Vec<f64>; 3] = Default::default();
    for frame in 1..=60u32 {
        for (i, c) in clients.iter_mut().enumerate() {
            let input = PlayerInput { mask: ActionMask::new(ActionMask::FORWARD).unwrap(), client_frame: frame };
            let mut d = Vec::new();
            // Acknowledgements as a protocol 3 client sends them (the receive merges them
            // into the player's view).
            let acks = AckField::new(u64::from(frame) + 64, u64::MAX);
            c.seal(&ClientMessage::Action { input, acks }, &mut d).unwrap();
            net.push(SocketAddr::from(([10, 0, (i >> 8) as u8, i as u8], 5000)), d);
        }
        world.tick += 1;
        let t = Instant::now();
        let report =
            receive(&mut transport, &mut sessions, &mut world, info, Some(&mut gate), &mut buffers, Instant::now());
        times.push(t.elapsed().as_secs_f64() * 1e3);
        for (all, took) in phases.iter_mut().zip(report.phases) {
            all.push(took.as_secs_f64() * 1e3);
        }
        assert_eq!(report.actions, n as u64);
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let [admit, own, shared] = phases.each_mut().map(median);
    eprintln!(
        "phases (medians, ms): admit {admit:.3}, open and apply each player's part {own:.3}, the shared part {shared:.3}"
    );
    times.sort_by(f64::total_cmp);
    eprintln!(
        "receive of {n} actions (parallel from {PARALLEL_OPEN_MIN}, {} threads): median {:.3} ms, fastest {:.3} ms",
        rayon::current_num_threads(),
        times[times.len() / 2],
        times[0]
    );
}
