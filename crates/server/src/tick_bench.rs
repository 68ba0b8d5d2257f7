//! The end-to-end tick benchmark: the server's real tick (receive, physics, AOI and
//! interest management, sealing, `sendmmsg`) with every user object of a world played by
//! a bot on loopback, with a UDP socket of its own or one shared by a group of bots
//! ([`BotOptions`]).
//!
//! It runs the same code as `myriad serve`, minus the TLS login (players are admitted
//! directly with fresh session keys, as a login would) and minus pacing, persistence
//! and metrics, which are not stages. It receives as `serve` does: by default on the
//! receiver thread (`receive_thread`), and before each timed tick it waits, untimed,
//! until that thread has dealt with every datagram the bots sent, so the tick takes all
//! of them; the `receive` stage is then the tick's own share (the tag checks and
//! applying), and the receiver's work shows in the process's CPU time. Between two
//! timed ticks, untimed, the bots send their sealed actions and then drain their
//! sockets: every datagram is handed to the bot its header's session id names (the
//! server tells sessions apart by id, so many bots can share a socket, as
//! `myriad bots --bots-per-socket` does), and that bot opens it with its session key
//! (tag, replay window, decode) — every datagram by default, or, to spare the bots' time
//! at 50,000 players, on every `open_every`-th tick in turn, the rest matched to their
//! session by header only. Each sample so proves what was sent arrived and that (a
//! sample of) it decoded as sealed by the player's key.
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! use myriad_server::tick_bench::TickBench;
//! let world = myriad_core::ScenarioSpec::reference(1, 42)?.build()?;
//! let backend = myriad_cuda::create_backend(myriad_physics::BackendKind::Cpu)?;
//! let mut bench = TickBench::new(myriad_server::ServerConfig::default(), world, backend)?;
//! let sample = bench.tick()?;
//! let stages = &sample.work.stages;
//! use myriad_server::TickStage::{Packets, Send};
//! println!("{} players, packets {:.3} ms, send {:.3} ms", bench.players(), stages[Packets], stages[Send]);
//! # Ok(()) }
//! ```

use std::collections::HashMap;
use std::io::ErrorKind;
use std::net::{SocketAddr, UdpSocket};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use myriad_core::{ObjectKind, World};
use myriad_cuda::CreatedBackend;
use myriad_net::{Endpoint, EndpointConfig};
use myriad_protocol::{
    ActionMask, ClientMessage, ClientSession, Direction, PlayerInput, ServerMessage, StateRecord, UpdateReceiver,
    peek_header,
};
use myriad_store::UserId;

use crate::config::ServerConfig;
use crate::error::ServerError;
use crate::receiver::ThreadedUdp;
use crate::stages::TickWork;
use crate::tick::TickLoop;
use crate::transport::{Transport, UdpTransport};

/// Longest a tick of the benchmark waits for the receiver thread to deal with what the
/// bots sent (datagrams the kernel dropped never come).
const RECEIVER_PATIENCE: Duration = Duration::from_millis(500);

/// Ticks between two actions of one bot. Bots take turns (bot `i` sends on the ticks
/// where `(tick + i) % ACTION_EVERY == 0`), so the server receives a steady third of
/// the players each tick, as from clients that send when their keys change, instead of
/// one burst of every player that could overflow the socket's receive buffer.
pub const ACTION_EVERY: u64 = 3;

/// The bench's session silence timeout, s. The wall time between two ticks is the
/// bots' and the caller's (draining, opening, `myriad bench`'s staleness probe at 50,000
/// players: seconds), not a network's, so a bot acting every [`ACTION_EVERY`] ticks
/// could look silent for longer than a server's timeout, and its session would end
/// mid-run: the players the bench says it measures would not all be served.
pub const BENCH_SESSION_TIMEOUT_S: f32 = 86_400.0;

/// Rounds of `Ready` sent again to bots that heard nothing before the bench gives up.
const READY_ROUNDS: usize = 5;

/// Ticks a bot holds one direction before it turns.
const TURN_EVERY: u64 = 30;

