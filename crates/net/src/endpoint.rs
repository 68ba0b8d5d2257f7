//! The endpoint: socket set-up (buffers, `SO_REUSEPORT`) and the batched calls.

use std::io;
use std::net::{SocketAddr, UdpSocket};

use socket2::{Domain, Protocol, Socket, Type};
use thiserror::Error;

use crate::recv::RecvBatch;
use crate::sys::Native;

/// Failure to set an endpoint up. Send and receive errors are plain `io::Error`s.
#[derive(Debug, Error)]
pub enum NetError {
    /// Creating, configuring or binding the socket failed.
    #[error("cannot {action} UDP socket on {addr}: {source}")]
    Socket {
        /// What was being done.
        action: &'static str,
        /// The address asked for.
        addr: SocketAddr,
        /// The system's error.
        #[source]
        source: io::Error,
    },
}

/// How to open an endpoint.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EndpointConfig {
    /// Address to bind (port 0 picks a free port).
    pub bind: SocketAddr,
    /// `SO_SNDBUF` to ask for, in bytes. The default, 8 MiB, holds a whole tick of
    /// updates for about 7,000 players at one 1200-byte datagram each.
    pub send_buffer: usize,
    /// `SO_RCVBUF` to ask for, in bytes (default 8 MiB).
    pub recv_buffer: usize,
    /// Set `SO_REUSEPORT` (needed by [`Endpoint::bind_group`]; Unix only).
    pub reuse_port: bool,
    /// Most datagrams per system call, clamped to 1..=1024 (Linux's `UIO_MAXIOV`).
    pub batch: usize,
}

impl EndpointConfig {
    /// Defaults for `bind`.
    pub fn new(bind: SocketAddr) -> Self {
        Self { bind, send_buffer: 8 << 20, recv_buffer: 8 << 20, reuse_port: false, batch: 512 }
    }
}

/// Socket buffer sizes the kernel granted (Linux reports twice the usable payload
/// room, for its bookkeeping, and caps requests at `net.core.wmem_max`/`rmem_max`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BufferSizes {
    /// Granted `SO_SNDBUF`.
    pub send: usize,
    /// Granted `SO_RCVBUF`.
    pub recv: usize,
}

/// Counters since the endpoint opened.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct EndpointStats {
    /// Datagrams handed to the kernel.
    pub sent: u64,
    /// Datagrams skipped because the kernel rejected them.
    pub send_errors: u64,
    /// Times a send stopped early because the socket buffer was full.
    pub send_would_block: u64,
    /// Batched send system calls made (Linux).
    pub send_calls: u64,
    /// Datagrams received and returned.
    pub received: u64,
    /// Datagrams dropped on receipt for being larger than [`crate::MAX_RECV`].
    pub truncated: u64,
    /// Batched receive system calls made (Linux).
    pub recv_calls: u64,
}

/// A non-blocking UDP socket with batched send and receive.
#[derive(Debug)]
pub struct Endpoint {
    socket: UdpSocket,
    local: SocketAddr,
    buffers: BufferSizes,
    batcher: Native,
    stats: EndpointStats,
}

impl Endpoint {
    /// Opens and binds one endpoint.
    pub fn bind(config: EndpointConfig) -> Result<Self, NetError> {
        let addr = config.bind;
        let err = |action: &'static str| move |source| NetError::Socket { action, addr, source };
        let socket = Socket::new(Domain::for_address(addr), Type::DGRAM, Some(Protocol::UDP)).map_err(err("create"))?;
        socket.set_nonblocking(true).map_err(err("make non-blocking"))?;
        #[cfg(unix)]
        if config.reuse_port {
            socket.set_reuse_port(true).map_err(err("set SO_REUSEPORT on"))?;
        }
        // A refused size is not fatal: the granted size is reported instead.
        let _ = socket.set_send_buffer_size(config.send_buffer);
        let _ = socket.set_recv_buffer_size(config.recv_buffer);
        socket.bind(&addr.into()).map_err(err("bind"))?;
        let buffers = BufferSizes {
            send: socket.send_buffer_size().map_err(err("read SO_SNDBUF of"))?,
            recv: socket.recv_buffer_size().map_err(err("read SO_RCVBUF of"))?,
        };
        let socket: UdpSocket = socket.into();
        let local = socket.local_addr().map_err(err("read the address of"))?;
        Ok(Self {
            socket,
            local,
            buffers,
            batcher: Native::new(config.batch.clamp(1, 1024)),
            stats: EndpointStats::default(),
        })
    }

