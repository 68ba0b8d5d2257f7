//! A logged-in client: the TLS login, then the sealed UDP session.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use myriad_protocol::login::{
    FRAME_PREFIX_LEN, LoginAccepted, LoginRequest, LoginResponse, MAX_RESPONSE_FRAME, MapData, frame_len,
};
use myriad_protocol::{
    ActionMask, ClientMessage, ClientSession, DeltaUpdateView, DisconnectReason, ErrorClass, MAX_DATAGRAM, OpenError,
    PlayerInput, ServerInfo, ServerMessage, StateRecord, UpdateReceiver,
};
use rustls::pki_types::ServerName;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpStream, UdpSocket};

use crate::error::ClientError;
use crate::liveness::{DISCONNECT_COPIES, Due, Liveness};
use crate::mirror::{Interpolation, WorldMirror};
use crate::stats::{ClientStats, SequenceTracker};
use crate::tls::Trust;

/// Where and how to connect.
#[derive(Debug, Clone)]
pub struct ClientConfig {
    /// The login service (TCP, TLS).
    pub login_addr: SocketAddr,
    /// The name to check the certificate against (ignored when pinning).
    pub server_name: String,
    /// rustls configuration built from a [`Trust`].
    pub tls: Arc<rustls::ClientConfig>,
    /// Objects without news for this long are marked stale in the mirror.
    pub stale_after: Duration,
    /// The mirror's render delay and extrapolation cap ([`WorldMirror::render_tick`]).
    pub interpolation: Interpolation,
    /// A keep-alive is sent when nothing was sent for this long ([`Connection::on_timer`];
    /// zero: no regular keep-alives, the caller sends its own with
    /// [`Connection::keepalive_if_due`]).
    pub keepalive_every: Duration,
    /// A session that was silent this long, its keep-alive probes unanswered, is over
    /// ([`SessionEnd::Silent`]; the rule is in `liveness.rs`).
    pub silence_timeout: Duration,
    /// Deadline of a login.
    pub login_timeout: Duration,
    /// Ask for the terrain and static objects at login.
    pub want_map: bool,
    /// Local address to connect from (none: the system picks). Lets a test or the flood
    /// tool log in from `127.0.0.2` and so on, as another client would.
    pub local_ip: Option<std::net::IpAddr>,
    /// Login request version to send ([`myriad_protocol::login::LOGIN_VERSION`]). An
    /// older version is for tests and the flood tool: a server refuses it as
    /// [`myriad_protocol::login::RefusalReason::OutdatedClient`] (this client speaks
    /// datagram protocol 3 only).
    pub login_version: u8,
}

impl ClientConfig {
    /// Defaults for a server at `login_addr` trusted through `trust`.
    pub fn new(login_addr: SocketAddr, trust: &Trust) -> Result<Self, ClientError> {
        Ok(Self {
            login_addr,
            server_name: "localhost".into(),
            tls: trust.client_config()?,
            stale_after: Duration::from_secs(1),
            interpolation: Interpolation::default(),
            keepalive_every: Duration::from_secs(1),
            silence_timeout: Duration::from_secs(5),
            login_timeout: Duration::from_secs(30),
            want_map: false,
            local_ip: None,
            login_version: myriad_protocol::login::LOGIN_VERSION,
        })
    }
}

/// A username and password. `Debug` does not print the password.
#[derive(Clone, PartialEq, Eq)]
pub struct Credentials {
    /// Account name.
    pub username: String,
    /// Password.
    pub password: String,
}

impl std::fmt::Debug for Credentials {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Credentials").field("username", &self.username).finish_non_exhaustive()
    }
}

impl Credentials {
    /// The reference's test account `user<i>` / `password<i>`.
    pub fn test_user(i: usize) -> Self {
        Self { username: format!("user{i}"), password: format!("password{i}") }
    }
}