/// Receive buffer asked for a bot socket, per bot sharing it: room for the datagrams of
/// a tick at AOI 100 (a few of 1.2 kB, with the kernel's overhead) and slack. The kernel
/// may grant less (`net.core.rmem_max`); datagrams it then drops show as
/// `TickSample::lost`.
const RECV_BUFFER_PER_BOT: usize = 16 << 10;

/// The largest receive buffer asked for one bot socket.
const MAX_RECV_BUFFER: usize = 64 << 20;

/// How the bots of a [`TickBench`] share sockets and how many of their datagrams they
/// open. The default is a socket per bot, every datagram opened.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BotOptions {
    /// Bots sharing one UDP socket (1: a socket each). Many players' worth of sockets
    /// need many file descriptors (`ulimit -n`); a group needs one.
    pub bots_per_socket: usize,
    /// Bot `i` opens its datagrams (tag, replay window, decode) on the ticks where
    /// `(tick + i) % open_every == 0` and matches them to its session by header alone on
    /// the others. 1: every datagram is opened.
    pub open_every: u64,
}

impl Default for BotOptions {
    fn default() -> Self {
        BotOptions { bots_per_socket: 1, open_every: 1 }
    }
}

/// One measured tick: the server's work and what the bots saw.
#[derive(Debug, Clone, Copy, Default)]
pub struct TickSample {
    /// What the server's tick did, with its stage times.
    pub work: TickWork,
    /// Actions the bots sent before this tick.
    pub actions_sent: u64,
    /// Datagrams that reached the bot their header names (opened or not).
    pub delivered: u64,
    /// Of those, datagrams the bots opened (session key, replay window, decode); all of
    /// them with [`BotOptions::open_every`] 1.
    pub opened: u64,
    /// Datagrams the server sent that no bot received (the kernel dropped them: a bot
    /// socket's receive buffer was full).
    pub lost: u64,
    /// Datagrams a bot received but could not open, or whose header named no bot:
    /// always 0 unless something is broken.
    pub rejected: u64,
    /// Records the bots decoded and resolved.
    pub records_delivered: u64,
    /// Delta records the bots could not resolve (baseline missing): 0 unless something
    /// is broken, since a bot acknowledges only what it resolved.
    pub unresolved: u64,
    /// Bots that opened their datagrams this tick (all of them with `open_every` 1).
    pub opening_bots: usize,
    /// Of those, bots whose update this tick contained their own object.
    pub saw_own: usize,
    /// Wall time of the bots' untimed work (sealing and sending actions, draining and
    /// opening), in ms: one thread, so also its CPU time, which a caller that measures
    /// the process's CPU time subtracts to get the server's.
    pub bots_ms: f64,
}

impl TickSample {
    /// The whole tick's work in milliseconds (the sum of the stages).
    pub fn total_ms(&self) -> f64 {
        self.work.stages.total()
    }
}

struct Bot {
    /// Index of the bot's socket in `TickBench::sockets`.
    socket: usize,
    session: ClientSession,
    entity: u64,
    frame: u32,
    /// The states its delta records are relative to, and the datagrams it acknowledges
    /// with its next action: the updates it opened and resolved whole. A bot that does
    /// not open (not its turn, `open_every`) does not acknowledge either, as a client
    /// that lost them: the server sends it more.
    receiver: UpdateReceiver,
    /// The bot's update held its own object this tick.
    saw_own: bool,
    /// A datagram for the bot arrived since the flag was last cleared.
    heard: bool,
}

/// The server tick with one bot per user object; see the module docs.
pub struct TickBench {
    tick: TickLoop,
    bots: Vec<Bot>,
    /// The bots' sockets, each shared by up to `options.bots_per_socket` bots.
    sockets: Vec<UdpSocket>,
    /// Session id → index in `bots`: whom a datagram is for.
    by_session: HashMap<u64, usize>,
    options: BotOptions,
    server_addr: SocketAddr,
    buf: Vec<u8>,
    datagram: Vec<u8>,
    /// The receiver thread's count of datagrams dealt with (with `receive_thread`).
    dealt_with: Option<Arc<AtomicU64>>,
    /// Datagrams the bots sent.
    sent: u64,
    /// `Ready` messages sent again to players the first one did not make active.
    ready_resent: u64,
}

