//! A reusable arena of datagrams: one byte vector and the end offset of each datagram,
//! so building thousands of datagrams per tick allocates nothing once warm.

use std::ops::Range;

/// Many datagrams stored back to back.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct DatagramBatch {
    bytes: Vec<u8>,
    ends: Vec<usize>,
}

impl DatagramBatch {
    /// An empty batch.
    pub fn new() -> Self {
        Self::default()
    }

    /// Removes every datagram, keeping the memory.
    pub fn clear(&mut self) {
        self.bytes.clear();
        self.ends.clear();
    }

    /// Number of datagrams.
    pub fn len(&self) -> usize {
        self.ends.len()
    }

    /// Whether the batch holds no datagram.
    pub fn is_empty(&self) -> bool {
        self.ends.is_empty()
    }

    /// Total bytes of all datagrams.
    pub fn total_bytes(&self) -> usize {
        self.ends.last().copied().unwrap_or(0)
    }

    fn range(&self, i: usize) -> Option<Range<usize>> {
        let end = *self.ends.get(i)?;
        let start = if i == 0 { 0 } else { self.ends[i - 1] };
        Some(start..end)
    }

    /// Datagram `i`.
    pub fn get(&self, i: usize) -> Option<&[u8]> {
        self.range(i).map(|r| &self.bytes[r])
    }

    /// Datagram `i`, mutable (for sealing in place).
    pub fn get_mut(&mut self, i: usize) -> Option<&mut [u8]> {
        self.range(i).map(|r| &mut self.bytes[r])
    }

    /// The datagrams in order.
    pub fn iter(&self) -> impl Iterator<Item = &[u8]> + '_ {
        (0..self.len()).filter_map(|i| self.get(i))
    }

    /// Appends a copy of `datagram`.
    pub fn push(&mut self, datagram: &[u8]) {
        self.bytes.truncate(self.total_bytes());
        self.bytes.extend_from_slice(datagram);
        self.ends.push(self.bytes.len());
    }

    /// Starts a datagram of at most `capacity` bytes and returns its zeroed space;
    /// [`finish`](Self::finish) sets its final length. A `begin` without `finish` is
    /// discarded by the next `begin`.
    pub fn begin(&mut self, capacity: usize) -> &mut [u8] {
        let start = self.total_bytes();
        self.bytes.truncate(start);
        self.bytes.resize(start + capacity, 0);
        &mut self.bytes[start..]
    }

    /// Ends the datagram started by [`begin`](Self::begin) at `len` bytes (clamped to
    /// the space `begin` returned).
    pub fn finish(&mut self, len: usize) {
        let start = self.total_bytes();
        let end = (start + len).min(self.bytes.len());
        self.bytes.truncate(end);
        self.ends.push(end);
    }

    /// Calls `f` on every datagram, mutably, stopping at the first error.
    pub fn try_for_each_mut<E>(&mut self, mut f: impl FnMut(&mut [u8]) -> Result<(), E>) -> Result<(), E> {
        let mut start = 0;
        for &end in &self.ends {
            f(&mut self.bytes[start..end])?;
            start = end;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn begin_finish_push() {
        let mut b = DatagramBatch::new();
        b.push(&[1, 2]);
        let space = b.begin(10);
        assert_eq!(space.len(), 10);
        space[0] = 7;
        b.finish(3);
        b.begin(5)[0] = 9; // abandoned
        b.push(&[4]);
        let all: Vec<&[u8]> = b.iter().collect();
        assert_eq!(all, vec![&[1u8, 2][..], &[7, 0, 0], &[4]]);
        assert_eq!(b.total_bytes(), 6);
        b.clear();
        assert!(b.is_empty() && b.get(0).is_none());
    }
}