/// Logs in over TLS; returns the server's answer and, when asked for, the map.
pub async fn login(
    config: &ClientConfig,
    credentials: &Credentials,
) -> Result<(LoginAccepted, Option<MapData>), ClientError> {
    tokio::time::timeout(config.login_timeout, async {
        // No fallback to an older login version: this client speaks datagram protocol 3
        // only, which an older login would not promise the server.
        login_inner(config, credentials, config.login_version).await
    })
    .await
    .map_err(|_| ClientError::Timeout("login"))?
}

async fn login_inner(
    config: &ClientConfig,
    credentials: &Credentials,
    version: u8,
) -> Result<(LoginAccepted, Option<MapData>), ClientError> {
    let mut request = LoginRequest::new(credentials.username.clone(), credentials.password.clone(), config.want_map);
    request.version = version;
    let mut frame = Vec::new();
    request.encode(&mut frame).map_err(|e| ClientError::Invalid(e.to_string()))?;
    let tcp = connect_from(config.local_ip, config.login_addr)
        .await
        .map_err(ClientError::io("connecting to the login service"))?;
    let _ = tcp.set_nodelay(true);
    let name = ServerName::try_from(config.server_name.clone())
        .map_err(|e| ClientError::Invalid(format!("server name {:?}: {e}", config.server_name)))?;
    let connector = tokio_rustls::TlsConnector::from(config.tls.clone());
    let mut tls = connector.connect(name, tcp).await.map_err(ClientError::io("TLS handshake"))?;
    tls.write_all(&frame).await.map_err(ClientError::io("sending the login"))?;
    let body = read_frame(&mut tls).await?;
    let accepted = match LoginResponse::decode(&body).map_err(|e| ClientError::Protocol(e.to_string()))? {
        LoginResponse::Accepted(a) => *a,
        LoginResponse::Refused(r) => {
            return Err(ClientError::Refused { reason: r.reason, retry_after_ms: r.retry_after_ms });
        }
    };
    let map = if config.want_map {
        let body = read_frame(&mut tls).await?;
        Some(MapData::decode(&body).map_err(|e| ClientError::Protocol(e.to_string()))?)
    } else {
        None
    };
    Ok((accepted, map))
}

/// A TCP connection to `to`, from `local` (any port) when given.
pub(crate) async fn connect_from(local: Option<std::net::IpAddr>, to: SocketAddr) -> std::io::Result<TcpStream> {
    let Some(ip) = local else { return TcpStream::connect(to).await };
    let socket = if to.is_ipv4() { tokio::net::TcpSocket::new_v4()? } else { tokio::net::TcpSocket::new_v6()? };
    socket.bind(SocketAddr::new(ip, 0))?;
    socket.connect(to).await
}

async fn read_frame<S: AsyncReadExt + Unpin>(s: &mut S) -> Result<Vec<u8>, ClientError> {
    let mut prefix = [0u8; FRAME_PREFIX_LEN];
    s.read_exact(&mut prefix).await.map_err(ClientError::io("reading the login response"))?;
    let len = frame_len(prefix, MAX_RESPONSE_FRAME).map_err(|e| ClientError::Protocol(e.to_string()))?;
    let mut body = vec![0u8; len];
    s.read_exact(&mut body).await.map_err(ClientError::io("reading the login response"))?;
    Ok(body)
}

/// What one received datagram meant.
#[derive(Debug, Clone, PartialEq)]
pub enum Event {
    /// A state update for `tick` with this many records.
    Update {
        /// Server tick.
        tick: u64,
        /// Records of the datagram applied to the mirror (those whose baseline the
        /// client held; see [`ClientStats::unresolved`]).
        records: usize,
        /// Time dilation in thousandths.
        dilation_permille: u16,
    },
    /// Tick rate and dilation (answer to Ready).
    Info(ServerInfo),
    /// The server's keep-alive.
    KeepAlive,
    /// The server ended the session.
    Disconnected(DisconnectReason),
    /// The datagram was dropped (not authentic, replayed, malformed).
    Rejected,
}

