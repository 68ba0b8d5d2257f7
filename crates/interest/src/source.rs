//! The inputs: read access to the world's objects and the AOI query result.

use myriad_protocol::ShapeKind;

/// Read access to the world's dynamic objects by slot index (the index the physics
/// AOI query returns). The server implements it over its structure-of-arrays world;
/// [`SoaObjects`] is a ready-made implementation over plain slices.
pub trait ObjectSource: Sync {
    /// The object in `slot`: its id, kind and position, or `None` for an invalid slot.
    fn get(&self, slot: u32) -> Option<(u64, ShapeKind, [f32; 3])>;

    /// Hints that `slot` will be read soon. AOI lists hit the object arrays at random
    /// slots, so the gather loop is bound by cache misses; prefetching a few slots
    /// ahead hides them. The default does nothing.
    #[inline]
    fn prefetch(&self, slot: u32) {
        let _ = slot;
    }
}

/// Objects as three parallel slices.
#[derive(Debug, Clone, Copy)]
pub struct SoaObjects<'a> {
    /// Object ids, by slot.
    pub ids: &'a [u64],
    /// Object kinds, by slot.
    pub kinds: &'a [ShapeKind],
    /// Positions in world units, by slot.
    pub positions: &'a [[f32; 3]],
}

impl ObjectSource for SoaObjects<'_> {
    #[inline]
    fn get(&self, slot: u32) -> Option<(u64, ShapeKind, [f32; 3])> {
        let i = slot as usize;
        Some((*self.ids.get(i)?, *self.kinds.get(i)?, *self.positions.get(i)?))
    }

    #[inline]
    fn prefetch(&self, slot: u32) {
        let i = slot as usize;
        prefetch_read(self.ids.get(i));
        prefetch_read(self.kinds.get(i));
        prefetch_read(self.positions.get(i));
    }
}

/// Asks the CPU to bring `value`'s cache line in (x86_64; a no-op elsewhere).
#[inline(always)]
pub(crate) fn prefetch_read<T>(value: Option<&T>) {
    #[cfg(target_arch = "x86_64")]
    if let Some(v) = value {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        // SAFETY: a prefetch is only a hint; it never faults and reads nothing
        // architecturally, and the pointer comes from a live reference anyway.
        unsafe { _mm_prefetch::<_MM_HINT_T0>((v as *const T).cast::<i8>()) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = value;
}

/// The AOI query result in compressed sparse row form: the objects seen by subscriber
/// `i` are `objects[offsets[i] .. offsets[i + 1]]`, so `offsets` has one entry more
/// than there are subscribers.
#[derive(Debug, Clone, Copy)]
pub struct AoiLists<'a> {
    /// Start of each subscriber's list in `objects`, plus the end of the last one.
    pub offsets: &'a [u32],
    /// Slot indices of the objects in view, list after list.
    pub objects: &'a [u32],
}

impl<'a> AoiLists<'a> {
    /// Number of lists.
    pub fn len(&self) -> usize {
        self.offsets.len().saturating_sub(1)
    }

    /// Whether there is no list.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// List `i`, or `None` if the offsets are out of order or out of range (a broken
    /// query result must not crash the server).
    pub fn get(&self, i: usize) -> Option<&'a [u32]> {
        let start = *self.offsets.get(i)? as usize;
        let end = *self.offsets.get(i + 1)? as usize;
        self.objects.get(start..end)
    }
}
