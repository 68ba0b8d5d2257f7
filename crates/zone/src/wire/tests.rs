use super::*;
use proptest::prelude::*;

fn key() -> ClusterKey {
    ClusterKey::new(&[7; 32]).unwrap()
}

fn object(id: u32, x: f32) -> ObjectState {
    ObjectState {
        id: EntityId(id),
        kind: ObjectKind::User,
        shape: ShapeKind::Capsule,
        half: Vec3::new(0.5, 1.5, 0.5),
        radius: 0.5,
        pos: Vec3::new(x, 2.0, -3.0),
        prev: Vec3::new(x - 0.1, 2.0, -3.0),
        action: 9,
        flags: flags::ON_TERRAIN,
    }
}

fn message() -> Border {
    Border {
        run: 0xfeed,
        tick: 12,
        from: ZoneId(3),
        to: ZoneId(4),
        part: 1,
        parts: 2,
        objects: vec![
            BorderRecord { state: object(5, 1.0), yours: true },
            BorderRecord { state: object(9, -7.5), yours: false },
        ],
    }
}

#[test]
fn round_trips_and_is_the_documented_size() {
    let b = encode_border(&key(), &message()).unwrap();
    assert_eq!(b.len(), HEADER_LEN + 2 * RECORD_LEN + TAG_LEN);
    assert_eq!(decode(&key(), &b).unwrap(), Message::Border(message()));
    let objects = vec![object(1, 0.5), object(2, 3.0)];
    let cuts = (vec![0.0, 100.5, 200.0], vec![-4.0, 8.0]);
    let c = encode_checkpoint(&key(), 9, 30, ZoneId(2), &cuts, &objects).unwrap();
    assert_eq!(c.len(), HEADER_LEN + 5 * 4 + 2 * RECORD_LEN + TAG_LEN, "the cuts, then the records");
    let checkpoint = Message::Checkpoint { run: 9, tick: 30, zone: ZoneId(2), cuts: cuts.clone(), objects };
    assert_eq!(decode(&key(), &c).unwrap(), checkpoint);
    let load = Load { step_us: 12_345, owned: 6_000, cuts: 0x0123_4567_89ab_cdef, pending: 90 };
    let cut = CutMove { decided_at: 60, apply_at: 90, xs: vec![0.0, 120.0, 200.0], zs: vec![-4.0, 8.0] };
    for m in [
        Message::Heartbeat { run: 3, tick: 77, zone: ZoneId(1), state: ZoneState::Stalled, load },
        Message::Halt { run: 4 },
        Message::Start { run: 4, tick: 60, cuts: cuts.clone() },
        Message::Claim { time_ms: 1_764_000_000_000, account: 0xdead_beef, gateway: 3 },
        Message::CutMove { run: 4, cut: cut.clone() },
    ] {
        assert_eq!(decode(&key(), &encode_control(&key(), &m).unwrap()).unwrap(), m);
    }
    assert_eq!(encode_cut_move(&key(), 4, &cut).unwrap().len(), HEADER_LEN + 8 + 5 * 4 + TAG_LEN);
    // Cuts that are no cuts are refused when encoding and when decoding.
    for (xs, zs) in
        [(vec![0.0], vec![0.0, 1.0]), (vec![0.0, f32::NAN], vec![0.0, 1.0]), (vec![2.0, 1.0], vec![0.0, 1.0])]
    {
        let bad = CutMove { xs: xs.clone(), zs: zs.clone(), ..cut.clone() };
        assert_eq!(encode_cut_move(&key(), 4, &bad), Err(WireError::Field("cuts")));
        let mut raw = encode_cut_move(&key(), 4, &cut).unwrap();
        raw.truncate(raw.len() - TAG_LEN);
        raw[24..26].copy_from_slice(&(xs.len() as u16).to_le_bytes());
        raw[26..28].copy_from_slice(&(zs.len() as u16).to_le_bytes());
        raw.truncate(HEADER_LEN + 8);
        raw.extend(xs.iter().chain(&zs).flat_map(|c| c.to_le_bytes()));
        assert_eq!(decode(&key(), &sign(&key(), &raw)), Err(WireError::Field("cuts")), "{xs:?} {zs:?}");
    }
    assert!(encode_control(&key(), &Message::Border(message())).is_err());
    let states = Border { to: ALL, objects: vec![BorderRecord::seen(object(5, 1.0))], ..message() };
    assert_eq!(decode(&key(), &encode_states(&key(), &states).unwrap()).unwrap(), Message::States(states.clone()));
    assert!(encode_states(&key(), &message()).is_err(), "a state message hands nothing and goes to all");
    for kind in [IntentKind::Join, IntentKind::Action, IntentKind::Leave] {
        let i = Intents { incarnation: 1_700_000, tick: 44, gateway: 2, kind, objects: vec![object(1 << 30, 2.0)] };
        assert_eq!(
            decode(&key(), &encode(&key(), &Message::Intents(i.clone())).unwrap()).unwrap(),
            Message::Intents(i)
        );
    }
    // A checkpoint record with the hand-off bit is refused, not silently cleared.
    let mut raw = c[..c.len() - TAG_LEN].to_vec();
    raw[HEADER_LEN + 5 * 4 + 7] |= YOURS;
    assert!(matches!(decode(&key(), &sign(&key(), &raw)), Err(WireError::Record { index: 0, .. })));
}

