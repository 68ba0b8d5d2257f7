//! Small helpers for writing disjoint elements of a slice from several threads.

use std::marker::PhantomData;

/// A slice that several rayon tasks may write to, each at indices no other task touches
/// at the same time.
///
/// Used where the algorithm guarantees disjointness but the borrow checker cannot see it:
/// the radix sort's scatter (each chunk owns precomputed output positions) and the LBVH
/// refit (a node is written by exactly one thread, after both children are final,
/// ordered by an atomic counter).
pub(crate) struct SharedMut<'a, T> {
    ptr: *mut T,
    len: usize,
    _borrow: PhantomData<&'a mut [T]>,
}

// SAFETY: the wrapper only hands out element access through unsafe methods whose callers
// promise that no two threads touch the same index concurrently; T: Send is what moving
// values across threads needs.
unsafe impl<T: Send> Send for SharedMut<'_, T> {}
unsafe impl<T: Send> Sync for SharedMut<'_, T> {}

impl<'a, T: Copy> SharedMut<'a, T> {
    /// Wraps a mutable slice for the duration of its borrow.
    pub(crate) fn new(slice: &'a mut [T]) -> Self {
        SharedMut { ptr: slice.as_mut_ptr(), len: slice.len(), _borrow: PhantomData }
    }

    /// Writes `value` at `i`.
    ///
    /// # Safety
    /// No other thread may read or write index `i` concurrently, and `i < len`.
    #[inline]
    pub(crate) unsafe fn write(&self, i: usize, value: T) {
        debug_assert!(i < self.len);
        // SAFETY: in bounds and exclusive, by the caller's promise.
        unsafe { self.ptr.add(i).write(value) }
    }

    /// A raw pointer to element `i`, for writing one field of it while another thread
    /// writes a different field.
    ///
    /// # Safety
    /// `i < len`; what the caller does through the pointer must not race.
    #[inline]
    pub(crate) unsafe fn ptr(&self, i: usize) -> *mut T {
        debug_assert!(i < self.len);
        // SAFETY: in bounds by the caller's promise.
        unsafe { self.ptr.add(i) }
    }

    /// Reads index `i`.
    ///
    /// # Safety
    /// No other thread may write index `i` concurrently (its last write must
    /// happen-before this read), and `i < len`.
    #[inline]
    pub(crate) unsafe fn read(&self, i: usize) -> T {
        debug_assert!(i < self.len);
        // SAFETY: in bounds and not concurrently written, by the caller's promise.
        unsafe { self.ptr.add(i).read() }
    }
}
