//! The dynamics' previous positions and flag bits, which a backend may leave where its
//! step computed them until something reads them ([`HeldState`]).
//!
//! A GPU server tick reads neither on the host: the replicas read the device's copy,
//! the interest and the players' own positions need only the current positions. Leaving
//! them on the device spares the bus 13 of the 26 bytes an object that a step would
//! otherwise bring back every tick. Every reader still sees them: the first read after
//! such a step fetches them (once, from any thread), and every change to them fetches
//! them first, so no caller can tell held arrays from arrays that are here, except by
//! the time the first read takes.

use std::fmt;
use std::sync::{Arc, Mutex, OnceLock};

use glam::Vec3;

/// Previous positions and flag bits of every dynamic object, as a backend's step left
/// them where it computed them (a device's memory); see the module docs.
pub trait HeldState: Send + Sync {
    /// Writes them into `prev` and `flags` (one element a slot, in slot order, as many
    /// as the dynamics held when the step ended). Called at most once, from any thread.
    /// A holder that cannot read them back panics: the state is lost (a failed device),
    /// and no world may go on with stale values in their place.
    fn fetch(&self, prev: &mut [Vec3], flags: &mut [u8]);
}

/// The arrays that may be held elsewhere.
#[derive(Clone, Debug, Default, PartialEq)]
pub(super) struct LateArrays {
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
            holder.fetch(&mut arrays.prev, &mut arrays.flags);
            arrays
        })
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
    #[cfg(test)]
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

    /// Holds `prev` (each element `v`) and `flags` (each `f`), counting its fetches.
    struct Holder {
        v: f32,
        f: u8,
        fetches: AtomicUsize,
    }

    impl HeldState for Holder {
        fn fetch(&self, prev: &mut [Vec3], flags: &mut [u8]) {
            self.fetches.fetch_add(1, Ordering::Relaxed);
            prev.fill(Vec3::splat(self.v));
            flags.fill(self.f);
        }
    }

    fn holder(v: f32, f: u8) -> Arc<Holder> {
        Arc::new(Holder { v, f, fetches: AtomicUsize::new(0) })
    }

    fn here(n: usize) -> Late {
        Late::new(LateArrays { prev: vec![Vec3::ZERO; n], flags: vec![0; n] })
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
