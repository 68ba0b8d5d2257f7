//! Property tests: every message round-trips, every damaged sealed packet is rejected
//! without changing the opener, and the replay window matches a set-based model.

use std::collections::HashSet;

use myriad_protocol::*;
use proptest::prelude::*;

fn keys() -> SessionKeys {
    SessionKeys { session_id: 0x1122_3344_5566_7788, client_to_server: [7; 32], server_to_client: [9; 32] }
}

fn arb_kind() -> impl Strategy<Value = ShapeKind> {
    prop_oneof![Just(ShapeKind::Sphere), Just(ShapeKind::Box), Just(ShapeKind::Capsule)]
}

fn arb_pos() -> impl Strategy<Value = QuantPos> {
    prop_oneof![
        (any::<i32>(), any::<i32>(), any::<i32>()).prop_map(|(x, y, z)| QuantPos::new(x, y, z)),
        (-40_000i32..40_000, -40_000i32..40_000, -40_000i32..40_000).prop_map(|(x, y, z)| QuantPos::new(x, y, z)),
    ]
}

fn arb_id() -> impl Strategy<Value = u64> {
    prop_oneof![0u64..1000, any::<u64>(), (1u64 << 30) - 5..(1u64 << 30) + 5]
}

fn arb_record() -> impl Strategy<Value = StateRecord> {
    (arb_id(), arb_kind(), arb_pos()).prop_map(|(id, kind, pos)| StateRecord { id, kind, pos })
}

fn arb_header() -> impl Strategy<Value = UpdateHeader> {
    (any::<u64>(), any::<u16>(), arb_pos()).prop_map(|(tick, dilation_permille, origin)| UpdateHeader {
        tick,
        dilation_permille,
        origin,
    })
}

fn arb_update(max: usize) -> impl Strategy<Value = StateUpdate> {
    (arb_header(), prop::collection::vec(arb_record(), 0..max))
        .prop_map(|(header, records)| StateUpdate { header, records })
}

fn arb_client() -> impl Strategy<Value = ClientMessage> {
    prop_oneof![
        (0u8..32, any::<u32>()).prop_map(|(m, client_frame)| ClientMessage::Action(PlayerInput {
            mask: ActionMask::new(m).expect("mask below 32"),
            client_frame
        })),
        Just(ClientMessage::Ready),
        Just(ClientMessage::KeepAlive),
        Just(ClientMessage::Disconnect),
    ]
}

fn arb_server() -> impl Strategy<Value = ServerMessage> {
    prop_oneof![
        // 46 extended records fill 1136 bytes of the 1166-byte body: always one datagram.
        arb_update(46).prop_map(ServerMessage::StateUpdate),
        Just(ServerMessage::KeepAlive),
        prop::sample::select(DisconnectReason::ALL.to_vec()).prop_map(ServerMessage::Disconnect),
        (any::<u16>(), any::<u16>()).prop_map(|(tick_rate_hz, dilation_permille)| {
            ServerMessage::ServerInfo(ServerInfo { tick_rate_hz, dilation_permille })
        }),
    ]
}

