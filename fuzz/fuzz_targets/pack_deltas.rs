//! The delta packer on arbitrary records, each chosen against an arbitrary history of
//! its object (`DeltaRecord::choose`, with a prior state before the baseline now and
//! then, so that records are also predicted), with or without the player's own object: every
//! datagram fits the size limit and decodes; its ids strictly increase; the own record
//! is in every datagram exactly once; together the datagrams give back exactly the
//! packed prefix, split where `ends` says; and a client's `Baselines` fed the same
//! history resolves every record of every datagram to exactly the state chosen.
#![no_main]

use libfuzzer_sys::fuzz_target;
use myriad_protocol::{
    Baseline, Baselines, DatagramBatch, DeltaRecord, DeltaUpdate, HEADER_LEN, MAX_DATAGRAM, PacketKind, QuantPos,
    RecordState, ShapeKind, StateRecord, TAG_LEN, UpdateHeader, pack_deltas,
};

fn i32_at(b: &[u8]) -> i32 {
    i32::from_le_bytes([b[0], b[1], b[2], b[3]])
}

/// Bytes per object in the input.
const OBJECT: usize = 20;

/// One object from `OBJECT` input bytes: its id (after `previous`, or whole), its
/// shape, its state now, and its baseline (the state the client holds) if it has one.
type Object = (StateRecord, Option<Baseline>, Option<Baseline>);

fn object(c: &[u8], previous: Option<u64>, tick: u64, origin: QuantPos) -> Option<Object> {
    // Gaps of every size: 32 bits shifted by up to 39.
    let gap = u64::from(u32::from_le_bytes([c[0], c[1], c[2], c[3]])).checked_shl(u32::from(c[4] % 40))?;
    let id = match previous {
        None => gap,
        Some(p) => p.checked_add(1)?.checked_add(gap)?,
    };
    let kind = ShapeKind::from_code(c[5] % 3)?;
    let base = if c[6] & 4 != 0 {
        // Within reach of the origin, so absolute records go `Near`.
        QuantPos::add_offset(
            origin,
            [i16::from_le_bytes([c[8], c[9]]), i16::from_le_bytes([c[10], c[11]]), c[12].into()],
        )
    } else {
        QuantPos::new(i32_at(&c[8..12]), i32_at(&c[12..16]), i32_at(&c[16..20]))
    };
    let pos = match c[6] & 3 {
        // Unchanged, a small move, or anywhere.
        0 | 1 => base,
        2 => QuantPos::new(
            base.x.saturating_add(i32::from(c[13] as i8)),
            base.y.saturating_add(i32::from(c[14] as i8)),
            base.z.saturating_add(i32::from(c[15] as i8)),
        ),
        _ => QuantPos::new(base.y, base.z, base.x),
    };
    // Baselines 1 to 70 ticks back (past 63, too old to use), or none.
    let back = 1 + u64::from(c[7] % 70);
    let has_baseline = c[6] & 3 != 0 && c[6] & 8 == 0;
    let baseline = if has_baseline { tick.checked_sub(back).map(|t| Baseline { tick: t, pos: base }) } else { None };
    // A prior 1 to 16 ticks before the baseline, where the object was before moving
    // about as it did since (a steady move, predicted well), or none.
    let prior = baseline.filter(|_| c[5] & 0x80 != 0).and_then(|b| {
        let tick = b.tick.checked_sub(1 + u64::from(c[5] >> 3 & 15))?;
        let step = |p: i32, b: i32| b.saturating_sub(p.saturating_sub(b) / 2);
        Some(Baseline { tick, pos: QuantPos::new(step(pos.x, b.pos.x), step(pos.y, b.pos.y), step(pos.z, b.pos.z)) })
    });
    Some((StateRecord { id, kind, pos }, baseline, prior))
}

fuzz_target!(|data: &[u8]| {
    let [max, own_flag, t0, t1, t2, t3, t4, t5, o0, o1, o2, o3, rest @ ..] = data else { return };
    let Some((own_bytes, rest)) = rest.split_at_checked(OBJECT) else { return };
    let tick = u64::from_le_bytes([*t0, *t1, *t2, *t3, *t4, *t5, 0, 0]);
    let origin = QuantPos::new(i32_at(&[*o0, *o1, *o2, *o3]), i32_at(&[*o3, *o2, *o1, *o0]).wrapping_neg(), 0);
    let header = UpdateHeader { tick, dilation_permille: 1000, origin };

    // The objects, their states now and their histories.
    let own = if own_flag & 1 == 1 { object(own_bytes, None, tick, origin) } else { None };
    let mut objects = Vec::new();
    let mut previous = None;
    for c in rest.chunks_exact(OBJECT) {
        let Some(o) = object(c, previous, tick, origin) else { break };
        previous = Some(o.0.id);
        // The own object is not among the others.
        if own.is_none_or(|own| own.0.id != o.0.id) {
            objects.push(o);
        }
    }
    let choose = |(s, b, p): &Object| DeltaRecord::choose(s.id, s.kind, s.pos, tick, *b, *p);
    let own_record = own.as_ref().map(choose);
    let records: Vec<DeltaRecord> = objects.iter().map(choose).collect();

    let max = usize::from(*max % 8);
    let mut batch = DatagramBatch::new();
    let mut ends = Vec::new();
    let packed = pack_deltas(&header, own_record.as_ref(), &records, max, &mut batch, &mut ends);
    assert!(batch.len() <= max);
    assert!(packed <= records.len());
    assert!(packed == records.len() || batch.len() == max);
    assert_eq!(ends.len(), batch.len());
    assert_eq!(ends.last().copied().unwrap_or(0), packed);
    // Every datagram after the first carries records of its own.
    assert!(ends.windows(2).all(|w| w[0] < w[1]));
    if max > 0 {
        assert_eq!(batch.is_empty(), records.is_empty() && own.is_none());
    }

    // The client holds every baseline: the states of the history, each received in the
    // update of its tick.
    let mut client = Baselines::default();
    for (state, baseline, prior) in own.iter().chain(&objects) {
        for b in prior.iter().chain(baseline) {
            let past = DeltaRecord { id: state.id, state: RecordState::Absolute { kind: state.kind, pos: b.pos } };
            client.resolve(b.tick, &past).expect("an absolute record always resolves");
        }
    }
    let truth = |id: u64| own.iter().chain(&objects).find(|o| o.0.id == id).map(|o| o.0);

    let mut got = Vec::new();
    let mut resolved = Vec::new();
    for (i, d) in batch.iter().enumerate() {
        assert!(d.len() <= MAX_DATAGRAM);
        assert_eq!(d[1], PacketKind::StateUpdate as u8);
        let update =
            DeltaUpdate::decode_body(&d[HEADER_LEN..d.len() - TAG_LEN]).expect("the packer's datagrams decode");
        assert_eq!(update.header, header);
        assert!(update.records.windows(2).all(|w| w[0].id < w[1].id), "ids strictly increase");
        if let Some(own) = own_record {
            assert_eq!(update.records.iter().filter(|r| **r == own).count(), 1, "the own record in every datagram");
        }
        resolved.clear();
        assert_eq!(client.resolve_update(&update, &mut resolved), 0, "a baseline the client holds is missing");
        for state in &resolved {
            assert_eq!(Some(*state), truth(state.id));
        }
        let others: Vec<_> = update.records.into_iter().filter(|r| own_record.is_none_or(|o| o.id != r.id)).collect();
        let start = if i == 0 { 0 } else { ends[i - 1] };
        assert_eq!(others, records[start..ends[i]]);
        got.extend(others);
    }
    assert_eq!(got, records[..packed]);
});
