//! The authoritative tick loop: one thread that owns the world.
//!
//! # How it works
//!
//! Each iteration, at a fixed rate (stretched by time dilation, see
//! [`crate::dilation`]):
//!
//! 1. joins from the login service are admitted (or refused: server full);
//! 2. every queued datagram is received in batches and checked by the session's
//!    opener (cheap checks, tag, decode, replay window) — a datagram that fails changes
//!    nothing and is answered with nothing; actions are stored in the world;
//! 3. silent sessions time out;
//! 4. the backend steps the world (stages `upload` … `forces`);
//! 5. the backend answers one AOI box per player, and interest management builds and
//!    seals each player's updates (stage `packets`);
//! 6. the datagrams go out in `sendmmsg` batches (stage `send`);
//! 7. player positions are handed to the persister every `persist_interval_ms`.
//!
//! **Invariant:** only a datagram that passed its session's authentication changes any
//! state (addresses, actions, timers, replay windows), and the server never sends to an
//! address that has not proved it holds a session key.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::sync::mpsc::{Receiver, TryRecvError};
use std::time::{Duration, Instant};

use myriad_core::{Aabb, Action, EntityId, ObjectKind, Shape, Vec3, World};
use myriad_interest::{AoiLists, InterestConfig, InterestManager, ObjectSource, Subscriber, TickInfo};
use myriad_net::{Endpoint, RecvBatch};
use myriad_physics::{AoiResults, Backend, Stage, TickConstants};
use myriad_protocol::login::{RefusalReason, ShapeDesc};
use myriad_protocol::{
    ClientMessage, Direction, DisconnectReason, ErrorClass, Opener, ServerInfo, ServerMessage, ServerSession,
    SessionKeys, ShapeKind as WireKind, peek_header,
};
use myriad_store::{MapId, Persister, PlayerState, UserId};
use ring::rand::{SecureRandom, SystemRandom};

use crate::config::ServerConfig;
use crate::dilation::DilationController;
use crate::status::{STAGES, Shared, StatusWindow};
use crate::world::{shape_desc, store_shape, wire_kind};

/// What the login service asks of the tick loop.
pub(crate) enum Command {
    /// Admit an authenticated user (or replace its current session).
    Join {
        user_id: UserId,
        username: String,
        state: Option<PlayerState>,
        reply: tokio::sync::oneshot::Sender<JoinResult>,
    },
}

/// The answer to a join.
pub(crate) type JoinResult = Result<Joined, RefusalReason>;

/// An admitted player: what the login response carries.
pub(crate) struct Joined {
    pub keys: SessionKeys,
    pub entity: u64,
    pub position: [f32; 3],
    pub shape: ShapeDesc,
    pub tick: u64,
    pub dilation_permille: u16,
}

/// The default player shape (a person-sized capsule).
pub const PLAYER_SHAPE: Shape = Shape::Capsule { radius: 0.4, half_height: 0.5 };

/// Indices of the server's own stages in [`STAGES`] (the physics stages come first).
const PACKETS: usize = Stage::ALL.len();
const SEND: usize = PACKETS + 1;
const RECEIVE: usize = SEND + 1;

/// Datagrams taken from the socket per `recvmmsg` call.
pub(crate) const RECV_BATCH: usize = 1024;

/// What one tick did: milliseconds per stage (indexed like [`STAGES`]) and what it sent.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct TickWork {
    pub stage_ms: [f64; STAGES.len()],
    /// The part of `packets` spent in the backend's AOI query, in ms.
    pub aoi_ms: f64,
    /// Bytes sent (control replies and updates).
    pub bytes: u64,
    /// Datagrams sent.
    pub datagrams: u64,
    /// State records packed.
    pub records: usize,
    /// Datagrams received from clients (before authentication).
    pub received: u64,
}

struct Player {
    user_id: UserId,
    username: String,
    entity: EntityId,
    session_id: u64,
    opener: Opener,
    /// Where the last authenticated datagram came from; nothing is sent before that.
    addr: Option<SocketAddr>,
    ready: bool,
    last_heard: Instant,
    last_frame: Option<u32>,
    shape: Shape,
}

