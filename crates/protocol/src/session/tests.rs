use super::*;
use crate::ack::AckField;
use crate::error::ErrorClass;

fn keys() -> SessionKeys {
    SessionKeys { session_id: 0x5eed, client_to_server: [0x11; 32], server_to_client: [0x22; 32] }
}

// Regression: an authentic datagram with sequence u64::MAX used to be accepted, after
// which the replay window sat at the top of the range and every later datagram of the
// session was rejected as replayed (the player froze).
#[test]
fn sequence_u64_max_is_rejected_before_cryptography_and_leaves_the_window() {
    let keys = keys();
    let mut server = ServerSession::new(&keys);
    let mut client = ClientSession::new(&keys);
    let mut first = Vec::new();
    client.seal(&ClientMessage::Ready, &mut first).unwrap();
    server.open(&mut first).unwrap();
    let window_before = server.opener.window().clone();

    let forged = forge_sealed(&keys, PacketKind::Ready, u64::MAX);
    // The tag is authentic (the same hand sealing one short of the top opens, below):
    // only the sequence rule rejects it.
    let mut d = forged.clone();
    let err = server.open(&mut d).unwrap_err();
    assert_eq!(err, OpenError::Malformed(DecodeError::ReservedSequence));
    assert_eq!(err.class(), ErrorClass::Malformed);
    assert_eq!(d, forged, "rejected before decryption: the datagram is untouched");
    assert_eq!(server.opener.window(), &window_before);

    // The session goes on: the client's next datagram is still accepted.
    let mut next = Vec::new();
    client.seal(&ClientMessage::KeepAlive { acks: None }, &mut next).unwrap();
    assert_eq!(server.open(&mut next).unwrap().header.sequence, 1);
    // The hand sealing is right: one short of the top opens.
    let mut below = forge_sealed(&keys, PacketKind::Ready, u64::MAX - 1);
    assert_eq!(server.open(&mut below).unwrap().header.sequence, u64::MAX - 1);
}

fn sealed(client: &mut ClientSession, msg: &ClientMessage) -> Vec<u8> {
    let mut d = Vec::new();
    client.seal(msg, &mut d).unwrap();
    d
}

/// Four threads verify through one shared opener at once (every third datagram has a
/// broken tag); then every authentic one commits, in order.
#[test]
fn an_opener_can_verify_on_several_threads() {
    let keys = keys();
    let mut server = ServerSession::new(&keys);
    let mut client = ClientSession::new(&keys);
    // Each keep-alive acknowledges a different sequence, so a commit handing back another
    // datagram's message would show.
    let keep_alive = |i: u64| ClientMessage::KeepAlive { acks: AckField::new(i * 3, i) };
    let mut datagrams: Vec<Vec<u8>> = (0..64).map(|i| sealed(&mut client, &keep_alive(i))).collect();
    for d in datagrams.iter_mut().skip(1).step_by(3) {
        *d.last_mut().unwrap() ^= 1;
    }
    let (opener, start) = (&server.opener, std::sync::Barrier::new(4));
    let results: Vec<_> = std::thread::scope(|s| {
        let threads: Vec<_> = datagrams
            .chunks_mut(16)
            .map(|chunk| {
                let start = &start;
                s.spawn(move || {
                    start.wait();
                    chunk.iter_mut().map(|d| opener.verify(d, ClientMessage::decode_body)).collect::<Vec<_>>()
                })
            })
            .collect();
        threads.into_iter().flat_map(|t| t.join().unwrap()).collect()
    });
    assert_eq!(results.len(), 64);
    for (i, r) in results.into_iter().enumerate() {
        match r {
            Err(e) => assert!(i % 3 == 1 && e == OpenError::Authentication, "datagram {i}: {e:?}"),
            Ok(v) => {
                assert!(i % 3 != 1, "datagram {i}: a broken tag verified");
                let opened = server.opener.commit(v).unwrap();
                assert_eq!((opened.header.sequence, opened.message), (i as u64, keep_alive(i as u64)));
            }
        }
    }
    assert_eq!(server.opener.window().newest(), Some(63));
}

#[test]
fn verify_does_not_move_the_window() {
    let keys = keys();
    let mut server = ServerSession::new(&keys);
    let mut client = ClientSession::new(&keys);
    let msg = ClientMessage::KeepAlive { acks: AckField::new(5, 0b11) };
    let mut d = sealed(&mut client, &msg);
    let verified = server.opener.verify(&mut d, ClientMessage::decode_body).unwrap();
    assert_eq!(verified.sequence(), 0);
    assert_eq!(server.opener.window().newest(), None, "verifying records nothing");
    let opened = server.opener.commit(verified).unwrap();
    assert_eq!((opened.header.sequence, opened.message), (0, msg));
    assert_eq!(server.opener.window().newest(), Some(0));
}