/// Every truncation and every single-bit flip of `sealed` must fail to open and leave
/// the opener unchanged; afterwards the intact datagram still opens.
fn assert_damage_rejected<T: std::fmt::Debug>(
    sealed: &[u8],
    mut open: impl FnMut(&mut [u8]) -> Result<T, OpenError>,
) -> Result<(), TestCaseError> {
    for len in 0..sealed.len() {
        let mut d = sealed[..len].to_vec();
        prop_assert!(open(&mut d).is_err(), "truncation to {} accepted", len);
    }
    for bit in 0..sealed.len() * 8 {
        let mut d = sealed.to_vec();
        d[bit / 8] ^= 1 << (bit % 8);
        prop_assert!(open(&mut d).is_err(), "flip of bit {} accepted", bit);
    }
    let mut d = sealed.to_vec();
    prop_assert!(open(&mut d).is_ok(), "intact packet rejected after damaged ones");
    let mut d = sealed.to_vec();
    prop_assert!(matches!(open(&mut d), Err(OpenError::Replayed(_))));
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn client_messages_round_trip(msgs in prop::collection::vec(arb_client(), 1..20)) {
        let mut client = ClientSession::new(&keys());
        let mut server = ServerSession::new(&keys());
        for msg in msgs {
            let mut body = Vec::new();
            msg.encode_body(&mut body);
            prop_assert_eq!(ClientMessage::decode_body(msg.kind(), &body), Ok(msg));
            let mut d = Vec::new();
            let seq = client.seal(&msg, &mut d).unwrap();
            let opened = server.open(&mut d).unwrap();
            prop_assert_eq!(opened.message, msg);
            prop_assert_eq!(opened.header.sequence, seq);
        }
    }

    #[test]
    fn server_messages_round_trip(msg in arb_server()) {
        let mut body = Vec::new();
        msg.encode_body(&mut body).unwrap();
        prop_assert_eq!(ServerMessage::decode_body(msg.kind(), &body), Ok(msg.clone()));
        let mut server = ServerSession::new(&keys());
        let mut client = ClientSession::new(&keys());
        let mut d = Vec::new();
        server.seal(&msg, &mut d).unwrap();
        prop_assert!(d.len() <= MAX_DATAGRAM);
        prop_assert_eq!(client.open(&mut d).unwrap().message, msg);
    }

    #[test]
    fn damaged_client_packets_are_rejected(msg in arb_client()) {
        let mut client = ClientSession::new(&keys());
        let mut server = ServerSession::new(&keys());
        let mut d = Vec::new();
        client.seal(&msg, &mut d).unwrap();
        assert_damage_rejected(&d, |p| server.open(p))?;
    }

    #[test]
    fn packed_updates_round_trip(header in arb_header(), records in prop::collection::vec(arb_record(), 0..400), max in 1usize..6) {
        let mut batch = DatagramBatch::new();
        let packed = pack_updates(&header, &records, max, &mut batch);
        prop_assert!(batch.len() <= max);
        prop_assert!(packed == records.len() || batch.len() == max);
        let mut server = ServerSession::new(&keys());
        let mut client = ClientSession::new(&keys());
        server.sealer.seal_batch(&mut batch).unwrap();
        let mut got = Vec::new();
        for d in batch.iter() {
            prop_assert!(d.len() <= MAX_DATAGRAM);
            let mut d = d.to_vec();
            match client.open(&mut d).unwrap().message {
                ServerMessage::StateUpdate(u) => {
                    prop_assert_eq!(u.header, header);
                    prop_assert!(!u.records.is_empty());
                    got.extend(u.records);
                }
                other => prop_assert!(false, "unexpected {:?}", other),
            }
        }
        prop_assert_eq!(&got[..], &records[..packed]);
    }

    #[test]
    fn compact_updates_use_the_fewest_datagrams(n in 1usize..1000, base in any::<u64>()) {
        let base = base.min(u64::MAX - 2000);
        let records: Vec<_> = (0..n as u64)
            .map(|i| StateRecord { id: base + i, kind: ShapeKind::Capsule, pos: QuantPos::new(i as i32, -(i as i32), 3) })
            .collect();
        let mut batch = DatagramBatch::new();
        prop_assert_eq!(pack_updates(&UpdateHeader::default(), &records, usize::MAX, &mut batch), n);
        prop_assert_eq!(batch.len(), n.div_ceil(MAX_COMPACT_RECORDS));
    }

    // What a receiver that verifies a whole batch (on several threads) before
    // committing it in order gets, with the window re-checked before a tag or body error
    // is reported, is exactly what opening the datagrams one by one gets.
    #[test]
    fn verifying_a_batch_then_committing_it_equals_opening_in_order(
        picks in prop::collection::vec((0usize..24, any::<bool>()), 1..80),
        batch in 1usize..40,
    ) {
        let k = keys();
        let mut client = ClientSession::new(&k);
        let mut pool = Vec::new();
        for i in 0..24u32 {
            if i == 12 {
                // Skip past the window, so older ones become too old.
                client.sealer.lease(REPLAY_WINDOW + 100).unwrap();
            }
            let msg = ClientMessage::Action(PlayerInput { mask: ActionMask::new(1).unwrap(), client_frame: i });
            let mut d = Vec::new();
            client.seal(&msg, &mut d).unwrap();
            pool.push(d);
        }
        let inputs: Vec<Vec<u8>> = picks
            .iter()
            .map(|&(i, forged)| {
                let mut d = pool[i].clone();
                if forged {
                    let n = d.len();
                    d[n - 1] ^= 1;
                }
                d
            })
            .collect();

        let mut one_by_one = ServerSession::new(&k);
        let expected: Vec<_> = inputs.iter().map(|d| one_by_one.open(&mut d.clone())).collect();

        let mut batched = ServerSession::new(&k);
        let mut got = Vec::new();
        for chunk in inputs.chunks(batch) {
            let mut copies = chunk.to_vec();
            let verified: Vec<_> =
                copies.iter_mut().map(|d| batched.opener.verify(d, ClientMessage::decode_body)).collect();
            for (d, v) in chunk.iter().zip(verified) {
                let sequence = peek_header(d, Direction::ClientToServer).unwrap().sequence;
                got.push(match v {
                    Ok(v) => batched.opener.commit(v),
                    Err(e) => Err(batched.opener.window().check(sequence).map_or_else(OpenError::Replayed, |()| e)),
                });
            }
        }
        prop_assert_eq!(got, expected);
        prop_assert_eq!(batched.opener.window(), one_by_one.opener.window());
    }

    #[test]
    fn replay_window_matches_model(seqs in prop::collection::vec(prop_oneof![0u64..3000, any::<u64>()], 1..300)) {
        let mut w = ReplayWindow::new();
        let mut seen = HashSet::new();
        let mut newest: Option<u64> = None;
        for s in seqs {
            let expected = if seen.contains(&s) {
                Err(ReplayError::Duplicate(s))
            } else if newest.is_some_and(|n| s < n && n - s >= REPLAY_WINDOW) {
                Err(ReplayError::TooOld(s))
            } else {
                Ok(())
            };
            // A duplicate that is also too old may be reported as too old.
            let got = w.check(s);
            match (expected, got) {
                (Err(ReplayError::Duplicate(_)), Err(ReplayError::TooOld(_))) => {
                    prop_assert!(newest.is_some_and(|n| n - s >= REPLAY_WINDOW));
                }
                (e, g) => prop_assert_eq!(e, g),
            }
            if got.is_ok() {
                prop_assert_eq!(w.commit(s), Ok(()));
                seen.insert(s);
                newest = Some(newest.map_or(s, |n| n.max(s)));
            }
            prop_assert_eq!(w.newest(), newest);
        }
    }
}

