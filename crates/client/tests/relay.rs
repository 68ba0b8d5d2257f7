//! The lossy relay against a UDP echo server on loopback: it forwards both ways, drops
//! what its rules name, and its fates are a function of the seed.

use std::net::SocketAddr;
use std::time::Duration;

use myriad_client::relay::{DropFirst, Link, Relay, RelayConfig};
use myriad_protocol::PacketKind;
use tokio::net::UdpSocket;

/// An echo server on 127.0.0.2 for as long as the runtime lives.
async fn echo() -> SocketAddr {
    let socket = UdpSocket::bind("127.0.0.2:0").await.unwrap();
    let addr = socket.local_addr().unwrap();
    tokio::spawn(async move {
        let mut buf = vec![0u8; 2048];
        while let Ok((n, from)) = socket.recv_from(&mut buf).await {
            let _ = socket.send_to(&buf[..n], from).await;
        }
    });
    addr
}

/// A datagram with a valid client-to-server header of `kind`, numbered `i`.
fn datagram(kind: PacketKind, i: u64) -> Vec<u8> {
    let mut d = vec![0u8; myriad_protocol::MIN_DATAGRAM];
    d[0] = myriad_protocol::PROTOCOL_VERSION;
    d[1] = kind as u8;
    d[2..10].copy_from_slice(&7u64.to_le_bytes());
    d[10..18].copy_from_slice(&i.to_le_bytes());
    d
}

async fn relay(link: Link, seed: u64, drop_first: Vec<DropFirst>) -> (Relay, UdpSocket) {
    let config = RelayConfig {
        seed,
        drop_first,
        ..RelayConfig::new("127.0.0.1:0".parse().unwrap(), echo().await, link, Duration::from_secs(30))
    };
    let relay = Relay::start(config).await.unwrap();
    let client = UdpSocket::bind("127.0.0.1:0").await.unwrap();
    client.connect(relay.local_addr()).await.unwrap();
    (relay, client)
}

/// Sends `n` datagrams one at a time, each waiting for its echo (or not); the numbers
/// that came back, in order.
async fn round_trips(client: &UdpSocket, n: u64) -> Vec<u64> {
    let mut back = Vec::new();
    let mut buf = vec![0u8; 2048];
    for i in 0..n {
        client.send(&datagram(PacketKind::Action, i)).await.unwrap();
        let deadline = tokio::time::Instant::now() + Duration::from_millis(40);
        while let Ok(Ok(len)) = tokio::time::timeout_at(deadline, client.recv(&mut buf)).await {
            let got = u64::from_le_bytes(buf[10..18].try_into().unwrap());
            assert_eq!(len, myriad_protocol::MIN_DATAGRAM);
            if got == i {
                back.push(i);
                break;
            }
        }
    }
    back
}

#[tokio::test]
async fn it_forwards_both_ways_and_drops_the_first_of_a_kind() {
    let rule = DropFirst { kind: PacketKind::Ready, count: 2 };
    let (relay, client) = relay(Link::PERFECT, 1, vec![rule]).await;
    for i in 0..3 {
        client.send(&datagram(PacketKind::Ready, i)).await.unwrap();
    }
    let mut buf = vec![0u8; 2048];
    let n = tokio::time::timeout(Duration::from_secs(2), client.recv(&mut buf)).await.unwrap().unwrap();
    assert_eq!(buf[..n], datagram(PacketKind::Ready, 2), "the third Ready came back");
    assert_eq!(round_trips(&client, 5).await, [0, 1, 2, 3, 4], "a perfect link loses nothing");
    let stats = relay.stop().await;
    assert_eq!(stats.upstream.dropped_by_rule, 2);
    assert_eq!(stats.upstream.received, 8);
    assert_eq!(stats.downstream.sent, 6);
    assert_eq!(stats.peers, 1);
}

#[tokio::test]
async fn the_same_seed_and_traffic_meet_the_same_fates() {
    let link = Link { loss: 0.3, ..Link::PERFECT };
    let run = |seed| async move {
        let (relay, client) = relay(link, seed, Vec::new()).await;
        let back = round_trips(&client, 60).await;
        let stats = relay.stop().await;
        assert_eq!(stats.upstream.lost + stats.upstream.sent, 60);
        back
    };
    let a = run(5).await;
    assert_eq!(a, run(5).await);
    assert_ne!(a, run(6).await);
    assert!((15..=45).contains(&a.len()), "about half the round trips survive 30 % loss each way: {}", a.len());
}

#[tokio::test]
async fn duplicates_and_held_back_datagrams_arrive_and_are_counted() {
    let link = Link { duplicate: 1.0, reorder: 0.5, delay: Duration::from_millis(5), ..Link::PERFECT };
    let (relay, client) = relay(link, 3, Vec::new()).await;
    for i in 0..20 {
        client.send(&datagram(PacketKind::Action, i)).await.unwrap();
    }
    // Each datagram twice up, each copy twice down: 80 echoes.
    let mut buf = vec![0u8; 2048];
    let mut got = Vec::new();
    while let Ok(Ok(_)) = tokio::time::timeout(Duration::from_millis(500), client.recv(&mut buf)).await {
        got.push(u64::from_le_bytes(buf[10..18].try_into().unwrap()));
        if got.len() == 80 {
            break;
        }
    }
    assert_eq!(got.len(), 80);
    assert!(got.windows(2).any(|w| w[1] < w[0]), "some arrived out of order");
    let stats = relay.stop().await;
    assert_eq!(stats.upstream.duplicated, 20);
    assert!(stats.upstream.reordered > 0);
}
