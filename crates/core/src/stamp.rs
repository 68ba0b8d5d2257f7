//! Process-unique stamps, for the values whose device copies a backend keeps.

use std::sync::atomic::{AtomicU64, Ordering};

/// A number no other value of this process ever had: a fresh one for every value made
/// and for every clone. A backend that keeps a device copy of a value keys that copy on
/// the stamp (with the value's generation, where it changes), never on an address: once a
/// value is dropped, the next one may be allocated at the same address, and an address
/// key takes it for the first (the GPU parity test met exactly that, the terrain and
/// statics of one world kept on the device for the next world's).
#[derive(Debug)]
pub struct Stamp(u64);

impl Stamp {
    /// A stamp never handed out before.
    pub fn new() -> Stamp {
        static NEXT: AtomicU64 = AtomicU64::new(1);
        Stamp(NEXT.fetch_add(1, Ordering::Relaxed))
    }

    /// Its number.
    pub fn get(&self) -> u64 {
        self.0
    }
}

impl Default for Stamp {
    fn default() -> Stamp {
        Stamp::new()
    }
}

impl Clone for Stamp {
    /// A clone is another value: it gets a stamp of its own.
    fn clone(&self) -> Stamp {
        Stamp::new()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_and_clones_get_stamps_never_seen_before() {
        let a = Stamp::new();
        let b = a.clone();
        let c = Stamp::default();
        assert!(a.get() != b.get() && b.get() != c.get() && a.get() != c.get());
    }
}