proptest! {
    // Bit flips of a ~1 kB update mean ~9,000 openings per case: fewer cases.
    #![proptest_config(ProptestConfig::with_cases(6))]

    #[test]
    fn damaged_server_packets_are_rejected(msg in arb_server()) {
        let mut server = ServerSession::new(&keys());
        let mut client = ClientSession::new(&keys());
        let mut d = Vec::new();
        server.seal(&msg, &mut d).unwrap();
        assert_damage_rejected(&d, |p| client.open(p))?;
    }
}

#[test]
fn arbitrary_bytes_never_panic_and_never_open() {
    // A deterministic xorshift stream of garbage, with valid-looking headers mixed in.
    let mut server = ServerSession::new(&keys());
    let mut x = 0x9e37_79b9_7f4a_7c15u64;
    for i in 0..20_000 {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        let len = (x % 1300) as usize;
        let mut d: Vec<u8> = (0..len).map(|j| (x >> (j % 57)) as u8).collect();
        if i % 2 == 0 && len >= HEADER_LEN {
            d[0] = PROTOCOL_VERSION;
            d[1] = PacketKind::Action as u8;
            d[2..10].copy_from_slice(&keys().session_id.to_le_bytes());
        }
        assert!(server.open(&mut d).is_err());
    }
    assert_eq!(server.opener.window().newest(), None);
}

#[test]
fn error_classes_are_distinct() {
    let mut client = ClientSession::new(&keys());
    let mut server = ServerSession::new(&keys());
    let mut d = Vec::new();
    client.seal(&ClientMessage::Ready, &mut d).unwrap();
    let mut forged = d.clone();
    *forged.last_mut().unwrap() ^= 1;
    assert_eq!(server.open(&mut forged).unwrap_err().class(), ErrorClass::Authentication);
    let mut short = d[..10].to_vec();
    assert_eq!(server.open(&mut short).unwrap_err().class(), ErrorClass::Malformed);
    let mut other = d.clone();
    other[2] ^= 1;
    assert!(matches!(server.open(&mut other), Err(OpenError::WrongSession { .. })));
    let mut ok = d.clone();
    server.open(&mut ok).unwrap();
    let mut again = d.clone();
    assert_eq!(server.open(&mut again).unwrap_err().class(), ErrorClass::Replayed);
    // A packet sealed by the server must not open as a client packet (reflection).
    let mut reflected = Vec::new();
    server.seal(&ServerMessage::KeepAlive, &mut reflected).unwrap();
    assert!(matches!(server.open(&mut reflected), Err(OpenError::Malformed(DecodeError::WrongDirection(_)))));
}

#[test]
fn authentic_but_undecodable_body_changes_nothing() {
    // Seal a frame whose body is an Action with a bad mask: the tag verifies, the body
    // does not decode, and the sequence number stays free.
    let k = keys();
    let mut sealer = Sealer::new(k.session_id, Direction::ClientToServer, &k.client_to_server);
    let mut server = ServerSession::new(&k);
    let mut d = vec![0u8; HEADER_LEN];
    d[1] = PacketKind::Action as u8;
    d.extend_from_slice(&[0x20, 0, 0, 0, 0]);
    d.extend_from_slice(&[0; TAG_LEN]);
    sealer.seal_in_place(&mut d).unwrap();
    assert_eq!(server.open(&mut d), Err(OpenError::Malformed(DecodeError::BadActionMask(0x20))));
    assert_eq!(server.opener.window().newest(), None);
}

#[test]
fn sealer_rejects_wrong_kind_and_length() {
    let k = keys();
    let mut sealer = Sealer::new(k.session_id, Direction::ServerToClient, &k.server_to_client);
    let mut d = Vec::new();
    encode_client(&ClientMessage::Ready, &mut d);
    assert_eq!(sealer.seal_in_place(&mut d), Err(SealError::BadKind(PacketKind::Ready as u8)));
    assert_eq!(sealer.seal_in_place(&mut [0u8; 10]), Err(SealError::BadLength(10)));
    let big = ServerMessage::StateUpdate(StateUpdate {
        header: UpdateHeader::default(),
        records: vec![StateRecord { id: 0, kind: ShapeKind::Box, pos: QuantPos::default() }; 200],
    });
    let mut server = ServerSession::new(&k);
    let mut out = Vec::new();
    assert!(matches!(server.seal(&big, &mut out), Err(SealError::Encode(_))));
    assert!(out.is_empty());
    assert_eq!(sealer.next_sequence(), 0);
}