/// Reads the world's dynamics for interest management.
struct WorldObjects<'a>(&'a World);

impl ObjectSource for WorldObjects<'_> {
    fn get(&self, slot: u32) -> Option<(u64, WireKind, [f32; 3])> {
        let d = &self.0.dynamics;
        let i = slot as usize;
        Some((u64::from(d.ids().get(i)?.0), wire_kind(*d.shapes().get(i)?), d.positions().get(i)?.to_array()))
    }
}

pub(crate) struct TickLoop {
    pub config: ServerConfig,
    pub world: World,
    pub backend: Box<dyn Backend>,
    pub endpoint: Endpoint,
    /// `None` in the tick benchmark, which has no database.
    pub persister: Option<Persister>,
    pub map_id: MapId,
    pub commands: Receiver<Command>,
    pub shared: Arc<Shared>,
    players: Vec<Player>,
    subscribers: Vec<Subscriber>,
    by_session: HashMap<u64, usize>,
    by_user: HashMap<i64, usize>,
    interest: InterestManager,
    rng: SystemRandom,
    /// Control replies (keep-alives, server info, disconnects) queued for this tick's send.
    control: Vec<(SocketAddr, Vec<u8>)>,
    dilation: DilationController,
    window: StatusWindow,
}

impl TickLoop {
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn new(
        config: ServerConfig,
        world: World,
        backend: Box<dyn Backend>,
        endpoint: Endpoint,
        persister: Option<Persister>,
        map_id: MapId,
        commands: Receiver<Command>,
        shared: Arc<Shared>,
    ) -> Self {
        let nominal = Duration::from_secs_f64(1.0 / f64::from(config.tick_rate));
        let interest = InterestManager::new(InterestConfig {
            max_datagrams: config.max_datagrams_per_player,
            ..Default::default()
        });
        let dilation = DilationController::new(nominal, config.dilation, config.dilation_min_permille);
        TickLoop {
            config,
            world,
            backend,
            endpoint,
            persister,
            map_id,
            commands,
            shared,
            players: Vec::new(),
            subscribers: Vec::new(),
            by_session: HashMap::new(),
            by_user: HashMap::new(),
            interest,
            rng: SystemRandom::new(),
            control: Vec::new(),
            dilation,
            window: StatusWindow::default(),
        }
    }

    /// Runs until the shared stop flag is set; then disconnects everyone and hands their
    /// final positions to the persister (unless the stop is a simulated crash).
    pub(crate) fn run(mut self) {
        let mut recv = RecvBatch::new(RECV_BATCH);
        let mut aoi = AoiResults::default();
        let mut boxes: Vec<Aabb> = Vec::new();
        let persist_every = Duration::from_millis(self.config.persist_interval_ms);
        let mut last_persist = Instant::now();
        let mut next = Instant::now();
        let log_every = Duration::from_secs_f32(self.config.log_stages_every_s);
        let mut last_log = Instant::now();
        while !self.shared.stop.load(Ordering::Acquire) {
            let start = Instant::now();
            let TickWork { stage_ms, bytes, datagrams, records: built, .. } =
                self.tick_once(&mut recv, &mut boxes, &mut aoi);

            if last_persist.elapsed() >= persist_every {
                self.persist_all();
                last_persist = Instant::now();
            }
            let load = self.shared.artificial_load_us.load(Ordering::Relaxed);
            if load > 0 {
                // A test knob: burn CPU as if the tick had more work.
                let until = Instant::now() + Duration::from_micros(u64::from(load));
                while Instant::now() < until {
                    std::hint::spin_loop();
                }
            }
            let work = start.elapsed();
            if self.dilation.record(work) {
                tracing::info!(dilation_permille = self.dilation.permille(), "time dilation changed");
            }
            self.shared.dilation_permille.store(u32::from(self.dilation.permille()), Ordering::Relaxed);
            self.shared.tick.store(self.world.tick, Ordering::Relaxed);
            self.shared.players.store(self.players.len(), Ordering::Relaxed);
            self.window.add(&stage_ms, ms(work), bytes, datagrams, built);
            record_metrics(
                &stage_ms,
                work,
                bytes,
                datagrams,
                self.players.len(),
                self.world.dynamics.len(),
                &self.dilation,
            );
            if self.window.elapsed() >= Duration::from_secs(1) {
                let status = self.window.finish(
                    self.world.tick,
                    self.players.len(),
                    self.world.dynamics.len(),
                    self.dilation.permille(),
                );
                if log_every > Duration::ZERO && last_log.elapsed() >= log_every {
                    tracing::info!(target: "myriad::stages", "{}", status.stage_line());
                    last_log = Instant::now();
                }
                *self.shared.status.lock().unwrap_or_else(|p| p.into_inner()) = status;
                if let Some(persister) = &self.persister {
                    let p = persister.stats();
                    metrics::gauge!("myriad_persist_queued").set(p.queued as f64);
                    metrics::gauge!("myriad_persist_rows_written").set(p.rows_written as f64);
                    metrics::gauge!("myriad_persist_failures").set(p.failures as f64);
                    metrics::gauge!("myriad_persist_dropped").set(p.dropped_overflow as f64);
                }
            }

            next += self.dilation.period();
            let now = Instant::now();
            if next > now {
                std::thread::sleep(next - now);
            } else {
                // Never try to catch up with a burst of ticks: that is what dilation is for.
                next = now;
            }
        }
        if self.shared.crash.load(Ordering::Acquire) {
            return;
        }
        for i in 0..self.players.len() {
            self.queue_disconnect(i, DisconnectReason::Shutdown);
        }
        self.persist_all();
        self.send();
    }