impl std::fmt::Debug for TickBench {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TickBench").field("players", &self.bots.len()).field("server", &self.server_addr).finish()
    }
}

impl TickBench {
    /// Binds the server's UDP endpoint on loopback, makes every [`ObjectKind::User`]
    /// object of `world` a player with a bot socket of its own, and runs one untimed
    /// tick in which the bots' `Ready` messages are received, so every player is active
    /// from the first measured tick. Only the tick-related keys of `config` matter
    /// (tick rate, AOI size, datagrams per player); `session_timeout_s` is raised to
    /// [`BENCH_SESSION_TIMEOUT_S`] and `max_players` is
    /// raised to the world's users if it is lower. `backend` is the
    /// factory's (with its device interest, if any) or any other physics backend.
    pub fn new(
        config: ServerConfig,
        world: World,
        backend: impl Into<CreatedBackend>,
    ) -> Result<TickBench, ServerError> {
        TickBench::with_bots(config, world, backend, BotOptions::default())
    }

    /// [`TickBench::new`] with the bots grouped on sockets and opening as `options` says.
    pub fn with_bots(
        config: ServerConfig,
        world: World,
        backend: impl Into<CreatedBackend>,
        options: BotOptions,
    ) -> Result<TickBench, ServerError> {
        let mut bench = TickBench::inactive(config, world, backend, options)?;
        let all = (0..bench.bots.len()).collect();
        bench.activate(all)?;
        Ok(bench)
    }

    /// The server and its bots, no player active yet.
    fn inactive(
        config: ServerConfig,
        world: World,
        backend: impl Into<CreatedBackend>,
        options: BotOptions,
    ) -> Result<TickBench, ServerError> {
        if options.bots_per_socket == 0 || options.open_every == 0 {
            return Err(ServerError::Internal(format!(
                "bench bots: {options:?} (bots per socket and open every must be at least 1)"
            )));
        }
        let backend = backend.into();
        let users: Vec<_> = world
            .dynamics
            .ids()
            .iter()
            .zip(world.dynamics.kinds())
            .filter(|(_, k)| **k == ObjectKind::User)
            .map(|(id, _)| *id)
            .collect();
        // Every user object is a player: a world of more users than `max_players`
        // (scenario 4's 50,000) raises the cap rather than refusing the surplus.
        let mut config = config;
        config.max_players = config.max_players.max(u32::try_from(users.len()).unwrap_or(u32::MAX));
        config.session_timeout_s = config.session_timeout_s.max(BENCH_SESSION_TIMEOUT_S);
        config.validate()?;
        let loopback = EndpointConfig::new(SocketAddr::from(([127, 0, 0, 1], 0)));
        let endpoints = Endpoint::bind_group(loopback, config.udp_socket_count())?;
        let server_addr = endpoints[0].local_addr();
        // The transport `serve` uses: receiving on a thread of its own by default (the
        // tick's receive stage then times only what the tick itself does).
        let (transport, dealt_with): (Box<dyn Transport>, _) = if config.receive_thread {
            let threaded = ThreadedUdp::start(endpoints, config.receive_limits())
                .map_err(|e| ServerError::io("starting the receive thread", e))?;
            let dealt_with = threaded.dealt_with();
            (Box::new(threaded), Some(dealt_with))
        } else {
            (Box::new(UdpTransport::group(endpoints)), None)
        };
        let mut tick = TickLoop::builder(config, world, backend.backend, transport)
            .device_replicas(backend.device_replicas)
            .build();
        let mut bots = Vec::with_capacity(users.len());
        let mut sockets = Vec::new();
        let mut by_session = HashMap::with_capacity(users.len());
        let group = options.bots_per_socket;
        let adopted = tick.adopt_all(users.into_iter().enumerate().map(|(i, entity)| (UserId(i as i64 + 1), entity)));
        let players = adopted.len();
        for (i, joined) in adopted.into_iter().enumerate() {
            let joined = joined.map_err(|r| ServerError::Internal(format!("admitting bench player {i}: {r:?}")))?;
            if i % group == 0 {
                let members = group.min(players - i);
                sockets.push(bot_socket(members).map_err(|e| {
                    let n = sockets.len() + 1;
                    ServerError::io(format!("binding bot socket {n} (raise `ulimit -n` or --bots-per-socket)"), e)
                })?);
            }
            by_session.insert(joined.keys.session_id, bots.len());
            bots.push(Bot {
                socket: sockets.len() - 1,
                session: ClientSession::new(&joined.keys),
                entity: joined.entity,
                frame: 0,
                receiver: UpdateReceiver::default(),
                saw_own: false,
                heard: false,
            });
        }
        Ok(TickBench {
            tick,
            bots,
            sockets,
            by_session,
            options,
            server_addr,
            buf: vec![0; 65_536],
            datagram: Vec::with_capacity(128),
            dealt_with,
            sent: 0,
            ready_resent: 0,
        })
    }

