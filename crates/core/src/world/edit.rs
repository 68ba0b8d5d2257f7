//! Editing dynamics in place while their ids stay ascending, and the record of what an
//! edit changed, so that a device copy applies the change instead of uploading
//! everything.
//!
//! A zone keeps its world from tick to tick (`docs/zones.md`); each tick a few objects
//! arrive (hand-offs, ghosts), a few leave, and the ghosts' states are replaced by their
//! owners'. The physics sums each object's responses in the order of its partners' slots,
//! so a zone's slots must follow entity ids as a scenario's do: [`Dynamics::apply_sorted`]
//! removes, writes and inserts in one pass that keeps them ascending, moving the kept
//! objects with `copy_within` (memory speed), never re-validating or re-hashing them.
//!
//! [`Changes`] says what happened since the last step: which slots came from which
//! (runs), which slots hold states written by the host, and whether actions changed. A
//! backend that holds a device copy made at [`Changes::base_generation`] can bring it up
//! to date with those alone.

use super::{Dynamics, EntityId, ObjectState};
use crate::error::CoreError;

/// One edit of dynamics whose ids ascend by slot (see [`Dynamics::apply_sorted`]).
#[derive(Clone, Debug, Default)]
pub struct SortedEdit {
    /// Slots to remove, ascending.
    pub remove: Vec<u32>,
    /// Whole states written into slots (numbered before the edit), each with the id the
    /// slot holds and its shape and kind: a write moves an object, never remakes it.
    pub write: Vec<(u32, ObjectState)>,
    /// Objects to add, ids ascending, none of them kept by the edit.
    pub insert: Vec<ObjectState>,
}

impl SortedEdit {
    /// Whether the edit changes nothing.
    pub fn is_empty(&self) -> bool {
        self.remove.is_empty() && self.write.is_empty() && self.insert.is_empty()
    }

    /// Forgets everything, keeping the allocations (a zone reuses one edit every tick).
    pub fn clear(&mut self) {
        self.remove.clear();
        self.write.clear();
        self.insert.clear();
    }
}

/// A run of slots that kept their objects through an edit: slots `to..to + len` now hold
/// what slots `from..from + len` held before.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SlotRun {
    /// First slot after the edit.
    pub to: u32,
    /// First slot before it.
    pub from: u32,
    /// Slots in the run.
    pub len: u32,
}

/// What changed in dynamics since their last physics step ([`Dynamics::state_mut`]),
/// when every change since went through a method that records it (see
/// [`Dynamics::changes`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Changes {
    /// [`Dynamics::generation`] right after the step: a device copy made then can apply
    /// these changes.
    pub base_generation: u64,
    /// [`Dynamics::layout_generation`] then.
    pub base_layout: u64,
    /// Objects then.
    pub base_len: usize,
    /// `None`: every slot still holds the object it held. `Some(runs)`: the slots the
    /// runs cover hold objects kept from the slots they name; every other slot holds a
    /// new object, listed in `written`.
    pub moved: Option<Vec<SlotRun>>,
    /// Slots (numbered now) whose whole state the host wrote, new objects included;
    /// ascending, without repeats.
    pub written: Vec<u32>,
    /// Whether any action was set.
    pub actions: bool,
}

impl Changes {
    fn after_step(d: &Dynamics) -> Changes {
        Changes {
            base_generation: d.generation,
            base_layout: d.layout_generation,
            base_len: d.len(),
            moved: None,
            written: Vec::new(),
            actions: false,
        }
    }
}

impl Dynamics {
    /// What changed since the last step, or `None` when something changed that is not
    /// recorded (a spawn, a despawn, a teleport, a second edit that moved slots, or no
    /// step yet): then a device copy must be made again from the whole state.
    pub fn changes(&self) -> Option<&Changes> {
        self.journal.as_ref()
    }

    /// Starts a record of changes at the current generation (called by
    /// [`Dynamics::state_mut`]: a step writes every slot).
    pub(super) fn restart_journal(&mut self) {
        self.journal = Some(Changes::after_step(self));
    }

