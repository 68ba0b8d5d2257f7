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
    // (a start's, a checkpoint's), or a decision tick and cuts (a cut move's).
    let prefix = (0u8..4, any::<[u64; 3]>());
    (
        (1u8..=10, any::<u64>(), any::<u64>()),
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
            prop_assert_eq!(encode(&key(), &m).unwrap(), signed);
        }
    }
}

proptest! {
    #[test]
    fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..400)) {
        let _ = decode(&key(), &bytes);
    }
}
