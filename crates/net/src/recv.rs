//! Receive buffers: one contiguous allocation of fixed-size slots, reused every call.

use std::net::{Ipv4Addr, SocketAddr};

/// Bytes per receive slot. Larger than the protocol's 1200-byte limit so that an
/// oversized datagram is recognised (and dropped) rather than silently cut short.
pub const MAX_RECV: usize = 1536;

/// Datagrams received by one [`Endpoint::recv_batch`](crate::Endpoint::recv_batch).
#[derive(Debug, Clone)]
pub struct RecvBatch {
    pub(crate) buf: Vec<u8>,
    pub(crate) lens: Vec<usize>,
    pub(crate) addrs: Vec<SocketAddr>,
    pub(crate) len: usize,
}

impl RecvBatch {
    /// Room for `capacity` datagrams per call (at least 1).
    pub fn new(capacity: usize) -> Self {
        let capacity = capacity.max(1);
        Self {
            buf: vec![0; capacity * MAX_RECV],
            lens: vec![0; capacity],
            addrs: vec![SocketAddr::from((Ipv4Addr::UNSPECIFIED, 0)); capacity],
            len: 0,
        }
    }

    /// Most datagrams one call can return.
    pub fn capacity(&self) -> usize {
        self.lens.len()
    }

    /// Datagrams held.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether none are held.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Datagram `i`: sender and bytes.
    pub fn get(&self, i: usize) -> Option<(SocketAddr, &[u8])> {
        if i >= self.len {
            return None;
        }
        let start = i * MAX_RECV;
        Some((self.addrs[i], &self.buf[start..start + self.lens[i]]))
    }

    /// Datagram `i`, mutable, so it can be opened (decrypted) in place.
    pub fn get_mut(&mut self, i: usize) -> Option<(SocketAddr, &mut [u8])> {
        if i >= self.len {
            return None;
        }
        let start = i * MAX_RECV;
        Some((self.addrs[i], &mut self.buf[start..start + self.lens[i]]))
    }

    /// The datagrams in arrival order.
    pub fn iter(&self) -> impl Iterator<Item = (SocketAddr, &[u8])> + '_ {
        (0..self.len).filter_map(|i| self.get(i))
    }

    /// Keeps the datagrams for which `keep` is true, in order (used to drop
    /// truncated ones after a call).
    pub(crate) fn retain_by_index(&mut self, mut keep: impl FnMut(usize) -> bool) {
        let mut w = 0;
        for r in 0..self.len {
            if keep(r) {
                if w != r {
                    self.buf.copy_within(r * MAX_RECV..r * MAX_RECV + self.lens[r], w * MAX_RECV);
                    self.lens[w] = self.lens[r];
                    self.addrs[w] = self.addrs[r];
                }
                w += 1;
            }
        }
        self.len = w;
    }
}
