//! An open-addressing hash table from object id to a `u64` key (a replica's track index),
//! used as per-thread scratch.
//!
//! Why: matching this tick's AOI list against last tick's tracks by sorting would cost
//! more than the rest of a player's update. Each replica keeps its track ids as a plain
//! list (read sequentially, which the hardware prefetcher handles); the thread loads that
//! list into this table, which stays hot in cache from one player to the next, and looks
//! every candidate up in it. A stamp per slot marks occupancy, so clearing is O(1).

#[derive(Debug, Clone, Copy, Default)]
struct Slot {
    id: u64,
    key: u64,
    /// Occupied when equal to the table's current stamp.
    stamp: u32,
    /// Whether [`StaleTable::take`] has given this id out since it was inserted.
    taken: bool,
}

/// Map from object id to staleness key.
#[derive(Debug, Default)]
pub(crate) struct StaleTable {
    slots: Vec<Slot>,
    stamp: u32,
    len: usize,
}

impl StaleTable {
    #[inline]
    fn start(&self, id: u64) -> usize {
        // Fibonacci hashing; the table length is a power of two.
        let bits = self.slots.len().trailing_zeros();
        (id.wrapping_mul(0x9e37_79b9_7f4a_7c15) >> (64 - bits)) as usize
    }

    /// Empties the table, keeping its memory.
    pub(crate) fn clear(&mut self) {
        self.len = 0;
        self.stamp = self.stamp.wrapping_add(1);
        if self.stamp == 0 {
            // After 2^32 clears, old stamps could alias: wipe them once.
            self.slots.fill(Slot::default());
            self.stamp = 1;
        }
    }

    /// Empties the table and makes room for `n` entries at a load of at most 1/2.
    pub(crate) fn reset(&mut self, n: usize) {
        let want = (n * 2).max(16).next_power_of_two();
        if self.slots.len() < want {
            self.slots = vec![Slot::default(); want];
            self.stamp = 0;
        }
        self.clear();
    }

    /// Number of entries.
    #[cfg(test)]
    pub(crate) fn len(&self) -> usize {
        self.len
    }

    /// Whether the table holds no entry.
    #[cfg(test)]
    pub(crate) fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Index of `id`'s slot, or of the empty slot where it would go.
    #[inline]
    fn find(&self, id: u64) -> usize {
        let mask = self.slots.len() - 1;
        let mut i = self.start(id);
        loop {
            let s = &self.slots[i];
            if s.stamp != self.stamp || s.id == id {
                return i;
            }
            i = (i + 1) & mask;
        }
    }

    /// The key of `id`.
    pub(crate) fn get(&self, id: u64) -> Option<u64> {
        if self.len == 0 {
            return None;
        }
        let s = &self.slots[self.find(id)];
        (s.stamp == self.stamp).then_some(s.key)
    }

    /// Inserts `id` with `key`; returns false (changing nothing) if `id` is present.
    /// The caller sized the table with [`reset`](Self::reset) for every insert.
    #[inline]
    pub(crate) fn insert(&mut self, id: u64, key: u64) -> bool {
        if self.len * 2 >= self.slots.len() {
            self.grow();
        }
        let i = self.find(id);
        let stamp = self.stamp;
        let s = &mut self.slots[i];
        if s.stamp == stamp {
            return false;
        }
        *s = Slot { id, key, stamp, taken: false };
        self.len += 1;
        true
    }

    /// The key of `id` the first time it is taken since it was inserted, or `fresh` for
    /// an id not in the table (which is inserted, taken); `None` when `id` was taken
    /// already (a duplicate). One probe where a lookup and a second table to drop
    /// duplicates took two. The caller sized the table for every id it takes.
    #[inline]
    pub(crate) fn take(&mut self, id: u64, fresh: u64) -> Option<u64> {
        if self.len * 2 >= self.slots.len() {
            self.grow();
        }
        let i = self.find(id);
        let stamp = self.stamp;
        let s = &mut self.slots[i];
        if s.stamp != stamp {
            *s = Slot { id, key: fresh, stamp, taken: true };
            self.len += 1;
            return Some(fresh);
        }
        if s.taken {
            return None;
        }
        s.taken = true;
        Some(s.key)
    }

    /// Doubles the table (only if a caller under-sized it: keeps inserts total).
    fn grow(&mut self) {
        let old = std::mem::take(&mut self.slots);
        let stamp = self.stamp;
        self.slots = vec![Slot::default(); (old.len() * 2).max(16)];
        self.stamp = 1;
        self.len = 0;
        for s in old.into_iter().filter(|s| s.stamp == stamp) {
            self.insert(s.id, s.key);
            let i = self.find(s.id);
            self.slots[i].taken = s.taken;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    #[test]
    fn behaves_like_a_map_across_clears() {
        let mut t = StaleTable::default();
        let mut x = 0x1234_5678_9abc_def0u64;
        for round in 0..50u64 {
            t.reset(100);
            let mut model = HashMap::new();
            for _ in 0..300 {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                // Few distinct ids, so duplicates happen; u64::MAX is a valid id too.
                let id = if x.is_multiple_of(97) { u64::MAX } else { x % 400 };
                let inserted = t.insert(id, round);
                assert_eq!(inserted, !model.contains_key(&id));
                model.entry(id).or_insert(round);
            }
            assert_eq!(t.len(), model.len());
            for id in (0..400).chain([u64::MAX]) {
                assert_eq!(t.get(id), model.get(&id).copied());
            }
        }
        t.clear();
        assert!(t.is_empty() && t.get(3).is_none());
    }

    #[test]
    fn take_gives_each_id_once_with_its_stored_or_fresh_key() {
        let mut t = StaleTable::default();
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        let mut next_id = move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x % 300
        };
        for round in 0..40u64 {
            // Under-sized on purpose in odd rounds: growing keeps what was taken.
            t.reset(if round % 2 == 0 { 400 } else { 4 });
            let mut stored = HashMap::new();
            for _ in 0..100 {
                let id = next_id();
                if t.insert(id, round * 1000 + id) {
                    stored.insert(id, round * 1000 + id);
                }
            }
            let mut taken = HashMap::new();
            for _ in 0..300 {
                let id = next_id();
                let want = if taken.contains_key(&id) { None } else { Some(*stored.get(&id).unwrap_or(&7)) };
                assert_eq!(t.take(id, 7), want, "round {round}, id {id}");
                taken.insert(id, ());
            }
        }
    }
}
