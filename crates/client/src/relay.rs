//! A lossy UDP relay on loopback: drops, delays (with jitter), duplicates and reorders
//! datagrams both ways between clients and a server, as a real network would (this
//! machine's kernel has no `netem`). The protocol's tests and `myriad relay` use it.
//!
//! Clients send to [`RelayConfig::listen`]; for each client address the relay opens a
//! socket of its own towards [`RelayConfig::server`], so the server sees one stable
//! address a client and answers there, and what comes back is forwarded to that client.
//!
//! **Deterministic given the seed**: every decision about the `i`-th datagram of a
//! direction is drawn from that direction's stream of [`myriad_core::rng::Stream`], the
//! same number of draws for every datagram, so the same seed and the same datagrams in the
//! same order meet the same fate. (Which datagram comes `i`-th still depends on the
//! timing of the senders.) [`DropFirst`] rules drop the first datagrams of a kind whatever
//! the dice say, for tests that must lose exactly one Ready.
//!
//! **Bounded and local**: both addresses must be loopback ones, the relay stops after
//! [`RelayConfig::duration`] (at most [`MAX_DURATION`]) or [`RelayConfig::max_datagrams`],
//! and it serves at most [`MAX_PEERS`] client addresses.

use std::cmp::Ordering as CmpOrdering;
use std::collections::{BinaryHeap, HashMap};
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use myriad_core::rng::Stream;
use myriad_protocol::{Direction, PacketKind, peek_header};
use tokio::net::UdpSocket;
use tokio::sync::{mpsc, oneshot};
use tokio::task::JoinSet;
use tokio::time::Instant;

use crate::error::ClientError;
use crate::flood::check_loopback;

/// The longest a relay may run.
pub const MAX_DURATION: Duration = Duration::from_secs(3600);

/// Client addresses a relay serves at most (each costs a socket and a task).
pub const MAX_PEERS: usize = 4096;

/// What the link does to each datagram, in each direction alike.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Link {
    /// Share of datagrams dropped, 0..=1.
    pub loss: f64,
    /// Delay of every datagram.
    pub delay: Duration,
    /// The delay varies uniformly by up to this much either way (never below zero).
    pub jitter: Duration,
    /// Share of datagrams delivered twice (the copy with a delay of its own), 0..=1.
    pub duplicate: f64,
    /// Share of datagrams held back by a further delay plus jitter (and a millisecond),
    /// so that the ones sent after them overtake them, 0..=1.
    pub reorder: f64,
}

impl Link {
    /// A perfect link: nothing lost, delayed, duplicated or reordered.
    pub const PERFECT: Link =
        Link { loss: 0.0, delay: Duration::ZERO, jitter: Duration::ZERO, duplicate: 0.0, reorder: 0.0 };
}

/// Drop the first `count` datagrams of `kind` (its direction is the kind's), whatever
/// the link's dice say.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DropFirst {
    /// The packet kind.
    pub kind: PacketKind,
    /// How many to drop.
    pub count: u32,
}

/// Settings of a relay.
#[derive(Debug, Clone)]
pub struct RelayConfig {
    /// Where clients send (port 0: any free one, see [`Relay::local_addr`]).
    pub listen: SocketAddr,
    /// The server's UDP address.
    pub server: SocketAddr,
    /// What happens to each datagram.
    pub link: Link,
    /// Seed of the decisions.
    pub seed: u64,
    /// The relay stops after this long (at most [`MAX_DURATION`]).
    pub duration: Duration,
    /// The relay stops after this many datagrams received, both ways together.
    pub max_datagrams: u64,
    /// Datagrams dropped deterministically.
    pub drop_first: Vec<DropFirst>,
}

impl RelayConfig {
    /// A relay from `listen` to `server` over `link` for `duration`, seed 1, at most
    /// ten million datagrams.
    pub fn new(listen: SocketAddr, server: SocketAddr, link: Link, duration: Duration) -> Self {
        RelayConfig { listen, server, link, seed: 1, duration, max_datagrams: 10_000_000, drop_first: Vec::new() }
    }

    fn check(&self) -> Result<(), ClientError> {
        // The one loopback rule of this crate's traffic tools (IPv4-mapped addresses too).
        check_loopback(self.listen.ip())?;
        check_loopback(self.server.ip())?;
        let l = &self.link;
        for (what, p) in [("loss", l.loss), ("duplicate", l.duplicate), ("reorder", l.reorder)] {
            if !(0.0..=1.0).contains(&p) {
                return Err(ClientError::Invalid(format!("{what} {p} is not a share in 0..=1")));
            }
        }
        if self.duration > MAX_DURATION {
            return Err(ClientError::Invalid(format!("a relay runs {MAX_DURATION:?} at most")));
        }
        Ok(())
    }
}