    /// Whether ids ascend by slot (a scenario's world, a zone's world).
    pub fn ids_ascending(&self) -> bool {
        self.id.windows(2).all(|w| w[0] < w[1])
    }

    /// The slot of `id` by binary search, for dynamics whose ids ascend (a zone's world
    /// changes every tick and would rebuild the slot map each time); on others the answer
    /// may be `None` for an object that is there.
    pub fn slot_in_order(&self, id: EntityId) -> Option<usize> {
        self.id.binary_search(&id).ok()
    }

    /// Removes, writes and inserts in one pass, keeping the ids ascending (see the module
    /// docs); all or nothing. The ids must ascend before (checked in debug builds; a zone
    /// keeps them so). Fails, changing nothing, when a slot is out of range or removed and
    /// written, the removals or insertions do not ascend, a written state's id is not its
    /// slot's, an inserted id is already kept or is `u32::MAX`, or a state is not valid.
    /// Returns where the edit put things ([`EditPlan`]), to edit a column of the
    /// caller's own alike.
    pub fn apply_sorted(&mut self, e: &SortedEdit) -> Result<EditPlan<Vec<u32>, Vec<usize>>, CoreError> {
        debug_assert!(self.ids_ascending(), "apply_sorted needs ascending ids");
        let n = self.len();
        if e.is_empty() {
            return Ok(EditPlan { remove: Vec::new(), at: Vec::new() });
        }
        if !e.remove.windows(2).all(|w| w[0] < w[1]) || e.remove.last().is_some_and(|&s| s as usize >= n) {
            return Err(CoreError::invalid("removed slots", "not ascending or out of range"));
        }
        for &(slot, s) in &e.write {
            let held = self.id.get(slot as usize);
            if held != Some(&s.id) {
                return Err(CoreError::invalid("written slot", format!("slot {slot} holds {held:?}, not {}", s.id.0)));
            }
            if e.remove.binary_search(&slot).is_ok() {
                return Err(CoreError::invalid("written slot", format!("slot {slot} is removed and written")));
            }
            // An object keeps its shape and kind: a write moves it, never remakes it (so
            // a device copy need only take the moving state of a written slot).
            let i = slot as usize;
            if (s.shape, s.half, s.radius, s.kind) != (self.shape[i], self.half[i], self.radius[i], self.kind[i]) {
                return Err(CoreError::invalid("written slot", format!("{} would change its shape or kind", s.id.0)));
            }
            s.validate()?;
        }
        // Where each insertion goes among the kept objects, counted before removals.
        let mut at = Vec::with_capacity(e.insert.len());
        for (i, s) in e.insert.iter().enumerate() {
            s.validate()?;
            if s.id.0 == u32::MAX || (i > 0 && e.insert[i - 1].id >= s.id) {
                return Err(CoreError::invalid("inserted ids", format!("{} is reserved or out of order", s.id.0)));
            }
            let p = self.id.partition_point(|&id| id < s.id);
            if p < n && self.id[p] == s.id && e.remove.binary_search(&(p as u32)).is_err() {
                return Err(CoreError::invalid("entity id", format!("{} is taken", s.id.0)));
            }
            at.push(p);
        }
        // Positions among the kept objects (removals done): an insertion goes before the
        // kept object it names.
        let removed_before = |p: usize| e.remove.partition_point(|&r| (r as usize) < p);
        let at: Vec<usize> = at.iter().map(|&p| p - removed_before(p)).collect();
        let layout_changes = !e.remove.is_empty() || !e.insert.is_empty();
        let runs = layout_changes.then(|| runs(n, &e.remove, &at));

        if layout_changes {
            let plan = EditPlan { remove: &e.remove, at: &at };
            let Dynamics { id, half, radius, shape, kind, action, late, .. } = self;
            let super::late::LateArrays { pos, prev, flags } = late.get_mut();
            // On the calling thread, field after field: zones share a process's cores
            // (and rayon's pool, which the backends' copies use), and moving the nine
            // fields at once on the pool made 4 zones of scenario 3 on one H200's host
            // slower, not faster (moving 0.29–0.41 ms a tick against 0.22–0.25 serial,
            // docs/zones.md).
            macro_rules! each_field {
                ($($field:ident),*) => {$(
                    plan.apply($field, |i| e.insert[i].$field);
                )*};
            }
            each_field!(id, pos, prev, half, radius, shape, kind, action, flags);
        }

        // A written slot's new number: its kept index plus the insertions before it.
        let renumber = |old: usize| {
            let kept = old - removed_before(old);
            kept + at.partition_point(|&p| p <= kept)
        };
        let mut written: Vec<u32> = Vec::with_capacity(e.write.len() + e.insert.len());
        for &(slot, s) in &e.write {
            let to = renumber(slot as usize);
            self.put(to, &s);
            written.push(to as u32);
        }
        written.extend(at.iter().enumerate().map(|(j, &p)| (p + j) as u32));
        written.sort_unstable();
        written.dedup();

        if let Some(last) = e.insert.last() {
            self.next_id = self.next_id.max(last.id.0 + 1);
        }
        self.slot_of.take();
        self.generation += 1;
        if layout_changes {
            self.layout_generation += 1;
        }
        self.journal = match self.journal.take() {
            // A second edit that moves slots would need the runs composed: rare (a zone
            // edits once a tick), so the record is dropped and the next sync is whole.
            Some(j) if j.moved.is_some() && layout_changes => None,
            Some(mut j) if j.written.is_empty() || !layout_changes => {
                j.moved = runs.or(j.moved);
                j.written.extend(written);
                j.written.sort_unstable();
                j.written.dedup();
                Some(j)
            }
            _ => None,
        };
        Ok(EditPlan { remove: e.remove.clone(), at })
    }