    /// One tick's work, steps 1 to 6 of the module docs: joins, receive, expiry, the
    /// physics step, interest management and the send. Pacing, persistence, dilation and
    /// metrics stay in [`TickLoop::run`], so the tick benchmark times exactly this.
    pub(crate) fn tick_once(&mut self, recv: &mut RecvBatch, boxes: &mut Vec<Aabb>, aoi: &mut AoiResults) -> TickWork {
        let mut stage_ms = [0f64; STAGES.len()];
        self.drain_commands();
        let t = Instant::now();
        let received = self.receive(recv);
        self.expire(Instant::now());
        stage_ms[RECEIVE] = ms(t.elapsed());

        let k = TickConstants::new(&self.config.physics(), 1.0);
        match self.backend.step(&mut self.world, &k) {
            Ok(report) => stage_ms[..Stage::ALL.len()].copy_from_slice(&report.stage_ms),
            Err(e) => {
                tracing::error!(error = %e, "physics step failed");
                metrics::counter!("myriad_physics_errors_total").increment(1);
            }
        }
        self.world.tick += 1;

        let t = Instant::now();
        let (records, aoi_ms) = self.build_updates(boxes, aoi);
        stage_ms[PACKETS] = ms(t.elapsed());
        let t = Instant::now();
        let (bytes, datagrams) = self.send();
        stage_ms[SEND] = ms(t.elapsed());
        TickWork { stage_ms, aoi_ms, bytes, datagrams, records, received }
    }

    fn drain_commands(&mut self) {
        loop {
            match self.commands.try_recv() {
                Ok(Command::Join { user_id, username, state, reply }) => {
                    let result = self.join(user_id, username, state);
                    // The login task may have given up (client gone): nothing to undo, the
                    // session times out unused.
                    let _ = reply.send(result);
                }
                Err(TryRecvError::Empty | TryRecvError::Disconnected) => return,
            }
        }
    }

    fn fresh_keys(&self) -> Result<SessionKeys, RefusalReason> {
        let mut bytes = [0u8; 72];
        loop {
            self.rng.fill(&mut bytes).map_err(|_| RefusalReason::Unavailable)?;
            let session_id = u64::from_le_bytes(bytes[..8].try_into().unwrap_or_default());
            if session_id != 0 && !self.by_session.contains_key(&session_id) {
                let mut keys = SessionKeys { session_id, client_to_server: [0; 32], server_to_client: [0; 32] };
                keys.client_to_server.copy_from_slice(&bytes[8..40]);
                keys.server_to_client.copy_from_slice(&bytes[40..72]);
                return Ok(keys);
            }
        }
    }

