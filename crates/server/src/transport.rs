//! Where the tick's datagrams come from and go to: the [`Transport`] trait, the UDP
//! endpoint behind it, and an in-memory transport that lets the whole tick run in a
//! test without sockets.

use std::collections::VecDeque;
use std::io;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex, MutexGuard};

use myriad_net::{Endpoint, RecvBatch};

/// Datagrams taken from the socket per `recvmmsg` call.
pub const RECV_BATCH: usize = 1024;

/// A datagram transport as the tick loop uses it: non-blocking batches in and out.
pub trait Transport: Send {
    /// Receives one batch of queued datagrams (at most [`RECV_BATCH`]), calling `each`
    /// with the sender and the bytes (which it may decrypt in place) for every one.
    /// Returns how many were taken; 0 means nothing is queued. Never blocks.
    fn receive(&mut self, each: &mut dyn FnMut(SocketAddr, &mut [u8])) -> io::Result<usize>;

    /// Sends a prefix of `out`, as much as the transport takes now; returns its length
    /// (0 when the transport is full). Never blocks.
    fn send(&mut self, out: &[(SocketAddr, &[u8])]) -> io::Result<usize>;

    /// The address clients send to.
    fn local_addr(&self) -> SocketAddr;
}

/// The UDP endpoint (`recvmmsg`/`sendmmsg`) as a [`Transport`].
#[derive(Debug)]
pub struct UdpTransport {
    endpoint: Endpoint,
    batch: RecvBatch,
    /// The endpoint's count of oversized datagrams already reported to the metrics.
    oversized_seen: u64,
}

impl UdpTransport {
    /// Wraps a bound endpoint.
    pub fn new(endpoint: Endpoint) -> Self {
        UdpTransport { endpoint, batch: RecvBatch::new(RECV_BATCH), oversized_seen: 0 }
    }
}

impl Transport for UdpTransport {
    fn receive(&mut self, each: &mut dyn FnMut(SocketAddr, &mut [u8])) -> io::Result<usize> {
        let n = self.endpoint.recv_batch(&mut self.batch)?;
        // Datagrams too large for a receive slot never reach `each`: the endpoint drops
        // and counts them. Report them with the ones `inbound` finds over 1200 bytes.
        let oversized = self.endpoint.stats().truncated;
        if oversized > self.oversized_seen {
            metrics::counter!("myriad_packets_dropped_total", "reason" => "oversized")
                .increment(oversized - self.oversized_seen);
            self.oversized_seen = oversized;
        }
        for i in 0..n {
            if let Some((from, bytes)) = self.batch.get_mut(i) {
                each(from, bytes);
            }
        }
        Ok(n)
    }

    fn send(&mut self, out: &[(SocketAddr, &[u8])]) -> io::Result<usize> {
        self.endpoint.send_batch(out)
    }

    fn local_addr(&self) -> SocketAddr {
        self.endpoint.local_addr()
    }
}

/// Both directions of a [`MemoryTransport`].
#[derive(Debug, Default)]
pub struct MemoryQueues {
    /// Datagrams for the server, oldest first: `(from, bytes)`.
    pub inbox: VecDeque<(SocketAddr, Vec<u8>)>,
    /// Datagrams the server sent, oldest first: `(to, bytes)`.
    pub outbox: Vec<(SocketAddr, Vec<u8>)>,
    /// Most datagrams the server may send before the transport reports itself full
    /// (`None`: unlimited). Lets a test exercise a full send buffer.
    pub send_capacity: Option<usize>,
}

/// An in-memory [`Transport`]: clones share the same queues, so a test keeps one clone,
/// hands the other to the tick loop, pushes datagrams into the inbox and reads what the
/// server sent from the outbox.
#[derive(Debug, Clone)]
pub struct MemoryTransport {
    queues: Arc<Mutex<MemoryQueues>>,
    addr: SocketAddr,
}

impl MemoryTransport {
    /// An empty transport that pretends to listen on `addr`.
    pub fn new(addr: SocketAddr) -> Self {
        MemoryTransport { queues: Arc::default(), addr }
    }

    /// The shared queues (lock held until the guard drops).
    pub fn queues(&self) -> MutexGuard<'_, MemoryQueues> {
        // A panic elsewhere while holding the lock leaves plain data behind: keep going.
        self.queues.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Queues a datagram for the server.
    pub fn push(&self, from: SocketAddr, datagram: Vec<u8>) {
        self.queues().inbox.push_back((from, datagram));
    }

    /// Takes everything the server sent so far.
    pub fn take_sent(&self) -> Vec<(SocketAddr, Vec<u8>)> {
        std::mem::take(&mut self.queues().outbox)
    }
}

impl Transport for MemoryTransport {
    fn receive(&mut self, each: &mut dyn FnMut(SocketAddr, &mut [u8])) -> io::Result<usize> {
        // Take the batch out first: `each` may run for a while, and a test thread may
        // want to push meanwhile.
        let batch: Vec<_> = {
            let mut q = self.queues();
            let n = q.inbox.len().min(RECV_BATCH);
            q.inbox.drain(..n).collect()
        };
        for (from, mut bytes) in batch.iter().cloned() {
            each(from, &mut bytes);
        }
        Ok(batch.len())
    }

    fn send(&mut self, out: &[(SocketAddr, &[u8])]) -> io::Result<usize> {
        let mut q = self.queues();
        let room = q.send_capacity.map_or(out.len(), |c| c.saturating_sub(q.outbox.len()));
        let n = room.min(out.len());
        q.outbox.extend(out[..n].iter().map(|(to, d)| (*to, d.to_vec())));
        Ok(n)
    }

    fn local_addr(&self) -> SocketAddr {
        self.addr
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn memory_transport_delivers_in_order_and_respects_capacity() {
        let addr: SocketAddr = "127.0.0.2:7777".parse().unwrap();
        let client: SocketAddr = "127.0.0.1:5000".parse().unwrap();
        let test_side = MemoryTransport::new(addr);
        let mut server_side = test_side.clone();
        test_side.push(client, vec![1]);
        test_side.push(client, vec![2, 2]);
        let mut seen = Vec::new();
        let n = server_side.receive(&mut |from, b| seen.push((from, b.to_vec()))).unwrap();
        assert_eq!(n, 2);
        assert_eq!(seen, vec![(client, vec![1]), (client, vec![2, 2])]);
        assert_eq!(server_side.receive(&mut |_, _| unreachable!()).unwrap(), 0);

        test_side.queues().send_capacity = Some(1);
        let out = [(client, &[9u8][..]), (client, &[8u8][..])];
        assert_eq!(server_side.send(&out).unwrap(), 1);
        assert_eq!(server_side.send(&out[1..]).unwrap(), 0, "full");
        assert_eq!(test_side.take_sent(), vec![(client, vec![9])]);
        assert_eq!(server_side.local_addr(), addr);
    }
}
