//! The receiver thread: UDP receive and the [gate](crate::gate) off the tick thread.
//!
//! Receiving costs a system call per batch and a header check and two table lookups per
//! datagram even when every datagram is dropped, so a flood of junk that the server
//! only drops still takes the tick's time if the tick receives. [`ThreadedUdp`] moves
//! all of that to a thread of its own, at the lowest normal priority: it drains the
//! sockets as datagrams arrive, gates each one against the [`SessionDirectory`] the tick
//! publishes, and queues those that pass (at most [`MAX_QUEUED`] datagrams and
//! [`MAX_QUEUED_BYTES`] bytes; more is dropped as `queue_full`). The tick takes the
//! queue in one swap and pays only for what passed: the tag checks, which the gate
//! bounds per session. Sending stays on the tick thread (or its workers), on other
//! handles of the same sockets.
//!
//! Why a lower priority (nice 10, like the async runtime's workers) and not a core of its
//! own: on a small machine the tick and its physics workers must win most contests for
//! a core, so a flood cannot slow them much; the receiver takes what they leave, which
//! is most of every tick period. Not the lowest (nice 19, a weight of 15 against the
//! tick's 1024): with every core busy (1,000 bots on the same two cores) such a thread
//! gets too small a share to keep up with legitimate traffic, where nice 10 still gets
//! about a tenth. While it waits, datagrams wait in the socket buffer (8 MiB), and the
//! kernel drops what overflows, at the sender's cost.
//!
//! The tick never waits for the receiver: it takes the queue with `try_lock`, and if the
//! receiver holds the lock (say, preempted inside its short hand-over) the tick takes
//! nothing this time and everything next tick. Waiting there would let a low-priority
//! thread stall the tick (priority inversion).

use std::io;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::Duration;

use myriad_net::{Endpoint, RecvBatch};

use crate::gate::{Gate, ReceiveLimits, Refusal, SessionDirectory};
use crate::inbound::Inbox;
use crate::transport::{GateCounts, Lane, RECV_BATCH, Sent, Transport, UdpTransport, report_oversized};

/// Most datagrams waiting for the tick; beyond that the receiver drops them.
pub const MAX_QUEUED: usize = 65_536;

/// Most bytes waiting for the tick.
pub const MAX_QUEUED_BYTES: usize = 16 << 20;

/// Niceness of the receiver thread; see the module docs.
const RECEIVER_NICE: i32 = 10;

/// Longest the receiver waits for a datagram before it looks at the stop flag again.
const POLL_MS: i32 = 50;

/// Pause after the sockets run dry, so that a steady trickle of datagrams wakes the
/// receiver at most a thousand times a second instead of once per datagram.
const PAUSE: Duration = Duration::from_millis(1);

/// Queues `datagram` in `inbox` unless that would pass [`MAX_QUEUED`] or
/// [`MAX_QUEUED_BYTES`]; false when it did not.
fn queue(inbox: &mut Inbox, from: SocketAddr, datagram: &[u8]) -> bool {
    inbox.push_within(from, datagram, MAX_QUEUED, MAX_QUEUED_BYTES)
}