    /// Opens `count` endpoints on one address with `SO_REUSEPORT`, one per I/O
    /// thread; the kernel spreads senders over them by address hash. With port 0 the
    /// first socket picks the port and the others join it.
    ///
    /// A fixed port must be free: a plain socket is bound to it first (and closed), so
    /// a second server started on a port a running one holds fails as it would without
    /// `SO_REUSEPORT`, instead of silently taking half of its traffic.
    pub fn bind_group(config: EndpointConfig, count: usize) -> Result<Vec<Self>, NetError> {
        if config.bind.port() != 0 {
            drop(Self::bind(EndpointConfig { reuse_port: false, ..config })?);
        }
        let mut config = EndpointConfig { reuse_port: true, ..config };
        let mut group = Vec::with_capacity(count);
        for _ in 0..count {
            let endpoint = Self::bind(config)?;
            config.bind = endpoint.local;
            group.push(endpoint);
        }
        Ok(group)
    }

    /// The bound address.
    pub fn local_addr(&self) -> SocketAddr {
        self.local
    }

    /// The socket buffer sizes the kernel granted.
    pub fn buffer_sizes(&self) -> BufferSizes {
        self.buffers
    }

    /// Counters since the endpoint opened.
    pub fn stats(&self) -> EndpointStats {
        self.stats
    }

    /// A second handle on the same socket, with its own batch headers and counters, so
    /// that one thread can receive while another sends (the kernel allows both at
    /// once on one socket). It shares the socket's non-blocking mode.
    pub fn try_clone(&self) -> io::Result<Endpoint> {
        Ok(Endpoint {
            socket: self.socket.try_clone()?,
            local: self.local,
            buffers: self.buffers,
            batcher: Native::new(self.batcher.batch()),
            stats: EndpointStats::default(),
        })
    }

    /// The underlying socket (for polling readiness, for example).
    pub fn socket(&self) -> &UdpSocket {
        &self.socket
    }

    /// Sends datagrams in order, batched, without blocking. Returns how many from the
    /// front were consumed: sent, or skipped because the kernel rejected that one
    /// datagram (counted in [`EndpointStats::send_errors`]). Fewer than all means the
    /// socket buffer is full; the caller may retry the rest later or drop them.
    pub fn send_batch(&mut self, datagrams: &[(SocketAddr, &[u8])]) -> io::Result<usize> {
        self.batcher.send(&self.socket, datagrams, &mut self.stats)
    }