    /// Makes every player active (address known, ready) before measuring starts: `Ready`
    /// from the bots `first`, in waves small enough for the server's receive buffer, each
    /// received by a tick; then again from every bot that heard nothing.
    fn activate(&mut self, first: Vec<usize>) -> Result<(), ServerError> {
        let mut waiting = first;
        for round in 0..=READY_ROUNDS {
            for wave in waiting.chunks(2_000) {
                for &i in wave {
                    self.send(i, &ClientMessage::Ready)?;
                }
                self.run_tick();
                self.drain(0, |_, _, _| {});
            }
            // An active player gets an update every tick. A Ready the kernel dropped (the
            // server's receive buffer full at tens of thousands of players) leaves its
            // player silent, and the run would measure fewer players than it says: send
            // those Ready again, and refuse to start if some never come.
            self.bots.iter_mut().for_each(|b| b.heard = false);
            self.run_tick();
            self.drain(0, |_, _, _| {});
            waiting = (0..self.bots.len()).filter(|&i| !self.bots[i].heard).collect();
            if waiting.is_empty() {
                return Ok(());
            }
            if round < READY_ROUNDS {
                self.ready_resent += waiting.len() as u64;
            }
        }
        Err(ServerError::Internal(format!(
            "{} of {} bench players got no update after {READY_ROUNDS} rounds of Ready sent again",
            waiting.len(),
            self.bots.len()
        )))
    }

    /// `Ready` messages sent again while starting, to players the first one did not
    /// make active (the server's receive buffer overflowed); 0 when every one arrived.
    pub fn ready_resent(&self) -> u64 {
        self.ready_resent
    }

    /// The bots' sockets and how they open their datagrams.
    pub fn bot_options(&self) -> BotOptions {
        self.options
    }

    /// Players (and bots).
    pub fn players(&self) -> usize {
        self.bots.len()
    }

    /// The simulated world.
    pub fn world(&self) -> &World {
        self.tick.world()
    }

    /// Forgets what the device's profile gathered so far (`TickLoop::restart_profile`):
    /// called when measuring starts, so that the profile leaves out the ticks that made
    /// the players active and the warm-up.
    pub fn restart_profile(&self) {
        self.tick.restart_profile();
    }

    /// The bots whose turn it is send their actions (untimed), the server runs one tick
    /// (timed per stage), then every bot drains and opens what it received (untimed).
    pub fn tick(&mut self) -> Result<TickSample, ServerError> {
        self.tick_with(|_, _, _| {})
    }

    /// The object bot `bot` plays (bots are numbered from 0, as in [`TickBench::tick_with`]).
    pub fn bot_entity(&self, bot: usize) -> Option<u64> {
        self.bots.get(bot).map(|b| b.entity)
    }

