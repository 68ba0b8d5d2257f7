//! The dynamics' positions, previous positions and flag bits, which a backend may leave
//! where its step computed them until something reads them ([`HeldState`]).
//!
//! A GPU server tick reads none of them whole on the host: the replicas and the
//! interest read the device's copy, and the players' own positions (the centres of their
//! areas of interest, a few percent of the objects) come back alone
//! ([`HeldState::positions_at`]). Leaving them on the device spares the bus 25 of the 26
//! bytes an object that a step would otherwise bring back every tick (the actions
//! still come back). Every reader still sees them: the first read of the arrays after
//! such a step fetches them (once, from any thread), and every change to them fetches
//! them first, so no caller can tell held arrays from arrays that are here, except by
//! the time the first read takes.

use std::fmt;
use std::sync::{Arc, Mutex, OnceLock};

use glam::Vec3;

/// Positions, previous positions and flag bits of every dynamic object, as a backend's
/// step left them where it computed them (a device's memory); see the module docs.
pub trait HeldState: Send + Sync {
    /// Writes them into `pos`, `prev` and `flags` (one element a slot, in slot order, as
    /// many as the dynamics held when the step ended). Called at most once, from any
    /// thread. A holder that cannot read them back panics: the state is lost (a failed
    /// device), and no world may go on with stale values in their place.
    fn fetch(&self, pos: &mut [Vec3], prev: &mut [Vec3], flags: &mut [u8]);

    /// Writes the positions of `slots` (each below the number of objects held) into
    /// `out`, in order, leaving everything held. Called any number of times, from any
    /// thread, until the arrays are fetched; panics as [`HeldState::fetch`] does.
    fn positions_at(&self, slots: &[u32], out: &mut [Vec3]);
}

/// The arrays that may be held elsewhere.
#[derive(Clone, Debug, Default, PartialEq)]
pub(super) struct LateArrays {
    /// Current positions.
    pub pos: Vec<Vec3>,
    /// Positions one step ago.
    pub prev: Vec<Vec3>,
    /// Flag bits (see [`super::flags`]).
    pub flags: Vec<u8>,
}

/// [`LateArrays`] either here or held by a [`HeldState`] until first read.
///
/// Invariant: exactly one of `here` and `held` has the arrays. While they are held, the
/// vectors in `held` keep their memory (and length) with stale contents, for the fetch
/// to write into.
pub(super) struct Late {
    here: OnceLock<LateArrays>,
    held: Mutex<Option<(LateArrays, Arc<dyn HeldState>)>>,
}

impl Late {
    /// Arrays that are here.
    pub fn new(arrays: LateArrays) -> Late {
        Late { here: OnceLock::from(arrays), held: Mutex::new(None) }
    }

    /// The arrays, fetched from their holder first if they are held.
    pub fn get(&self) -> &LateArrays {
        self.here.get_or_init(|| {
            // The guard drops at the end of this statement: a holder that panics leaves
            // no lock behind (and, its values lost, no arrays: later reads panic too).
            let taken = self.held.lock().unwrap_or_else(|p| p.into_inner()).take();
            let (mut arrays, holder) = taken.expect("the late arrays are either here or held");
            holder.fetch(&mut arrays.pos, &mut arrays.prev, &mut arrays.flags);
            arrays
        })
    }

    /// The positions of `slots` into `out` (as long as `slots`), from the holder
    /// without fetching the arrays when they are held.
    pub fn positions_at(&self, slots: &[u32], out: &mut [Vec3]) {
        let held = {
            let guard = self.held.lock().unwrap_or_else(|p| p.into_inner());
            guard.as_ref().map(|(arrays, holder)| (arrays.pos.len(), holder.clone()))
        };
        // Not held (or fetched by another reader since): read them here. The lock is not
        // kept while the holder reads: a fetch on another thread may go on meanwhile, and
        // this holder's values stay valid while it is alive.
        let Some((n, holder)) = held else {
            let pos = &self.get().pos;
            for (o, &s) in out.iter_mut().zip(slots) {
                *o = pos[s as usize];
            }
            return;
        };
        if let Some(&s) = slots.iter().find(|&&s| s as usize >= n) {
            panic!("slot {s} out of range: {n} objects");
        }
        holder.positions_at(slots, out);
    }

    /// The arrays to change, fetched first if they are held.
    pub fn get_mut(&mut self) -> &mut LateArrays {
        self.get();
        self.here.get_mut().expect("fetched just above")
    }

    /// Leaves the arrays' values with `holder` (their memory stays here). A holder
    /// before it is forgotten without fetching: its values are older.
    pub fn hold(&mut self, holder: Arc<dyn HeldState>) {
        let held = self.held.get_mut().unwrap_or_else(|p| p.into_inner());
        let arrays = match self.here.take() {
            Some(arrays) => arrays,
            None => held.take().expect("the late arrays are either here or held").0,
        };
        *held = Some((arrays, holder));
    }

    /// Whether the arrays are held elsewhere (not yet fetched).
    pub fn is_held(&self) -> bool {
        self.here.get().is_none()
    }
}

impl Default for Late {
    fn default() -> Late {
        Late::new(LateArrays::default())
    }
}

impl Clone for Late {
    /// A copy of the arrays, fetched first if they are held (a clone owes its holder
    /// nothing).
    fn clone(&self) -> Late {
        Late::new(self.get().clone())
    }
}

impl fmt::Debug for Late {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        // Printing does not fetch.
        match self.here.get() {
            Some(arrays) => arrays.fmt(f),
            None => f.write_str("LateArrays { held by the backend's device }"),
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicUsize, Ordering};