// Two copies of one datagram verified before either commits (on two threads, say)
// must not both be accepted.
#[test]
fn commit_of_a_duplicate_verified_sequence_is_refused() {
    let keys = keys();
    let mut server = ServerSession::new(&keys);
    let mut client = ClientSession::new(&keys);
    let d = sealed(&mut client, &ClientMessage::Ready);
    let (mut a, mut b) = (d.clone(), d);
    let first = server.opener.verify(&mut a, ClientMessage::decode_body).unwrap();
    let second = server.opener.verify(&mut b, ClientMessage::decode_body).unwrap();
    assert_eq!(server.opener.commit(first).unwrap().message, ClientMessage::Ready);
    let window = server.opener.window().clone();
    let err = server.opener.commit(second).unwrap_err();
    assert_eq!(err, OpenError::Replayed(crate::ReplayError::Duplicate(0)));
    assert_eq!(server.opener.window(), &window, "a refused commit changes nothing");
    // Once committed, the window refuses the copy before its tag is looked at.
    let mut c = a.clone();
    c[HEADER_LEN..].fill(0);
    assert_eq!(server.opener.verify(&mut c, ClientMessage::decode_body).unwrap_err().class(), ErrorClass::Replayed);
}

#[test]
fn a_forged_tag_never_commits() {
    let keys = keys();
    let mut server = ServerSession::new(&keys);
    let mut client = ClientSession::new(&keys);
    let mut forged = sealed(&mut client, &ClientMessage::KeepAlive { acks: None });
    let n = forged.len();
    forged[n - 1] ^= 1;
    let err = server.opener.verify(&mut forged, ClientMessage::decode_body).unwrap_err();
    assert_eq!(err, OpenError::Authentication);
    assert_eq!(server.opener.window().newest(), None);
    // Nor can what another opener verified: its tag was checked under another key.
    let other = SessionKeys { session_id: keys.session_id + 1, ..keys.clone() };
    let mut other_client = ClientSession::new(&other);
    let mut d = sealed(&mut other_client, &ClientMessage::KeepAlive { acks: None });
    let verified = ServerSession::new(&other).opener.verify(&mut d, ClientMessage::decode_body).unwrap();
    assert!(matches!(server.opener.commit(verified), Err(OpenError::WrongSession { .. })));
    // A server datagram verified by the client's opener of the same session.
    let mut reply = Vec::new();
    server.seal(&ServerMessage::KeepAlive, &mut reply).unwrap();
    let verified = client.opener.verify(&mut reply, ServerMessage::decode_body).unwrap();
    assert!(matches!(server.opener.commit(verified), Err(OpenError::Malformed(DecodeError::WrongDirection(_)))));
    assert_eq!(server.opener.window().newest(), None);
    // The genuine datagram still opens.
    let mut genuine = sealed(&mut client, &ClientMessage::KeepAlive { acks: None });
    assert_eq!(server.open(&mut genuine).unwrap().header.sequence, 1);
}

#[test]
fn keys_never_reach_debug_output() {
    let keys = keys();
    let mut sealer = Sealer::new(keys.session_id, Direction::ServerToClient, &keys.server_to_client);
    let lease = sealer.lease(10).unwrap();
    let texts = [format!("{sealer:?}"), format!("{lease:?}"), format!("{:?}", lease.into_sealer())];
    for text in texts {
        assert!(!text.contains("34"), "{text}"); // 0x22 in decimal
        assert!(!text.contains("22, 22"), "{text}");
        assert!(!text.to_lowercase().contains("key"), "{text}");
    }
}

#[test]
fn a_lease_at_the_top_stops_one_short_of_u64_max() {
    let keys = keys();
    let mut sealer = Sealer::with_range(
        keys.session_id,
        Direction::ServerToClient,
        SecretKey(keys.server_to_client),
        u64::MAX - 3,
        u64::MAX,
        false,
    );
    assert_eq!(sealer.lease(4).unwrap_err(), SealError::LeaseTooLarge { requested: 4, available: 3 });
    assert_eq!(sealer.next_sequence(), u64::MAX - 3, "a refused lease changes nothing");
    let lease = sealer.lease(3).unwrap();
    assert_eq!((lease.first_sequence(), lease.end_sequence()), (u64::MAX - 3, u64::MAX));
    assert_eq!(sealer.remaining(), 0);
    assert!(sealer.lease(0).unwrap().is_empty());
    assert_eq!(sealer.lease(1).unwrap_err(), SealError::LeaseTooLarge { requested: 1, available: 0 });
    let mut out = Vec::new();
    assert_eq!(sealer.seal_server_message(&ServerMessage::KeepAlive, &mut out), Err(SealError::SequenceExhausted));
    assert!(out.is_empty());

    let mut leased = lease.into_sealer();
    let mut client = ClientSession::new(&keys);
    for want in [u64::MAX - 3, u64::MAX - 2, u64::MAX - 1] {
        out.clear();
        assert_eq!(leased.seal_server_message(&ServerMessage::KeepAlive, &mut out), Ok(want));
        assert_eq!(client.open(&mut out).unwrap().header.sequence, want);
    }
    out.clear();
    assert_eq!(leased.seal_server_message(&ServerMessage::KeepAlive, &mut out), Err(SealError::LeaseExhausted));
    assert!(out.is_empty());
    assert_eq!(leased.next_sequence(), u64::MAX - 1 + 1);
}