/// What one direction of a relay did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DirectionStats {
    /// Datagrams received.
    pub received: u64,
    /// Datagrams dropped by the link's loss.
    pub lost: u64,
    /// Datagrams dropped by a [`DropFirst`] rule.
    pub dropped_by_rule: u64,
    /// Extra copies delivered.
    pub duplicated: u64,
    /// Datagrams held back to be overtaken.
    pub reordered: u64,
    /// Datagrams sent on (copies included).
    pub sent: u64,
}

/// What a relay did, both ways.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RelayStats {
    /// Client to server.
    pub upstream: DirectionStats,
    /// Server to client.
    pub downstream: DirectionStats,
    /// Client addresses served.
    pub peers: u64,
    /// Client addresses turned away ([`MAX_PEERS`]).
    pub peers_refused: u64,
}

/// One direction's counters, as [`DirectionStats`] names them.
#[derive(Debug, Default)]
struct DirectionCounters {
    received: AtomicU64,
    lost: AtomicU64,
    dropped_by_rule: AtomicU64,
    duplicated: AtomicU64,
    reordered: AtomicU64,
    sent: AtomicU64,
}

impl DirectionCounters {
    fn snapshot(&self) -> DirectionStats {
        let f = |c: &AtomicU64| c.load(Ordering::Relaxed);
        DirectionStats {
            received: f(&self.received),
            lost: f(&self.lost),
            dropped_by_rule: f(&self.dropped_by_rule),
            duplicated: f(&self.duplicated),
            reordered: f(&self.reordered),
            sent: f(&self.sent),
        }
    }
}

/// Adds `n` to a counter.
fn add(counter: &AtomicU64, n: u64) {
    counter.fetch_add(n, Ordering::Relaxed);
}

#[derive(Debug, Default)]
struct Counters {
    /// Upstream ([`UP`]) and downstream ([`DOWN`]).
    dirs: [DirectionCounters; 2],
    peers: AtomicU64,
    peers_refused: AtomicU64,
}

impl Counters {
    fn snapshot(&self) -> RelayStats {
        RelayStats {
            upstream: self.dirs[UP].snapshot(),
            downstream: self.dirs[DOWN].snapshot(),
            peers: self.peers.load(Ordering::Relaxed),
            peers_refused: self.peers_refused.load(Ordering::Relaxed),
        }
    }
}

/// The directions' places in `Counters::dirs` and the dice.
const UP: usize = 0;
const DOWN: usize = 1;

/// A running relay.
#[derive(Debug)]
pub struct Relay {
    local_addr: SocketAddr,
    counters: Arc<Counters>,
    stop: Option<oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<()>,
}

impl Relay {
    /// Binds the listening socket and starts relaying on the current tokio runtime.
    pub async fn start(config: RelayConfig) -> Result<Relay, ClientError> {
        config.check()?;
        let listen = UdpSocket::bind(config.listen).await.map_err(ClientError::io("binding the relay"))?;
        let local_addr = listen.local_addr().map_err(ClientError::io("reading the relay's address"))?;
        let counters = Arc::new(Counters::default());
        let (stop, stopped) = oneshot::channel();
        let task = tokio::spawn(run(config, Arc::new(listen), counters.clone(), stopped));
        Ok(Relay { local_addr, counters, stop: Some(stop), task })
    }

    /// Where clients send.
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }

    /// What it did so far.
    pub fn stats(&self) -> RelayStats {
        self.counters.snapshot()
    }

    /// Whether a bound (duration, datagrams) ended the relay.
    pub fn is_finished(&self) -> bool {
        self.task.is_finished()
    }

    /// Waits until a bound (duration, datagrams) ends the relay.
    pub async fn finished(mut self) -> RelayStats {
        let _ = (&mut self.task).await;
        self.counters.snapshot()
    }

    /// Stops relaying now (datagrams still held back are dropped).
    pub async fn stop(mut self) -> RelayStats {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        let _ = (&mut self.task).await;
        self.counters.snapshot()
    }
}

/// The dice of one direction; see the module docs.
struct Dice {
    stream: Stream,
    link: Link,
}