/// What the tick and the receiver thread share: the link between the two.
#[derive(Debug, Default)]
struct ReceiverLink {
    stop: AtomicBool,
    /// The tick whose budget arriving datagrams spend.
    tick: AtomicU64,
    /// The sessions to gate against, and a version that changes with it.
    directory: Mutex<Arc<SessionDirectory>>,
    directory_version: AtomicU64,
    /// Datagrams gated and waiting for the tick, in arrival order.
    inbox: Mutex<Inbox>,
    /// Datagrams taken from the sockets, and those refused over a budget, since the
    /// tick last asked.
    taken: AtomicU64,
    over_budget: AtomicU64,
    /// Datagrams read from the sockets and dealt with (queued for the tick or refused),
    /// since the start; never reset.
    dealt_with: Arc<AtomicU64>,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // Plain data: a panic elsewhere while holding the lock leaves nothing half-done.
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// A [`Transport`] that receives and gates on its own thread; see the module docs.
#[derive(Debug)]
pub struct ThreadedUdp {
    send: UdpTransport,
    link: Arc<ReceiverLink>,
    thread: Option<JoinHandle<()>>,
    /// The tick's side of the inbox, swapped with the receiver's each tick.
    taken: Inbox,
}

impl ThreadedUdp {
    /// Starts the receiver on other handles of `endpoints` (one socket or a
    /// `SO_REUSEPORT` group), gating with `limits`; the tick sends on `endpoints`.
    pub fn start(endpoints: Vec<Endpoint>, limits: ReceiveLimits) -> io::Result<ThreadedUdp> {
        let receiving = endpoints.iter().map(Endpoint::try_clone).collect::<io::Result<Vec<_>>>()?;
        let link = Arc::new(ReceiverLink::default());
        let for_thread = link.clone();
        let thread = std::thread::Builder::new()
            .name("myriad-receive".into())
            .spawn(move || receive_loop(receiving, &for_thread, Gate::new(limits)))?;
        Ok(ThreadedUdp { send: UdpTransport::group(endpoints), link, thread: Some(thread), taken: Inbox::default() })
    }

