//! Attack traffic against a Myriad server, bounded and on loopback only: what the server's
//! abuse tests and `myriad flood` send (issue 14's table, one function per attack).
//!
//! Every function refuses a target or a source address that is not a loopback address
//! ([`check_loopback`]), and every loop ends by itself: at a count, a rate and a
//! duration ([`Bounds`], at most [`MAX_DURATION`]).
//!
//! - [`udp_flood`]: datagrams from one socket, as fast as it goes or at a rate:
//!   [`UdpKind::LiveSession`] (a live session id in clear, fresh sequence numbers, a
//!   random tag: each one used to cost the server a Poly1305 check),
//!   [`UdpKind::Garbage`], [`UdpKind::Oversized`].
//! - [`max_sequence`]: a correctly sealed datagram with sequence `u64::MAX`, then whether
//!   the session still answers.
//! - [`idle_connections`]: TCP connections to the login port that never speak.
//! - [`login_storm`]: wrong-password logins from many loopback addresses at once.
//! - [`probe_login`]: one legitimate login, timed (what the defences must keep working).

use std::collections::BTreeMap;
use std::net::{IpAddr, Ipv4Addr, SocketAddr, UdpSocket};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use myriad_protocol::login::LoginAccepted;
use myriad_protocol::{
    ClientMessage, ClientSession, HEADER_LEN, Header, MAX_DATAGRAM, MIN_DATAGRAM, PacketKind, ServerMessage,
};

use crate::connection::{ClientConfig, Credentials, connect_from, login};
use crate::error::ClientError;

/// The longest any flood may run.
pub const MAX_DURATION: Duration = Duration::from_secs(300);

/// Where a flood stops: whichever comes first.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bounds {
    /// Most datagrams or attempts (0: no count limit, the duration still holds).
    pub count: u64,
    /// Per second at most (0: as fast as one socket or task goes).
    pub rate: f64,
    /// How long, at most [`MAX_DURATION`].
    pub duration: Duration,
}

impl Bounds {
    /// `duration` long, no count or rate limit.
    pub fn for_time(duration: Duration) -> Self {
        Bounds { count: 0, rate: 0.0, duration }
    }

    fn end(&self) -> Instant {
        Instant::now() + self.duration.min(MAX_DURATION)
    }

    fn count_done(&self, n: u64) -> bool {
        self.count > 0 && n >= self.count
    }

    /// How many may have gone by `elapsed` at the rate (unlimited without one).
    fn allowed(&self, elapsed: Duration) -> u64 {
        if self.rate > 0.0 { (elapsed.as_secs_f64() * self.rate) as u64 + 1 } else { u64::MAX }
    }
}

/// Refuses any address that is not loopback: floods and the lossy relay
/// ([`crate::relay`]) must never leave the machine.
pub fn check_loopback(ip: IpAddr) -> Result<(), ClientError> {
    if ip.is_loopback() || ip.to_canonical().is_loopback() {
        Ok(())
    } else {
        Err(ClientError::Invalid(format!("{ip} is not a loopback address: this traffic stays on this machine")))
    }
}

/// The loopback addresses `127.0.0.<first>` to `127.0.0.<first + n - 1>` (wrapping into
/// the next octets), for attacks from many addresses.
pub fn loopback_sources(first: u32, n: u32) -> Vec<IpAddr> {
    (0..n)
        .map(|i| {
            let x = (127u32 << 24) | (first + i).min(0x00ff_fffe);
            IpAddr::V4(Ipv4Addr::from(x))
        })
        .collect()
}

/// A small non-cryptographic generator (the bytes only need to look random).
struct Noise(u64);

impl Noise {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    fn fill(&mut self, out: &mut [u8]) {
        for chunk in out.chunks_mut(8) {
            let v = self.next().to_le_bytes();
            chunk.copy_from_slice(&v[..chunk.len()]);
        }
    }
}

/// What a UDP flood sends.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UdpKind {
    /// Action datagrams naming `session_id` (which travels in clear), with fresh
    /// sequence numbers from `first_sequence` up and a random body and tag.
    LiveSession {
        /// The session named.
        session_id: u64,
        /// The first sequence number used.
        first_sequence: u64,
    },
    /// Random bytes of random length (34 to 1200).
    Garbage,
    /// 1,400-byte datagrams (over the protocol's 1,200).
    Oversized,
}

/// What a UDP flood did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct UdpReport {
    /// Datagrams sent.
    pub sent: u64,
    /// Sends the kernel refused (buffer full and the like).
    pub send_errors: u64,
    /// Datagrams that came back to the flooding socket (the server must send none).
    pub replies: u64,
    /// Seconds it ran.
    pub seconds: f64,
}

