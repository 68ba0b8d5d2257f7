//! Where the tick's datagrams come from and go to: the [`Transport`] trait, the UDP
//! endpoint behind it, and an in-memory transport that lets the whole tick run in a
//! test without sockets.

use std::collections::VecDeque;
use std::io;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex, MutexGuard};

use myriad_net::{Endpoint, RecvBatch};
use rayon::prelude::*;

use crate::gate::{Refusal, SessionDirectory};

/// Datagrams taken from the socket per `recvmmsg` call.
pub const RECV_BATCH: usize = 1024;

/// What one [`Transport::send`] did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Sent {
    /// Datagrams handed to the network.
    pub datagrams: usize,
    /// Their bytes.
    pub bytes: u64,
}

/// What a gating transport's gate did since the tick last asked
/// ([`Transport::gate_counts`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct GateCounts {
    /// Datagrams taken from the network (before the gate).
    pub taken: u64,
    /// Datagrams the gate refused over a session's budget.
    pub over_budget: u64,
}

/// A datagram transport as the tick loop uses it: non-blocking batches in and out.
///
/// A transport either hands over everything it receives, for the tick to gate
/// ([`crate::gate`]) inline, or gates on a thread of its own ([`Transport::gates`]):
/// then the tick publishes the sessions to gate against and takes only what passed.
pub trait Transport: Send {
    /// Receives one batch of queued datagrams per socket (at most [`RECV_BATCH`] each),
    /// calling `each` with the sender and the bytes of every one (lent for the call: the
    /// caller copies what it keeps). Returns how many were taken; 0 means nothing is
    /// queued. Never blocks.
    fn receive(&mut self, each: &mut dyn FnMut(SocketAddr, &[u8])) -> io::Result<usize>;

    /// Sends as much of `out` as the network takes now, retrying briefly while a socket
    /// buffer is full; what is left is dropped (the caller counts it). Never blocks for
    /// long. The datagrams sent need not be a prefix of `out` when several sockets send
    /// in parallel.
    fn send(&mut self, out: &[(SocketAddr, &[u8])]) -> io::Result<Sent>;

    /// The sending side as lanes, one per socket: several threads send at once, each on
    /// a lane of its own ([`Transport::send`] spreads one list over them).
    fn lanes(&mut self) -> Vec<&mut dyn Lane>;

    /// The address clients send to.
    fn local_addr(&self) -> SocketAddr;

    /// Whether what [`Transport::receive`] hands over has passed the gate already.
    fn gates(&self) -> bool {
        false
    }

    /// For a gating transport: the tick whose budget arriving datagrams spend, and the
    /// sessions to gate against when they changed (`None`: the last ones hold).
    fn publish(&mut self, _tick: u64, _directory: Option<Arc<SessionDirectory>>) {}

    /// For a gating transport: what its gate did since the last call.
    fn gate_counts(&mut self) -> GateCounts {
        GateCounts::default()
    }
}

/// One socket's sending side ([`Transport::lanes`]).
pub trait Lane: Send {
    /// Sends as much of `out` as the socket takes now, as [`Transport::send`] does.
    fn transmit(&mut self, out: &[(SocketAddr, &[u8])]) -> io::Result<Sent>;
}

impl Lane for Endpoint {
    fn transmit(&mut self, out: &[(SocketAddr, &[u8])]) -> io::Result<Sent> {
        send_all(self, out)
    }
}

/// Below this many datagrams a tick's send stays on one socket: waking the other
/// senders costs more than it saves.
const PARALLEL_SEND_MIN: usize = 256;

/// The one rule for splitting a tick's sends across lanes (sockets): each lane's
/// contiguous share of `items` (datagrams, or players of a datagram or two) on `lanes`
/// lanes, or `None`: all on one lane, when there is one or the items are too few to pay
/// for waking the others.
pub(crate) fn lane_share(items: usize, lanes: usize) -> Option<usize> {
    (lanes > 1 && items >= PARALLEL_SEND_MIN).then(|| items.div_ceil(lanes))
}

/// Times a socket may report itself full in a row before the rest of its share is
/// dropped.
const SEND_STALLS: usize = 3;

