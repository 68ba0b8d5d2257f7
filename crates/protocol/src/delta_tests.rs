use proptest::prelude::*;

use super::*;

fn q(x: i32, y: i32, z: i32) -> QuantPos {
    QuantPos::new(x, y, z)
}

#[test]
fn the_smallest_form_is_chosen() {
    let base = Some(Baseline { tick: 10, pos: q(100, 0, -100) });
    let origin = q(0, 0, 0);
    let same = DeltaRecord::choose(5, ShapeKind::Box, q(100, 0, -100), 12, base);
    assert_eq!(same.state, RecordState::Same { back: 2 });
    assert_eq!(same.encoded_len(None, origin), 2);
    let small = DeltaRecord::choose(5, ShapeKind::Box, q(227, -128, -100), 12, base);
    assert_eq!(small.state, RecordState::Delta { back: 2, d: [127, -128, 0] });
    assert_eq!(small.encoded_len(Some(1), origin), 5);
    let near = DeltaRecord::choose(5, ShapeKind::Box, q(228, 0, -100), 12, base);
    assert_eq!(near.state, RecordState::Absolute { kind: ShapeKind::Box, pos: q(228, 0, -100) });
    assert_eq!(near.encoded_len(Some(4), origin), 8);
    let far = DeltaRecord::choose(300, ShapeKind::Capsule, q(1 << 20, 0, 0), 12, None);
    assert_eq!(far.encoded_len(None, origin), 1 + 2 + 12);
    // A baseline too old, or not older than the update, is not used.
    for tick in [10, 10 + MAX_BACK + 1] {
        let r = DeltaRecord::choose(5, ShapeKind::Box, q(100, 0, -100), tick, base);
        assert!(matches!(r.state, RecordState::Absolute { .. }), "tick {tick}");
    }
}

#[test]
fn varints_have_one_encoding() {
    for v in [0, 1, 127, 128, 16_383, 16_384, u64::from(u32::MAX), u64::MAX] {
        let mut out = [0u8; 10];
        let n = write_varint(v, &mut out);
        assert_eq!(n, varint_len(v));
        assert_eq!(Reader::new(&out[..n]).varint(), Ok(v));
    }
    for bad in [
        &[0x80, 0x00][..],
        &[0xff; 10][..],
        &[0x80; 11][..],
        &[0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x02],
    ] {
        assert!(Reader::new(bad).varint().is_err(), "{bad:?}");
    }
}

#[test]
fn malformed_records_are_refused() {
    let header = |count: u16| {
        let mut b = vec![0u8; DELTA_HEADER_LEN];
        b[22..24].copy_from_slice(&count.to_le_bytes());
        b
    };
    let cases: [(&[u8], DecodeError); 5] = [
        (&[0x00, 5, 1, 2, 3], DecodeError::BadBack(0)),
        (&[0x01, 5], DecodeError::BadBack(0)),
        (&[0x12 | 0x20, 5, 0, 0, 0, 0, 0, 0], DecodeError::ReservedBits(0x32)),
        (&[0x0e, 5, 0, 0, 0, 0, 0, 0], DecodeError::BadShapeKind(3)),
        (&[0x04 | 1, 0x80, 0x00], DecodeError::BadVarint),
    ];
    for (record, error) in cases {
        let mut body = header(1);
        body.extend_from_slice(record);
        assert_eq!(DeltaUpdateView::parse(&body).unwrap_err(), error, "{record:?}");
    }
    // Ids past u64::MAX, a count larger than the body, trailing bytes.
    let mut body = header(2);
    body.extend_from_slice(&[0x05, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x01, 0x05, 0x00]);
    assert_eq!(DeltaUpdateView::parse(&body).unwrap_err(), DecodeError::IdOverflow);
    assert!(matches!(DeltaUpdateView::parse(&header(9)), Err(DecodeError::RecordCount { count: 9 })));
    let mut body = header(0);
    body.push(0);
    assert!(matches!(DeltaUpdateView::parse(&body), Err(DecodeError::TrailingBytes { extra: 1 })));
    let unordered = DeltaUpdate {
        header: UpdateHeader::default(),
        records: vec![DeltaRecord { id: 3, state: RecordState::Same { back: 1 } }; 2],
    };
    assert_eq!(unordered.encode_body(&mut Vec::new()), Err(crate::EncodeError::Unordered));
}

