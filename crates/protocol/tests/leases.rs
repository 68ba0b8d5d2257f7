//! Sequence-number leases: a session's sealer hands ranges of its sequence numbers to
//! other threads (or a device), and no number is ever sealed twice.

use std::ops::Range;

use myriad_protocol::*;
use proptest::prelude::*;

fn keys() -> SessionKeys {
    SessionKeys { session_id: 0xabcd_ef01, client_to_server: [0x31; 32], server_to_client: [0x42; 32] }
}

/// One step on the session's own sealer.
#[derive(Debug, Clone)]
enum Op {
    /// Seal one datagram on the parent.
    Seal,
    /// Lease this many sequence numbers.
    Lease(u64),
}

fn arb_ops() -> impl Strategy<Value = Vec<Op>> {
    // At most 40 × 20 numbers, so everything fits one replay window and every datagram
    // can be opened below in any order.
    prop::collection::vec(prop_oneof![Just(Op::Seal), (0u64..20).prop_map(Op::Lease)], 0..40)
}

fn overlaps(a: &Range<u64>, b: &Range<u64>) -> bool {
    a.start < b.end && b.start < a.end
}

proptest! {
    /// Leases interleaved with the parent's own seals never overlap each other or any
    /// number the parent used, and every datagram sealed under a lease (on its own
    /// thread) opens with the peer's opener exactly once.
    #[test]
    fn leases_never_overlap_and_their_datagrams_open(ops in arb_ops(), reverse in any::<bool>()) {
        let keys = keys();
        let mut server = ServerSession::new(&keys);
        let mut parent_seqs = Vec::new();
        let mut datagrams = Vec::new();
        let mut leases = Vec::new();
        for op in &ops {
            match op {
                Op::Seal => {
                    let mut out = Vec::new();
                    parent_seqs.push(server.seal(&ServerMessage::KeepAlive, &mut out).unwrap());
                    datagrams.push(out);
                }
                Op::Lease(n) => {
                    let lease = server.sealer.lease(*n).unwrap();
                    prop_assert_eq!(lease.len(), *n);
                    prop_assert_eq!(lease.session_id(), keys.session_id);
                    prop_assert_eq!(lease.direction(), Direction::ServerToClient);
                    prop_assert_eq!(lease.end_sequence(), server.sealer.next_sequence());
                    leases.push(lease);
                }
            }
        }
        let ranges: Vec<Range<u64>> = leases.iter().map(|l| l.first_sequence()..l.end_sequence()).collect();
        for (i, a) in ranges.iter().enumerate() {
            for b in &ranges[i + 1..] {
                prop_assert!(!overlaps(a, b), "leases {a:?} and {b:?} overlap");
            }
            for s in &parent_seqs {
                prop_assert!(!a.contains(s), "the parent used {s}, inside lease {a:?}");
            }
        }

        // Seal every lease to exhaustion on its own thread.
        let sealed: Vec<Vec<(u64, Vec<u8>)>> = std::thread::scope(|scope| {
            let handles: Vec<_> = leases
                .into_iter()
                .map(|lease| {
                    scope.spawn(move || {
                        let mut sealer = lease.into_sealer();
                        let mut got = Vec::new();
                        loop {
                            let mut out = Vec::new();
                            match sealer.seal_server_message(&ServerMessage::KeepAlive, &mut out) {
                                Ok(seq) => got.push((seq, out)),
                                Err(e) => {
                                    assert_eq!(e, SealError::LeaseExhausted);
                                    assert!(out.is_empty());
                                    break got;
                                }
                            }
                        }
                    })
                })
                .collect();
            handles.into_iter().map(|h| h.join().unwrap()).collect()
        });
        for (range, got) in ranges.iter().zip(&sealed) {
            let seqs: Vec<u64> = got.iter().map(|(s, _)| *s).collect();
            prop_assert_eq!(seqs, range.clone().collect::<Vec<_>>());
        }

        let mut all: Vec<Vec<u8>> = datagrams;
        all.extend(sealed.into_iter().flatten().map(|(_, d)| d));
        if reverse {
            all.reverse();
        }
        let mut client = ClientSession::new(&keys);
        let mut seen = std::collections::HashSet::new();
        for d in &all {
            let mut d = d.clone();
            let opened = client.open(&mut d).expect("a datagram sealed under a lease opens");
            prop_assert!(seen.insert(opened.header.sequence), "sequence {} twice", opened.header.sequence);
            // The same datagram again is a replay.
            let mut again = all.iter().find(|x| x[10..18] == opened.header.sequence.to_le_bytes()).unwrap().clone();
            prop_assert_eq!(client.open(&mut again).unwrap_err().class(), ErrorClass::Replayed);
        }
    }
}