impl Dice {
    /// The delays of the copies of the next datagram (none: lost), and whether each was
    /// held back. Always six draws.
    fn roll(&mut self) -> ([Option<(Duration, bool)>; 2], bool) {
        let s = &mut self.stream;
        let (lost, dup) = (s.unit() < self.link.loss as f32, s.unit() < self.link.duplicate as f32);
        let mut copies = [None, None];
        for (i, copy) in copies.iter_mut().enumerate() {
            let (jitter, held) = (s.range(-1.0, 1.0), s.unit() < self.link.reorder as f32);
            if lost || (i == 1 && !dup) {
                continue;
            }
            let l = &self.link;
            let mut delay = (l.delay.as_secs_f64() + f64::from(jitter) * l.jitter.as_secs_f64()).max(0.0);
            if held {
                delay += (l.delay + l.jitter + Duration::from_millis(1)).as_secs_f64();
            }
            *copy = Some((Duration::from_secs_f64(delay), held));
        }
        (copies, dup && !lost)
    }
}

/// A datagram waiting for its time.
struct Pending {
    due: Instant,
    /// Arrival order, to break ties (so equal delays keep the order).
    order: u64,
    to: Target,
    bytes: Vec<u8>,
}

enum Target {
    /// Upstream, from the client's own socket.
    Server(Arc<UdpSocket>),
    /// Downstream, from the listening socket.
    Client(SocketAddr),
}

impl PartialEq for Pending {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == CmpOrdering::Equal
    }
}
impl Eq for Pending {}
impl PartialOrd for Pending {
    fn partial_cmp(&self, other: &Self) -> Option<CmpOrdering> {
        Some(self.cmp(other))
    }
}
impl Ord for Pending {
    /// Reversed: the heap's top is the earliest.
    fn cmp(&self, other: &Self) -> CmpOrdering {
        (other.due, other.order).cmp(&(self.due, self.order))
    }
}

/// The relay's one task: reads clients' datagrams, gets the server's from the peers'
/// tasks, and sends everything when it is due.
async fn run(config: RelayConfig, listen: Arc<UdpSocket>, counters: Arc<Counters>, mut stop: oneshot::Receiver<()>) {
    let deadline = Instant::now() + config.duration;
    let (tx, mut from_server) = mpsc::channel::<(SocketAddr, Vec<u8>)>(4096);
    let mut peers: HashMap<SocketAddr, Arc<UdpSocket>> = HashMap::new();
    let mut readers = JoinSet::new();
    let mut queue: BinaryHeap<Pending> = BinaryHeap::new();
    let mut dice = [UP, DOWN].map(|d| Dice { stream: Stream::new(config.seed, d as u64), link: config.link });
    let mut rules = config.drop_first.clone();
    let (mut order, mut received) = (0u64, 0u64);
    let mut buf = vec![0u8; 65_536];
    while received < config.max_datagrams {
        let next = queue.peek().map_or(deadline, |p| p.due.min(deadline));
        let (dir, target, bytes) = tokio::select! {
            _ = &mut stop => break,
            _ = tokio::time::sleep_until(next) => {
                if Instant::now() >= deadline {
                    break;
                }
                send_due(&mut queue, &listen, &counters).await;
                continue;
            }
            r = listen.recv_from(&mut buf) => {
                let Ok((n, from)) = r else { continue };
                let Some(socket) = peer(&config, &mut peers, &mut readers, &tx, &counters, from).await else {
                    continue;
                };
                (UP, Target::Server(socket), buf[..n].to_vec())
            }
            Some((client, bytes)) = from_server.recv() => (DOWN, Target::Client(client), bytes),
        };
        received += 1;
        add(&counters.dirs[dir].received, 1);
        let kind = peek_header(&bytes, if dir == UP { Direction::ClientToServer } else { Direction::ServerToClient })
            .ok()
            .map(|h| h.kind);
        let (copies, duplicated) = dice[dir].roll();
        if let Some(rule) = rules.iter_mut().find(|r| Some(r.kind) == kind && r.count > 0) {
            rule.count -= 1;
            add(&counters.dirs[dir].dropped_by_rule, 1);
            continue;
        }
        if copies[0].is_none() {
            add(&counters.dirs[dir].lost, 1);
            continue;
        }
        add(&counters.dirs[dir].duplicated, u64::from(duplicated));
        let now = Instant::now();
        for (delay, held) in copies.into_iter().flatten() {
            add(&counters.dirs[dir].reordered, u64::from(held));
            let to = match &target {
                Target::Server(s) => Target::Server(s.clone()),
                Target::Client(c) => Target::Client(*c),
            };
            order += 1;
            queue.push(Pending { due: now + delay, order, to, bytes: bytes.clone() });
        }
        send_due(&mut queue, &listen, &counters).await;
    }
    readers.abort_all();
}