impl UdpReport {
    /// Datagrams sent per second.
    pub fn rate(&self) -> f64 {
        self.sent as f64 / self.seconds.max(1e-9)
    }
}

/// Sends `kind` from one socket on `source` (port chosen by the system) to `target`
/// within `bounds`; blocking (run it on a thread of its own).
pub fn udp_flood(target: SocketAddr, source: IpAddr, kind: UdpKind, bounds: Bounds) -> Result<UdpReport, ClientError> {
    check_loopback(target.ip())?;
    check_loopback(source)?;
    let socket = UdpSocket::bind(SocketAddr::new(source, 0)).map_err(ClientError::io("binding the flood socket"))?;
    socket.set_nonblocking(true).map_err(ClientError::io("configuring the flood socket"))?;
    let mut noise = Noise(u64::from(std::process::id()) << 32 | u64::from(target.port()));
    let mut buf = vec![0u8; 1400];
    let mut sequence = match kind {
        UdpKind::LiveSession { first_sequence, .. } => first_sequence,
        _ => 0,
    };
    let mut report = UdpReport::default();
    let start = Instant::now();
    let end = bounds.end();
    let mut reply = [0u8; 2048];
    'outer: loop {
        let now = Instant::now();
        if now >= end {
            break;
        }
        let allowed = bounds.allowed(now - start);
        // Send in chunks of up to 256, checking the clock and the rate between them.
        for _ in 0..256 {
            if bounds.count_done(report.sent) || report.sent >= allowed {
                if bounds.count_done(report.sent) {
                    break 'outer;
                }
                std::thread::sleep(Duration::from_micros(200));
                break;
            }
            let len = match kind {
                UdpKind::LiveSession { session_id, .. } => {
                    let len = MIN_DATAGRAM + 5;
                    let head: &mut [u8; HEADER_LEN] =
                        (&mut buf[..HEADER_LEN]).try_into().map_err(|_| ClientError::Invalid("header".into()))?;
                    Header { kind: PacketKind::Action, session_id, sequence }.write(head);
                    sequence = sequence.wrapping_add(1).min(u64::MAX - 1);
                    noise.fill(&mut buf[HEADER_LEN..len]);
                    len
                }
                UdpKind::Garbage => {
                    let len = MIN_DATAGRAM + (noise.next() as usize % (MAX_DATAGRAM - MIN_DATAGRAM + 1));
                    noise.fill(&mut buf[..len]);
                    len
                }
                UdpKind::Oversized => {
                    noise.fill(&mut buf[..1400]);
                    1400
                }
            };
            match socket.send_to(&buf[..len], target) {
                Ok(_) => report.sent += 1,
                Err(_) => {
                    report.send_errors += 1;
                    std::thread::yield_now();
                }
            }
        }
        while socket.recv_from(&mut reply).is_ok() {
            report.replies += 1;
        }
    }
    // Anything the server sent back in the last moment.
    std::thread::sleep(Duration::from_millis(50));
    while socket.recv_from(&mut reply).is_ok() {
        report.replies += 1;
    }
    report.seconds = start.elapsed().as_secs_f64();
    Ok(report)
}

/// What [`max_sequence`] saw.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MaxSequenceReport {
    /// Whether anything came back to the `u64::MAX` datagram (it must not).
    pub answered_forged: bool,
    /// Whether the session still answered a normal KeepAlive afterwards.
    pub session_alive: bool,
}

/// Logs in, sends a sealed `Ready` with sequence `u64::MAX`, then a normal `KeepAlive`
/// with the session's own sealer, and reports whether the session still answers.
pub async fn max_sequence(config: &ClientConfig, credentials: &Credentials) -> Result<MaxSequenceReport, ClientError> {
    let (accepted, _) = login(config, credentials).await?;
    let udp = SocketAddr::new(config.login_addr.ip(), accepted.udp_port);
    check_loopback(udp.ip())?;
    let socket = tokio::net::UdpSocket::bind(SocketAddr::new(config.login_addr.ip(), 0))
        .await
        .map_err(ClientError::io("binding a UDP socket"))?;
    let forged = myriad_protocol::session::forge_sealed(&accepted.keys, PacketKind::Ready, u64::MAX);
    socket.send_to(&forged, udp).await.map_err(ClientError::io("sending"))?;
    let mut buf = [0u8; 2048];
    let answered_forged =
        matches!(tokio::time::timeout(Duration::from_millis(300), socket.recv_from(&mut buf)).await, Ok(Ok(_)));
    let mut session = ClientSession::new(&accepted.keys);
    let session_alive = keepalive_answered(&socket, udp, &mut session).await?;
    Ok(MaxSequenceReport { answered_forged, session_alive })
}