fn subscription() -> Subscription {
    Subscription {
        incarnation: 1_764_000_000_123,
        gateway: 7,
        version: 3,
        confirmed: Some((2, 99)),
        resyncs: 5,
        cell: 32.0,
        cols: 3,
        rows: 5,
        cells: vec![0b1010_0101, 0b0110_0000],
        ground: 0x0123_4567_89ab_cdef,
    }
}

fn view() -> View {
    View {
        run: 2,
        tick: 101,
        zone: ZoneId(1),
        gateway: 7,
        part: 0,
        parts: 2,
        base: Some(99),
        objects: vec![object(5, 1.0), object(9, -7.5)],
        moves: vec![(EntityId(2), Vec3::new(1.0, 2.0, 3.0)), (EntityId(6), Vec3::new(-4.0, 0.5, 9.0))],
        nudges: vec![
            Nudge { id: EntityId(4), prediction: Prediction::Off, bits: [3277, -2, 0] },
            Nudge { id: EntityId(700), prediction: Prediction::Steady, bits: [0, 0, -64] },
            Nudge { id: EntityId(701), prediction: Prediction::Ground, bits: [0, 0, 0] },
        ],
        gone: vec![EntityId(3), EntityId(1 << 30)],
        acts: vec![(EntityId(4), 0b1_0101), (EntityId(701), 0)],
    }
}

#[test]
fn subscriptions_and_views_round_trip_and_are_the_documented_size() {
    let s = encode_subscription(&key(), &subscription()).unwrap();
    assert_eq!(s.len(), HEADER_LEN + 32 + 2 + TAG_LEN);
    assert_eq!(decode(&key(), &s).unwrap(), Message::Subscription(subscription()));
    let none = Subscription { confirmed: None, resyncs: MAX_RESYNCS - 1, ..subscription() };
    assert_eq!(
        decode(&key(), &encode(&key(), &Message::Subscription(none.clone())).unwrap()).unwrap(),
        Message::Subscription(none)
    );
    let v = encode_view(&key(), &view()).unwrap();
    // Nudges: id 4 (1 byte), 3277 (2), -2 (1), 0 (1); id 700 as 696 more, predicted (2),
    // 0, 0, -64 (1); id 701 as 1 more on the ground, exact (1).
    let nudges = (1 + 2 + 1 + 1) + (2 + 1 + 1 + 1) + 1;
    let body = 28 + 2 * RECORD_LEN + 2 * MOVE_LEN + 2 * 4 + 2 * ACT_LEN + nudges;
    assert_eq!(v.len(), HEADER_LEN + body + TAG_LEN);
    assert_eq!(decode(&key(), &v).unwrap(), Message::View(view()));
    let whole = View { base: None, gone: vec![], moves: vec![], nudges: vec![], acts: vec![], ..view() };
    assert_eq!(decode(&key(), &encode(&key(), &Message::View(whole.clone())).unwrap()).unwrap(), Message::View(whole));
    assert_eq!(decode(&ClusterKey::new(&[8; 32]).unwrap(), &s), Err(WireError::Tag));
}

