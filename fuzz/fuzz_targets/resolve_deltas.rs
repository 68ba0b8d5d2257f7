//! A client's `Baselines` fed an arbitrary sequence of decoded delta updates (each body
//! prefixed by its `u16` length; any tick, any record): resolving never panics, every
//! record either resolves or is counted as skipped, and what resolves is what a model
//! that keeps every state forever says: an absolute record its own state, a relative
//! one its baseline's position (moved by the delta) at exactly `tick - back`, a
//! predicted one its baseline moved along its move since the prior at `tick - back -
//! prior` (`predict`), then by the delta; a record whose baseline (or prior) the model
//! lacks is skipped, never applied to another state.
#![no_main]

use std::collections::HashMap;

use libfuzzer_sys::fuzz_target;
use myriad_protocol::{Baselines, DeltaUpdate, QuantPos, RecordState, predict};

/// `from + d`, saturated at the `i32` range.
fn moved(from: [i64; 3], d: [i16; 3]) -> QuantPos {
    let at = |a: i64, d: i16| (a + i64::from(d)).clamp(i32::MIN.into(), i32::MAX.into()) as i32;
    QuantPos::new(at(from[0], d[0]), at(from[1], d[1]), at(from[2], d[2]))
}

fuzz_target!(|data: &[u8]| {
    let mut client = Baselines::default();
    // (id, tick) → position of every state resolved so far.
    let mut model: HashMap<(u64, u64), QuantPos> = HashMap::new();
    let mut states = Vec::new();
    let mut rest = data;
    while let [l0, l1, tail @ ..] = rest {
        let len = usize::from(u16::from_le_bytes([*l0, *l1])).min(tail.len());
        let (body, tail) = tail.split_at(len);
        rest = tail;
        let Ok(update) = DeltaUpdate::decode_body(body) else { continue };
        let tick = update.header.tick;
        states.clear();
        let skipped = client.resolve_update(&update, &mut states);
        assert_eq!(states.len() + skipped, update.records.len());
        // The resolved states are the records' in order, less the skipped ones.
        let mut resolved = states.iter();
        for record in &update.records {
            let expected = match record.state {
                RecordState::Absolute { pos, .. } => Some(pos),
                RecordState::Delta { back, d } => tick.checked_sub(u64::from(back)).and_then(|at| {
                    let b = model.get(&(record.id, at))?;
                    Some(moved([b.x, b.y, b.z].map(i64::from), d))
                }),
                RecordState::Predicted { back, prior, d } => tick.checked_sub(u64::from(back)).and_then(|at| {
                    let b = model.get(&(record.id, at))?;
                    let p = model.get(&(record.id, at.checked_sub(u64::from(prior))?))?;
                    Some(moved(predict(*b, *p, back, prior), d))
                }),
                RecordState::Same { back } => {
                    tick.checked_sub(u64::from(back)).and_then(|at| model.get(&(record.id, at)).copied())
                }
            };
            // The client forgets states over 63 ticks old; the model does not. So a
            // record the model lacks a baseline for is skipped, and one it has may be.
            let Some(expected) = expected else { continue };
            if let RecordState::Absolute { kind, .. } = record.state {
                let state = resolved.next().expect("an absolute record always resolves");
                assert_eq!((state.id, state.kind, state.pos), (record.id, kind, expected));
                model.insert((record.id, tick), expected);
            } else if let Some(state) = resolved.as_slice().first().filter(|s| s.id == record.id) {
                assert_eq!(state.pos, expected, "a record applied to another state than its baseline");
                resolved.next();
                model.insert((record.id, tick), expected);
            }
        }
        assert!(resolved.next().is_none(), "a record resolved that has no baseline");
    }
});
