use proptest::prelude::*;

use super::*;
use crate::update::StateRecord;

fn q(x: i32, y: i32, z: i32) -> QuantPos {
    QuantPos::new(x, y, z)
}

#[test]
fn the_smallest_form_is_chosen() {
    let base = Some(Baseline { tick: 10, pos: q(100, 0, -100) });
    let origin = q(0, 0, 0);
    let bits = |r: &DeltaRecord| r.bits(origin, 0).unwrap();
    let same = DeltaRecord::choose(5, ShapeKind::Box, q(100, 0, -100), 12, base, None);
    assert_eq!(same.state, RecordState::Same { back: 2 });
    assert_eq!(bits(&same), 3 + 7);
    assert_eq!(same.bits(origin, 2), Some(3 + 1));
    let small = DeltaRecord::choose(5, ShapeKind::Box, q(103, -4, -100), 12, base, None);
    assert_eq!(small.state, RecordState::Delta { back: 2, d: [3, -4, 0] });
    assert_eq!(bits(&small), 1 + 7 + 1 + 2 + 3 * 3);
    let wide = DeltaRecord::choose(5, ShapeKind::Box, q(611, -512, -100), 12, base, None);
    assert_eq!(wide.state, RecordState::Delta { back: 2, d: [511, -512, 0] });
    assert_eq!(bits(&wide), 1 + 7 + 1 + 2 + 3 * 10);
    let near = DeltaRecord::choose(5, ShapeKind::Box, q(612, 0, -100), 12, base, None);
    assert_eq!(near.state, RecordState::Absolute { kind: ShapeKind::Box, pos: q(612, 0, -100) });
    assert_eq!(bits(&near), 2 + 2 + 2 + 3 * 12);
    let far = DeltaRecord::choose(300, ShapeKind::Capsule, q(1 << 20, 0, 0), 12, None, None);
    assert_eq!(bits(&far), 3 + 2 + 96);
    // A baseline too old, or not older than the update, is not used.
    for tick in [10, 10 + MAX_BACK + 1] {
        let r = DeltaRecord::choose(5, ShapeKind::Box, q(100, 0, -100), tick, base, None);
        assert!(matches!(r.state, RecordState::Absolute { .. }), "tick {tick}");
    }
}

#[test]
fn a_steady_move_is_predicted_and_a_stop_is_not() {
    // Moving +40 steps a tick on x: sent at 4, 7, now 10.
    let prior = Some(Baseline { tick: 4, pos: q(0, 0, 0) });
    let base = Some(Baseline { tick: 7, pos: q(120, 0, 0) });
    let steady = DeltaRecord::choose(9, ShapeKind::Sphere, q(241, 0, -1), 10, base, prior);
    assert_eq!(steady.state, RecordState::Predicted { back: 3, prior: 3, d: [1, 0, -1] });
    assert_eq!(steady.bits(q(0, 0, 0), 3), Some(1 + 1 + 1 + 1 + 2 + 3 * 3));
    // Stopped: the plain delta is smaller than the prediction's.
    let stopped = DeltaRecord::choose(9, ShapeKind::Sphere, q(121, 0, 0), 10, base, prior);
    assert_eq!(stopped.state, RecordState::Delta { back: 3, d: [1, 0, 0] });
    // A prior too old to name with the back is not used.
    let far_prior = DeltaRecord::choose(
        9,
        ShapeKind::Sphere,
        q(241, 0, 0),
        70,
        Some(Baseline { tick: 67, pos: q(120, 0, 0) }),
        Some(Baseline { tick: 6, pos: q(0, 0, 0) }),
    );
    assert!(!matches!(far_prior.state, RecordState::Predicted { .. }));
    // Rounding: to nearest, halves up, on every axis the same.
    assert_eq!(predict(q(10, -10, 0), q(0, 0, 1), 1, 2), [15, -15, 0]);
    assert_eq!(predict(q(3, -3, 0), q(0, 0, 0), 1, 2), [5, -4, 0]);
}