    use super::*;

    /// Holds positions (slot `s` at `v + s` on x), `prev` (each element `v`) and `flags`
    /// (each `f`), counting its fetches and its reads of some positions.
    struct Holder {
        v: f32,
        f: u8,
        fetches: AtomicUsize,
        gathers: AtomicUsize,
    }

    impl Holder {
        fn at(&self, slot: usize) -> Vec3 {
            Vec3::new(self.v + slot as f32, 0.0, 0.0)
        }
    }

    impl HeldState for Holder {
        fn fetch(&self, pos: &mut [Vec3], prev: &mut [Vec3], flags: &mut [u8]) {
            self.fetches.fetch_add(1, Ordering::Relaxed);
            for (s, p) in pos.iter_mut().enumerate() {
                *p = self.at(s);
            }
            prev.fill(Vec3::splat(self.v));
            flags.fill(self.f);
        }

        fn positions_at(&self, slots: &[u32], out: &mut [Vec3]) {
            self.gathers.fetch_add(1, Ordering::Relaxed);
            for (o, &s) in out.iter_mut().zip(slots) {
                *o = self.at(s as usize);
            }
        }
    }

    fn holder(v: f32, f: u8) -> Arc<Holder> {
        Arc::new(Holder { v, f, fetches: AtomicUsize::new(0), gathers: AtomicUsize::new(0) })
    }

    fn here(n: usize) -> Late {
        Late::new(LateArrays { pos: vec![Vec3::ZERO; n], prev: vec![Vec3::ZERO; n], flags: vec![0; n] })
    }

    fn some_positions(late: &Late, slots: &[u32]) -> Vec<Vec3> {
        let mut out = vec![Vec3::NAN; slots.len()];
        late.positions_at(slots, &mut out);
        out
    }

    #[test]
    fn some_positions_come_from_the_holder_without_fetching_and_equal_the_fetched_ones() {
        let mut late = here(5);
        let h = holder(10.0, 1);
        late.hold(h.clone());
        let slots = [4, 0, 2, 2];
        let read = some_positions(&late, &slots);
        std::thread::scope(|s| {
            for _ in 0..3 {
                s.spawn(|| assert_eq!(some_positions(&late, &slots), read));
            }
        });
        assert_eq!((h.fetches.load(Ordering::Relaxed), h.gathers.load(Ordering::Relaxed)), (0, 4));
        assert!(late.is_held(), "reading some positions leaves the arrays held");
        let fetched: Vec<Vec3> = slots.iter().map(|&s| late.get().pos[s as usize]).collect();
        assert_eq!(read, fetched);
        assert_eq!(read[0], Vec3::new(14.0, 0.0, 0.0));
        // Once fetched, they are read here.
        assert_eq!(some_positions(&late, &slots), read);
        assert_eq!((h.fetches.load(Ordering::Relaxed), h.gathers.load(Ordering::Relaxed)), (1, 4));
        assert!(some_positions(&late, &[]).is_empty());
    }

    #[test]
    #[should_panic(expected = "slot 5 out of range: 5 objects")]
    fn a_slot_out_of_range_panics_before_the_holder_reads() {
        let mut late = here(5);
        late.hold(holder(1.0, 0));
        some_positions(&late, &[1, 5]);
    }

    #[test]
    fn held_arrays_are_fetched_once_at_the_first_read_into_their_own_memory() {
        let mut late = here(3);
        let memory = late.get().prev.as_ptr();
        let h = holder(2.0, 1);
        late.hold(h.clone());
        assert!(late.is_held());
        assert_eq!(h.fetches.load(Ordering::Relaxed), 0, "holding fetches nothing");
        assert_eq!(format!("{late:?}"), "LateArrays { held by the backend's device }", "nor does printing");
        // Readers on several threads at once: one fetch.
        std::thread::scope(|s| {
            for _ in 0..4 {
                s.spawn(|| assert_eq!(late.get().prev, vec![Vec3::splat(2.0); 3]));
            }
        });
        assert_eq!(late.get().flags, vec![1; 3]);
        assert_eq!(late.get().pos, (0..3).map(|s| h.at(s)).collect::<Vec<_>>());
        assert_eq!(h.fetches.load(Ordering::Relaxed), 1);
        assert_eq!(late.get().prev.as_ptr(), memory, "fetched into the memory it had");
        assert!(!late.is_held());
    }

    #[test]
    fn a_newer_holder_replaces_an_older_one_unfetched_and_changes_fetch_first() {
        let mut late = here(2);
        let (older, newer) = (holder(1.0, 1), holder(5.0, 2));
        late.hold(older.clone());
        late.hold(newer.clone());
        late.get_mut().prev[0] = Vec3::ONE;
        assert_eq!(older.fetches.load(Ordering::Relaxed), 0, "the older values are never read");
        assert_eq!(newer.fetches.load(Ordering::Relaxed), 1, "a change starts from the newest values");
        assert_eq!(late.get().prev, vec![Vec3::ONE, Vec3::splat(5.0)]);
        assert_eq!(late.get().flags, vec![2, 2]);
    }

    #[test]
    fn a_clone_of_held_arrays_fetches_them_and_owes_the_holder_nothing() {
        let mut late = here(2);
        let h = holder(3.0, 1);
        late.hold(h.clone());
        let copy = late.clone();
        assert_eq!(h.fetches.load(Ordering::Relaxed), 1);
        assert!(!copy.is_held() && !late.is_held());
        assert_eq!(copy.get(), late.get());
        drop(late);
        assert_eq!(Arc::strong_count(&h), 1, "neither copy keeps the holder");
    }
}