#[test]
fn bad_subscriptions_and_views_are_refused_with_their_reason() {
    // Refused when encoding.
    let cells = |cols, rows| Subscription { cols, rows, cells: vec![0; cell_bytes(cols, rows)], ..subscription() };
    assert_eq!(encode_subscription(&key(), &cells(1024, 1024)), Err(WireError::Cells(1 << 20)));
    assert_eq!(encode_subscription(&key(), &cells(0, 4)), Err(WireError::Cells(0)));
    let tail = Subscription { cells: vec![0, 0b1000_0000], ..subscription() };
    assert!(encode_subscription(&key(), &tail).is_err(), "a cell past the grid");
    assert!(encode_subscription(&key(), &Subscription { cell: f32::NAN, ..subscription() }).is_err());
    let resyncs = Subscription { resyncs: MAX_RESYNCS, ..subscription() };
    assert!(encode_subscription(&key(), &resyncs).is_err(), "resyncs share a word with a flag");
    let whole = View { base: None, moves: vec![], gone: vec![], nudges: vec![], acts: vec![], ..view() };
    assert!(encode_view(&key(), &View { acts: view().acts, ..whole.clone() }).is_err(), "acts in a whole view");
    let acts = |acts: &[(u32, u8)]| View { acts: acts.iter().map(|&(id, a)| (EntityId(id), a)).collect(), ..view() };
    assert_eq!(encode_view(&key(), &acts(&[(4, 0b10_0000)])), Err(WireError::Field("view acts")), "no such action");
    assert!(encode_view(&key(), &acts(&[(4, 1), (4, 2)])).is_err(), "one object's action twice");
    assert!(encode_view(&key(), &View { gone: view().gone, ..whole.clone() }).is_err(), "gone ids in a whole view");
    assert!(encode_view(&key(), &View { moves: view().moves, ..whole.clone() }).is_err(), "moves in a whole view");
    assert!(encode_view(&key(), &View { nudges: view().nudges, ..whole }).is_err(), "nudges in a whole view");
    let both = vec![Nudge { id: EntityId(6), prediction: Prediction::Off, bits: [1, 1, 1] }];
    assert!(encode_view(&key(), &View { nudges: both, ..view() }).is_err(), "one object moved and nudged");
    let nan = vec![(EntityId(2), Vec3::new(f32::NAN, 0.0, 0.0))];
    assert!(encode_view(&key(), &View { moves: nan, ..view() }).is_err(), "a move nowhere");
    let twice = vec![(EntityId(2), Vec3::ZERO), (EntityId(2), Vec3::ONE)];
    assert!(encode_view(&key(), &View { moves: twice, ..view() }).is_err(), "one object moved twice");
    assert!(encode_view(&key(), &View { gone: vec![EntityId(4), EntityId(3)], ..view() }).is_err(), "ids descend");
    assert!(encode_view(&key(), &View { part: 2, ..view() }).is_err());
    // Refused when decoding, behind a valid tag: each signed as the cluster would.
    let s = encode_subscription(&key(), &subscription()).unwrap();
    let resigned = |b: &[u8], edit: &dyn Fn(&mut Vec<u8>)| {
        let mut raw = b[..b.len() - TAG_LEN].to_vec();
        edit(&mut raw);
        decode(&key(), &sign(&key(), &raw))
    };
    assert_eq!(resigned(&s, &|r| r[24..28].copy_from_slice(&[0xff; 4])), Err(WireError::Cells(65_535 * 65_535)));
    assert!(matches!(resigned(&s, &|r| r.truncate(r.len() - 1)), Err(WireError::Length { .. })));
    assert_eq!(resigned(&s, &|r| r[HEADER_LEN] = 2), Err(WireError::Field("subscription confirmation")));
    assert_eq!(resigned(&s, &|r| *r.last_mut().unwrap() = 0xff), Err(WireError::Field("subscription cells")));
    let v = encode_view(&key(), &view()).unwrap();
    assert_eq!(
        resigned(&v, &|r| r[22..24].copy_from_slice(&ALL.0.to_le_bytes())),
        Err(WireError::Field("view header"))
    );
    assert!(matches!(resigned(&v, &|r| r.extend_from_slice(&[0; 4])), Err(WireError::Length { .. })));
    // Acts: an action no client can hold (the second act's byte, before the 11 bytes of
    // nudges), and acts out of order (swap the two).
    let a = v.len() - TAG_LEN - 11;
    assert_eq!(resigned(&v, &|r| r[a - 1] = 0x20), Err(WireError::Field("view acts")));
    assert_eq!(
        resigned(&v, &|r| {
            let (x, y) = (r[a - 10..a - 5].to_vec(), r[a - 5..a].to_vec());
            r[a - 10..a - 5].copy_from_slice(&y);
            r[a - 5..a].copy_from_slice(&x);
        }),
        Err(WireError::Field("view ids"))
    );
    // Gone ids out of order (swap the two; the view's two acts and 11 bytes of nudges
    // follow them).
    let n = v.len() - TAG_LEN - 11 - 2 * ACT_LEN;
    assert_eq!(
        resigned(&v, &|r| {
            let (a, b) = (r[n - 8..n - 4].to_vec(), r[n - 4..n].to_vec());
            r[n - 8..n - 4].copy_from_slice(&b);
            r[n - 4..n].copy_from_slice(&a);
        }),
        Err(WireError::Field("view ids"))
    );
}

