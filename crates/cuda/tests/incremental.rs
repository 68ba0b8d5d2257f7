//! A zone's ticks on the CUDA backends: between steps the world is edited in place
//! (`Dynamics::apply_sorted`: objects removed, ghosts' states overwritten, new objects
//! inserted between the kept ones, actions set), and the backends must bring their device
//! copy up to date from the world's record of those changes alone, ending every tick in
//! the `cpu` backend's state, bit for bit.
//!
//! Without a GPU these skip (saying so); with `MYRIAD_REQUIRE_CUDA=1` they fail instead.

mod common;

use common::cuda_backends;
use myriad_core::rng::hash3;
use myriad_core::world::SortedEdit;
use myriad_core::{Aabb, Action, Dynamics, EntityId, ObjectState, Placement, Vec3, World};
use myriad_physics::conformance::crowded;
use myriad_physics::{AoiResults, BackendKind, TickConstants, create_cpu_backend};

/// Bytes the full upload of the dynamics sends per object when slots changed meaning:
/// half extents (12), radius (4), shape, kind (1 each), id (4), then positions and
/// previous positions (12 each), action and flags (1 each).
const FULL_BYTES: u64 = 48;
/// Bytes the incremental upload sends per run of kept slots (to, from, len).
const RUN_BYTES: u64 = 12;
/// Bytes it sends per written state: the slot, three vectors, radius, id, one word of
/// the four byte-sized fields.
const STATE_BYTES: u64 = 52;

/// The crowded test world with odd ids only, so that new ids fit between kept ones.
fn spaced_world() -> World {
    let mut w = crowded(31, Placement::Uniform);
    let d = &w.dynamics;
    let states: Vec<ObjectState> =
        (0..d.len()).map(|s| ObjectState { id: EntityId(2 * d.ids()[s].0 + 1), ..d.state_of(s) }).collect();
    w.dynamics = Dynamics::default();
    w.dynamics.insert_all(states.into_iter()).expect("the spaced world builds");
    assert!(w.dynamics.ids_ascending());
    w
}

/// Tick `t`'s edit of `w` (the same for every world equal to `w`): a few slots removed,
/// a few states overwritten with the same object moved a little (a ghost's owner's
/// state), a few new objects above kept ones under ids free between them; on
/// `write_only` ticks nothing moves slots.
fn edit_for(w: &World, t: u64, write_only: bool) -> SortedEdit {
    let d = &w.dynamics;
    let n = d.len() as u64;
    let pick = |k: u64| (hash3(0x7a11, t, k) % n) as u32;
    let mut e = SortedEdit::default();
    if !write_only {
        e.remove = (0..3).map(pick).collect();
        e.remove.sort_unstable();
        e.remove.dedup();
    }
    for k in 10..15 {
        let s = pick(k);
        if e.remove.binary_search(&s).is_err() && e.write.iter().all(|(x, _)| *x != s) {
            let mut o = d.state_of(s as usize);
            let nudge = Vec3::new(0.02, 0.0, -0.03) * (1 + k % 3) as f32;
            (o.pos, o.prev) = (o.pos + nudge, o.prev + nudge * 0.5);
            o.flags = 0;
            e.write.push((s, o));
        }
    }
    if !write_only {
        for k in 20..24 {
            let s = pick(k) as usize;
            // The id just below a kept one: free unless an earlier tick took it.
            let Some(id) = d.ids()[s].0.checked_sub(1).map(EntityId) else { continue };
            if d.slot_in_order(id).is_none() && e.insert.iter().all(|o| o.id != id) {
                let mut o = d.state_of(s);
                o.id = id;
                o.pos.y += 2.5;
                (o.prev, o.action, o.flags) = (o.pos, (hash3(3, t, k) & 0x1f) as u8, 0);
                e.insert.push(o);
            }
        }
        e.insert.sort_by_key(|o| o.id);
    }
    e
}