    fn join(&mut self, user_id: UserId, username: String, state: Option<PlayerState>) -> JoinResult {
        let keys = self.fresh_keys()?;
        let session = ServerSession::new(&keys);
        let idx = if let Some(&idx) = self.by_user.get(&user_id.0) {
            // A second login replaces the first session; the object (and its position in
            // the world, newer than the stored one) stays.
            self.queue_disconnect(idx, DisconnectReason::Replaced);
            let p = &mut self.players[idx];
            self.by_session.remove(&p.session_id);
            p.session_id = keys.session_id;
            p.opener = session.opener;
            p.addr = None;
            p.ready = false;
            p.last_frame = None;
            p.last_heard = Instant::now();
            let slot = self.world.dynamics.slot(p.entity).unwrap_or(0) as u32;
            self.subscribers[idx] = Subscriber::new(slot, [0.0; 3], session.sealer);
            tracing::info!(user = %username, "session replaced by a new login");
            idx
        } else {
            if self.players.len() >= self.config.max_players as usize {
                return Err(RefusalReason::ServerFull);
            }
            let (shape, pos) = match state {
                Some(s) => (crate::world::core_shape(s.shape), self.clamp_into_world(Vec3::from_array(s.position))),
                None => (PLAYER_SHAPE, self.spawn_point(user_id, PLAYER_SHAPE)),
            };
            let entity = self.world.dynamics.spawn(shape, pos, ObjectKind::User).map_err(|e| {
                tracing::error!(error = %e, "cannot spawn a player");
                RefusalReason::Unavailable
            })?;
            let idx = self.admit(user_id, username.clone(), entity, shape, keys.session_id, session);
            if state.is_none()
                && let Some(persister) = &self.persister
            {
                // First visit: record the spawn point now so the next login finds it.
                let _ = persister.submit(PlayerState::new(user_id, self.map_id, store_shape(shape), pos.to_array()));
            }
            tracing::info!(user = %username, entity = entity.0, "player joined");
            idx
        };
        Ok(self.joined(idx, keys))
    }

    /// Adds a player for `entity`, an object already in the world; returns its index.
    fn admit(
        &mut self,
        user_id: UserId,
        username: String,
        entity: EntityId,
        shape: Shape,
        session_id: u64,
        session: ServerSession,
    ) -> usize {
        let slot = self.world.dynamics.slot(entity).unwrap_or(0);
        let pos = self.world.dynamics.positions()[slot];
        self.players.push(Player {
            user_id,
            username,
            entity,
            session_id,
            opener: session.opener,
            addr: None,
            ready: false,
            last_heard: Instant::now(),
            last_frame: None,
            shape,
        });
        self.subscribers.push(Subscriber::new(slot as u32, pos.to_array(), session.sealer));
        let idx = self.players.len() - 1;
        self.by_user.insert(user_id.0, idx);
        idx
    }

    /// Registers player `idx`'s new session and describes it for the login response.
    fn joined(&mut self, idx: usize, keys: SessionKeys) -> Joined {
        self.by_session.insert(keys.session_id, idx);
        let p = &self.players[idx];
        let slot = self.world.dynamics.slot(p.entity).unwrap_or(0);
        Joined {
            keys,
            entity: u64::from(p.entity.0),
            position: self.world.dynamics.positions()[slot].to_array(),
            shape: shape_desc(p.shape),
            tick: self.world.tick,
            dilation_permille: self.dilation.permille(),
        }
    }

    /// The tick benchmark's join: makes `entity`, an object already in the world (one of
    /// a scenario's users), a player with a fresh session, as a login would.
    pub(crate) fn adopt(&mut self, user_id: UserId, entity: EntityId) -> JoinResult {
        if self.by_user.contains_key(&user_id.0) || self.world.dynamics.slot(entity).is_none() {
            return Err(RefusalReason::Unavailable);
        }
        let keys = self.fresh_keys()?;
        let session = ServerSession::new(&keys);
        let shape = self.world.dynamics.shape_of(self.world.dynamics.slot(entity).unwrap_or(0));
        let idx = self.admit(user_id, format!("bench{}", user_id.0), entity, shape, keys.session_id, session);
        Ok(self.joined(idx, keys))
    }