/// A body with `count` records whose stream is what `write` puts after the params.
fn body_of(count: u16, usual: u8, k: u32, write: impl FnOnce(&mut BitWriter<'_>)) -> Vec<u8> {
    let mut b = vec![0u8; DELTA_HEADER_LEN + 64];
    b[22..24].copy_from_slice(&count.to_le_bytes());
    let mut w = BitWriter::new(&mut b[DELTA_HEADER_LEN..]);
    StreamParams { usual, k }.write(&mut w);
    write(&mut w);
    let len = DELTA_HEADER_LEN + w.finish();
    b.truncate(len);
    b
}

#[test]
fn malformed_records_are_refused() {
    type Case = (fn(&mut BitWriter<'_>), u8, DecodeError);
    let cases: [Case; 6] = [
        // Id 5, Same with the usual back, which is 0.
        (
            |w| {
                w.put_exp_golomb(5, 0);
                w.put(0b100, 3);
                w.put(1, 1)
            },
            0,
            DecodeError::BadBack(0),
        ),
        // Delta with back 0 written out.
        (
            |w| {
                w.put_exp_golomb(5, 0);
                w.put(1, 1);
                w.put(0, 1);
                w.put(0, 6)
            },
            3,
            DecodeError::BadBack(0),
        ),
        // Predicted: back 60, prior 4.
        (
            |w| {
                w.put_exp_golomb(5, 0);
                w.put(1, 1);
                w.put(0, 1);
                w.put(60, 6);
                w.put(1, 1);
                w.put(0, 1);
                w.put(4, 6)
            },
            3,
            DecodeError::BadPrior { back: 60, prior: 4 },
        ),
        // Predicted with prior 0.
        (
            |w| {
                w.put_exp_golomb(5, 0);
                w.put(1, 1);
                w.put(1, 1);
                w.put(1, 1);
                w.put(0, 1);
                w.put(0, 6)
            },
            3,
            DecodeError::BadPrior { back: 3, prior: 0 },
        ),
        // Near and Far of kind 3.
        (
            |w| {
                w.put_exp_golomb(5, 0);
                w.put(0b10, 2);
                w.put(3, 2);
                w.put(0, 2);
                w.put(0, 30)
            },
            3,
            DecodeError::BadShapeKind(3),
        ),
        (
            |w| {
                w.put_exp_golomb(5, 0);
                w.put(0b000, 3);
                w.put(3, 2);
                w.put(0, 64);
                w.put(0, 32)
            },
            3,
            DecodeError::BadShapeKind(3),
        ),
    ];
    for (i, (write, usual, error)) in cases.into_iter().enumerate() {
        assert_eq!(DeltaUpdateView::parse(&body_of(1, usual, 0, write)).unwrap_err(), error, "case {i}");
    }
    // Ids past u64::MAX, a count larger than the body, trailing bytes, set padding.
    let body = body_of(2, 1, 0, |w| {
        w.put_exp_golomb(u64::MAX, 0);
        w.put(0b100, 3);
        w.put(1, 1);
        w.put_exp_golomb(0, 0);
        w.put(0b100, 3);
        w.put(1, 1);
    });
    assert_eq!(DeltaUpdateView::parse(&body).unwrap_err(), DecodeError::IdOverflow);
    assert!(matches!(DeltaUpdateView::parse(&body_of(9, 0, 0, |_| {})), Err(DecodeError::RecordCount { count: 9 })));
    let mut body = body_of(0, 0, 0, |_| {});
    body.push(0);
    assert!(matches!(DeltaUpdateView::parse(&body), Err(DecodeError::TrailingBytes { extra: 1 })));
    let mut body = body_of(0, 0, 0, |_| {});
    *body.last_mut().unwrap() |= 0x80;
    assert!(matches!(DeltaUpdateView::parse(&body), Err(DecodeError::ReservedBits(_))));
    // A delta out of the widest class cannot be encoded.
    let wide = DeltaUpdate {
        header: UpdateHeader::default(),
        records: vec![DeltaRecord { id: 3, state: RecordState::Delta { back: 1, d: [512, 0, 0] } }],
    };
    assert_eq!(wide.encode_body(&mut Vec::new()), Err(crate::EncodeError::OutOfRange));
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
        (0..3000u64).map(|i| DeltaRecord { id: i * 3, state: RecordState::Delta { back: 1, d: [1, 2, 3] } }).collect();
    let mut out = DatagramBatch::new();
    let mut ends = Vec::new();
    let packed = pack_deltas(&header, Some(&pinned), &records, 3, &mut out, &mut ends);
    assert_eq!(out.len(), 3);
    assert_eq!(ends.len(), 3);
    assert_eq!(ends[2], packed);
    assert!(packed < records.len() && packed > 1200, "{packed}");
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

/// A body packed elsewhere, framed, is the datagram `pack_deltas` makes; a body of a
/// length no datagram has is refused and adds nothing.
#[test]
fn a_framed_body_is_the_packed_datagram() {
    let header = UpdateHeader { tick: 9, dilation_permille: 950, origin: q(-5, 6, 7) };
    let records: Vec<_> = (0..900u64)
        .map(|i| DeltaRecord { id: 4 + i * 2, state: RecordState::Delta { back: 2, d: [1, -1, 2] } })
        .collect();
    let mut packed = DatagramBatch::new();
    let mut ends = Vec::new();
    pack_deltas(&header, None, &records, 2, &mut packed, &mut ends);
    assert_eq!(packed.len(), 2);
    let mut framed = DatagramBatch::new();
    for d in packed.iter() {
        frame_delta_body(&d[HEADER_LEN..d.len() - TAG_LEN], &mut framed).unwrap();
    }
    assert_eq!(framed, packed);
    for len in [0, DELTA_HEADER_LEN - 1, MAX_BODY + 1] {
        assert_eq!(frame_delta_body(&vec![0; len], &mut framed), Err(BodyLengthError(len)));
    }
    assert_eq!(framed, packed);
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
    // Predicted from 102 along its move since 100, then moved by d.
    let predicted = DeltaRecord { id: 7, state: RecordState::Predicted { back: 2, prior: 2, d: [0, 1, 0] } };
    assert_eq!(b.resolve(104, &predicted).unwrap().pos, q(12, 19, 30));
    // Its prior must be held too.
    let lacking = DeltaRecord { id: 7, state: RecordState::Predicted { back: 3, prior: 1, d: [0, 0, 0] } };
    assert_eq!(b.resolve(105, &lacking), Err(ResolveError::MissingBaseline { id: 7, tick: 101 }));
    // Once the window has moved past it, the old state is gone.
    let other = DeltaRecord { id: 8, state: RecordState::Same { back: 1 } };
    assert!(b.resolve(100 + MAX_BACK + 10, &abs).is_ok());
    assert!(b.resolve(100 + MAX_BACK + 11, &DeltaRecord { id: 7, state: RecordState::Same { back: 11 } }).is_err());
    assert!(b.resolve(1, &other).is_err());
}

fn arb_state() -> impl Strategy<Value = RecordState> {
    prop_oneof![
        (1u8..=63, proptest::array::uniform3(-512i16..512)).prop_map(|(back, d)| RecordState::Delta { back, d }),
        (1u8..=62, 1u8..=62, proptest::array::uniform3(-512i16..512)).prop_filter_map(
            "back + prior <= 63",
            |(back, prior, d)| {
                (u16::from(back) + u16::from(prior) <= 63).then_some(RecordState::Predicted { back, prior, d })
            }
        ),
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