#[test]
fn a_leased_sealer_refuses_to_go_past_its_lease() {
    let keys = keys();
    let mut parent = Sealer::new(keys.session_id, Direction::ClientToServer, &keys.client_to_server);
    let mut out = Vec::new();
    parent.seal_client_message(&ClientMessage::Ready, &mut out).unwrap();
    let lease = parent.lease(3).unwrap();
    assert_eq!((lease.first_sequence(), lease.end_sequence()), (1, 4));
    assert_eq!(parent.next_sequence(), 4, "the parent moved past the lease");

    let mut leased = lease.into_sealer();
    assert_eq!((leased.next_sequence(), leased.end_sequence(), leased.remaining()), (1, 4, 3));
    let mut server = ServerSession::new(&keys);
    for want in 1..4 {
        out.clear();
        assert_eq!(leased.seal_client_message(&ClientMessage::KeepAlive { acks: None }, &mut out), Ok(want));
        assert_eq!(server.open(&mut out).unwrap().header.sequence, want);
    }
    out.clear();
    assert_eq!(
        leased.seal_client_message(&ClientMessage::KeepAlive { acks: None }, &mut out),
        Err(SealError::LeaseExhausted)
    );
    assert!(out.is_empty(), "nothing appended on error");
    let mut frame = vec![0u8; HEADER_LEN];
    frame[1] = PacketKind::ClientKeepAlive as u8;
    AckField::encode(None, &mut frame);
    frame.extend_from_slice(&[0; TAG_LEN]);
    assert_eq!(leased.seal_in_place(&mut frame), Err(SealError::LeaseExhausted));
    assert_eq!(leased.next_sequence(), 4, "a refused seal uses no number");

    // A leased sealer can lease on, within its own range only.
    let mut leased = parent.lease(5).unwrap().into_sealer();
    assert_eq!(leased.lease(6).unwrap_err(), SealError::LeaseTooLarge { requested: 6, available: 5 });
    let sub = leased.lease(2).unwrap();
    assert_eq!((sub.first_sequence(), sub.end_sequence()), (4, 6));
    assert_eq!((leased.next_sequence(), leased.end_sequence()), (6, 9));

    // The parent goes on after the leases, and its datagrams still open.
    out.clear();
    assert_eq!(parent.seal_client_message(&ClientMessage::KeepAlive { acks: None }, &mut out), Ok(9));
    assert_eq!(server.open(&mut out).unwrap().header.sequence, 9);
}

#[test]
fn a_device_sealing_from_the_lease_fields_matches_the_leased_sealer() {
    // A device gets only the exposed fields (session id, direction, key, range) and
    // builds headers and nonces itself. Stand-in for the device: a fresh sealer with those
    // fields, advanced to the lease's first number. Its bytes must equal the leased
    // sealer's, and open on the peer.
    let keys = keys();
    let mut parent = Sealer::new(keys.session_id, Direction::ServerToClient, &keys.server_to_client);
    let mut out = Vec::new();
    parent.seal_server_message(&ServerMessage::KeepAlive, &mut out).unwrap();
    let lease = parent.lease(2).unwrap();
    assert_eq!(lease.key_bytes(), &keys.server_to_client);
    assert!(!format!("{lease:?}").contains("66"), "no key byte (0x42 = 66) in Debug output");
    let mut device = Sealer::new(lease.session_id(), lease.direction(), lease.key_bytes());
    while device.next_sequence() < lease.first_sequence() {
        device.seal_server_message(&ServerMessage::KeepAlive, &mut Vec::new()).unwrap();
    }
    let mut from_device = Vec::new();
    device.seal_server_message(&ServerMessage::KeepAlive, &mut from_device).unwrap();
    let mut from_lease = Vec::new();
    assert_eq!(lease.into_sealer().seal_server_message(&ServerMessage::KeepAlive, &mut from_lease), Ok(1));
    assert_eq!(from_device, from_lease);
    let mut client = ClientSession::new(&keys);
    assert_eq!(client.open(&mut from_lease).unwrap().header.sequence, 1);
}