/// The UDP endpoints (`recvmmsg`/`sendmmsg`) as a [`Transport`]: one socket, or a
/// `SO_REUSEPORT` group on one port. A group sends in parallel, one socket per worker of
/// the rayon pool, each with its own contiguous share of the tick's datagrams; clients
/// see one server address either way.
#[derive(Debug)]
pub struct UdpTransport {
    endpoints: Vec<Endpoint>,
    /// Receive slots, made at the first receive (1.5 MiB that a transport used only to
    /// send, as behind the receiver thread, never needs).
    batch: Option<RecvBatch>,
    /// The endpoints' count of oversized datagrams already reported to the metrics.
    oversized_seen: u64,
}

impl UdpTransport {
    /// Wraps one bound endpoint.
    pub fn new(endpoint: Endpoint) -> Self {
        Self::group(vec![endpoint])
    }

    /// Wraps a group of endpoints bound to one address with `SO_REUSEPORT`
    /// ([`Endpoint::bind_group`]); at least one.
    pub fn group(endpoints: Vec<Endpoint>) -> Self {
        assert!(!endpoints.is_empty(), "a transport needs a socket");
        UdpTransport { endpoints, batch: None, oversized_seen: 0 }
    }
}

/// Datagrams too large for a receive slot never reach the gate: the endpoints drop and
/// count them. Reports those counted since `seen` as `oversized`, with the ones the gate
/// finds over 1200 bytes.
pub(crate) fn report_oversized(endpoints: &[Endpoint], seen: &mut u64) {
    let oversized: u64 = endpoints.iter().map(|e| e.stats().truncated).sum();
    if oversized > *seen {
        Refusal::Oversized.count_many(oversized - *seen);
        *seen = oversized;
    }
}

/// Sends all of `out` on `endpoint`, retrying while its buffer is full, at most
/// [`SEND_STALLS`] times in a row.
fn send_all(endpoint: &mut Endpoint, out: &[(SocketAddr, &[u8])]) -> io::Result<Sent> {
    let mut sent = Sent::default();
    let mut stalls = 0;
    while sent.datagrams < out.len() {
        match endpoint.send_batch(&out[sent.datagrams..])? {
            0 => {
                stalls += 1;
                if stalls > SEND_STALLS {
                    break;
                }
                std::thread::yield_now();
            }
            n => {
                let range = sent.datagrams..sent.datagrams + n;
                sent.bytes += out[range].iter().map(|(_, d)| d.len() as u64).sum::<u64>();
                sent.datagrams += n;
                stalls = 0;
            }
        }
    }
    Ok(sent)
}

impl Transport for UdpTransport {
    fn receive(&mut self, each: &mut dyn FnMut(SocketAddr, &[u8])) -> io::Result<usize> {
        let mut total = 0;
        let batch = self.batch.get_or_insert_with(|| RecvBatch::new(RECV_BATCH));
        for endpoint in &mut self.endpoints {
            let n = endpoint.recv_batch(batch)?;
            for (from, bytes) in batch.iter() {
                each(from, bytes);
            }
            total += n;
        }
        report_oversized(&self.endpoints, &mut self.oversized_seen);
        Ok(total)
    }

    fn send(&mut self, out: &[(SocketAddr, &[u8])]) -> io::Result<Sent> {
        let Some(share) = lane_share(out.len(), self.endpoints.len()) else {
            return send_all(&mut self.endpoints[0], out);
        };
        let results: Vec<io::Result<Sent>> = self
            .endpoints
            .par_iter_mut()
            .zip(out.par_chunks(share))
            .map(|(endpoint, chunk)| send_all(endpoint, chunk))
            .collect();
        let mut sent = Sent::default();
        for r in results {
            let r = r?;
            sent.datagrams += r.datagrams;
            sent.bytes += r.bytes;
        }
        Ok(sent)
    }

    fn lanes(&mut self) -> Vec<&mut dyn Lane> {
        self.endpoints.iter_mut().map(|e| e as &mut dyn Lane).collect()
    }