/// Why a session is over, as the client decides it from evidence: the server said so,
/// or it stayed silent through the retries ([`ClientConfig::silence_timeout`]). One lost
/// datagram is never such evidence.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SessionEnd {
    /// The server ended the session.
    Disconnected(DisconnectReason),
    /// Nothing authentic arrived for the silence timeout, keep-alive probes included.
    Silent,
}

/// A logged-in player: the UDP session and the world mirror.
pub struct Connection {
    config: ClientConfig,
    credentials: Credentials,
    socket: Arc<UdpSocket>,
    /// Whether the socket is this connection's alone (a reconnect then opens a new one).
    owns_socket: bool,
    session: ClientSession,
    accepted: LoginAccepted,
    map: Option<MapData>,
    mirror: WorldMirror,
    /// Every object's states of the last 63 ticks, which delta records are relative to,
    /// and the server datagrams to acknowledge in the next action or keep-alive.
    receiver: UpdateReceiver,
    /// One update's records once resolved (reused).
    resolved: Vec<StateRecord>,
    stats: ClientStats,
    sequences: SequenceTracker,
    frame: u32,
    last_sent: Instant,
    out: Vec<u8>,
    dilation_permille: u16,
    disconnected: Option<DisconnectReason>,
    /// The session's retransmission and silence timers (made afresh by every login).
    liveness: Liveness,
}

impl std::fmt::Debug for Connection {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Connection")
            .field("user", &self.credentials.username)
            .field("entity", &self.accepted.entity_id)
            .finish_non_exhaustive()
    }
}

impl Connection {
    /// Logs in, opens the UDP session on a socket of its own and sends Ready.
    pub async fn connect(config: ClientConfig, credentials: Credentials) -> Result<Self, ClientError> {
        let (accepted, map) = login(&config, &credentials).await?;
        let socket = Arc::new(open_socket(&config, accepted.udp_port).await?);
        Self::on_socket(config, credentials, accepted, map, socket, true).await
    }

    /// The session of a login already made (`accepted`, `map`) on `socket`, which
    /// [`server_socket`] connected to the server's UDP port and which other connections
    /// may share: the server tells sessions apart by id, so many players can sit behind
    /// one address, and whoever reads the socket hands each datagram to the connection
    /// whose [`session_id`](Self::session_id) its header names
    /// ([`Connection::handle_datagram`]). Sends Ready.
    pub async fn from_login(
        config: ClientConfig,
        credentials: Credentials,
        accepted: LoginAccepted,
        map: Option<MapData>,
        socket: Arc<UdpSocket>,
    ) -> Result<Self, ClientError> {
        check_peer(&socket, &config, accepted.udp_port)?;
        Self::on_socket(config, credentials, accepted, map, socket, false).await
    }

    async fn on_socket(
        config: ClientConfig,
        credentials: Credentials,
        accepted: LoginAccepted,
        map: Option<MapData>,
        socket: Arc<UdpSocket>,
        owns_socket: bool,
    ) -> Result<Self, ClientError> {
        let session = ClientSession::new(&accepted.keys);
        let liveness = Liveness::start(Instant::now(), config.silence_timeout);
        let mut mirror = WorldMirror::new(config.stale_after).with_interpolation(config.interpolation);
        mirror.set_timing(accepted.tick_rate_hz, accepted.dilation_permille, Instant::now());
        let mut c = Connection {
            mirror,
            receiver: UpdateReceiver::default(),
            resolved: Vec::new(),
            dilation_permille: accepted.dilation_permille,
            config,
            credentials,
            socket,
            owns_socket,
            session,
            accepted,
            map,
            stats: ClientStats::default(),
            sequences: SequenceTracker::default(),
            frame: 0,
            last_sent: Instant::now(),
            out: Vec::with_capacity(64),
            disconnected: None,
            liveness,
        };
        c.send(ClientMessage::Ready).await?;
        Ok(c)
    }

