//! Pair lists in the pipeline's canonical form, and their comparison.
//!
//! A pair is packed into a `u64` as `first << 32 | second`, the form the `cpu` backend's
//! broad phase produces: `(lower slot, higher slot)` for two dynamic objects and
//! `(dynamic slot, static primitive)` for an object against scenery. Sorted lists of
//! packed pairs compare as sets with one linear merge.

use myriad_core::Aabb;

/// Packs a pair as `a << 32 | b`.
#[inline]
pub fn pack(a: u32, b: u32) -> u64 {
    (a as u64) << 32 | b as u64
}

/// The two halves of a packed pair.
#[inline]
pub fn unpack(p: u64) -> (u32, u32) {
    ((p >> 32) as u32, p as u32)
}

/// The broad phase's answer for one set of boxes: both lists sorted ascending, no
/// duplicates.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Pairs {
    /// Overlapping dynamic boxes, `(lower slot, higher slot)`.
    pub dynamic: Vec<u64>,
    /// A dynamic box overlapping a static primitive's, `(slot, primitive)`.
    pub statics: Vec<u64>,
}

impl Pairs {
    /// Both lists empty, their buffers kept.
    pub fn clear(&mut self) {
        self.dynamic.clear();
        self.statics.clear();
    }

    /// Every overlapping pair by testing all of them: the reference the tests check both
    /// broad phases against. Quadratic; for a few thousand boxes at most.
    pub fn brute_force(dynamic: &[Aabb], statics: &[Aabb]) -> Pairs {
        let mut out = Pairs::default();
        for (i, a) in dynamic.iter().enumerate() {
            for (j, b) in dynamic.iter().enumerate().skip(i + 1) {
                if a.overlaps(b) {
                    out.dynamic.push(pack(i as u32, j as u32));
                }
            }
            for (p, b) in statics.iter().enumerate() {
                if a.overlaps(b) {
                    out.statics.push(pack(i as u32, p as u32));
                }
            }
        }
        out
    }

    /// Sorts both lists and removes duplicates (for answers collected unordered).
    pub fn canonicalize(&mut self) {
        for v in [&mut self.dynamic, &mut self.statics] {
            v.sort_unstable();
            v.dedup();
        }
    }
}

/// How two pair lists differ.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct PairDiff {
    /// Pairs only in the first list.
    pub only_first: Vec<u64>,
    /// Pairs only in the second list.
    pub only_second: Vec<u64>,
}

impl PairDiff {
    /// The difference of two sorted, duplicate-free lists.
    pub fn of(first: &[u64], second: &[u64]) -> PairDiff {
        debug_assert!(first.is_sorted() && second.is_sorted());
        let mut d = PairDiff::default();
        let (mut i, mut j) = (0, 0);
        while i < first.len() && j < second.len() {
            match first[i].cmp(&second[j]) {
                std::cmp::Ordering::Less => {
                    d.only_first.push(first[i]);
                    i += 1;
                }
                std::cmp::Ordering::Greater => {
                    d.only_second.push(second[j]);
                    j += 1;
                }
                std::cmp::Ordering::Equal => {
                    i += 1;
                    j += 1;
                }
            }
        }
        d.only_first.extend_from_slice(&first[i..]);
        d.only_second.extend_from_slice(&second[j..]);
        d
    }

    /// Whether the lists were equal.
    pub fn is_empty(&self) -> bool {
        self.only_first.is_empty() && self.only_second.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn diff_finds_both_sides() {
        let d = PairDiff::of(&[1, 2, 5, 9], &[2, 3, 9, 10]);
        assert_eq!(d.only_first, vec![1, 5]);
        assert_eq!(d.only_second, vec![3, 10]);
        assert!(PairDiff::of(&[4, 7], &[4, 7]).is_empty());
        assert_eq!(unpack(pack(7, 3)), (7, 3));
    }
}