#[test]
fn exhaustion_near_u64_max() {
    let keys = keys();
    let mut parent = Sealer::new(keys.session_id, Direction::ServerToClient, &keys.server_to_client);
    // Everything but the last two usable numbers goes to one lease.
    let big = parent.lease(u64::MAX - 2).unwrap();
    assert_eq!((big.first_sequence(), big.end_sequence()), (0, u64::MAX - 2));
    assert_eq!(parent.remaining(), 2);
    assert_eq!(parent.lease(3).unwrap_err(), SealError::LeaseTooLarge { requested: 3, available: 2 });
    assert_eq!(parent.lease(u64::MAX).unwrap_err(), SealError::LeaseTooLarge { requested: u64::MAX, available: 2 });
    let top = parent.lease(2).unwrap();
    assert_eq!((top.first_sequence(), top.end_sequence()), (u64::MAX - 2, u64::MAX));
    let mut out = Vec::new();
    assert_eq!(parent.seal_server_message(&ServerMessage::KeepAlive, &mut out), Err(SealError::SequenceExhausted));

    let mut client = ClientSession::new(&keys);
    let mut top = top.into_sealer();
    for want in [u64::MAX - 2, u64::MAX - 1] {
        out.clear();
        assert_eq!(top.seal_server_message(&ServerMessage::KeepAlive, &mut out), Ok(want));
        assert_eq!(client.open(&mut out).unwrap().header.sequence, want);
    }
    out.clear();
    assert_eq!(top.seal_server_message(&ServerMessage::KeepAlive, &mut out), Err(SealError::LeaseExhausted));
    assert_eq!(top.next_sequence(), u64::MAX, "u64::MAX itself was never sealed");
}

/// The unused tail of the latest lease comes back; any other lease, or more numbers used
/// than leased, is refused and changes nothing.
#[test]
fn only_the_latest_lease_returns_its_unused_tail() {
    let mut sealer = Sealer::new(5, Direction::ServerToClient, &[3; 32]);
    let lease = sealer.lease(3).unwrap();
    assert_eq!((lease.first_sequence(), sealer.next_sequence()), (0, 3));
    sealer.return_unused(lease, 1).unwrap();
    assert_eq!(sealer.next_sequence(), 1);

    // More used than leased.
    let lease = sealer.lease(2).unwrap();
    let again = Sealer::new(5, Direction::ServerToClient, &[3; 32]).lease(0).unwrap();
    assert_eq!(sealer.return_unused(again, 0), Err(SealError::LeaseNotReturnable));
    let first = lease.first_sequence();
    let mut copy = Sealer::new(5, Direction::ServerToClient, &[3; 32]);
    copy.lease(first).unwrap();
    let twin = copy.lease(2).unwrap();
    assert_eq!(sealer.return_unused(twin, 3), Err(SealError::LeaseNotReturnable));
    assert_eq!(sealer.next_sequence(), 3);
    sealer.return_unused(lease, 2).unwrap();
    assert_eq!(sealer.next_sequence(), 3);

    // Not the latest: the sealer sealed since.
    let lease = sealer.lease(2).unwrap();
    let mut out = Vec::new();
    sealer.seal_server_message(&ServerMessage::KeepAlive, &mut out).unwrap();
    assert_eq!(sealer.return_unused(lease, 0), Err(SealError::LeaseNotReturnable));
    assert_eq!(sealer.next_sequence(), 6);

    // Another session's, and the other direction's.
    let mut other = Sealer::new(6, Direction::ServerToClient, &[3; 32]);
    let lease = other.lease(2).unwrap();
    let mut mine = Sealer::new(5, Direction::ServerToClient, &[3; 32]);
    mine.lease(0).unwrap();
    let mut mine_at_2 = Sealer::new(5, Direction::ServerToClient, &[3; 32]);
    mine_at_2.lease(2).unwrap();
    assert_eq!(mine_at_2.return_unused(lease, 0), Err(SealError::LeaseNotReturnable));
    let mut client = Sealer::new(5, Direction::ClientToServer, &[3; 32]);
    let lease = client.lease(2).unwrap();
    assert_eq!(mine_at_2.return_unused(lease, 0), Err(SealError::LeaseNotReturnable));
    assert_eq!(mine_at_2.next_sequence(), 2);
}