    /// [`TickBench::tick`], handing every state update a bot opened to `on_update`
    /// (the bot's number, the update's tick, its records resolved against the bot's
    /// baselines) as it drains, untimed: a caller mirrors what some bots received
    /// (`myriad bench`'s staleness and error).
    pub fn tick_with(&mut self, on_update: impl FnMut(usize, u64, &[StateRecord])) -> Result<TickSample, ServerError> {
        let tick = self.tick.world().tick;
        let before = Instant::now();
        let mut actions_sent = 0;
        for i in 0..self.bots.len() {
            if (tick + i as u64).is_multiple_of(ACTION_EVERY) {
                let mask = [ActionMask::FORWARD, ActionMask::RIGHT, ActionMask::BACK, ActionMask::LEFT]
                    [((tick / TURN_EVERY + i as u64) % 4) as usize];
                let frame = self.bots[i].frame.wrapping_add(1);
                self.bots[i].frame = frame;
                let input = PlayerInput { mask: ActionMask::new(mask).unwrap_or_default(), client_frame: frame };
                let acks = self.bots[i].receiver.acks();
                self.send(i, &ClientMessage::Action { input, acks })?;
                actions_sent += 1;
            }
        }
        let bots_before = before.elapsed();
        let work = self.run_tick();
        let after = Instant::now();
        let mut sample = self.drain(tick, on_update);
        sample.lost = work.datagrams.saturating_sub(sample.delivered + sample.rejected);
        sample.bots_ms = (bots_before + after.elapsed()).as_secs_f64() * 1e3;
        sample.work = work;
        sample.actions_sent = actions_sent;
        Ok(sample)
    }

    fn run_tick(&mut self) -> TickWork {
        // With the receiver thread, wait (untimed) until it has dealt with every datagram
        // the bots sent: the tick then takes all of them, as with inline receiving. A
        // datagram the kernel dropped never comes: give up after a while.
        if let Some(dealt_with) = &self.dealt_with {
            let deadline = Instant::now() + RECEIVER_PATIENCE;
            while dealt_with.load(Ordering::Acquire) < self.sent && Instant::now() < deadline {
                std::thread::yield_now();
            }
        }
        self.tick.tick_once()
    }

    fn send(&mut self, i: usize, msg: &ClientMessage) -> Result<(), ServerError> {
        self.datagram.clear();
        let bot = &mut self.bots[i];
        bot.session.seal(msg, &mut self.datagram).map_err(|e| ServerError::Internal(format!("sealing: {e}")))?;
        match self.sockets[bot.socket].send_to(&self.datagram, self.server_addr) {
            // A full loopback queue loses the datagram, as a network would: the server's
            // `received` count shows it.
            Ok(_) => {
                self.sent += 1;
                Ok(())
            }
            Err(e) if e.kind() == ErrorKind::WouldBlock => Ok(()),
            Err(e) => Err(ServerError::io(format!("bot {} sending", i + 1), e)),
        }
    }

    /// Reads everything queued on every bot socket, hands each datagram to the bot its
    /// header names, which opens it if it is its turn (`tick`) and hands each state update
    /// it opened to `on_update`.
    fn drain(&mut self, tick: u64, mut on_update: impl FnMut(usize, u64, &[StateRecord])) -> TickSample {
        let mut s = TickSample::default();
        let mut resolved = Vec::new();
        for bot in &mut self.bots {
            bot.saw_own = false;
        }
        for socket in &self.sockets {
            // Until WouldBlock: drained. Any other error (an ICMP error queued on the
            // socket) is not the server's datagram either.
            while let Ok(n) = socket.recv(&mut self.buf) {
                let datagram = &mut self.buf[..n];
                let Some(&i) = peek_header(datagram, Direction::ServerToClient)
                    .ok()
                    .and_then(|h| self.by_session.get(&h.session_id))
                else {
                    s.rejected += 1;
                    continue;
                };
                self.bots[i].heard = true;
                if !opens(tick, i, self.options.open_every) {
                    s.delivered += 1;
                    continue;
                }
                let bot = &mut self.bots[i];
                match bot.session.open(datagram) {
                    Ok(opened) => {
                        s.delivered += 1;
                        s.opened += 1;
                        if let ServerMessage::StateUpdate(u) = opened.message {
                            resolved.clear();
                            let unresolved = bot.receiver.receive_update(opened.header.sequence, &u, &mut resolved);
                            s.unresolved += unresolved as u64;
                            s.records_delivered += resolved.len() as u64;
                            bot.saw_own |= resolved.iter().any(|r| r.id == bot.entity);
                            on_update(i, u.header.tick, &resolved);
                        }
                    }
                    Err(_) => s.rejected += 1,
                }
            }
        }
        for i in 0..self.bots.len() {
            if opens(tick, i, self.options.open_every) {
                s.opening_bots += 1;
                s.saw_own += usize::from(self.bots[i].saw_own);
            }
        }
        s
    }
}