    /// A spawn point for a first visit: spread over the map by user id, on the terrain.
    fn spawn_point(&self, user: UserId, shape: Shape) -> Vec3 {
        let b = self.world.bounds;
        let h = myriad_core::rng::hash3(self.world.seed, 0x5e5e, user.0 as u64);
        let fx = (h & 0xffff_ffff) as f32 / u32::MAX as f32;
        let fz = (h >> 32) as f32 / u32::MAX as f32;
        let margin = 4.0f32.min(b.size().x / 4.0);
        let x = b.min.x + margin + fx * (b.size().x - 2.0 * margin);
        let z = b.min.z + margin + fz * (b.size().z - 2.0 * margin);
        Vec3::new(x, self.world.terrain.height_at(x, z) + shape.half_extents().y + 0.1, z)
    }

    /// A stored position may come from another map version: keep it inside the bounds
    /// and above the terrain.
    fn clamp_into_world(&self, p: Vec3) -> Vec3 {
        let b = self.world.bounds;
        let p = if p.is_finite() { p } else { b.center() };
        let p = p.clamp(b.min + Vec3::splat(0.5), b.max - Vec3::splat(0.5));
        let floor = self.world.terrain.height_at(p.x, p.z);
        Vec3::new(p.x, p.y.max(floor + 0.05), p.z)
    }

    /// Receives and handles what is queued on the socket; returns the datagrams taken.
    fn receive(&mut self, recv: &mut RecvBatch) -> u64 {
        let now = Instant::now();
        let mut leaving = Vec::new();
        let mut received = 0;
        // Bounded so a flood cannot starve the tick; what is left waits for the next one.
        for _ in 0..64 {
            let n = match self.endpoint.recv_batch(recv) {
                Ok(0) => break,
                Ok(n) => n,
                Err(e) => {
                    tracing::warn!(error = %e, "udp receive failed");
                    break;
                }
            };
            metrics::counter!("myriad_datagrams_received_total").increment(n as u64);
            received += n as u64;
            for i in 0..n {
                let Some((from, bytes)) = recv.get_mut(i) else { continue };
                if let Some(idx) = self.handle(from, bytes, now) {
                    leaving.push(idx);
                }
            }
        }
        // Remove from the highest index down so swap_remove does not move a pending one.
        leaving.sort_unstable();
        leaving.dedup();
        for idx in leaving.into_iter().rev() {
            self.remove(idx, None);
        }
        received
    }

    /// Handles one datagram; returns the player index if it asked to leave.
    fn handle(&mut self, from: SocketAddr, bytes: &mut [u8], now: Instant) -> Option<usize> {
        let header = match peek_header(bytes, Direction::ClientToServer) {
            Ok(h) => h,
            Err(_) => {
                dropped("malformed");
                return None;
            }
        };
        let Some(&idx) = self.by_session.get(&header.session_id) else {
            dropped("unknown_session");
            return None;
        };
        let p = &mut self.players[idx];
        let opened = match p.opener.open_with(bytes, ClientMessage::decode_body) {
            Ok(o) => o,
            Err(e) => {
                dropped(match e.class() {
                    ErrorClass::Malformed => "malformed",
                    ErrorClass::Authentication => "authentication",
                    ErrorClass::Replayed => "replayed",
                });
                return None;
            }
        };
        // Authenticated: the sender holds the session key, so its address is the player's
        // (this also follows a client whose NAT mapping changed).
        p.addr = Some(from);
        p.last_heard = now;
        match opened.message {
            ClientMessage::Action(a) => {
                // Keep only the newest frame; wrapping comparison on the frame counter.
                let newer = p.last_frame.is_none_or(|f| a.client_frame.wrapping_sub(f) as i32 > 0);
                if newer {
                    p.last_frame = Some(a.client_frame);
                    let entity = p.entity;
                    self.world.dynamics.set_action(entity, Action::from_bits_truncate(a.mask.bits()));
                }
                None
            }
            ClientMessage::Ready => {
                p.ready = true;
                let info = ServerInfo {
                    tick_rate_hz: self.config.tick_rate.round() as u16,
                    dilation_permille: self.dilation.permille(),
                };
                self.queue_message(idx, &ServerMessage::ServerInfo(info));
                None
            }
            ClientMessage::KeepAlive => {
                self.queue_message(idx, &ServerMessage::KeepAlive);
                None
            }
            ClientMessage::Disconnect => Some(idx),
        }
    }