    /// Logs in again with the same credentials (after a drop or a server restart): new
    /// keys, a new socket (the same one when the socket is shared), empty mirror;
    /// statistics carry on.
    pub async fn reconnect(&mut self) -> Result<(), ClientError> {
        let (accepted, map) = login(&self.config, &self.credentials).await?;
        let socket = if self.owns_socket {
            Arc::new(open_socket(&self.config, accepted.udp_port).await?)
        } else {
            self.socket.clone()
        };
        self.resume(accepted, map, socket).await
    }

    /// Takes a new login of the same credentials (made by the caller, for a socket it
    /// shares) on `socket` (the shared one, or a new one if the server's UDP port moved):
    /// new keys, empty mirror; statistics carry on. Sends Ready.
    pub async fn resume(
        &mut self,
        accepted: LoginAccepted,
        map: Option<MapData>,
        socket: Arc<UdpSocket>,
    ) -> Result<(), ClientError> {
        check_peer(&socket, &self.config, accepted.udp_port)?;
        self.socket = socket;
        self.session = ClientSession::new(&accepted.keys);
        self.dilation_permille = accepted.dilation_permille;
        self.accepted = accepted;
        if map.is_some() {
            self.map = map;
        }
        self.mirror.clear();
        self.mirror.set_timing(self.accepted.tick_rate_hz, self.dilation_permille, Instant::now());
        // A new session numbers its datagrams afresh and knows nothing we hold.
        self.receiver = UpdateReceiver::default();
        self.sequences = SequenceTracker::default();
        self.disconnected = None;
        self.liveness = Liveness::start(Instant::now(), self.config.silence_timeout);
        self.stats.reconnects += 1;
        self.send(ClientMessage::Ready).await
    }

    /// The session id, which the header of every datagram of this session carries.
    pub fn session_id(&self) -> u64 {
        self.accepted.keys.session_id
    }

    /// The login's answer: entity id, spawn position, shape, map description.
    pub fn accepted(&self) -> &LoginAccepted {
        &self.accepted
    }

    /// The player's object id.
    pub fn entity_id(&self) -> u64 {
        self.accepted.entity_id
    }

    /// The map data, if it was asked for.
    pub fn map(&self) -> Option<&MapData> {
        self.map.as_ref()
    }

    /// The mirror of the world around the player.
    pub fn mirror(&self) -> &WorldMirror {
        &self.mirror
    }

    /// Mutable access to the mirror (stale marking).
    pub fn mirror_mut(&mut self) -> &mut WorldMirror {
        &mut self.mirror
    }

    /// The player's own object as last heard.
    pub fn own_position(&self) -> Option<[f32; 3]> {
        self.mirror.get(self.accepted.entity_id).map(|o| o.position)
    }

    /// Counters so far.
    pub fn stats(&self) -> ClientStats {
        self.stats
    }

    /// Time dilation last announced.
    pub fn dilation_permille(&self) -> u16 {
        self.dilation_permille
    }

    /// Why the server ended the session, if it did.
    pub fn disconnected(&self) -> Option<DisconnectReason> {
        self.disconnected
    }

    /// Whether the session is over, and why: the server's Disconnect, or silence through
    /// the retries ([`Connection::on_timer`] decides that).
    pub fn ended(&self) -> Option<SessionEnd> {
        match self.disconnected {
            Some(reason) => Some(SessionEnd::Disconnected(reason)),
            None => self.liveness.silent().then_some(SessionEnd::Silent),
        }
    }

    /// The UDP socket (to wait for datagrams in a `select!`).
    pub fn socket(&self) -> Arc<UdpSocket> {
        self.socket.clone()
    }

