//! Property tests: every message round-trips, every damaged sealed packet is rejected
//! without changing the opener, the delta packer fills datagrams and keeps the player's
//! own object in each, a client resolves delta records only against their true
//! baselines, and the replay window matches a set-based model.

use std::collections::{HashMap, HashSet};

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

fn arb_state() -> impl Strategy<Value = RecordState> {
    prop_oneof![
        (1u8..=MAX_BACK as u8, prop::array::uniform3(-512i16..512))
            .prop_map(|(back, d)| RecordState::Delta { back, d }),
        (1u8..=62, 1u8..=62, prop::array::uniform3(-512i16..512)).prop_filter_map(
            "back + prior <= 63",
            |(back, prior, d)| {
                (u16::from(back) + u16::from(prior) <= 63).then_some(RecordState::Predicted { back, prior, d })
            }
        ),
        (1u8..=MAX_BACK as u8).prop_map(|back| RecordState::Same { back }),
        (arb_kind(), arb_pos()).prop_map(|(kind, pos)| RecordState::Absolute { kind, pos }),
    ]
}

/// Records with strictly increasing ids, as every update carries them.
fn arb_records(max: usize) -> impl Strategy<Value = Vec<DeltaRecord>> {
    prop::collection::vec((arb_id(), arb_state()), 0..max).prop_map(|mut v| {
        v.sort_unstable_by_key(|r| r.0);
        v.dedup_by_key(|r| r.0);
        v.into_iter().map(|(id, state)| DeltaRecord { id, state }).collect()
    })
}

/// How an object moves in a tick: mostly stays or steps a little (so that records are
/// relative), now and then jumps or teleports (so that they are not).
fn arb_move() -> impl Strategy<Value = u8> {
    prop_oneof![3 => Just(0u8), 3 => Just(1u8), 1 => Just(2u8), 1 => Just(3u8)]
}

fn arb_header() -> impl Strategy<Value = UpdateHeader> {
    (any::<u64>(), any::<u16>(), arb_pos()).prop_map(|(tick, dilation_permille, origin)| UpdateHeader {
        tick,
        dilation_permille,
        origin,
    })
}

fn arb_update(max: usize) -> impl Strategy<Value = DeltaUpdate> {
    (arb_header(), arb_records(max)).prop_map(|(header, records)| DeltaUpdate { header, records })
}

/// Acknowledgements a client can send: none, or any valid field.
fn arb_acks() -> impl Strategy<Value = Option<AckField>> {
    prop_oneof![
        Just(None),
        (prop_oneof![0u64..200, any::<u64>()], any::<u64>()).prop_map(|(newest, bits)| {
            let newest = newest.min(u64::MAX - 1);
            // Bits may only name sequence numbers 0 and above.
            let valid = if newest >= 64 { u64::MAX } else { (1u64 << newest) - 1 };
            AckField::new(newest, bits & valid)
        }),
    ]
}

fn arb_client() -> impl Strategy<Value = ClientMessage> {
    prop_oneof![
        (0u8..32, any::<u32>(), arb_acks()).prop_map(|(m, client_frame, acks)| ClientMessage::Action {
            input: PlayerInput { mask: ActionMask::new(m).expect("mask below 32"), client_frame },
            acks,
        }),
        Just(ClientMessage::Ready),
        arb_acks().prop_map(|acks| ClientMessage::KeepAlive { acks }),
        Just(ClientMessage::Disconnect),
    ]
}

