//! The host side of the incremental upload, without a GPU: the records the world keeps
//! are accepted, bad ones refused, and the staged words, read the way the two kernels of
//! `kernels/patch.cu` read them (mirrored here operation for operation), turn the old
//! arrays into the new world's.

use myriad_core::world::{SlotRun, SortedEdit};
use myriad_core::{Action, EntityId, ObjectKind, ObjectState, ShapeKind, Vec3};

use super::*;

/// A small deterministic generator (no rand dependency in this crate).
struct Lcg(u64);
impl Lcg {
    fn next(&mut self, m: u64) -> u64 {
        self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (self.0 >> 33) % m
    }
}

/// A valid state of every shape and both kinds, by `v`.
fn state(id: u32, v: u32) -> ObjectState {
    let x = v as f32 * 0.5;
    let (shape, half, radius) = match v % 3 {
        0 => (ShapeKind::Sphere, Vec3::splat(0.5), 0.5),
        1 => (ShapeKind::Box, Vec3::new(0.4, 0.6, 0.3), 0.0),
        _ => (ShapeKind::Capsule, Vec3::new(0.3, 0.9, 0.3), 0.3),
    };
    ObjectState {
        id: EntityId(id),
        kind: if v.is_multiple_of(2) { ObjectKind::Npc } else { ObjectKind::User },
        shape,
        half,
        radius,
        pos: Vec3::new(x, 1.0 + x, -x),
        prev: Vec3::new(x - 0.25, 1.0 + x, -x),
        action: (v % 32) as u8,
        flags: (v % 4) as u8,
    }
}

/// One object's nine device arrays, as the words and bytes the device holds.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Row {
    pos: [u32; 3],
    prev: [u32; 3],
    half: [u32; 3],
    radius: u32,
    shape: u8,
    kind: u8,
    id: u32,
    action: u8,
    flags: u8,
}

fn rows(d: &Dynamics) -> Vec<Row> {
    let bits = |v: Vec3| v.to_array().map(f32::to_bits);
    (0..d.len())
        .map(|s| Row {
            pos: bits(d.positions()[s]),
            prev: bits(d.prev_positions()[s]),
            half: bits(d.half_extents()[s]),
            radius: d.radii()[s].to_bits(),
            shape: d.shapes()[s] as u8,
            kind: d.kinds()[s] as u8,
            id: d.ids()[s].0,
            action: d.actions()[s],
            flags: d.flags()[s],
        })
        .collect()
}

/// `k_patch_gather` on the host: the old slot of new slot `i`, by the kernel's binary
/// search over the staged runs.
fn gather_source(runs: &[u32], nruns: u32, i: u32) -> Option<u32> {
    let (mut lo, mut hi) = (0u32, nruns);
    while lo < hi {
        let mid = lo + (hi - lo) / 2;
        if runs[3 * mid as usize] <= i {
            lo = mid + 1;
        } else {
            hi = mid;
        }
    }
    if lo == 0 {
        return None;
    }
    let r = 3 * (lo - 1) as usize;
    let (to, from, len) = (runs[r], runs[r + 1], runs[r + 2]);
    (i - to < len).then_some(from + (i - to))
}

/// Both kernels on the host, over the staged words: the old rows moved and the written
/// states put in place; `None` where neither wrote (stale on the device).
fn replay(old: &[Row], n: usize, words: &[u32], nruns: usize, moved: bool) -> Vec<Option<Row>> {
    let mut new: Vec<Option<Row>> = if moved {
        (0..n as u32).map(|i| gather_source(words, nruns as u32, i).map(|j| old[j as usize])).collect()
    } else {
        old.iter().copied().map(Some).collect()
    };
    let staged = &words[RUN_WORDS * nruns..];
    let w = staged.len() / STATE_WORDS;
    assert_eq!(staged.len(), STATE_WORDS * w, "whole states staged");
    let v = &staged[w..];
    for k in 0..w {
        let s = staged[k] as usize;
        let three = |at: usize| [v[at + 3 * k], v[at + 3 * k + 1], v[at + 3 * k + 2]];
        let bytes = v[11 * w + k].to_le_bytes();
        new[s] = Some(Row {
            pos: three(0),
            prev: three(3 * w),
            half: three(6 * w),
            radius: v[9 * w + k],
            id: v[10 * w + k],
            shape: bytes[0],
            kind: bytes[1],
            action: bytes[2],
            flags: bytes[3],
        });
    }
    new
}

/// Dynamics of `ids` (ascending) right after a step: the record starts there.
fn stepped(ids: &[u32]) -> Dynamics {
    let mut d = Dynamics::default();
    d.insert_all(ids.iter().map(|&i| state(i, i))).unwrap();
    d.state_mut();
    d
}