    /// Writes a whole state into `slot` (already checked).
    fn put(&mut self, slot: usize, s: &ObjectState) {
        let late = self.late.get_mut();
        late.pos[slot] = s.pos;
        late.prev[slot] = s.prev;
        late.flags[slot] = s.flags;
        self.half[slot] = s.half;
        self.radius[slot] = s.radius;
        self.shape[slot] = s.shape;
        self.kind[slot] = s.kind;
        self.action[slot] = s.action;
    }
}

/// Where an edit removed and inserted, in a form that edits any column alike: a caller
/// that keeps a column of its own beside the dynamics (a zone's owned flags) applies
/// the plan [`Dynamics::apply_sorted`] returned to it.
#[derive(Clone, Copy, Debug)]
pub struct EditPlan<R, A> {
    /// Slots removed, ascending.
    remove: R,
    /// Where each insertion went among the kept elements.
    at: A,
}

impl<R: AsRef<[u32]>, A: AsRef<[usize]>> EditPlan<R, A> {
    /// Removes and inserts in `v` as the edit did in the dynamics: insertion `j` (in the
    /// edit's order) gets `value(j)`.
    pub fn apply<T: Copy>(&self, v: &mut Vec<T>, value: impl Fn(usize) -> T) {
        compact(v, self.remove.as_ref());
        spread(v, self.at.as_ref(), value);
    }
}

/// Removes the elements at `remove` (ascending indices), moving the rest down in runs.
fn compact<T: Copy>(v: &mut Vec<T>, remove: &[u32]) {
    let Some(&first) = remove.first() else { return };
    let mut w = first as usize;
    for (i, &r) in remove.iter().enumerate() {
        let start = r as usize + 1;
        let end = remove.get(i + 1).map_or(v.len(), |&x| x as usize);
        v.copy_within(start..end, w);
        w += end - start;
    }
    v.truncate(w);
}