    /// Sends the held inputs (a 5-bit mask) for the next client frame.
    pub async fn send_action(&mut self, mask: u8) -> Result<(), ClientError> {
        let mask = ActionMask::new(mask).ok_or_else(|| ClientError::Invalid(format!("action mask {mask:#x}")))?;
        self.frame = self.frame.wrapping_add(1);
        let input = PlayerInput { mask, client_frame: self.frame };
        self.send(ClientMessage::Action { input, acks: self.receiver.acks() }).await
    }

    /// Sends a keep-alive if nothing was sent for the keep-alive interval.
    pub async fn keepalive_if_due(&mut self) -> Result<(), ClientError> {
        if self.last_sent.elapsed() >= self.config.keepalive_every {
            self.send(ClientMessage::KeepAlive { acks: self.receiver.acks() }).await?;
        }
        Ok(())
    }

    /// The session's timers, for every caller's loop (a few times a second or more; a
    /// game's frame or a bot's tick): resends Ready until the session starts, probes a
    /// silent server with keep-alives and declares it [`SessionEnd::Silent`] when they
    /// go unanswered, and sends the regular keep-alive
    /// ([`ClientConfig::keepalive_every`]). [`Connection::recv`] calls it too.
    pub async fn on_timer(&mut self, now: Instant) -> Result<(), ClientError> {
        if self.disconnected.is_some() {
            return Ok(());
        }
        while let Some(due) = self.liveness.due(now) {
            self.stats.resent += 1;
            match due {
                Due::Ready => self.send(ClientMessage::Ready).await?,
                Due::Probe => self.send(ClientMessage::KeepAlive { acks: self.receiver.acks() }).await?,
            }
        }
        if !self.config.keepalive_every.is_zero() {
            self.keepalive_if_due().await?;
        }
        Ok(())
    }

    /// Tells the server we leave: [`DISCONNECT_COPIES`] datagrams, so that a lost one
    /// does not leave the session to its time-out (nothing answers them).
    pub async fn disconnect(&mut self) -> Result<(), ClientError> {
        for _ in 0..DISCONNECT_COPIES {
            self.send(ClientMessage::Disconnect).await?;
        }
        Ok(())
    }

    async fn send(&mut self, msg: ClientMessage) -> Result<(), ClientError> {
        self.out.clear();
        self.session.seal(&msg, &mut self.out).map_err(|e| ClientError::Protocol(e.to_string()))?;
        self.socket.send(&self.out).await.map_err(ClientError::io("sending a datagram"))?;
        self.stats.sent += 1;
        self.last_sent = Instant::now();
        Ok(())
    }

    /// Runs the timers ([`Connection::on_timer`]), then waits up to `timeout` for one
    /// datagram and handles it; `None` on timeout.
    pub async fn recv(&mut self, timeout: Duration) -> Result<Option<Event>, ClientError> {
        self.on_timer(Instant::now()).await?;
        let mut buf = [0u8; MAX_DATAGRAM + 64];
        let socket = self.socket.clone();
        match tokio::time::timeout(timeout, socket.recv(&mut buf)).await {
            Err(_) => Ok(None),
            Ok(Err(e)) => Err(ClientError::Io { what: "receiving a datagram", source: e }),
            Ok(Ok(n)) => Ok(Some(self.handle_datagram(&mut buf[..n], Instant::now()))),
        }
    }