#[test]
fn staged_words_replayed_as_the_kernels_do_rebuild_every_edit() {
    let mut rng = Lcg(5);
    let mut words = Vec::new();
    for round in 0..300 {
        let n = rng.next(50) as u32;
        let ids: Vec<u32> = (0..n).map(|i| i * 4 + 2).collect();
        let mut d = stepped(&ids);
        let old = rows(&d);
        let mut e = SortedEdit::default();
        for s in 0..n {
            match rng.next(6) {
                0 => e.remove.push(s),
                1 => {
                    // A write moves an object; its shape and kind stay (apply_sorted checks).
                    let (mut o, was) = (state(ids[s as usize], 1000 + s + round), d.state_of(s as usize));
                    (o.shape, o.half, o.radius, o.kind) = (was.shape, was.half, was.radius, was.kind);
                    e.write.push((s, o));
                }
                _ => {}
            }
        }
        // Some rounds only write (no slot moves), some move everything.
        if round % 5 != 0 {
            for c in 0..(n * 4 + 5) {
                if c % 4 != 2 && rng.next(5) == 0 {
                    e.insert.push(state(c, 2000 + c + round));
                }
            }
        }
        d.apply_sorted(&e).unwrap();
        for _ in 0..rng.next(3) {
            if !d.is_empty() {
                let s = rng.next(d.len() as u64) as usize;
                d.set_action_at(s, Action::from_bits_truncate(rng.next(32) as u8));
            }
        }
        let c = d.changes().expect("recorded").clone();
        assert!(applicable(&c, n as usize, d.len()), "round {round}: the world's own record applies");
        let nruns = pack(&c, &d, &mut words);
        assert_eq!(nruns, c.moved.as_ref().map_or(0, Vec::len));
        assert_eq!(words.len(), RUN_WORDS * nruns + STATE_WORDS * c.written.len(), "round {round}");
        let got = replay(&old, d.len(), &words, nruns, c.moved.is_some());
        // The actions travel whole when any was set; the rest must be exact already.
        let want = rows(&d);
        for (s, (g, w)) in got.iter().zip(&want).enumerate() {
            let g = g.unwrap_or_else(|| panic!("round {round}: slot {s} left stale"));
            let g = if c.actions { Row { action: w.action, ..g } } else { g };
            assert_eq!(g, *w, "round {round}, slot {s}");
        }
    }
}

#[test]
fn the_gather_search_finds_each_run_and_nothing_between() {
    // New slots 0..10: 0..3 from 5..8, 3 and 4 new, 5..7 from 0..2, 7..10 new.
    let runs = [0, 5, 3, 5, 0, 2];
    let want = [Some(5), Some(6), Some(7), None, None, Some(0), Some(1), None, None, None];
    for (i, w) in want.iter().enumerate() {
        assert_eq!(gather_source(&runs, 2, i as u32), *w, "slot {i}");
    }
    assert_eq!(gather_source(&[], 0, 0), None, "no runs: every slot is new");
}

fn record(old: usize, moved: Option<Vec<SlotRun>>, written: Vec<u32>) -> Changes {
    Changes { base_generation: 1, base_layout: 1, base_len: old, moved, written, actions: false }
}

#[test]
fn records_that_do_not_fit_are_refused() {
    let run = |to, from, len| SlotRun { to, from, len };
    // Old 4 slots, new 5: slots 0..2 from 0..2, 2 new, 3..5 from 2..4.
    let good = record(4, Some(vec![run(0, 0, 2), run(3, 2, 2)]), vec![2]);
    assert!(applicable(&good, 4, 5));
    let bad = [
        ("a new slot not written", record(4, Some(vec![run(0, 0, 2), run(3, 2, 2)]), vec![]), 4, 5),
        ("runs overlapping", record(4, Some(vec![run(0, 0, 3), run(2, 2, 2)]), vec![4]), 4, 5),
        ("runs out of order", record(4, Some(vec![run(3, 2, 2), run(0, 0, 2)]), vec![2]), 4, 5),
        ("a run past the new length", record(4, Some(vec![run(0, 0, 2), run(3, 2, 2)]), vec![2]), 4, 4),
        ("a run past the old length", record(3, Some(vec![run(0, 0, 2), run(3, 2, 2)]), vec![2]), 3, 5),
        ("a new slot at the end not written", record(4, Some(vec![run(0, 0, 4)]), vec![]), 4, 5),
        ("written slots repeated", record(4, Some(vec![run(0, 0, 2), run(3, 2, 2)]), vec![2, 2]), 4, 5),
        ("a written slot out of range", record(5, None, vec![5]), 5, 5),
        ("lengths differ with no runs", record(4, None, vec![]), 4, 5),
    ];
    for (what, c, old, new) in bad {
        assert!(!applicable(&c, old, new), "{what}");
    }
}