/// Inserts `value(j)` before element `at[j]` (ascending; equal positions keep `j`'s
/// order), moving the rest up in runs from the back.
fn spread<T: Copy>(v: &mut Vec<T>, at: &[usize], value: impl Fn(usize) -> T) {
    if at.is_empty() {
        return;
    }
    let old = v.len();
    v.resize(old + at.len(), value(0));
    let mut end = old;
    for (j, &p) in at.iter().enumerate().rev() {
        v.copy_within(p..end, p + j + 1);
        v[p + j] = value(j);
        end = p;
    }
}

/// The runs of kept slots of an edit of `n` slots that removes `remove` and inserts
/// before the kept positions `at`.
fn runs(n: usize, remove: &[u32], at: &[usize]) -> Vec<SlotRun> {
    let mut out = Vec::with_capacity(remove.len() + at.len() + 1);
    // Kept segments of the old slots: (old start, kept start, len).
    let mut kept = 0usize;
    let mut old = 0usize;
    let mut j = 0usize;
    for end in remove.iter().map(|&r| r as usize).chain(std::iter::once(n)) {
        // Old slots old..end are kept, numbered kept..kept + (end - old).
        let (mut o, mut k) = (old, kept);
        let stop = kept + (end - old);
        while k < stop {
            // Insertions before kept position k shift everything from k on.
            while j < at.len() && at[j] <= k {
                j += 1;
            }
            let next = at.get(j).copied().unwrap_or(usize::MAX).min(stop);
            out.push(SlotRun { to: (k + j) as u32, from: o as u32, len: (next - k) as u32 });
            o += next - k;
            k = next;
        }
        kept = stop;
        old = end + 1;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{ObjectKind, ShapeKind, Vec3};

    fn state(id: u32, x: f32) -> ObjectState {
        ObjectState {
            id: EntityId(id),
            kind: ObjectKind::Npc,
            shape: ShapeKind::Sphere,
            half: Vec3::splat(0.5),
            radius: 0.5,
            pos: Vec3::new(x, 1.0, 0.0),
            prev: Vec3::new(x, 1.0, 0.0),
            action: 0,
            flags: 0,
        }
    }

    fn dynamics(ids: &[u32]) -> Dynamics {
        let mut d = Dynamics::default();
        d.insert_all(ids.iter().map(|&i| state(i, i as f32))).unwrap();
        d.state_mut();
        d
    }

    /// A small deterministic generator (the crate's tests avoid a rand dependency).
    struct Lcg(u64);
    impl Lcg {
        fn next(&mut self, m: u64) -> u64 {
            self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (self.0 >> 33) % m
        }
    }

    #[test]
    fn random_edits_equal_a_rebuild_and_their_runs_replay_them() {
        let mut rng = Lcg(7);
        for round in 0..400 {
            let n = rng.next(40) as u32;
            let ids: Vec<u32> = (0..n).map(|i| i * 3 + 1).collect();
            let mut d = dynamics(&ids);
            let before: Vec<ObjectState> = (0..d.len()).map(|s| d.state_of(s)).collect();
            let mut e = SortedEdit::default();
            for s in 0..n {
                match rng.next(5) {
                    0 => e.remove.push(s),
                    1 => e.write.push((s, state(ids[s as usize], 100.0 + s as f32))),
                    _ => {}
                }
            }
            // New ids between and around the old ones (never equal to a kept one).
            for c in 0..(n * 3 + 3) {
                if c % 3 != 1 && rng.next(6) == 0 {
                    e.insert.push(state(c, -(c as f32)));
                }
            }
            d.apply_sorted(&e).unwrap();
            // The rebuild: kept (written or not) plus inserted, sorted by id.
            let mut want: Vec<ObjectState> = before
                .iter()
                .enumerate()
                .filter(|(s, _)| !e.remove.contains(&(*s as u32)))
                .map(|(s, o)| e.write.iter().find(|w| w.0 == s as u32).map_or(*o, |w| w.1))
                .chain(e.insert.iter().copied())
                .collect();
            want.sort_by_key(|o| o.id);
            let got: Vec<ObjectState> = (0..d.len()).map(|s| d.state_of(s)).collect();
            assert_eq!(got, want, "round {round}");
            assert!(d.ids_ascending());
            // Replaying the record on the old arrays gives the new ones.
            let c = d.changes().expect("recorded").clone();
            let mut replay: Vec<Option<ObjectState>> = vec![None; d.len()];
            for r in c.moved.clone().unwrap_or_else(|| vec![SlotRun { to: 0, from: 0, len: n }]) {
                for i in 0..r.len as usize {
                    replay[r.to as usize + i] = Some(before[r.from as usize + i]);
                }
            }
            for &w in &c.written {
                replay[w as usize] = Some(d.state_of(w as usize));
            }
            let replay: Vec<ObjectState> = replay.into_iter().map(|o| o.expect("every slot covered")).collect();
            assert_eq!(replay, got, "round {round}: runs and written slots rebuild the edit");
            assert_eq!(d.slot(EntityId(u32::MAX - 1)), None);
            for (s, o) in got.iter().enumerate() {
                assert_eq!(d.slot(o.id), Some(s), "the slot map follows");
            }
        }
    }

    #[test]
    fn bad_edits_change_nothing() {
        let mut d = dynamics(&[1, 4, 9]);
        let g = d.generation();
        let bad = [
            SortedEdit { remove: vec![2, 1], ..SortedEdit::default() },
            SortedEdit { remove: vec![3], ..SortedEdit::default() },
            SortedEdit { write: vec![(0, state(4, 0.0))], ..SortedEdit::default() },
            SortedEdit { remove: vec![1], write: vec![(1, state(4, 0.0))], ..SortedEdit::default() },
            SortedEdit { insert: vec![state(4, 0.0)], ..SortedEdit::default() },
            SortedEdit { insert: vec![state(6, 0.0), state(5, 0.0)], ..SortedEdit::default() },
            SortedEdit { insert: vec![state(u32::MAX, 0.0)], ..SortedEdit::default() },
            SortedEdit { insert: vec![ObjectState { pos: Vec3::NAN, ..state(5, 0.0) }], ..SortedEdit::default() },
            SortedEdit { write: vec![(1, ObjectState { radius: 0.6, ..state(4, 0.0) })], ..SortedEdit::default() },
            SortedEdit {
                write: vec![(1, ObjectState { kind: ObjectKind::User, ..state(4, 0.0) })],
                ..SortedEdit::default()
            },
        ];
        for e in bad {
            assert!(d.apply_sorted(&e).is_err(), "{e:?}");
            assert_eq!(d.generation(), g);
            assert_eq!(d.ids(), &[EntityId(1), EntityId(4), EntityId(9)]);
        }
        // Removing a slot and inserting its id again is a replacement, allowed.
        d.apply_sorted(&SortedEdit { remove: vec![1], insert: vec![state(4, 7.0)], ..SortedEdit::default() }).unwrap();
        assert_eq!(d.state_of(1).pos.x, 7.0);
    }

    #[test]
    fn the_record_lasts_until_an_unrecorded_change() {
        let mut d = dynamics(&[1, 2, 3]);
        let c = d.changes().unwrap().clone();
        assert_eq!((c.base_generation, c.moved, c.written.len(), c.actions), (d.generation(), None, 0, false));
        d.apply_sorted(&SortedEdit { write: vec![(1, state(2, 5.0))], ..SortedEdit::default() }).unwrap();
        d.set_action_at(0, crate::Action::from_bits_truncate(1));
        let c = d.changes().unwrap();
        assert_eq!((c.written.as_slice(), c.actions, c.moved.is_none()), (&[1][..], true, true));
        d.apply_sorted(&SortedEdit { insert: vec![state(0, 0.0)], ..SortedEdit::default() }).unwrap();
        assert!(d.changes().is_none(), "slots moved after a write: not composed, dropped");
        d.state_mut();
        assert!(d.changes().is_some(), "a step starts a new record");
        d.teleport(EntityId(1), Vec3::ONE);
        assert!(d.changes().is_none(), "a teleport is not recorded");
    }
}
