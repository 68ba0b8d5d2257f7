//! `sendmmsg(2)`/`recvmmsg(2)` through nix, with preallocated message headers.

use std::io::{self, IoSlice, IoSliceMut};
use std::net::{SocketAddr, UdpSocket};
use std::os::fd::AsRawFd;

use nix::errno::Errno;
use nix::sys::socket::{MsgFlags, MultiHeaders, SockaddrStorage, recvmmsg, sendmmsg};

use crate::endpoint::EndpointStats;
use crate::recv::{MAX_RECV, RecvBatch};

/// Reused per-endpoint state: the kernel-facing header arrays and the address list.
#[derive(Debug)]
pub(crate) struct Batcher {
    batch: usize,
    send_headers: MultiHeaders<SockaddrStorage>,
    recv_headers: MultiHeaders<SockaddrStorage>,
    addrs: Vec<Option<SockaddrStorage>>,
}

// SAFETY: `MultiHeaders` holds raw pointers, which makes it `!Send`. The only memory
// they point to between calls is its own heap allocations (the address array) and
// stale pointers into buffers of the previous call, which are rewritten before every
// system call and never read otherwise. No state is shared with another thread, so
// moving the batcher to another thread (an endpoint to its I/O thread) is sound.
unsafe impl Send for Batcher {}

fn to_io(e: Errno) -> io::Error {
    io::Error::from_raw_os_error(e as i32)
}

impl Batcher {
    pub(crate) fn new(batch: usize) -> Self {
        Self {
            batch,
            send_headers: MultiHeaders::preallocate(batch, None),
            recv_headers: MultiHeaders::preallocate(batch, None),
            addrs: Vec::with_capacity(batch),
        }
    }

    /// Most datagrams per system call.
    pub(crate) fn batch(&self) -> usize {
        self.batch
    }

    pub(crate) fn send(
        &mut self,
        socket: &UdpSocket,
        datagrams: &[(SocketAddr, &[u8])],
        stats: &mut EndpointStats,
    ) -> io::Result<usize> {
        let fd = socket.as_raw_fd();
        let mut done = 0;
        while done < datagrams.len() {
            let chunk = &datagrams[done..(done + self.batch).min(datagrams.len())];
            self.addrs.clear();
            self.addrs.extend(chunk.iter().map(|(a, _)| Some(SockaddrStorage::from(*a))));
            // One small allocation per system call of up to `batch` datagrams.
            let slices: Vec<[IoSlice<'_>; 1]> = chunk.iter().map(|(_, d)| [IoSlice::new(d)]).collect();
            let result = sendmmsg(fd, &mut self.send_headers, &slices, &self.addrs, [], MsgFlags::MSG_DONTWAIT);
            match result {
                Ok(results) => {
                    let n = results.count();
                    stats.sent += n as u64;
                    stats.send_calls += 1;
                    done += n;
                    if n == 0 {
                        // Nothing went out and no error: treat as a full buffer.
                        stats.send_would_block += 1;
                        break;
                    }
                }
                Err(Errno::EAGAIN) => {
                    stats.send_would_block += 1;
                    break;
                }
                Err(Errno::EINTR) => {}
                Err(Errno::ENOBUFS) => {
                    // Transient kernel memory shortage: like a full buffer.
                    stats.send_would_block += 1;
                    break;
                }
                Err(_) => {
                    // sendmmsg reports an error only when the first datagram of the
                    // call failed: skip that one and go on with the rest.
                    stats.send_errors += 1;
                    done += 1;
                }
            }
        }
        Ok(done)
    }

    pub(crate) fn recv(
        &mut self,
        socket: &UdpSocket,
        out: &mut RecvBatch,
        stats: &mut EndpointStats,
    ) -> io::Result<usize> {
        out.len = 0;
        let want = out.capacity().min(self.batch);
        // Allocates only if a datagram was truncated, which only hostile peers cause.
        let mut truncated: Vec<bool> = Vec::new();
        let received = {
            let mut slices: Vec<[IoSliceMut<'_>; 1]> =
                out.buf.chunks_exact_mut(MAX_RECV).take(want).map(|c| [IoSliceMut::new(c)]).collect();
            // No retry loop: a non-blocking call is not interrupted in practice, and an
            // EINTR simply reports nothing this time (the caller polls every tick).
            match recvmmsg(socket.as_raw_fd(), &mut self.recv_headers, slices.iter_mut(), MsgFlags::MSG_DONTWAIT, None)
            {
                Ok(results) => {
                    let mut n = 0;
                    for (i, msg) in results.enumerate() {
                        out.lens[i] = msg.bytes.min(MAX_RECV);
                        out.addrs[i] = msg.address.and_then(|a| to_socket_addr(&a)).unwrap_or(out.addrs[i]);
                        if msg.flags.contains(MsgFlags::MSG_TRUNC) || msg.address.is_none() {
                            truncated.resize(i + 1, false);
                            truncated[i] = true;
                        }
                        n = i + 1;
                    }
                    n
                }
                Err(Errno::EAGAIN | Errno::EINTR) => 0,
                // Errors of earlier sends (ICMP) can surface here; they are not about
                // this call. Report nothing received this time.
                Err(Errno::ECONNREFUSED) => 0,
                Err(e) => return Err(to_io(e)),
            }
        };
        out.len = received;
        stats.recv_calls += 1;
        if truncated.iter().any(|&t| t) {
            let before = out.len;
            out.retain_by_index(|i| !truncated.get(i).copied().unwrap_or(false));
            stats.truncated += (before - out.len) as u64;
        }
        stats.received += out.len as u64;
        Ok(out.len)
    }
}

fn to_socket_addr(a: &SockaddrStorage) -> Option<SocketAddr> {
    if let Some(v4) = a.as_sockaddr_in() {
        Some(SocketAddr::from(*v4))
    } else {
        a.as_sockaddr_in6().map(|v6| SocketAddr::from(*v6))
    }
}