#[test]
fn refuses_other_keys_alterations_and_bad_records() {
    let b = encode_border(&key(), &message()).unwrap();
    assert_eq!(decode(&ClusterKey::new(&[8; 32]).unwrap(), &b), Err(WireError::Tag));
    for i in 0..b.len() {
        let mut c = b.clone();
        c[i] ^= 0x10;
        assert!(decode(&key(), &c).is_err(), "flipping byte {i}");
    }
    assert_eq!(decode(&key(), &b[..40]), Err(WireError::Truncated(40)));
    let mut bad = message();
    bad.objects[0].state.pos.x = f32::NAN;
    let signed = encode_border(&key(), &bad).unwrap();
    assert!(matches!(decode(&key(), &signed), Err(WireError::Record { index: 0, .. })));
    assert!(encode_border(&key(), &Border { part: 2, ..message() }).is_err());
    assert!(ClusterKey::new(b"short").is_err());
}

/// Signed headers of every kind with fields from a few telling values, and bodies of
/// valid or random records: whatever decodes re-encodes to the same bytes (one
/// encoding per message), as the `zone_message` fuzz target checks without limits.
fn signed_message() -> impl Strategy<Value = Vec<u8>> {
    let ids = prop_oneof![Just(0u16), Just(1), Just(ALL.0)];
    let record = prop_oneof![
        (any::<u32>(), any::<bool>()).prop_map(|(id, yours)| {
            let objects = vec![BorderRecord { state: object(id, 1.5), yours }];
            let b = encode_border(&key(), &Border { objects, ..message() }).unwrap();
            b[HEADER_LEN..HEADER_LEN + RECORD_LEN].to_vec()
        }),
        proptest::collection::vec(any::<u8>(), RECORD_LEN),
    ];
    // What may open a body: nothing, a heartbeat's load, cuts as the header counts them
    // (a start's, a checkpoint's), or a decision tick and cuts (a cut move's). Kinds 10
    // and 11 (subscription, view) have bodies of their own: random words and records
    // reach their parsers too.
    let prefix = (0u8..4, any::<[u64; 3]>());
    (
        (1u8..=13, any::<u64>(), any::<u64>()),
        (ids.clone(), ids, 0u16..4, 0u16..4),
        prefix,
        proptest::collection::vec(record, 0..3),
    )
        .prop_map(|((kind, run, tick), (from, to, aux0, aux1), (shape, words), records)| {
            let mut b = MAGIC.to_vec();
            b.extend_from_slice(&[VERSION, kind]);
            b.extend_from_slice(&run.to_le_bytes());
            b.extend_from_slice(&tick.to_le_bytes());
            for v in [from, to, aux0, aux1] {
                b.extend_from_slice(&v.to_le_bytes());
            }
            b.extend_from_slice(&(records.len() as u32).to_le_bytes());
            let cuts = (0..aux0).map(|i| i as f32 * 3.0).chain((0..aux1).map(|i| i as f32 - 1.0));
            match shape {
                0 => {}
                1 => words.iter().for_each(|w| b.extend_from_slice(&w.to_le_bytes())),
                2 => cuts.for_each(|c| b.extend_from_slice(&c.to_le_bytes())),
                _ => {
                    b.extend_from_slice(&words[0].to_le_bytes());
                    cuts.for_each(|c| b.extend_from_slice(&c.to_le_bytes()));
                }
            }
            records.iter().for_each(|r| b.extend_from_slice(r));
            sign(&key(), &b)
        })
}