/// Whether bot `i` opens its datagrams on `tick` ([`BotOptions::open_every`]).
fn opens(tick: u64, i: usize, open_every: u64) -> bool {
    (tick + i as u64).is_multiple_of(open_every)
}

/// A nonblocking bot socket on loopback for `members` bots, its receive buffer asked to
/// hold a tick of their datagrams.
fn bot_socket(members: usize) -> std::io::Result<UdpSocket> {
    let socket = UdpSocket::bind(SocketAddr::from(([127, 0, 0, 1], 0)))?;
    socket.set_nonblocking(true)?;
    if members > 1 {
        // The kernel may grant less (net.core.rmem_max): what it drops shows as `lost`.
        let _ =
            socket2::SockRef::from(&socket).set_recv_buffer_size((members * RECV_BUFFER_PER_BOT).min(MAX_RECV_BUFFER));
    }
    Ok(socket)
}

#[cfg(test)]
mod tests {
    use super::*;
    use myriad_core::ScenarioSpec;
    use myriad_physics::BackendKind;

    #[test]
    fn every_player_gets_its_own_object_and_packets_and_send_are_timed() {
        let world = ScenarioSpec::custom(7).counts(1_200, 60, 300).map_size(256.0, 129).build().unwrap();
        let backend = myriad_physics::create_cpu_backend(BackendKind::Cpu).unwrap();
        use crate::stages::TickStage::{Packets, Send};
        let mut bench = TickBench::new(ServerConfig::default(), world, backend).unwrap();
        assert_eq!(bench.players(), 60);
        let d = &bench.world().dynamics;
        let users: Vec<_> = (0..d.len()).filter(|&i| d.kinds()[i] == ObjectKind::User).map(|i| d.ids()[i]).collect();
        let start: Vec<_> = users.iter().map(|&id| d.positions()[d.slot(id).unwrap()]).collect();
        let mut samples = Vec::new();
        for _ in 0..12 {
            samples.push(bench.tick().unwrap());
        }
        for s in &samples {
            // Every player is active: at least one update datagram each, all delivered
            // and opened, and each update holds the player's own object.
            let w = &s.work;
            assert!(w.datagrams >= 60, "{s:?}");
            assert_eq!(s.delivered, w.datagrams, "{s:?}");
            assert_eq!((s.opened, s.lost, s.rejected), (s.delivered, 0, 0), "{s:?}");
            assert_eq!((s.saw_own, s.opening_bots), (60, 60));
            assert!(s.records_delivered >= w.records as u64 && w.records > 0, "{s:?}");
            // Every delta record resolved: the bots acknowledge only what they hold.
            assert_eq!(s.unresolved, 0, "{s:?}");
            // The bots' actions arrive: a third of them each tick, and each is applied.
            assert_eq!(w.received, s.actions_sent, "{s:?}");
            assert_eq!(w.actions, s.actions_sent, "{s:?}");
            assert_eq!(s.actions_sent, 20);
            assert!(w.stages[Packets] > 0.0 && w.stages[Send] > 0.0, "packets and send are measured: {s:?}");
            assert!(w.aoi_ms > 0.0 && w.aoi_ms < w.stages[Packets], "the AOI query is part of packets: {s:?}");
        }
        // The users moved as commanded (walking, not just settling).
        let d = &bench.world().dynamics;
        let moved = users
            .iter()
            .zip(&start)
            .filter(|&(&id, a)| {
                let b = d.positions()[d.slot(id).unwrap()];
                (b.x - a.x).hypot(b.z - a.z) > 0.5
            })
            .count();
        assert!(moved >= 50, "only {moved} of 60 players walked");
        // With the bots' acknowledgements, most of what the server sent by the end was
        // relative to a state the bot held.
        let late = &samples[8..];
        let (relative, records): (usize, usize) =
            late.iter().map(|s| (s.work.relative, s.work.records)).fold((0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
        assert!(relative * 2 > records, "{relative} of {records} records relative to an acknowledged state");
    }

    /// Bots in groups of 16 on a socket, each opening its datagrams every third tick:
    /// every datagram still reaches the bot it is for, a third of the bots open theirs
    /// each tick (and find their own object), and what they open decodes. More users
    /// than `max_players` all play.
    #[test]
    fn grouped_bots_receive_everything_and_open_their_turns() {
        let world = ScenarioSpec::custom(8).counts(1_200, 60, 300).map_size(256.0, 129).build().unwrap();
        let backend = myriad_physics::create_cpu_backend(BackendKind::Cpu).unwrap();
        let options = BotOptions { bots_per_socket: 16, open_every: 3 };
        // Fewer player slots than users: the bench raises the cap (scenario 4's 50,000
        // users against the default 10,000).
        let config = ServerConfig { max_players: 10, ..ServerConfig::default() };
        let mut bench = TickBench::with_bots(config, world, backend, options).unwrap();
        assert_eq!((bench.players(), bench.sockets.len()), (60, 4));
        let mut opened = 0;
        for _ in 0..6 {
            let s = bench.tick().unwrap();
            assert!(s.work.datagrams >= 60, "{s:?}");
            assert_eq!((s.delivered, s.lost, s.rejected), (s.work.datagrams, 0, 0), "{s:?}");
            assert_eq!((s.opening_bots, s.saw_own), (20, 20), "{s:?}");
            assert!(s.opened >= 20 && s.opened < s.delivered, "{s:?}");
            assert!(s.records_delivered > 0, "{s:?}");
            assert_eq!(s.work.received, s.actions_sent, "the bots' actions arrive from shared sockets: {s:?}");
            opened += s.opened;
        }
        assert!(opened > 0);
        let none = BotOptions { bots_per_socket: 0, open_every: 1 };
        let world = ScenarioSpec::custom(8).counts(100, 5, 10).map_size(64.0, 17).build().unwrap();
        let backend = myriad_physics::create_cpu_backend(BackendKind::Cpu).unwrap();
        assert!(TickBench::with_bots(ServerConfig::default(), world, backend, none).is_err());
    }

    /// A player whose first Ready never arrived (as when the server's receive buffer
    /// overflows at tens of thousands of players) is found silent and sent Ready again,
    /// so every player is active when measuring starts.
    #[test]
    fn a_player_whose_ready_was_lost_is_made_active_before_measuring() {
        let world = ScenarioSpec::custom(9).counts(600, 30, 100).map_size(128.0, 65).build().unwrap();
        let backend = myriad_physics::create_cpu_backend(BackendKind::Cpu).unwrap();
        let options = BotOptions { bots_per_socket: 8, open_every: 1 };
        let mut bench = TickBench::inactive(ServerConfig::default(), world, backend, options).unwrap();
        // Bots 4 and 17 "lose" their first Ready: it is never sent.
        let first = (0..30).filter(|i| ![4, 17].contains(i)).collect();
        bench.activate(first).unwrap();
        assert_eq!(bench.ready_resent(), 2);
        let s = bench.tick().unwrap();
        assert_eq!((s.opening_bots, s.saw_own), (30, 30), "{s:?}");
    }

    /// Slow untimed work between ticks (longer than the server's silence timeout, with
    /// bots that act every third tick) ends no session: every player is still served.
    #[test]
    fn slow_work_between_ticks_ends_no_session() {
        let world = ScenarioSpec::custom(10).counts(300, 12, 50).map_size(96.0, 49).build().unwrap();
        let backend = myriad_physics::create_cpu_backend(BackendKind::Cpu).unwrap();
        let config = ServerConfig { session_timeout_s: 1.0, ..ServerConfig::default() };
        let mut bench = TickBench::new(config, world, backend).unwrap();
        for _ in 0..3 {
            std::thread::sleep(Duration::from_millis(1_100));
            let s = bench.tick().unwrap();
            assert_eq!((s.opening_bots, s.saw_own), (12, 12), "{s:?}");
        }
    }
}