    /// Opens and applies one datagram received on [`Connection::socket`].
    pub fn handle_datagram(&mut self, datagram: &mut [u8], now: Instant) -> Event {
        let len = datagram.len() as u64;
        let opened = match self.session.opener.open_with(datagram, |kind, body| {
            // State updates are applied straight from the zero-copy view below; decode
            // everything else fully.
            if kind == myriad_protocol::PacketKind::StateUpdate {
                DeltaUpdateView::parse(body).map(|_| None)
            } else {
                ServerMessage::decode_body(kind, body).map(Some)
            }
        }) {
            Ok(o) => o,
            Err(e) => {
                self.stats.rejected += 1;
                // A datagram for another session is not a decode error: after a
                // reconnect, an ephemeral port can be reused while the server still
                // addresses an old session to it.
                if e.class() == ErrorClass::Malformed && !matches!(e, OpenError::WrongSession { .. }) {
                    self.stats.decode_errors += 1;
                }
                return Event::Rejected;
            }
        };
        self.stats.datagrams += 1;
        self.stats.bytes += len;
        self.stats.lost += self.sequences.record(opened.header.sequence);
        let started = matches!(opened.message, None | Some(ServerMessage::ServerInfo(_)));
        self.liveness.heard(now, started);
        let sequence = opened.header.sequence;
        match opened.message {
            None => {
                let body = &datagram[myriad_protocol::HEADER_LEN..datagram.len() - myriad_protocol::TAG_LEN];
                let Ok(view) = DeltaUpdateView::parse(body) else {
                    self.stats.decode_errors += 1;
                    return Event::Rejected;
                };
                let header = view.header();
                self.resolved.clear();
                // Acknowledged only when every record resolved (`UpdateReceiver`).
                let unresolved = self.receiver.receive(sequence, header.tick, view.records(), &mut self.resolved);
                self.stats.updates += 1;
                self.stats.records += self.resolved.len() as u64;
                self.stats.unresolved += unresolved as u64;
                self.stats.last_tick = self.stats.last_tick.max(header.tick);
                self.dilation_permille = header.dilation_permille;
                self.mirror.set_timing(self.mirror.tick_rate_hz(), header.dilation_permille, now);
                self.mirror.apply(header.tick, self.resolved.iter().copied(), now);
                Event::Update {
                    tick: header.tick,
                    records: self.resolved.len(),
                    dilation_permille: header.dilation_permille,
                }
            }
            Some(ServerMessage::ServerInfo(info)) => {
                self.dilation_permille = info.dilation_permille;
                self.mirror.set_timing(info.tick_rate_hz, info.dilation_permille, now);
                Event::Info(info)
            }
            Some(ServerMessage::KeepAlive) => Event::KeepAlive,
            Some(ServerMessage::Disconnect(reason)) => {
                self.disconnected = Some(reason);
                Event::Disconnected(reason)
            }
            Some(ServerMessage::StateUpdate(_)) => Event::Rejected,
        }
    }
}

async fn open_socket(config: &ClientConfig, udp_port: u16) -> Result<UdpSocket, ClientError> {
    let server = SocketAddr::new(config.login_addr.ip(), udp_port);
    let bind: SocketAddr = if server.is_ipv4() { "0.0.0.0:0" } else { "[::]:0" }.parse().expect("literal");
    let socket = UdpSocket::bind(bind).await.map_err(ClientError::io("binding a UDP socket"))?;
    socket.connect(server).await.map_err(ClientError::io("connecting the UDP socket"))?;
    Ok(socket)
}

/// A UDP socket connected to the server's game port (`udp_port`, from a login's answer),
/// for [`Connection::from_login`]: one socket that many connections share. Its receive
/// buffer is asked for `recv_buffer` bytes (the kernel may grant less), room for every
/// sharer's datagrams of a tick or two.
pub async fn server_socket(config: &ClientConfig, udp_port: u16, recv_buffer: usize) -> Result<UdpSocket, ClientError> {
    let socket = open_socket(config, udp_port).await?;
    let _ = socket2::SockRef::from(&socket).set_recv_buffer_size(recv_buffer);
    Ok(socket)
}

/// Refuses a socket that is not connected to the server's UDP port of this login.
fn check_peer(socket: &UdpSocket, config: &ClientConfig, udp_port: u16) -> Result<(), ClientError> {
    let want = SocketAddr::new(config.login_addr.ip(), udp_port);
    match socket.peer_addr() {
        Ok(peer) if peer == want => Ok(()),
        Ok(peer) => Err(ClientError::Invalid(format!("the socket is connected to {peer}, the login named {want}"))),
        Err(e) => Err(ClientError::Io { what: "reading the socket's peer", source: e }),
    }
}