proptest! {
    // About one case in fifty decodes (every kind does, now and then).
    #![proptest_config(ProptestConfig::with_cases(4096))]
    #[test]
    fn whatever_decodes_has_one_encoding(signed in signed_message()) {
        if let Ok(m) = decode(&key(), &signed) {
            // A view has two encodings, plain and packed (whichever is smaller): both
            // decode to the same view.
            if matches!(m, Message::View(_)) {
                prop_assert_eq!(decode(&key(), &encode(&key(), &m).unwrap()).unwrap(), m);
            } else {
                prop_assert_eq!(encode(&key(), &m).unwrap(), signed);
            }
        }
    }
}

proptest! {
    #[test]
    fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..400)) {
        let _ = decode(&key(), &bytes);
    }
}

/// A view of a walking crowd (thousands of nudges of a byte or two an axis, whole records
/// of neighbours): packed, smaller, and it decodes to the same view.
fn crowd_view() -> View {
    let nudges = (0..3000u32)
        .map(|i| {
            let wobble = (i.wrapping_mul(2_654_435_761) >> 24) as i32 - 128;
            Nudge {
                id: EntityId(10 + 3 * i),
                prediction: [Prediction::Off, Prediction::Steady, Prediction::Airborne][i as usize % 3],
                bits: [wobble, -2846, wobble / 3],
            }
        })
        .collect();
    let objects = (0..200).map(|i| object(20_000 + i, 300.0 + i as f32 * 0.25)).collect();
    View { objects, moves: vec![], gone: vec![EntityId(9_000)], nudges, ..view() }
}

#[test]
fn a_crowds_view_travels_packed_and_decodes_to_the_same_view() {
    let v = crowd_view();
    let b = encode_view(&key(), &v).unwrap();
    assert_eq!(b[3], KIND_VIEW_PACKED);
    let plain = HEADER_LEN + 24 + 200 * RECORD_LEN + 4 + super::nudge::nudges_len(&v.nudges) + TAG_LEN;
    assert!(b.len() * 10 < plain * 9, "packed {} bytes of {plain}", b.len());
    assert_eq!(decode(&key(), &b).unwrap(), Message::View(v.clone()));
    // The same view through the general encoder.
    assert_eq!(encode(&key(), &Message::View(v)).unwrap(), b);
}

#[test]
fn packed_views_that_lie_about_their_length_or_frame_are_refused() {
    let b = encode_view(&key(), &crowd_view()).unwrap();
    let body = &b[HEADER_LEN..b.len() - TAG_LEN];
    let stated = u32::from_le_bytes(body[..4].try_into().unwrap()) as usize;
    let frame = body[4..].to_vec();
    // The same header, another body, signed as the cluster would.
    let with_body = |body: &[u8]| {
        let mut raw = b[..HEADER_LEN].to_vec();
        raw.extend_from_slice(body);
        decode(&key(), &sign(&key(), &raw))
    };
    let body_of = |len: usize, frame: &[u8]| {
        let mut v = (len as u32).to_le_bytes().to_vec();
        v.extend_from_slice(frame);
        v
    };
    assert!(with_body(&body_of(stated, &frame)).is_ok(), "the body as sent");
    assert_eq!(with_body(&body_of(stated - 1, &frame)), Err(WireError::Field("packed view")), "unpacks to more");
    assert_eq!(with_body(&body_of(stated + 1, &frame)), Err(WireError::Field("packed view length")), "to less");
    let huge = MAX_PACKED_VIEW_BODY + 1;
    assert_eq!(with_body(&body_of(huge, &frame)), Err(WireError::Field("packed view length")), "over the bound");
    assert_eq!(
        with_body(&body_of(8, &frame)),
        Err(WireError::Field("packed view length")),
        "under a view's fixed part"
    );
    let mut cut = frame.clone();
    cut.truncate(frame.len() / 2);
    assert_eq!(with_body(&body_of(stated, &cut)), Err(WireError::Field("packed view")), "a cut frame");
    assert!(matches!(with_body(&[1, 2]), Err(WireError::Length { .. })), "no room for the length");
    // A frame that unpacks to a bad plain body is refused as the plain view would be.
    let bad_plain = vec![0u8; 30];
    let packed = zstd::bulk::compress(&bad_plain, 1).unwrap();
    assert!(matches!(with_body(&body_of(30, &packed)), Err(WireError::Length { .. })));
}