/// Sends a KeepAlive (and Ready, which the server answers with ServerInfo) and waits up
/// to 2 s for a KeepAlive or ServerInfo that opens under the session.
async fn keepalive_answered(
    socket: &tokio::net::UdpSocket,
    to: SocketAddr,
    session: &mut ClientSession,
) -> Result<bool, ClientError> {
    let mut buf = [0u8; 2048];
    let end = Instant::now() + Duration::from_secs(2);
    for msg in [ClientMessage::KeepAlive { acks: None }, ClientMessage::Ready] {
        let mut d = Vec::new();
        session.seal(&msg, &mut d).map_err(|e| ClientError::Protocol(e.to_string()))?;
        socket.send_to(&d, to).await.map_err(ClientError::io("sending"))?;
    }
    while Instant::now() < end {
        let Ok(Ok((n, _))) = tokio::time::timeout(end - Instant::now(), socket.recv_from(&mut buf)).await else {
            break;
        };
        if let Ok(o) = session.open(&mut buf[..n])
            && matches!(o.message, ServerMessage::KeepAlive | ServerMessage::ServerInfo(_))
        {
            return Ok(true);
        }
    }
    Ok(false)
}

/// What [`idle_connections`] saw.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct IdleReport {
    /// Connections the kernel completed (the server may still close them at once).
    pub connected: u64,
    /// Connections that failed to connect.
    pub connect_failed: u64,
    /// Of the connected, those the server closed within the first second.
    pub closed_at_once: u64,
    /// Of the connected, those the server closed later, before the hold ended.
    pub closed_later: u64,
    /// Still open when the hold ended.
    pub open_at_end: u64,
}

/// Opens `count` TCP connections from `source` to the login service at `target` that
/// never send a byte, holds them for `hold`, and reports what the server did with them.
pub async fn idle_connections(
    target: SocketAddr,
    source: IpAddr,
    count: u32,
    hold: Duration,
) -> Result<IdleReport, ClientError> {
    check_loopback(target.ip())?;
    check_loopback(source)?;
    let hold = hold.min(MAX_DURATION);
    let mut report = IdleReport::default();
    let mut open = Vec::new();
    for _ in 0..count {
        match connect_from(Some(source), target).await {
            Ok(s) => {
                report.connected += 1;
                open.push(s);
            }
            Err(_) => report.connect_failed += 1,
        }
    }
    let start = Instant::now();
    let mut closed_at: Vec<Option<Duration>> = vec![None; open.len()];
    let end = start + hold;
    loop {
        for (s, closed) in open.iter().zip(closed_at.iter_mut()) {
            if closed.is_none() && is_closed(s) {
                *closed = Some(start.elapsed());
            }
        }
        if Instant::now() >= end || closed_at.iter().all(Option::is_some) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100).min(end.saturating_duration_since(Instant::now()))).await;
    }
    for c in &closed_at {
        match c {
            Some(t) if *t <= Duration::from_secs(1) => report.closed_at_once += 1,
            Some(_) => report.closed_later += 1,
            None => report.open_at_end += 1,
        }
    }
    Ok(report)
}

/// Whether the peer closed (or reset) the connection: a read would return end of stream
/// or an error rather than block.
fn is_closed(s: &tokio::net::TcpStream) -> bool {
    let mut b = [0u8; 1];
    match s.try_read(&mut b) {
        Ok(0) => true,
        Ok(_) => false,
        Err(e) => e.kind() != std::io::ErrorKind::WouldBlock,
    }
}

/// Which accounts a storm tries.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum StormAccounts {
    /// `ghost<i>`: accounts that do not exist.
    Unknown,
    /// One existing account, always with a wrong password.
    One(String),
}

/// What a login storm got back.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct StormReport {
    /// Attempts made.
    pub attempts: u64,
    /// Answers by kind: the refusal reason's text, `accepted`, or the error.
    pub answers: BTreeMap<String, u64>,
    /// Seconds it ran.
    pub seconds: f64,
}