    /// How many datagrams the receiver has read from the sockets and dealt with (queued
    /// for the tick, or refused) since it started. The tick benchmark waits on it so
    /// that a tick takes everything its bots sent before it, as a tick of `serve` takes
    /// what arrived during the previous period.
    pub fn dealt_with(&self) -> Arc<AtomicU64> {
        self.link.dealt_with.clone()
    }
}

impl Drop for ThreadedUdp {
    fn drop(&mut self) {
        self.link.stop.store(true, Ordering::Release);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Transport for ThreadedUdp {
    fn receive(&mut self, each: &mut dyn FnMut(SocketAddr, &[u8])) -> io::Result<usize> {
        self.taken.clear();
        let mut inbox = match self.link.inbox.try_lock() {
            Ok(inbox) => inbox,
            Err(std::sync::TryLockError::Poisoned(p)) => p.into_inner(),
            // The receiver is handing over: take it all next tick (module docs).
            Err(std::sync::TryLockError::WouldBlock) => return Ok(0),
        };
        std::mem::swap(&mut self.taken, &mut inbox);
        drop(inbox);
        for (from, datagram) in self.taken.iter() {
            each(from, datagram);
        }
        Ok(self.taken.len())
    }

    fn send(&mut self, out: &[(SocketAddr, &[u8])]) -> io::Result<Sent> {
        self.send.send(out)
    }

    fn lanes(&mut self) -> Vec<&mut dyn Lane> {
        self.send.lanes()
    }

    fn local_addr(&self) -> SocketAddr {
        self.send.local_addr()
    }

    fn gates(&self) -> bool {
        true
    }

    fn publish(&mut self, tick: u64, directory: Option<Arc<SessionDirectory>>) {
        if let Some(directory) = directory {
            *lock(&self.link.directory) = directory;
            self.link.directory_version.fetch_add(1, Ordering::Release);
        }
        self.link.tick.store(tick, Ordering::Release);
    }

    fn gate_counts(&mut self) -> GateCounts {
        GateCounts {
            taken: self.link.taken.swap(0, Ordering::AcqRel),
            over_budget: self.link.over_budget.swap(0, Ordering::AcqRel),
        }
    }
}

/// Waits until one of `endpoints` is readable, or [`POLL_MS`] passed.
fn wait_readable(endpoints: &[Endpoint]) {
    #[cfg(unix)]
    {
        use std::os::fd::AsRawFd;
        let mut fds: Vec<libc::pollfd> = endpoints
            .iter()
            .map(|e| libc::pollfd { fd: e.socket().as_raw_fd(), events: libc::POLLIN, revents: 0 })
            .collect();
        // SAFETY: `fds` is a live array of `fds.len()` pollfd structs for the call's
        // duration; poll only writes their `revents`.
        unsafe { libc::poll(fds.as_mut_ptr(), fds.len() as libc::nfds_t, POLL_MS) };
    }
    #[cfg(not(unix))]
    {
        let _ = endpoints;
        std::thread::sleep(PAUSE);
    }
}

/// The receiver's copy of the published [`SessionDirectory`], and the version it is.
struct Known {
    directory: Arc<SessionDirectory>,
    version: u64,
}

impl Known {
    fn new(link: &ReceiverLink) -> Known {
        let version = link.directory_version.load(Ordering::Acquire);
        Known { directory: lock(&link.directory).clone(), version }
    }

    /// Takes the tick's latest directory if it published a newer one; whether it did.
    fn refresh(&mut self, link: &ReceiverLink) -> bool {
        let latest = link.directory_version.load(Ordering::Acquire);
        if latest == self.version {
            return false;
        }
        self.directory = lock(&link.directory).clone();
        self.version = latest;
        true
    }
}

fn receive_loop(mut endpoints: Vec<Endpoint>, link: &ReceiverLink, mut gate: Gate) {
    crate::set_thread_nice(RECEIVER_NICE);
    let mut batch = RecvBatch::new(RECV_BATCH);
    let mut staged = Inbox::default();
    let mut known = Known::new(link);
    let mut truncated_seen = 0;
    while !link.stop.load(Ordering::Acquire) {
        wait_readable(&endpoints);
        loop {
            known.refresh(link);
            let tick = link.tick.load(Ordering::Acquire);
            let mut took = 0;
            let mut over_budget = 0;
            for endpoint in &mut endpoints {
                let n = match endpoint.recv_batch(&mut batch) {
                    Ok(n) => n,
                    Err(e) => {
                        tracing::warn!(error = %e, "receive failed");
                        0
                    }
                };
                for (from, bytes) in batch.iter() {
                    let mut admitted = gate.admit(&*known.directory, tick, from, bytes);
                    // The session may have joined after this batch's directory was read
                    // (its keys leave only after it is published): look again.
                    if admitted == Err(Refusal::UnknownSession) && known.refresh(link) {
                        admitted = gate.admit(&*known.directory, tick, from, bytes);
                    }
                    match admitted {
                        // A round stages at most `RECV_BATCH` a socket, far below the bounds.
                        Ok(_) => {
                            queue(&mut staged, from, bytes);
                        }
                        Err(refusal) => {
                            over_budget += u64::from(refusal.over_budget());
                            refusal.count();
                        }
                    }
                }
                took += n;
            }
            if took == 0 {
                break;
            }
            metrics::counter!("myriad_datagrams_received_total").increment(took as u64);
            link.taken.fetch_add(took as u64, Ordering::AcqRel);
            link.over_budget.fetch_add(over_budget, Ordering::AcqRel);
            hand_over(&mut staged, link);
            link.dealt_with.fetch_add(took as u64, Ordering::AcqRel);
        }
        report_oversized(&endpoints, &mut truncated_seen);
        std::thread::sleep(PAUSE);
    }
}

/// Moves what the receiver staged into the shared inbox, dropping (and counting) what
/// does not fit.
fn hand_over(staged: &mut Inbox, link: &ReceiverLink) {
    let mut full = 0u64;
    {
        let mut inbox = lock(&link.inbox);
        if inbox.is_empty() {
            // The common case: hand the whole staged buffer over in one swap.
            std::mem::swap(&mut *inbox, staged);
        } else {
            for (from, datagram) in staged.iter() {
                if !queue(&mut inbox, from, datagram) {
                    full += 1;
                }
            }
        }
    }
    staged.clear();
    if full > 0 {
        metrics::counter!("myriad_packets_dropped_total", "reason" => "queue_full").increment(full);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use myriad_net::EndpointConfig;
    use std::collections::HashMap;
    use std::time::Instant;

    fn sealed(session: u64) -> Vec<u8> {
        let keys =
            myriad_protocol::SessionKeys { session_id: session, client_to_server: [1; 32], server_to_client: [2; 32] };
        let mut out = Vec::new();
        myriad_protocol::ClientSession::new(&keys)
            .sealer
            .seal_client_message(&myriad_protocol::ClientMessage::KeepAlive { acks: None }, &mut out)
            .unwrap();
        out
    }

    /// Takes from `t` until `want` datagrams came or two seconds passed.
    fn take(t: &mut ThreadedUdp, want: usize) -> Vec<(SocketAddr, Vec<u8>)> {
        let mut got = Vec::new();
        let deadline = Instant::now() + Duration::from_secs(2);
        while got.len() < want && Instant::now() < deadline {
            t.receive(&mut |from, b| got.push((from, b.to_vec()))).unwrap();
            std::thread::sleep(Duration::from_millis(5));
        }
        got
    }

    #[test]
    fn the_receiver_gates_on_its_thread_and_the_tick_takes_what_passed() {
        let group = Endpoint::bind_group(EndpointConfig::new("127.0.0.1:0".parse().unwrap()), 2).unwrap();
        let limits = ReceiveLimits { per_session: 3, other_address: 1, time: Duration::from_millis(5) };
        let mut t = ThreadedUdp::start(group, limits).unwrap();
        assert!(t.gates());
        let server = t.local_addr();
        let player = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
        let stranger = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
        let directory = SessionDirectory::new(HashMap::from([(5, Some(player.local_addr().unwrap()))]));
        t.publish(1, Some(Arc::new(directory)));
        // Give the receiver a moment to pick the directory up before anything arrives.
        std::thread::sleep(Duration::from_millis(100));

        let d5 = sealed(5);
        for _ in 0..50 {
            stranger.send_to(&d5, server).unwrap();
            stranger.send_to(&sealed(99), server).unwrap();
            stranger.send_to(b"junk", server).unwrap();
        }
        for _ in 0..10 {
            player.send_to(&d5, server).unwrap();
        }
        let got = take(&mut t, 4);
        std::thread::sleep(Duration::from_millis(100));
        let more = take(&mut t, 1);
        assert_eq!(got.len() + more.len(), 4, "3 from the player's address and 1 from the stranger's");
        assert!(got.iter().all(|(_, b)| *b == d5));
        let counts = t.gate_counts();
        assert_eq!(counts.taken, 160, "everything was taken off the sockets");
        assert_eq!(counts.over_budget, 49 + 7);
        assert_eq!(t.gate_counts(), GateCounts::default(), "counts are since the last call");

        // The next tick's budget lets the player in again.
        t.publish(2, None);
        std::thread::sleep(Duration::from_millis(20));
        player.send_to(&d5, server).unwrap();
        assert_eq!(take(&mut t, 1).len(), 1);
        // Sending still works, from the server's one address.
        let sent = t.send(&[(player.local_addr().unwrap(), b"hello")]).unwrap();
        assert_eq!(sent.datagrams, 1);
        let mut buf = [0u8; 16];
        player.set_read_timeout(Some(Duration::from_secs(2))).unwrap();
        let (n, from) = player.recv_from(&mut buf).unwrap();
        assert_eq!((&buf[..n], from), (&b"hello"[..], server));
        drop(t); // joins the thread
    }

    #[test]
    fn the_inbox_is_bounded() {
        let mut inbox = Inbox::default();
        let from: SocketAddr = "127.0.0.1:1".parse().unwrap();
        let big = vec![0u8; 1200];
        let mut n = 0;
        while queue(&mut inbox, from, &big) {
            n += 1;
        }
        assert_eq!(n, MAX_QUEUED_BYTES / 1200);
        inbox.clear();
        let mut n = 0;
        while queue(&mut inbox, from, &[1]) {
            n += 1;
        }
        assert_eq!(n, MAX_QUEUED);
    }
}