/// The socket towards the server for client `from`, opened (with its reader task) on
/// its first datagram; `None` when the relay serves [`MAX_PEERS`] already or the socket
/// cannot be opened.
async fn peer(
    config: &RelayConfig,
    peers: &mut HashMap<SocketAddr, Arc<UdpSocket>>,
    readers: &mut JoinSet<()>,
    tx: &mpsc::Sender<(SocketAddr, Vec<u8>)>,
    counters: &Counters,
    from: SocketAddr,
) -> Option<Arc<UdpSocket>> {
    if let Some(s) = peers.get(&from) {
        return Some(s.clone());
    }
    if peers.len() >= MAX_PEERS {
        add(&counters.peers_refused, 1);
        return None;
    }
    let socket = UdpSocket::bind(SocketAddr::new(config.listen.ip(), 0)).await.ok()?;
    socket.connect(config.server).await.ok()?;
    let socket = Arc::new(socket);
    peers.insert(from, socket.clone());
    add(&counters.peers, 1);
    let (reader, tx) = (socket.clone(), tx.clone());
    readers.spawn(async move {
        let mut buf = vec![0u8; 65_536];
        // An error here is an ICMP report of an earlier send (the server's port closed):
        // it concerns no datagram; read on.
        loop {
            if let Ok(n) = reader.recv(&mut buf).await
                && tx.send((from, buf[..n].to_vec())).await.is_err()
            {
                return;
            }
        }
    });
    Some(socket)
}

/// Sends every held datagram whose time has come.
async fn send_due(queue: &mut BinaryHeap<Pending>, listen: &UdpSocket, counters: &Counters) {
    let now = Instant::now();
    while queue.peek().is_some_and(|p| p.due <= now) {
        let p = queue.pop().expect("peeked");
        let (dir, sent) = match &p.to {
            Target::Server(s) => (UP, s.send(&p.bytes).await.is_ok()),
            Target::Client(c) => (DOWN, listen.send_to(&p.bytes, c).await.is_ok()),
        };
        add(&counters.dirs[dir].sent, u64::from(sent));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn link() -> Link {
        Link {
            loss: 0.1,
            delay: Duration::from_millis(50),
            jitter: Duration::from_millis(20),
            duplicate: 0.05,
            reorder: 0.05,
        }
    }

    #[test]
    fn the_dice_are_a_function_of_the_seed_and_count() {
        let roll = |seed| {
            let mut d = Dice { stream: Stream::new(seed, 0), link: link() };
            (0..1000).map(|_| d.roll()).collect::<Vec<_>>()
        };
        assert_eq!(roll(7), roll(7));
        assert_ne!(roll(7), roll(8));
        let rolls = roll(7);
        let lost = rolls.iter().filter(|r| r.0[0].is_none()).count();
        let dup = rolls.iter().filter(|r| r.1).count();
        assert!((70..130).contains(&lost), "about 10 % lost: {lost}");
        assert!((25..75).contains(&dup), "about 5 % duplicated: {dup}");
        for (copies, _) in &rolls {
            for &(delay, held) in copies.iter().flatten() {
                let (lo, hi) = if held { (101, 141) } else { (30, 70) };
                assert!((lo..=hi).contains(&delay.as_millis()), "{delay:?} held {held}");
            }
        }
    }

    #[test]
    fn only_loopback_addresses_are_relayed() {
        let any = |a: &str, b: &str| {
            RelayConfig::new(a.parse().unwrap(), b.parse().unwrap(), Link::PERFECT, Duration::from_secs(1)).check()
        };
        assert!(any("127.0.0.1:0", "127.0.0.2:9").is_ok());
        assert!(any("0.0.0.0:0", "127.0.0.2:9").is_err());
        assert!(any("127.0.0.1:0", "10.0.0.1:9").is_err());
        let mut c =
            RelayConfig::new("127.0.0.1:0".parse().unwrap(), "127.0.0.1:9".parse().unwrap(), link(), MAX_DURATION);
        assert!(c.check().is_ok());
        c.duration += Duration::from_secs(1);
        assert!(c.check().is_err(), "bounded");
        c.duration = Duration::from_secs(1);
        c.link.loss = 1.5;
        assert!(c.check().is_err());
    }
}