fn arb_server() -> impl Strategy<Value = ServerMessage> {
    prop_oneof![
        // 49 of the largest records (23 bytes) fill 1127 bytes of the 1142 after the
        // update header: always one datagram.
        arb_update(50).prop_map(ServerMessage::StateUpdate),
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

    // The packer on arbitrary records (and maybe the player's own): every datagram fits,
    // seals, opens and decodes; each holds the own record exactly once, at its place in id
    // order; together they give back exactly the packed prefix, split where `ends` says.
    #[test]
    fn packed_updates_round_trip(
        header in arb_header(),
        records in arb_records(400),
        own in prop::option::of((arb_id(), arb_state())),
        max in 1usize..6,
    ) {
        let own = own.map(|(id, state)| DeltaRecord { id, state });
        // The own object is not among the others.
        let records: Vec<_> = records.into_iter().filter(|r| own.is_none_or(|o| o.id != r.id)).collect();
        let mut batch = DatagramBatch::new();
        let mut ends = Vec::new();
        let packed = pack_deltas(&header, own.as_ref(), &records, max, &mut batch, &mut ends);
        prop_assert!(batch.len() <= max);
        prop_assert!(packed == records.len() || batch.len() == max);
        prop_assert_eq!(ends.len(), batch.len());
        prop_assert_eq!(ends.last().copied().unwrap_or(0), packed);
        prop_assert_eq!(batch.is_empty(), records.is_empty() && own.is_none());
        let mut server = ServerSession::new(&keys());
        let mut client = ClientSession::new(&keys());
        server.sealer.seal_batch(&mut batch).unwrap();
        let mut got = Vec::new();
        for (i, d) in batch.iter().enumerate() {
            prop_assert!(d.len() <= MAX_DATAGRAM);
            let mut d = d.to_vec();
            let ServerMessage::StateUpdate(u) = client.open(&mut d).unwrap().message else {
                return Err(TestCaseError::fail("not a state update"));
            };
            prop_assert_eq!(u.header, header);
            prop_assert!(u.records.windows(2).all(|w| w[0].id < w[1].id), "ids increase");
            if let Some(own) = own {
                prop_assert_eq!(u.records.iter().filter(|r| **r == own).count(), 1);
            }
            let others: Vec<_> = u.records.into_iter().filter(|r| own.is_none_or(|o| o.id != r.id)).collect();
            let start = if i == 0 { 0 } else { ends[i - 1] };
            prop_assert!(!others.is_empty() || (own.is_some() && records.is_empty()), "an empty datagram");
            prop_assert_eq!(&others[..], &records[start..ends[i]]);
            got.extend(others);
        }
        prop_assert_eq!(&got[..], &records[..packed]);
    }

    // Records of consecutive ids cost a one-bit id code each after the first (order 0),
    // so the first datagram holds (9,124 - first) / 5 `Same` records with the usual back
    // (version 2: 571) or / 15 small deltas (version 2: 228); and the packer fills every
    // datagram before starting the next: none but the last could have taken the record
    // that follows it.
    #[test]
    fn small_records_use_the_fewest_datagrams(n in 1usize..4000, base in 0u64..128, same in any::<bool>()) {
        let state = if same { RecordState::Same { back: 1 } } else { RecordState::Delta { back: 1, d: [1, -1, 0] } };
        let records: Vec<_> = (0..n as u64).map(|i| DeltaRecord { id: base + i, state }).collect();
        let header = UpdateHeader::default();
        let mut batch = DatagramBatch::new();
        let mut ends = Vec::new();
        prop_assert_eq!(pack_deltas(&header, None, &records, usize::MAX, &mut batch, &mut ends), n);
        let payload = if same { 4 } else { 14 };
        // The first id whole: an order-0 code of `base`.
        let first = 2 * (64 - (base + 1).leading_zeros() as usize - 1) + 1 + payload;
        let room = (MAX_BODY - DELTA_HEADER_LEN) * 8 - 12;
        let expected = n.min(1 + (room - first) / (1 + payload));
        prop_assert_eq!(ends[0], expected);
        for (d, &end) in batch.iter().zip(&ends) {
            let body_len = d.len() - HEADER_LEN - TAG_LEN;
            if records.get(end).is_some() {
                prop_assert!((body_len - DELTA_HEADER_LEN) * 8 + 1 + payload > room);
            }
        }
    }

    // An update is refused exactly when its body would not fit a datagram, appending
    // nothing; otherwise its body is as long as its records say.
    #[test]
    fn a_too_large_update_is_refused(header in arb_header(), records in arb_records(300)) {
        let update = DeltaUpdate { header, records };
        let len = update.body_len().expect("every generated record can be carried");
        let msg = ServerMessage::StateUpdate(update);
        let mut out = vec![0xaa];
        let result = encode_server(&msg, &mut out);
        if len > MAX_BODY {
            prop_assert_eq!(result, Err(EncodeError::TooLarge { len, max: MAX_BODY }));
            prop_assert_eq!(out, vec![0xaa]);
            let mut server = ServerSession::new(&keys());
            let sealed = server.seal(&msg, &mut Vec::new());
            prop_assert_eq!(sealed, Err(SealError::Encode(EncodeError::TooLarge { len, max: MAX_BODY })));
            prop_assert_eq!(server.sealer.next_sequence(), 0, "a refused update uses no sequence number");
        } else {
            prop_assert_eq!(result, Ok(()));
            prop_assert_eq!(out.len(), 1 + HEADER_LEN + len + TAG_LEN);
            let body = &out[1 + HEADER_LEN..out.len() - TAG_LEN];
            prop_assert_eq!(ServerMessage::decode_body(PacketKind::StateUpdate, body), Ok(msg));
        }
    }

    // A server that sends each object relative to the newest state the client
    // acknowledged, over a link that loses, delays and reorders datagrams both ways: the
    // client never applies a record to the wrong state (every state it resolves is the
    // object's true state at that tick), and without loss it resolves every record.
    #[test]
    fn deltas_over_a_lossy_link_never_resolve_wrong(
        moves in prop::collection::vec(prop::collection::vec((arb_move(), any::<[i8; 3]>()), 6), 1..90),
        link in prop::collection::vec((0u8..10, 0u64..4), 90),
        lossless in any::<bool>(),
        optimistic in any::<bool>(),
    ) {
        let (_, skipped) = resolution_is_sound(&moves, &link, lossless, optimistic)?;
        if lossless && !optimistic {
            prop_assert_eq!(skipped, 0, "nothing lost, yet records were skipped");
        }
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
            let input = PlayerInput { mask: ActionMask::new(1).unwrap(), client_frame: i };
            let msg = ClientMessage::Action { input, acks: AckField::new(u64::from(i), 0) };
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

/// A sent datagram as the server remembers it: sequence number, tick, and the
/// `(id, position)` of each record it carried.
type Flight = (u64, u64, Vec<(u64, QuantPos)>);

/// The simulation behind `deltas_over_a_lossy_link_never_resolve_wrong`: six objects
/// (the player's own among them) move for `moves.len()` ticks; each tick the server sends
/// the own object and the objects due, each chosen against the newest state the client
/// acknowledged (or, if `optimistic`, against the newest state sent, which the client
/// may lack: a server that breaks the rule, to make the client skip); `link` decides
/// which datagrams are lost (unless `lossless`) and how late the others arrive, in both
/// directions. Returns how many records resolved against a baseline and how many were
/// skipped.
fn resolution_is_sound(
    moves: &[Vec<(u8, [i8; 3])>],
    link: &[(u8, u64)],
    lossless: bool,
    optimistic: bool,
) -> Result<(usize, usize), TestCaseError> {
    const IDS: [u64; 6] = [3, 4, 200, 1000, 1 << 33, u64::MAX - 1];
    const OWN: usize = 1;
    let kinds =
        [ShapeKind::Sphere, ShapeKind::Capsule, ShapeKind::Box, ShapeKind::Sphere, ShapeKind::Box, ShapeKind::Capsule];
    let origin = QuantPos::new(6400, 0, -6400);
    let mut pos = [origin; 6];
    let mut server = ServerSession::new(&keys());
    let mut client = ClientSession::new(&keys());
    // Server side: the newest acknowledged and the newest sent state of each object, and
    // what each sent datagram carried.
    // The newest state acknowledged (or sent) of each object, and the one before it.
    let mut acked: HashMap<u64, (Baseline, Option<Baseline>)> = HashMap::new();
    let mut sent: HashMap<u64, (Baseline, Option<Baseline>)> = HashMap::new();
    let mut flights: Vec<Flight> = Vec::new();
    // Every object's true state at every tick.
    let mut truth: HashMap<(u64, u64), StateRecord> = HashMap::new();
    // Datagrams on the way, with the step they arrive at.
    let mut to_client: Vec<(u64, Vec<u8>)> = Vec::new();
    let mut to_server: Vec<(u64, Vec<u8>)> = Vec::new();
    let mut baselines = Baselines::default();
    let mut tracker = AckTracker::default();
    let (mut batch, mut ends, mut states) = (DatagramBatch::new(), Vec::new(), Vec::new());
    let (mut relative_resolved, mut skipped) = (0, 0);
    // Three codes in ten are lost.
    let lost = |code: u8| !lossless && code < 3;
    for (step, tick_moves) in moves.iter().enumerate() {
        let (step, tick) = (step as u64, 1000 + step as u64);
        // The server takes the acknowledgements that arrived.
        let (now, later): (Vec<_>, Vec<_>) = to_server.drain(..).partition(|(at, _)| *at <= step);
        to_server = later;
        for (_, mut d) in now {
            let acks = server.open(&mut d).map_err(|e| TestCaseError::fail(e.to_string()))?.message.acks();
            for (sequence, sent_tick, carried) in &flights {
                if acks.is_some_and(|a| a.contains(*sequence)) {
                    for &(id, pos) in carried {
                        if acked.get(&id).is_none_or(|b| b.0.tick < *sent_tick) {
                            let before = acked.get(&id).map(|b| b.0);
                            acked.insert(id, (Baseline { tick: *sent_tick, pos }, before));
                        }
                    }
                }
            }
        }
        // The world moves: stays, steps a little, jumps, or teleports far away.
        for (i, &(how, d)) in tick_moves.iter().enumerate() {
            let [dx, dy, dz] = d.map(i32::from);
            let p = pos[i];
            pos[i] = match how {
                0 => p,
                1 => QuantPos::new(p.x + dx, p.y + dy, p.z + dz),
                2 => QuantPos::new(p.x + dx * 300, p.y + dy * 300, p.z + dz * 300),
                _ => QuantPos::new(dx << 20, dy << 20, dz << 20),
            };
            truth.insert((tick, IDS[i]), StateRecord { id: IDS[i], kind: kinds[i], pos: pos[i] });
        }
        // The own object and the others due this tick (some every tick, some every
        // second or third), each against its newest acknowledged (or sent) state.
        let base = if optimistic { &sent } else { &acked };
        let record = |i: usize| {
            let (newest, before) = base.get(&IDS[i]).copied().unzip();
            DeltaRecord::choose(IDS[i], kinds[i], pos[i], tick, newest, before.flatten())
        };
        let own = record(OWN);
        let others: Vec<_> =
            (0..6).filter(|&i| i != OWN && (step as usize + i).is_multiple_of(1 + i % 3)).map(record).collect();
        let header = UpdateHeader { tick, dilation_permille: 1000, origin };
        batch.clear();
        prop_assert_eq!(pack_deltas(&header, Some(&own), &others, 1, &mut batch, &mut ends), others.len());
        let sequence = server.sealer.next_sequence();
        server.sealer.seal_batch(&mut batch).unwrap();
        let carried: Vec<_> = std::iter::once(&own).chain(&others).map(|r| (r.id, truth[&(tick, r.id)].pos)).collect();
        for &(id, pos) in &carried {
            let before = sent.get(&id).map(|b| b.0);
            sent.insert(id, (Baseline { tick, pos }, before));
        }
        flights.push((sequence, tick, carried));
        let (code, delay) = link[step as usize % link.len()];
        if !lost(code) {
            to_client.push((step + delay, batch.get(0).unwrap().to_vec()));
        }
        // The client resolves what arrived and acknowledges what resolved whole.
        let (now, later): (Vec<_>, Vec<_>) = to_client.drain(..).partition(|(at, _)| *at <= step);
        to_client = later;
        for (_, mut d) in now {
            let opened = client.open(&mut d).map_err(|e| TestCaseError::fail(e.to_string()))?;
            let ServerMessage::StateUpdate(u) = opened.message else {
                return Err(TestCaseError::fail("not an update"));
            };
            states.clear();
            let failed = baselines.resolve_update(&u, &mut states);
            prop_assert_eq!(states.len() + failed, u.records.len());
            for s in &states {
                prop_assert_eq!(Some(s), truth.get(&(u.header.tick, s.id)), "tick {}", u.header.tick);
            }
            relative_resolved += u.records.iter().filter(|r| !matches!(r.state, RecordState::Absolute { .. })).count();
            relative_resolved -= failed;
            skipped += failed;
            if failed == 0 {
                tracker.record(opened.header.sequence);
            }
        }
        // The client's action of this frame carries its acknowledgement.
        let input = PlayerInput { mask: ActionMask::default(), client_frame: step as u32 };
        let mut d = Vec::new();
        client.seal(&ClientMessage::Action { input, acks: tracker.field() }, &mut d).unwrap();
        let (code, delay) = link[(step as usize * 7 + 3) % link.len()];
        if !lost(code) {
            to_server.push((step + 1 + delay, d));
        }
    }
    Ok((relative_resolved, skipped))
}

/// The simulation exercises what the property is about: records relative to baselines,
/// and records whose baseline the client lacks.
#[test]
fn the_lossy_link_simulation_sends_deltas_and_loses_baselines() {
    // Every object steps a little or stays, tick after tick.
    let moves: Vec<Vec<(u8, [i8; 3])>> =
        (0..80u8).map(|t| (0..6u8).map(|i| ((t + i) % 2, [1, -2, (t % 5) as i8])).collect()).collect();
    let link: Vec<(u8, u64)> = (0..90u64).map(|i| ((i * 7 % 10) as u8, i % 4)).collect();
    let (relative, skipped) = resolution_is_sound(&moves, &link, true, false).unwrap();
    assert!(relative > 200 && skipped == 0, "{relative} relative, {skipped} skipped");
    // A server following the rule never makes the client skip, even over loss...
    let (relative, skipped) = resolution_is_sound(&moves, &link, false, false).unwrap();
    assert!(relative > 50 && skipped == 0, "{relative} relative, {skipped} skipped");
    // ...one that sends against states never acknowledged does, and nothing resolves wrong.
    let (relative, skipped) = resolution_is_sound(&moves, &link, false, true).unwrap();
    assert!(relative > 0 && skipped > 10, "{relative} relative, {skipped} skipped");
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
    // A deterministic xorshift stream of garbage, with valid-looking headers mixed in,
    // to the server (as actions) and to the client (as state updates).
    let mut server = ServerSession::new(&keys());
    let mut client = ClientSession::new(&keys());
    let mut x = 0x9e37_79b9_7f4a_7c15u64;
    for i in 0..20_000 {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        let len = (x % 1300) as usize;
        let mut d: Vec<u8> = (0..len).map(|j| (x >> (j % 57)) as u8).collect();
        let to_client = i % 4 >= 2;
        if i % 2 == 0 && len >= HEADER_LEN {
            d[0] = PROTOCOL_VERSION;
            d[1] = if to_client { PacketKind::StateUpdate } else { PacketKind::Action } as u8;
            d[2..10].copy_from_slice(&keys().session_id.to_le_bytes());
        }
        if to_client {
            assert!(client.open(&mut d).is_err());
        } else {
            assert!(server.open(&mut d).is_err());
        }
    }
    assert_eq!(server.opener.window().newest(), None);
    assert_eq!(client.opener.window().newest(), None);
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
    // Seal frames whose bodies are an Action with a bad mask and a KeepAlive whose
    // acknowledgement names sequence numbers below 0: the tags verify, the bodies do not
    // decode, and the sequence numbers stay free.
    let k = keys();
    let mut sealer = Sealer::new(k.session_id, Direction::ClientToServer, &k.client_to_server);
    let mut server = ServerSession::new(&k);
    let frame = |kind: PacketKind, body: &[u8]| {
        let mut d = vec![0u8; HEADER_LEN];
        d[1] = kind as u8;
        d.extend_from_slice(body);
        d.extend_from_slice(&[0; TAG_LEN]);
        d
    };
    let mut action = vec![0x20, 0, 0, 0, 0];
    AckField::encode(None, &mut action);
    let mut d = frame(PacketKind::Action, &action);
    sealer.seal_in_place(&mut d).unwrap();
    assert_eq!(server.open(&mut d), Err(OpenError::Malformed(DecodeError::BadActionMask(0x20))));
    let mut ack = 1u64.to_le_bytes().to_vec();
    ack.extend_from_slice(&0b10u64.to_le_bytes());
    let mut d = frame(PacketKind::ClientKeepAlive, &ack);
    sealer.seal_in_place(&mut d).unwrap();
    assert_eq!(server.open(&mut d), Err(OpenError::Malformed(DecodeError::BadAck { newest: 1, bits: 0b10 })));
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
    // 100 absolute records far from the origin: 12 bits of stream parameters, then 102
    // bits each (a one-bit id code, the form, kind and 96 bits of position), more than
    // a datagram.
    let far = RecordState::Absolute { kind: ShapeKind::Box, pos: QuantPos::new(i32::MAX, 0, 0) };
    let big = ServerMessage::StateUpdate(DeltaUpdate {
        header: UpdateHeader::default(),
        records: (0..100).map(|id| DeltaRecord { id, state: far }).collect(),
    });
    let mut server = ServerSession::new(&k);
    let mut out = Vec::new();
    assert_eq!(
        server.seal(&big, &mut out),
        Err(SealError::Encode(EncodeError::TooLarge {
            len: DELTA_HEADER_LEN + (12 + 100 * 102usize).div_ceil(8),
            max: MAX_BODY
        }))
    );
    // Ids that do not increase are refused too.
    let unordered = ServerMessage::StateUpdate(DeltaUpdate {
        header: UpdateHeader::default(),
        records: vec![DeltaRecord { id: 9, state: far }, DeltaRecord { id: 9, state: far }],
    });
    assert_eq!(server.seal(&unordered, &mut out), Err(SealError::Encode(EncodeError::Unordered)));
    assert!(out.is_empty());
    assert_eq!(sealer.next_sequence(), 0);
}

// A record of tick 2 naming a baseline 5 ticks back names a tick before 0, which no
// state has: it is skipped, not applied to the state of tick 0.
#[test]
fn a_baseline_before_tick_0_is_missing() {
    let mut b = Baselines::default();
    let abs = DeltaRecord { id: 9, state: RecordState::Absolute { kind: ShapeKind::Box, pos: QuantPos::new(1, 2, 3) } };
    assert!(b.resolve(0, &abs).is_ok());
    for state in [RecordState::Same { back: 5 }, RecordState::Delta { back: 5, d: [1, 1, 1] }] {
        assert_eq!(b.resolve(2, &DeltaRecord { id: 9, state }), Err(ResolveError::MissingBaseline { id: 9, tick: 0 }));
    }
    // Naming tick 0 itself is fine.
    let same = DeltaRecord { id: 9, state: RecordState::Same { back: 2 } };
    assert_eq!(b.resolve(2, &same).map(|s| s.pos), Ok(QuantPos::new(1, 2, 3)));
}

// Found by the `resolve_deltas` fuzz target: once a tick near `u64::MAX` had been seen,
// the next state remembered overflowed the pruning schedule (a panic where overflow is
// checked).
#[test]
fn ticks_near_u64_max_resolve() {
    let mut b = Baselines::default();
    let abs =
        DeltaRecord { id: 1, state: RecordState::Absolute { kind: ShapeKind::Sphere, pos: QuantPos::new(5, 0, 0) } };
    for tick in [u64::MAX - 5, u64::MAX - 4, u64::MAX] {
        assert!(b.resolve(tick, &abs).is_ok());
    }
    let same = DeltaRecord { id: 1, state: RecordState::Same { back: 5 } };
    assert_eq!(b.resolve(u64::MAX, &same).map(|s| s.pos), Ok(QuantPos::new(5, 0, 0)));
}
