//! The protocol over real sockets: a client seals actions, the server receives them in
//! a batch and opens them in place; replays and forgeries sent over the wire are
//! rejected; the server's sealed updates reach the client.

use std::net::{Ipv4Addr, SocketAddr};
use std::time::{Duration, Instant};

use myriad_net::{Endpoint, EndpointConfig, RecvBatch};
use myriad_protocol::*;

fn local() -> EndpointConfig {
    EndpointConfig::new(SocketAddr::from((Ipv4Addr::LOCALHOST, 0)))
}

fn receive_at_least(ep: &mut Endpoint, batch: &mut RecvBatch, want: usize) -> Vec<(SocketAddr, Vec<u8>)> {
    let mut got = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(3);
    while got.len() < want && Instant::now() < deadline {
        if ep.recv_batch(batch).expect("recv") == 0 {
            std::thread::sleep(Duration::from_millis(1));
        }
        got.extend(batch.iter().map(|(a, d)| (a, d.to_vec())));
    }
    got
}

#[test]
fn sealed_traffic_both_ways() {
    let keys = SessionKeys { session_id: 42, client_to_server: [5; 32], server_to_client: [6; 32] };
    let mut server_ep = Endpoint::bind(local()).unwrap();
    let mut client_ep = Endpoint::bind(local()).unwrap();
    let mut server = ServerSession::new(&keys);
    let mut client = ClientSession::new(&keys);

    // 100 actions, then a replay of the first and a forgery.
    let mut wire = Vec::new();
    for frame in 0..100u32 {
        let mut d = Vec::new();
        let msg = ClientMessage::Action {
            input: PlayerInput { mask: ActionMask::new((frame % 32) as u8).unwrap(), client_frame: frame },
            acks: None,
        };
        client.seal(&msg, &mut d).unwrap();
        wire.push(d);
    }
    wire.push(wire[0].clone());
    // A fresh sequence number with a damaged body: only the tag can catch it.
    let mut forged = Vec::new();
    client.seal(&ClientMessage::Ready, &mut forged).unwrap();
    let last = forged.len() - 1;
    forged[last] ^= 0x40;
    wire.push(forged);
    let to_server: Vec<(SocketAddr, &[u8])> = wire.iter().map(|d| (server_ep.local_addr(), &d[..])).collect();
    assert_eq!(client_ep.send_batch(&to_server).unwrap(), wire.len());

    let mut batch = RecvBatch::new(64);
    let mut frames = Vec::new();
    let mut rejected = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(3);
    while frames.len() + rejected.len() < wire.len() && Instant::now() < deadline {
        if server_ep.recv_batch(&mut batch).unwrap() == 0 {
            std::thread::sleep(Duration::from_millis(1));
        }
        for i in 0..batch.len() {
            let (from, bytes) = batch.get_mut(i).unwrap();
            assert_eq!(from, client_ep.local_addr());
            match server.open(bytes) {
                Ok(Opened { message: ClientMessage::Action { input: a, .. }, .. }) => frames.push(a.client_frame),
                Ok(other) => panic!("unexpected {other:?}"),
                Err(e) => rejected.push(e.class()),
            }
        }
    }
    assert_eq!(frames, (0..100).collect::<Vec<_>>());
    rejected.sort_by_key(|c| format!("{c:?}"));
    assert_eq!(rejected, vec![ErrorClass::Authentication, ErrorClass::Replayed]);

    // The server answers with a two-datagram update.
    let records: Vec<StateRecord> = (0..400u64)
        .map(|i| StateRecord { id: i, kind: ShapeKind::Sphere, pos: QuantPos::new(i as i32, 0, 0) })
        .collect();
    // Absolute records (the client holds nothing yet): 400 `Near` records of 37 bits
    // (a one-bit id code, the form, kind and class, 3 × 10 bits of offset) need two
    // datagrams.
    let deltas: Vec<DeltaRecord> =
        records.iter().map(|r| DeltaRecord::choose(r.id, r.kind, r.pos, 0, None, None)).collect();
    let mut out = DatagramBatch::new();
    let mut ends = Vec::new();
    assert_eq!(pack_deltas(&UpdateHeader::default(), None, &deltas, 2, &mut out, &mut ends), 400);
    assert_eq!(out.len(), 2);
    server.sealer.seal_batch(&mut out).unwrap();
    let to_client: Vec<(SocketAddr, &[u8])> = out.iter().map(|d| (client_ep.local_addr(), d)).collect();
    assert_eq!(server_ep.send_batch(&to_client).unwrap(), 2);
    let mut got = Vec::new();
    let mut baselines = Baselines::default();
    for (_, mut d) in receive_at_least(&mut client_ep, &mut batch, 2) {
        match client.open(&mut d).unwrap().message {
            ServerMessage::StateUpdate(u) => assert_eq!(baselines.resolve_update(&u, &mut got), 0),
            other => panic!("unexpected {other:?}"),
        }
    }
    got.sort_by_key(|r| r.id);
    assert_eq!(got, records);
}