    /// Receives as many datagrams as are queued, up to `out`'s capacity and
    /// [`EndpointConfig::batch`] (one system call on Linux), without blocking: 0 when
    /// none are waiting. `out` is overwritten. Call it in a loop until it returns 0 to
    /// drain the socket.
    pub fn recv_batch(&mut self, out: &mut RecvBatch) -> io::Result<usize> {
        self.batcher.recv(&self.socket, out, &mut self.stats)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sys::portable;
    use std::net::Ipv4Addr;
    use std::time::{Duration, Instant};

    fn local() -> EndpointConfig {
        EndpointConfig::new(SocketAddr::from((Ipv4Addr::LOCALHOST, 0)))
    }

    /// Receives until `want` datagrams arrived or a second passed.
    fn drain(ep: &mut Endpoint, batch: &mut RecvBatch, want: usize) -> Vec<(SocketAddr, Vec<u8>)> {
        let mut got = Vec::new();
        let deadline = Instant::now() + Duration::from_secs(2);
        while got.len() < want && Instant::now() < deadline {
            if ep.recv_batch(batch).expect("recv") == 0 {
                std::thread::sleep(Duration::from_millis(1));
            }
            got.extend(batch.iter().map(|(a, d)| (a, d.to_vec())));
        }
        got
    }

    #[test]
    fn a_clone_receives_on_another_thread_while_the_original_sends() {
        let mut server = Endpoint::bind(local()).unwrap();
        let mut receiver = server.try_clone().unwrap();
        assert_eq!(receiver.local_addr(), server.local_addr());
        let mut client = Endpoint::bind(local()).unwrap();
        let to_server = server.local_addr();
        let reader = std::thread::spawn(move || {
            let mut batch = RecvBatch::new(64);
            let got = drain(&mut receiver, &mut batch, 20);
            (got.len(), receiver.stats().received)
        });
        let payloads: Vec<Vec<u8>> = (0..20u8).map(|i| vec![i; 8]).collect();
        let out: Vec<(SocketAddr, &[u8])> = payloads.iter().map(|d| (to_server, &d[..])).collect();
        assert_eq!(client.send_batch(&out).unwrap(), 20);
        assert_eq!(reader.join().unwrap(), (20, 20), "the clone took every datagram and counted them itself");
        // The original still sends from the same address.
        assert_eq!(server.send_batch(&[(client.local_addr(), b"back")]).unwrap(), 1);
        let mut batch = RecvBatch::new(4);
        assert_eq!(drain(&mut client, &mut batch, 1), vec![(to_server, b"back".to_vec())]);
        assert_eq!(server.stats().received, 0, "counters are per handle");
    }

    #[test]
    fn portable_backend_round_trip() {
        // The fallback used off Linux, exercised here on a real socket.
        let mut a = Endpoint::bind(local()).unwrap();
        let mut b = Endpoint::bind(local()).unwrap();
        let mut p = portable::Batcher::new(64);
        let payloads: Vec<Vec<u8>> = (0..50u8).map(|i| vec![i; 10 + i as usize]).collect();
        let to_b: Vec<(SocketAddr, &[u8])> = payloads.iter().map(|d| (b.local, &d[..])).collect();
        let mut stats = EndpointStats::default();
        assert_eq!(p.send(&a.socket, &to_b, &mut stats).unwrap(), 50);
        assert_eq!(stats.sent, 50);
        let mut batch = RecvBatch::new(16);
        let mut got = Vec::new();
        let deadline = Instant::now() + Duration::from_secs(2);
        while got.len() < 50 && Instant::now() < deadline {
            p.recv(&b.socket, &mut batch, &mut stats).unwrap();
            got.extend(batch.iter().map(|(addr, d)| (addr, d.to_vec())));
        }
        assert_eq!(got.len(), 50);
        assert!(got.iter().all(|(addr, _)| *addr == a.local));
        assert_eq!(got.iter().map(|g| g.1.clone()).collect::<Vec<_>>(), payloads);
        // Nothing queued: returns at once with 0.
        assert_eq!(p.recv(&b.socket, &mut batch, &mut stats).unwrap(), 0);
        let _ = (&mut a, &mut b);
    }

    #[test]
    fn native_send_and_receive_in_batches() {
        let mut a = Endpoint::bind(local()).unwrap();
        let mut b = Endpoint::bind(local()).unwrap();
        let payloads: Vec<Vec<u8>> = (0..700u32).map(|i| i.to_le_bytes().repeat(1 + (i % 300) as usize)).collect();
        let to_b: Vec<(SocketAddr, &[u8])> = payloads.iter().map(|d| (b.local, &d[..])).collect();
        let mut sent = 0;
        let mut received = Vec::new();
        let mut batch = RecvBatch::new(256);
        let deadline = Instant::now() + Duration::from_secs(5);
        // Send in pieces, draining in between, so the receive buffer never overflows.
        while received.len() < payloads.len() && Instant::now() < deadline {
            let end = (sent + 100).min(to_b.len());
            sent += a.send_batch(&to_b[sent..end]).unwrap();
            received.extend(drain(&mut b, &mut batch, sent - received.len()));
        }
        assert_eq!(received.len(), payloads.len());
        assert!(received.iter().zip(&payloads).all(|((addr, d), p)| *addr == a.local && d == p));
        assert_eq!(a.stats().sent, 700);
        assert_eq!(b.stats().received, 700);
        #[cfg(target_os = "linux")]
        assert!(a.stats().send_calls < 700, "sends were batched");
    }

    #[test]
    fn bad_destination_is_skipped_not_fatal() {
        let mut a = Endpoint::bind(local()).unwrap();
        let mut b = Endpoint::bind(local()).unwrap();
        let v6: SocketAddr = "[::1]:9".parse().unwrap();
        let list: Vec<(SocketAddr, &[u8])> = vec![(v6, b"x"), (b.local, b"one"), (v6, b"y"), (b.local, b"two")];
        assert_eq!(a.send_batch(&list).unwrap(), 4);
        assert_eq!(a.stats().send_errors, 2);
        let got = drain(&mut b, &mut RecvBatch::new(8), 2);
        assert_eq!(got.iter().map(|g| g.1.clone()).collect::<Vec<_>>(), vec![b"one".to_vec(), b"two".to_vec()]);
    }

    #[test]
    fn oversized_datagrams_are_dropped_and_counted() {
        let a = UdpSocket::bind((Ipv4Addr::LOCALHOST, 0)).unwrap();
        let mut b = Endpoint::bind(local()).unwrap();
        a.send_to(&[1u8; crate::MAX_RECV + 100], b.local).unwrap();
        a.send_to(&[2u8; 1200], b.local).unwrap();
        let got = drain(&mut b, &mut RecvBatch::new(8), 1);
        assert_eq!(got.len(), 1);
        assert_eq!(got[0].1, vec![2u8; 1200]);
        assert_eq!(b.stats().truncated, 1);
    }

    #[test]
    fn full_send_buffer_returns_instead_of_blocking() {
        // A tiny send buffer towards a receiver that never reads: the call must come
        // back, with the number consumed, however many datagrams are queued.
        let mut config = local();
        config.send_buffer = 4096;
        let mut a = Endpoint::bind(config).unwrap();
        let sink = Endpoint::bind(local()).unwrap();
        let data = vec![0u8; 1200];
        let list: Vec<(SocketAddr, &[u8])> = (0..20_000).map(|_| (sink.local, &data[..])).collect();
        let start = Instant::now();
        let n = a.send_batch(&list).unwrap();
        assert!(n <= list.len());
        assert!(start.elapsed() < Duration::from_secs(5));
        assert_eq!(a.stats().sent as usize + a.stats().send_errors as usize, n);
    }

    #[test]
    fn reuse_port_group_shares_one_port_and_reports_buffers() {
        let group = Endpoint::bind_group(local(), 3).unwrap();
        assert_eq!(group.len(), 3);
        assert!(group.iter().all(|e| e.local_addr() == group[0].local_addr()));
        let sizes = group[0].buffer_sizes();
        assert!(sizes.send > 0 && sizes.recv > 0);
        // Without SO_REUSEPORT the same port is refused.
        let mut plain = local();
        plain.bind = group[0].local_addr();
        assert!(matches!(Endpoint::bind(plain), Err(NetError::Socket { action: "bind", .. })));
        // Nor can a second group join a port a running group holds.
        assert!(matches!(Endpoint::bind_group(plain, 2), Err(NetError::Socket { action: "bind", .. })));
        // A fixed port that is free is fine.
        let port = group[0].local_addr();
        drop(group);
        let mut again = local();
        again.bind = port;
        assert_eq!(Endpoint::bind_group(again, 2).unwrap().len(), 2);
    }
}
