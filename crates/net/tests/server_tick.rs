//! The three crates together, as the server will use them: clients send sealed Ready
//! packets; the server receives them in a batch, routes each by the session id in its
//! header, opens it, builds one tick of interest-managed updates, and sends them in one
//! batch; every client opens its updates and finds its own object first.

use std::collections::HashMap;
use std::net::{Ipv4Addr, SocketAddr};
use std::time::{Duration, Instant};

use myriad_interest::{AoiLists, InterestConfig, InterestManager, SoaObjects, Subscriber, TickInfo};
use myriad_net::{Endpoint, EndpointConfig, RecvBatch};
use myriad_protocol::{
    Baselines, ClientMessage, ClientSession, Direction, ServerMessage, ServerSession, SessionKeys, ShapeKind,
    peek_header,
};

const CLIENTS: usize = 40;

fn local() -> EndpointConfig {
    EndpointConfig::new(SocketAddr::from((Ipv4Addr::LOCALHOST, 0)))
}

fn keys(i: usize) -> SessionKeys {
    SessionKeys { session_id: 1000 + i as u64, client_to_server: [i as u8; 32], server_to_client: [!(i as u8); 32] }
}

#[test]
fn one_server_tick_end_to_end() {
    // World: 400 objects on a line; client i plays object i.
    let ids: Vec<u64> = (0..400u64).map(|i| (1 << 33) + i).collect();
    let kinds = vec![ShapeKind::Capsule; 400];
    let positions: Vec<[f32; 3]> = (0..400).map(|i| [i as f32 * 0.5, 1.0, 0.0]).collect();

    let mut server_ep = Endpoint::bind(local()).unwrap();
    let mut clients: Vec<(Endpoint, ClientSession)> =
        (0..CLIENTS).map(|i| (Endpoint::bind(local()).unwrap(), ClientSession::new(&keys(i)))).collect();

    // Server side session table, keyed by session id.
    let mut openers = HashMap::new();
    let mut subscribers = Vec::new();
    for (i, &centre) in positions.iter().take(CLIENTS).enumerate() {
        let ServerSession { sealer, opener } = ServerSession::new(&keys(i));
        openers.insert(keys(i).session_id, (i, opener));
        subscribers.push(Subscriber::new(i as u32, centre, sealer));
    }

    // 1. Every client says Ready.
    for (ep, session) in &mut clients {
        let mut d = Vec::new();
        session.seal(&ClientMessage::Ready, &mut d).unwrap();
        assert_eq!(ep.send_batch(&[(server_ep.local_addr(), &d)]).unwrap(), 1);
    }

    // 2. The server drains its socket, routes by session id, opens.
    let mut inbox = RecvBatch::new(16);
    let mut addr_of = vec![None; CLIENTS];
    let deadline = Instant::now() + Duration::from_secs(3);
    while addr_of.iter().any(Option::is_none) && Instant::now() < deadline {
        if server_ep.recv_batch(&mut inbox).unwrap() == 0 {
            std::thread::sleep(Duration::from_millis(1));
            continue;
        }
        for k in 0..inbox.len() {
            let (from, bytes) = inbox.get_mut(k).unwrap();
            let header = peek_header(bytes, Direction::ClientToServer).unwrap();
            let (i, opener) = openers.get_mut(&header.session_id).unwrap();
            let opened = opener.open_with(bytes, ClientMessage::decode_body).unwrap();
            assert_eq!(opened.message, ClientMessage::Ready);
            addr_of[*i] = Some(from);
        }
    }
    assert!(addr_of.iter().all(Option::is_some));

    // 3. One tick: each player sees the 150 objects nearest its index.
    let mut offsets = vec![0u32];
    let mut objects = Vec::new();
    for i in 0..CLIENTS as u32 {
        objects.extend(i..i + 150);
        offsets.push(objects.len() as u32);
    }
    // 64 kbit/s at 30 Hz: 267 bytes a tick, room for about 20 of the 150 objects.
    let manager = InterestManager::new(InterestConfig::with_budget(1, 64.0, 30.0));
    let soa = SoaObjects { ids: &ids, kinds: &kinds, positions: &positions };
    let report = manager
        .build(
            TickInfo { tick: 7, dilation_permille: 1000 },
            &soa,
            AoiLists { offsets: &offsets, objects: &objects },
            &mut subscribers,
        )
        .unwrap();
    assert_eq!(report.datagrams, CLIENTS);
    assert!(report.deferred >= CLIENTS * 100, "150 objects do not fit the budget: {report:?}");
    let packed: Vec<usize> = subscribers.iter().map(|s| s.report().records).collect();
    let outgoing: Vec<(SocketAddr, &[u8])> = subscribers
        .iter()
        .enumerate()
        .flat_map(|(i, s)| {
            let addr = addr_of[i].unwrap();
            s.datagrams().iter().map(move |d| (addr, d))
        })
        .collect();
    let mut sent = 0;
    while sent < outgoing.len() {
        sent += server_ep.send_batch(&outgoing[sent..]).unwrap();
    }

    // 4. Every client gets its update: tick 7, with its own object, every record
    //    absolute (the client holds nothing yet) and resolved.
    for (i, (ep, session)) in clients.iter_mut().enumerate() {
        let mut got = None;
        let deadline = Instant::now() + Duration::from_secs(3);
        while got.is_none() && Instant::now() < deadline {
            if ep.recv_batch(&mut inbox).unwrap() == 0 {
                std::thread::sleep(Duration::from_millis(1));
                continue;
            }
            let (_, bytes) = inbox.get_mut(0).unwrap();
            got = Some(session.open(bytes).unwrap().message);
        }
        match got {
            Some(ServerMessage::StateUpdate(u)) => {
                assert_eq!(u.header.tick, 7);
                assert_eq!(u.records.len(), packed[i]);
                assert!(u.records.len() > 10, "the budget holds more than a few objects");
                let mut resolved = Vec::new();
                assert_eq!(Baselines::default().resolve_update(&u, &mut resolved), 0);
                assert!(resolved.iter().any(|r| r.id == ids[i]), "client {i} sees itself");
            }
            other => panic!("client {i} got {other:?}"),
        }
    }
}