    fn local_addr(&self) -> SocketAddr {
        self.endpoints[0].local_addr()
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
    fn receive(&mut self, each: &mut dyn FnMut(SocketAddr, &[u8])) -> io::Result<usize> {
        // Take the batch out first: `each` may run for a while, and a test thread may
        // want to push meanwhile.
        let batch: Vec<_> = {
            let mut q = self.queues();
            let n = q.inbox.len().min(RECV_BATCH);
            q.inbox.drain(..n).collect()
        };
        let n = batch.len();
        for (from, bytes) in batch {
            each(from, &bytes);
        }
        Ok(n)
    }

    fn send(&mut self, out: &[(SocketAddr, &[u8])]) -> io::Result<Sent> {
        self.transmit(out)
    }

    fn lanes(&mut self) -> Vec<&mut dyn Lane> {
        vec![self]
    }

    fn local_addr(&self) -> SocketAddr {
        self.addr
    }
}

impl Lane for MemoryTransport {
    fn transmit(&mut self, out: &[(SocketAddr, &[u8])]) -> io::Result<Sent> {
        let mut q = self.queues();
        let room = q.send_capacity.map_or(out.len(), |c| c.saturating_sub(q.outbox.len()));
        let n = room.min(out.len());
        q.outbox.extend(out[..n].iter().map(|(to, d)| (*to, d.to_vec())));
        Ok(Sent { datagrams: n, bytes: out[..n].iter().map(|(_, d)| d.len() as u64).sum() })
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
        assert_eq!(server_side.send(&out).unwrap(), Sent { datagrams: 1, bytes: 1 });
        assert_eq!(server_side.send(&out[1..]).unwrap().datagrams, 0, "full");
        assert_eq!(test_side.take_sent(), vec![(client, vec![9])]);
        assert_eq!(server_side.local_addr(), addr);
    }

    #[test]
    fn a_socket_group_sends_everything_in_parallel_from_one_address() {
        use myriad_net::EndpointConfig;
        let group = Endpoint::bind_group(EndpointConfig::new("127.0.0.1:0".parse().unwrap()), 3).unwrap();
        let mut transport = UdpTransport::group(group);
        let server = transport.local_addr();
        let clients: Vec<std::net::UdpSocket> =
            (0..4).map(|_| std::net::UdpSocket::bind("127.0.0.1:0").unwrap()).collect();
        let payloads: Vec<Vec<u8>> = (0..1000u32).map(|i| i.to_le_bytes().to_vec()).collect();
        let out: Vec<(SocketAddr, &[u8])> =
            payloads.iter().enumerate().map(|(i, p)| (clients[i % 4].local_addr().unwrap(), p.as_slice())).collect();
        let sent = transport.send(&out).unwrap();
        assert_eq!(sent, Sent { datagrams: 1000, bytes: 4000 });
        let receive_all = || {
            let mut got = Vec::new();
            let mut buf = [0u8; 16];
            for c in &clients {
                c.set_read_timeout(Some(std::time::Duration::from_secs(2))).unwrap();
                for _ in 0..250 {
                    let (n, from) = c.recv_from(&mut buf).unwrap();
                    assert_eq!(from, server, "every socket of the group sends from the one address");
                    got.push(u32::from_le_bytes(buf[..n].try_into().unwrap()));
                }
            }
            got.sort_unstable();
            got
        };
        assert_eq!(receive_all(), (0..1000).collect::<Vec<_>>());
        // A lane a socket, each sending on its own thread: the same datagrams, a share each.
        let lanes = transport.lanes();
        assert_eq!(lanes.len(), 3);
        let per_lane: Vec<Sent> = std::thread::scope(|s| {
            let sending: Vec<_> = lanes
                .into_iter()
                .zip(out.chunks(334))
                .map(|(lane, share)| s.spawn(move || lane.transmit(share).unwrap()))
                .collect();
            sending.into_iter().map(|h| h.join().unwrap()).collect()
        });
        assert_eq!(per_lane.iter().map(|s| s.datagrams).collect::<Vec<_>>(), [334, 334, 332]);
        assert_eq!(receive_all(), (0..1000).collect::<Vec<_>>());
        // And a client's datagrams reach the group, whichever socket the kernel picks.
        for c in &clients {
            c.send_to(b"hi", server).unwrap();
        }
        let mut seen = 0;
        for _ in 0..100 {
            seen += transport.receive(&mut |_, b| assert_eq!(b, b"hi")).unwrap();
            if seen == 4 {
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(5));
        }
        assert_eq!(seen, 4);
    }
}