    fn queue_message(&mut self, idx: usize, msg: &ServerMessage) {
        let Some(addr) = self.players[idx].addr else { return };
        let mut out = Vec::with_capacity(64);
        if self.subscribers[idx].sealer.seal_server_message(msg, &mut out).is_ok() {
            self.control.push((addr, out));
        }
    }

    fn queue_disconnect(&mut self, idx: usize, reason: DisconnectReason) {
        self.queue_message(idx, &ServerMessage::Disconnect(reason));
    }

    fn expire(&mut self, now: Instant) {
        let timeout = Duration::from_secs_f32(self.config.session_timeout_s);
        let mut i = self.players.len();
        while i > 0 {
            i -= 1;
            if now.duration_since(self.players[i].last_heard) > timeout {
                tracing::info!(user = %self.players[i].username, "session timed out");
                self.remove(i, Some(DisconnectReason::Timeout));
            }
        }
    }

    /// Removes player `idx`: final position to the persister, object out of the world.
    fn remove(&mut self, idx: usize, reason: Option<DisconnectReason>) {
        if let Some(reason) = reason {
            self.queue_disconnect(idx, reason);
        }
        self.persist_one(idx);
        let p = self.players.swap_remove(idx);
        self.subscribers.swap_remove(idx);
        self.by_session.remove(&p.session_id);
        self.by_user.remove(&p.user_id.0);
        self.world.dynamics.despawn(p.entity);
        if idx < self.players.len() {
            let moved = &self.players[idx];
            self.by_session.insert(moved.session_id, idx);
            self.by_user.insert(moved.user_id.0, idx);
        }
        tracing::info!(user = %p.username, "player left");
    }

    fn state_of(&self, idx: usize) -> Option<PlayerState> {
        let p = &self.players[idx];
        let slot = self.world.dynamics.slot(p.entity)?;
        let pos = self.world.dynamics.positions()[slot].to_array();
        Some(PlayerState::new(p.user_id, self.map_id, store_shape(p.shape), pos))
    }

    fn persist_one(&self, idx: usize) {
        if let Some(persister) = &self.persister
            && let Some(state) = self.state_of(idx)
            && let Err(e) = persister.submit(state)
        {
            tracing::warn!(error = %e, "position not queued for the database");
        }
    }

    fn persist_all(&self) {
        let Some(persister) = &self.persister else { return };
        let states: Vec<PlayerState> = (0..self.players.len()).filter_map(|i| self.state_of(i)).collect();
        if let Err(e) = persister.submit_many(&states) {
            tracing::warn!(error = %e, "positions not queued for the database");
        }
    }