/// `concurrency` tasks log in with wrong passwords, each from the next address of
/// `sources` in turn, until `bounds` end.
pub async fn login_storm(
    config: &ClientConfig,
    sources: &[IpAddr],
    accounts: StormAccounts,
    concurrency: usize,
    bounds: Bounds,
) -> Result<StormReport, ClientError> {
    check_loopback(config.login_addr.ip())?;
    for ip in sources {
        check_loopback(*ip)?;
    }
    if sources.is_empty() {
        return Err(ClientError::Invalid("a storm needs at least one source address".into()));
    }
    let attempts = Arc::new(AtomicU64::new(0));
    let stop = Arc::new(AtomicBool::new(false));
    let answers = Arc::new(std::sync::Mutex::new(BTreeMap::<String, u64>::new()));
    let start = Instant::now();
    let end = bounds.end();
    let mut tasks = Vec::new();
    for _ in 0..concurrency.clamp(1, 4096) {
        let (attempts, stop, answers) = (attempts.clone(), stop.clone(), answers.clone());
        let (sources, accounts, config) = (sources.to_vec(), accounts.clone(), config.clone());
        tasks.push(tokio::spawn(async move {
            while !stop.load(Ordering::Relaxed) && Instant::now() < end {
                let n = attempts.fetch_add(1, Ordering::Relaxed);
                if bounds.count_done(n) {
                    break;
                }
                while n >= bounds.allowed(start.elapsed()) && Instant::now() < end {
                    tokio::time::sleep(Duration::from_millis(5)).await;
                }
                let mut c = config.clone();
                c.local_ip = Some(sources[n as usize % sources.len()]);
                c.login_timeout =
                    c.login_timeout.min(end.saturating_duration_since(Instant::now()) + Duration::from_secs(2));
                let username = match &accounts {
                    StormAccounts::Unknown => format!("ghost{n}"),
                    StormAccounts::One(name) => name.clone(),
                };
                let creds = Credentials { username, password: format!("wrong{n}") };
                let answer = match login(&c, &creds).await {
                    Ok(_) => "accepted".to_string(),
                    Err(ClientError::Refused { reason, .. }) => reason.to_string(),
                    Err(e) => format!("error: {}", short_error(&e)),
                };
                *answers.lock().unwrap_or_else(|p| p.into_inner()).entry(answer).or_default() += 1;
            }
        }));
    }
    for t in tasks {
        let _ = t.await;
    }
    stop.store(true, Ordering::Relaxed);
    let answers = answers.lock().unwrap_or_else(|p| p.into_inner()).clone();
    let attempts = answers.values().sum();
    Ok(StormReport { attempts, answers, seconds: start.elapsed().as_secs_f64() })
}

fn short_error(e: &ClientError) -> String {
    match e {
        ClientError::Io { what, source } => format!("{what}: {:?}", source.kind()),
        other => other.to_string(),
    }
}

/// One legitimate login from `source`, timed.
#[derive(Debug)]
pub struct Probe {
    /// How long the answer took.
    pub latency: Duration,
    /// The server's answer.
    pub result: Result<Box<LoginAccepted>, ClientError>,
}

/// Logs `credentials` in from `source` (any loopback address) and times the answer.
pub async fn probe_login(config: &ClientConfig, credentials: &Credentials, source: IpAddr) -> Probe {
    let start = Instant::now();
    let result = match check_loopback(source).and_then(|()| check_loopback(config.login_addr.ip())) {
        Err(e) => Err(e),
        Ok(()) => {
            let mut c = config.clone();
            c.local_ip = Some(source);
            login(&c, credentials).await.map(|(a, _)| Box::new(a))
        }
    };
    Probe { latency: start.elapsed(), result }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_loopback_targets_and_sources() {
        assert!(check_loopback("127.0.0.1".parse().unwrap()).is_ok());
        assert!(check_loopback("127.4.5.6".parse().unwrap()).is_ok());
        assert!(check_loopback("::1".parse().unwrap()).is_ok());
        assert!(check_loopback("::ffff:127.0.0.1".parse().unwrap()).is_ok());
        for bad in ["10.0.0.1", "192.168.1.1", "8.8.8.8", "::", "0.0.0.0", "2001:db8::1"] {
            assert!(check_loopback(bad.parse().unwrap()).is_err(), "{bad}");
        }
        let r = udp_flood(
            "8.8.8.8:7777".parse().unwrap(),
            "127.0.0.1".parse().unwrap(),
            UdpKind::Garbage,
            Bounds::for_time(Duration::from_millis(1)),
        );
        assert!(r.is_err(), "a non-loopback target is refused before anything is sent");
    }

    #[test]
    fn sources_are_consecutive_loopback_addresses() {
        let s = loopback_sources(2, 300);
        assert_eq!(s[0], "127.0.0.2".parse::<IpAddr>().unwrap());
        assert_eq!(s[299], "127.0.1.45".parse::<IpAddr>().unwrap());
        assert!(s.iter().all(|ip| ip.is_loopback()));
    }

    #[test]
    fn a_flood_stops_at_its_count() {
        let sink = UdpSocket::bind("127.0.0.1:0").unwrap();
        let bounds = Bounds { count: 500, rate: 0.0, duration: Duration::from_secs(5) };
        let r = udp_flood(sink.local_addr().unwrap(), "127.0.0.1".parse().unwrap(), UdpKind::Garbage, bounds).unwrap();
        assert_eq!(r.sent, 500);
        assert_eq!(r.replies, 0);
    }
}
