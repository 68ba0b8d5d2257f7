//! One system call per datagram, with std only: the fallback for non-Linux systems.

use std::io;
use std::net::{SocketAddr, UdpSocket};

use crate::endpoint::EndpointStats;
use crate::recv::{MAX_RECV, RecvBatch};

/// Stateless; exists to mirror the Linux back end's shape.
#[derive(Debug)]
pub(crate) struct Batcher;

impl Batcher {
    pub(crate) fn new(_batch: usize) -> Self {
        Self
    }

    /// One datagram per call here.
    #[allow(dead_code)] // used off Linux only; compiled on Linux for the tests
    pub(crate) fn batch(&self) -> usize {
        1
    }

    pub(crate) fn send(
        &mut self,
        socket: &UdpSocket,
        datagrams: &[(SocketAddr, &[u8])],
        stats: &mut EndpointStats,
    ) -> io::Result<usize> {
        let mut done = 0;
        while done < datagrams.len() {
            let (addr, bytes) = datagrams[done];
            match socket.send_to(bytes, addr) {
                Ok(_) => {
                    stats.sent += 1;
                    done += 1;
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                    stats.send_would_block += 1;
                    break;
                }
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(_) => {
                    // This datagram cannot be sent (bad address, too large…): skip it.
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
        // One extra byte tells an oversized datagram from one of exactly MAX_RECV.
        let mut scratch = [0u8; MAX_RECV + 1];
        while out.len < out.capacity() {
            match socket.recv_from(&mut scratch) {
                Ok((n, addr)) if n <= MAX_RECV => {
                    let i = out.len;
                    out.buf[i * MAX_RECV..i * MAX_RECV + n].copy_from_slice(&scratch[..n]);
                    out.lens[i] = n;
                    out.addrs[i] = addr;
                    out.len += 1;
                    stats.received += 1;
                }
                Ok(_) => stats.truncated += 1,
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => break,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                // ICMP errors of earlier sends surface here on some systems
                // (ECONNREFUSED, ECONNRESET): not about this receive; keep reading.
                Err(e) if matches!(e.kind(), io::ErrorKind::ConnectionRefused | io::ErrorKind::ConnectionReset) => {}
                Err(e) => return Err(e),
            }
        }
        Ok(out.len)
    }
}