/// The edit, actions and (on some ticks) a teleport applied to one world.
fn change(w: &mut World, e: &SortedEdit, t: u64, teleport: bool) {
    w.dynamics.apply_sorted(e).expect("the edit applies");
    let n = w.dynamics.len() as u64;
    for k in 0..4 {
        let s = (hash3(0xac7, t, k) % n) as usize;
        w.dynamics.set_action_at(s, Action::from_bits_truncate((hash3(9, t, k) & 0x1f) as u8));
    }
    if teleport {
        let id = w.dynamics.ids()[(t as usize * 7) % n as usize];
        let c = w.bounds.center();
        assert!(w.dynamics.teleport(id, Vec3::new(c.x, c.y + 4.0, c.z)));
    }
}

fn aoi_boxes(w: &World) -> Vec<Aabb> {
    let c = w.bounds.center();
    let p = w.dynamics.positions()[0];
    [c, p].iter().map(|&m| Aabb { min: m - Vec3::splat(10.0), max: m + Vec3::splat(10.0) }).collect()
}

/// 60 ticks of zone edits on each CUDA backend next to `cpu`: the same state hash after
/// every step; on edited ticks the backend sent only the record's runs, written states
/// and actions (or that plus a full upload, when the step was redone for a pair list
/// that outgrew its buffer), never the whole world; after a teleport (an unrecorded
/// change) it sent everything and still agrees; an AOI query between the edit and the
/// step sees the edited world and leaves the step nothing to send.
#[test]
fn zone_edits_between_steps_travel_alone_and_keep_the_cpu_world() {
    let Some(mut gpus) = cuda_backends("zone_edits_between_steps_travel_alone_and_keep_the_cpu_world") else {
        return;
    };
    let k = TickConstants::default();
    let start = spaced_world();
    for gpu in &mut gpus {
        let name = gpu.kind();
        let mut cpu = create_cpu_backend(BackendKind::Cpu).unwrap();
        let (mut want, mut got) = (start.clone(), start.clone());
        let (mut incremental, mut redone) = (0, 0);
        for t in 0..60u64 {
            let teleport = t % 10 == 7;
            let query = t % 10 == 3;
            let mut first = None;
            if t > 0 {
                let e = edit_for(&want, t, t % 10 == 5);
                change(&mut want, &e, t, teleport);
                change(&mut got, &e, t, teleport);
                let c = got.dynamics.changes();
                assert_eq!(c.is_none(), teleport, "tick {t}: only the teleport goes unrecorded");
                first = c.map(|c| {
                    let runs = c.moved.as_ref().map_or(0, Vec::len) as u64;
                    let actions = if c.actions { got.dynamics.len() as u64 } else { 0 };
                    RUN_BYTES * runs + STATE_BYTES * c.written.len() as u64 + actions
                });
            }
            if query {
                let (mut a, mut b) = (AoiResults::default(), AoiResults::default());
                cpu.query_aoi(&want, &aoi_boxes(&want), &mut a).unwrap();
                gpu.query_aoi(&got, &aoi_boxes(&got), &mut b).unwrap();
                assert_eq!(b, a, "{name} tick {t}: the query sees another world");
                assert!(!a.objects.is_empty(), "the query must find objects");
            }
            cpu.step(&mut want, &k).unwrap();
            let report = gpu.step(&mut got, &k).unwrap();
            assert_eq!(got.state_hash(), want.state_hash(), "{name} differs from cpu at tick {t}");
            let full = FULL_BYTES * got.dynamics.len() as u64;
            let sent = report.upload_bytes;
            match first {
                _ if t == 0 => assert!(sent >= full, "{name}: the first step sends everything, sent {sent}"),
                None => assert!(sent >= full, "{name} tick {t}: after a teleport everything travels, sent {sent}"),
                Some(_) if query => {
                    assert!(sent == 0 || sent == full, "{name} tick {t}: the query already sent the edit, {sent}")
                }
                Some(inc) => {
                    assert!(sent == inc || sent == inc + full, "{name} tick {t}: sent {sent}, the edit is {inc}");
                    assert!(inc * 8 < full, "{name} tick {t}: the edit ({inc} bytes) is not small next to {full}");
                    incremental += 1;
                    redone += usize::from(sent != inc);
                }
            }
        }
        assert_ne!(want.state_hash(), start.state_hash(), "the world must have moved");
        println!("{name}: {incremental} ticks patched ({redone} redone for pair buffers), same hash as cpu");
    }
}