    /// AOI queries and interest management for every active player (ready, address
    /// known); returns the records packed. Inactive players get nothing sealed, so their
    /// sequence numbers start with what they actually receive. Also returns the time of
    /// the AOI query in ms (part of the `packets` stage).
    fn build_updates(&mut self, boxes: &mut Vec<Aabb>, aoi: &mut AoiResults) -> (usize, f64) {
        let half = Vec3::splat(self.config.aoi_size / 2.0);
        boxes.clear();
        let positions = self.world.dynamics.positions();
        let mut active: Vec<&mut Subscriber> = Vec::with_capacity(self.players.len());
        for (p, s) in self.players.iter().zip(self.subscribers.iter_mut()) {
            if !(p.ready && p.addr.is_some()) {
                continue;
            }
            let Some(slot) = self.world.dynamics.slot(p.entity) else { continue };
            let centre = positions[slot];
            s.object = slot as u32;
            s.centre = centre.to_array();
            boxes.push(Aabb::from_center_half(centre, half));
            active.push(s);
        }
        if active.is_empty() {
            return (0, 0.0);
        }
        let t = Instant::now();
        let queried = self.backend.query_aoi(&self.world, boxes, aoi);
        let aoi_ms = ms(t.elapsed());
        if let Err(e) = queried {
            tracing::error!(error = %e, "AOI query failed");
            return (0, aoi_ms);
        }
        let tick = TickInfo { tick: self.world.tick, dilation_permille: self.dilation.permille() };
        let lists = AoiLists { offsets: &aoi.offsets, objects: &aoi.objects };
        let records = match self.interest.build(tick, &WorldObjects(&self.world), lists, &mut active) {
            Ok(report) => {
                if report.seal_failures > 0 {
                    metrics::counter!("myriad_seal_failures_total").increment(report.seal_failures as u64);
                }
                report.records
            }
            Err(e) => {
                tracing::error!(error = %e, "interest management failed");
                0
            }
        };
        (records, aoi_ms)
    }

    /// Sends the control replies and every ready player's updates; returns bytes and
    /// datagrams sent.
    fn send(&mut self) -> (u64, u64) {
        let mut out: Vec<(SocketAddr, &[u8])> = Vec::new();
        for (addr, d) in &self.control {
            out.push((*addr, d));
        }
        // Start at a different player every tick: when the socket buffer fills and the
        // tail is dropped, the loss is spread over everyone instead of starving the same
        // players tick after tick.
        let n = self.players.len();
        // A scrambled offset, not tick % n: shifting by one player per tick would keep
        // starving almost the same tail.
        let first =
            if n == 0 { 0 } else { ((self.world.tick.wrapping_mul(0x9e37_79b9_7f4a_7c15) >> 32) % n as u64) as usize };
        for i in (first..n).chain(0..first) {
            let (p, s) = (&self.players[i], &self.subscribers[i]);
            // The same filter as build_updates: only active players had datagrams built.
            if let (true, Some(addr), true) = (p.ready, p.addr, self.world.dynamics.slot(p.entity).is_some()) {
                out.extend(s.datagrams().iter().map(|d| (addr, d)));
            }
        }
        let mut sent = 0;
        let mut bytes = 0u64;
        let mut stalls = 0;
        while sent < out.len() {
            match self.endpoint.send_batch(&out[sent..]) {
                Ok(0) => {
                    stalls += 1;
                    if stalls > 3 {
                        break;
                    }
                    std::thread::yield_now();
                }
                Ok(n) => {
                    bytes += out[sent..sent + n].iter().map(|(_, d)| d.len() as u64).sum::<u64>();
                    sent += n;
                }
                Err(e) => {
                    tracing::warn!(error = %e, "udp send failed");
                    break;
                }
            }
        }
        if sent < out.len() {
            metrics::counter!("myriad_packets_dropped_total", "reason" => "send_buffer_full")
                .increment((out.len() - sent) as u64);
        }
        self.control.clear();
        (bytes, sent as u64)
    }
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1000.0
}

fn dropped(reason: &'static str) {
    metrics::counter!("myriad_packets_dropped_total", "reason" => reason).increment(1);
}

fn record_metrics(
    stage_ms: &[f64],
    work: Duration,
    bytes: u64,
    datagrams: u64,
    players: usize,
    objects: usize,
    dilation: &DilationController,
) {
    metrics::histogram!("myriad_tick_duration_seconds").record(work.as_secs_f64());
    for (name, v) in STAGES.iter().zip(stage_ms) {
        metrics::histogram!("myriad_stage_duration_seconds", "stage" => *name).record(v / 1000.0);
    }
    metrics::counter!("myriad_bytes_sent_total").increment(bytes);
    metrics::counter!("myriad_datagrams_sent_total").increment(datagrams);
    metrics::gauge!("myriad_players").set(players as f64);
    metrics::gauge!("myriad_objects").set(objects as f64);
    metrics::gauge!("myriad_time_dilation").set(dilation.factor());
    metrics::counter!("myriad_ticks_total").increment(1);
}