#[test]
fn the_pinned_record_is_in_every_datagram_in_id_order() {
    let header = UpdateHeader { tick: 50, dilation_permille: 1000, origin: q(0, 0, 0) };
    let pinned = DeltaRecord { id: 1_000, state: RecordState::Absolute { kind: ShapeKind::Capsule, pos: q(1, 2, 3) } };
    let records: Vec<_> =
        (0..700u64).map(|i| DeltaRecord { id: i * 3, state: RecordState::Delta { back: 1, d: [1, 2, 3] } }).collect();
    let mut out = DatagramBatch::new();
    let mut ends = Vec::new();
    let packed = pack_deltas(&header, Some(&pinned), &records, 3, &mut out, &mut ends);
    assert_eq!(out.len(), 3);
    assert_eq!(ends.len(), 3);
    assert_eq!(ends[2], packed);
    assert!(packed < records.len() && packed > 400, "{packed}");
    let mut seen = Vec::new();
    for (i, d) in out.iter().enumerate() {
        assert!(d.len() <= MAX_DATAGRAM);
        let body = &d[HEADER_LEN..d.len() - TAG_LEN];
        let update = DeltaUpdate::decode_body(body).unwrap();
        assert_eq!(update.header, header);
        assert_eq!(update.records.iter().filter(|r| **r == pinned).count(), 1);
        let others: Vec<_> = update.records.into_iter().filter(|r| r.id != pinned.id).collect();
        assert_eq!(others.len(), ends[i] - if i == 0 { 0 } else { ends[i - 1] });
        seen.extend(others);
    }
    assert_eq!(seen, records[..packed]);
    // With nothing else, the pinned record alone.
    let mut out = DatagramBatch::new();
    assert_eq!(pack_deltas(&header, Some(&pinned), &[], 2, &mut out, &mut ends), 0);
    assert_eq!(ends, [0]);
    assert_eq!(out.len(), 1);
}

#[test]
fn a_missing_baseline_skips_the_record_and_changes_nothing() {
    let mut b = Baselines::default();
    let abs = DeltaRecord { id: 7, state: RecordState::Absolute { kind: ShapeKind::Box, pos: q(10, 20, 30) } };
    assert_eq!(b.resolve(100, &abs).unwrap().pos, q(10, 20, 30));
    let moved = DeltaRecord { id: 7, state: RecordState::Delta { back: 2, d: [1, -1, 0] } };
    assert_eq!(b.resolve(102, &moved).unwrap(), StateRecord { id: 7, kind: ShapeKind::Box, pos: q(11, 19, 30) });
    assert_eq!(b.resolve(103, &moved), Err(ResolveError::MissingBaseline { id: 7, tick: 101 }));
    let same = DeltaRecord { id: 7, state: RecordState::Same { back: 3 } };
    assert_eq!(b.resolve(105, &same).unwrap().pos, q(11, 19, 30));
    // Once the window has moved past it, the old state is gone.
    let other = DeltaRecord { id: 8, state: RecordState::Same { back: 1 } };
    assert!(b.resolve(100 + MAX_BACK + 10, &abs).is_ok());
    assert!(b.resolve(100 + MAX_BACK + 11, &DeltaRecord { id: 7, state: RecordState::Same { back: 11 } }).is_err());
    assert!(b.resolve(1, &other).is_err());
}

fn arb_state() -> impl Strategy<Value = RecordState> {
    prop_oneof![
        (1u8..=63, any::<[i8; 3]>()).prop_map(|(back, d)| RecordState::Delta { back, d }),
        (1u8..=63).prop_map(|back| RecordState::Same { back }),
        (0u8..3, any::<(i32, i32, i32)>(), -40_000i32..40_000).prop_map(|(k, (x, y, z), small)| {
            let pos = if x % 2 == 0 { q(small, -small, small / 3) } else { q(x, y, z) };
            RecordState::Absolute { kind: ShapeKind::from_code(k).unwrap(), pos }
        }),
    ]
}

proptest! {
    /// Whatever records a server writes, the body decodes to the same records.
    #[test]
    fn bodies_round_trip(
        tick in any::<u64>(),
        origin in any::<(i32, i32, i32)>(),
        gaps in proptest::collection::vec((0u64..5_000_000, arb_state()), 0..60),
    ) {
        let mut id = 0u64;
        let records: Vec<_> = gaps.into_iter().map(|(g, state)| {
            id = id.saturating_add(g + 1);
            DeltaRecord { id, state }
        }).collect();
        let mut records = records;
        records.dedup_by_key(|r| r.id);
        let update = DeltaUpdate {
            header: UpdateHeader { tick, dilation_permille: 1000, origin: q(origin.0, origin.1, origin.2) },
            records,
        };
        let mut body = Vec::new();
        update.encode_body(&mut body).unwrap();
        prop_assert_eq!(DeltaUpdate::decode_body(&body).unwrap(), update);
    }

    /// Decoding never panics, and what it accepts encodes to a body that decodes to the
    /// same records.
    #[test]
    fn garbage_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..200)) {
        if let Ok(update) = DeltaUpdate::decode_body(&bytes) {
            let mut again = Vec::new();
            update.encode_body(&mut again).unwrap();
            prop_assert_eq!(DeltaUpdate::decode_body(&again).unwrap(), update);
        }
    }
}
