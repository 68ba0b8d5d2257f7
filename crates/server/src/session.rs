//! The sessions table: every logged-in player, both halves of its session, and the
//! control messages queued for it.
//!
//! [`Sessions`] is the one owner of a player's session state: the opener (client to
//! server), the sealer (server to client, inside the player's interest [`Subscriber`]),
//! the address, the ready flag, the last-heard time and the indexes by session id and by
//! user. Joins, replacements, adoptions, expiry and removal all go through it, so the
//! indexes cannot drift from the table. It touches the world only to spawn and despawn
//! player objects and to read their positions.
//!
//! A player's object missing from the world is a broken invariant, not slot 0: it is
//! logged, counted (`myriad_missing_entity_total`) and the player is skipped.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use myriad_core::{Action, EntityId, ObjectKind, Shape, Vec3, World};
use myriad_interest::Subscriber;
use myriad_protocol::login::RefusalReason;
use myriad_protocol::{DisconnectReason, MIN_DATAGRAM, Opener, ServerMessage, ServerSession, SessionKeys};
use myriad_store::{MapId, PlayerState, UserId};
use ring::rand::{SecureRandom, SystemRandom};

use crate::gate::{SessionAddresses, SessionDirectory};
use crate::world::{clamp_into_world, shape_desc, spawn_point, store_shape};

/// Copies of a Disconnect the server sends (each sealed afresh), so that one lost
/// datagram does not leave the client waiting for its silence timeout
/// (docs/protocol.md §7a).
pub(crate) const DISCONNECT_COPIES: usize = 3;

/// Players from which the silence check runs on the pool.
const PARALLEL_EXPIRE_MIN: usize = 4096;

/// The default player shape (a person-sized capsule).
pub const PLAYER_SHAPE: Shape = Shape::Capsule { radius: 0.4, half_height: 0.5 };

/// An admitted player: what the login response carries.
pub(crate) struct Joined {
    pub keys: SessionKeys,
    pub entity: u64,
    pub position: [f32; 3],
    pub shape: myriad_protocol::login::ShapeDesc,
    pub tick: u64,
    pub dilation_permille: u16,
}

/// The answer to a join.
pub(crate) type JoinResult = Result<Joined, RefusalReason>;

/// One logged-in player.
pub(crate) struct Player {
    pub user_id: UserId,
    pub username: String,
    pub entity: EntityId,
    /// The slot `entity` had when the tick last looked (a hint for
    /// `Dynamics::slot_hinted`; slots move only when objects come or go).
    pub slot_hint: Option<u32>,
    pub shape: Shape,
    pub session_id: u64,
    /// Opens what the client sends.
    pub opener: Opener,
    /// What the outbound keeps of this player (the host outbound's interest state, the
    /// device outbound's index into its own), its datagrams of the tick, and the sealer
    /// of what the server sends.
    pub view: Subscriber,
    /// Where the last authenticated datagram came from; nothing is sent before that.
    /// Only [`Player::answer`] changes it once the player is in the table (the
    /// published [`SessionDirectory`] follows it through [`Sessions::take_answer`]).
    pub addr: Option<SocketAddr>,
    /// The client asked for state updates. A repeated Ready (the client resends it
    /// until the session starts) only sets it again: it resets nothing.
    pub ready: bool,
    /// When an authenticated datagram last came. Only ever moves forward (to `now`):
    /// [`Sessions::expire`] keeps a bound on the earliest silence from it.
    pub last_heard: Instant,
    /// Bytes of authenticated datagrams received from `addr` not yet spent on replies
    /// to it ([`Player::answer`]).
    reply_credit: usize,
    /// A reply waiting for credit (the newest one).
    reply_owed: Option<ServerMessage>,
    /// Newest client frame applied (actions of older frames are ignored).
    last_frame: Option<u32>,
    /// The tick of the last action applied with the jump bit set.
    jump_tick: Option<u64>,
    /// When the player logged in (wall clock, for operators; a replaced session keeps
    /// it: the player never left).
    pub connected_since: std::time::SystemTime,
    /// Update bytes sealed for this player since it joined (counted as the next tick's
    /// outbound starts, so the last tick's are in).
    pub bytes_sent: u64,
    /// `bytes_sent` and the time at the admin API's last snapshot (its bytes/s).
    pub rate_mark: (u64, Instant),
}

impl Player {
    /// Whether this player gets state updates: it asked for them, and its address is
    /// known from an authenticated datagram.
    pub fn active(&self) -> bool {
        self.ready && self.addr.is_some()
    }

    /// Whether an action of `frame` is newer than the last one applied; if so it
    /// becomes the last. Wrapping comparison, so the frame counter may wrap.
    pub fn accept_frame(&mut self, frame: u32) -> bool {
        let newer = self.last_frame.is_none_or(|f| frame.wrapping_sub(f) as i32 > 0);
        if newer {
            self.last_frame = Some(frame);
        }
        newer
    }

    /// The action to apply for `mask`, taken in tick `tick`: the newest action's bits,
    /// except that a jump asked for by any action taken in the same tick stays asked
    /// for. A jump is an event, not a held key: a client that taps jump for less than a
    /// frame sends it in one action only, and a newer action taken in the same tick
    /// must not cancel it.
    pub fn action_for(&mut self, mask: u8, tick: u64) -> Action {
        let mut bits = mask;
        if bits & Action::JUMP != 0 {
            self.jump_tick = Some(tick);
        } else if self.jump_tick == Some(tick) {
            bits |= Action::JUMP;
        }
        Action::from_bits_truncate(bits)
    }

    /// Records an authenticated datagram of `len` bytes from `from` and seals `reply`,
    /// if any, within the reply credit: the server never sends an address more bytes in
    /// answer than it received from it since it became the session's address
    /// (docs/protocol.md §6.2). A ServerInfo (38 bytes) answering a session's first
    /// Ready (34) therefore waits for its next datagram (an action, a resent Ready).
    /// The address follows the datagram (a client whose NAT mapping changed); a new
    /// address starts with no credit. Touches only this player, so that the receive
    /// answers many at once; what the table must know comes back
    /// ([`Sessions::take_answer`]).
    pub fn answer(&mut self, from: SocketAddr, len: usize, reply: Option<ServerMessage>) -> Answered {
        let moved = self.addr != Some(from);
        if moved {
            self.addr = Some(from);
            self.reply_credit = 0;
        }
        self.reply_credit = self.reply_credit.saturating_add(len);
        if reply.is_some() {
            self.reply_owed = reply;
        }
        let mut answered = Answered { moved, reply: None };
        let Some(msg) = self.reply_owed.take() else { return answered };
        let mut body = Vec::new();
        let size = match msg.encode_body(&mut body) {
            Ok(()) => MIN_DATAGRAM + body.len(),
            Err(_) => usize::MAX,
        };
        if size <= self.reply_credit {
            self.reply_credit -= size;
            answered.reply = self.seal_control(&msg);
        } else {
            self.reply_owed = Some(msg);
        }
        answered
    }

    /// `msg` sealed for this player's address; `None` before the address is known, or
    /// when sealing failed (logged and counted).
    fn seal_control(&mut self, msg: &ServerMessage) -> Option<(SocketAddr, Vec<u8>)> {
        let addr = self.addr?;
        let mut out = Vec::with_capacity(64);
        match self.view.sealer.seal_server_message(msg, &mut out) {
            Ok(_) => Some((addr, out)),
            Err(e) => {
                tracing::warn!(error = %e, user = %self.username, "control message not sealed");
                metrics::counter!("myriad_seal_failures_total").increment(1);
                None
            }
        }
    }
}

/// What [`Player::answer`] leaves for the table ([`Sessions::take_answer`]).
#[must_use = "the table must take the answer: a moved address, a reply to queue"]
#[derive(Debug)]
pub(crate) struct Answered {
    /// The player's address moved (the published directory is stale).
    moved: bool,
    /// The reply, sealed, and where it goes.
    reply: Option<(SocketAddr, Vec<u8>)>,
}

/// Context a join needs besides the world.
#[derive(Debug, Clone, Copy)]
pub(crate) struct JoinContext {
    pub tick: u64,
    pub dilation_permille: u16,
}

/// What a join did to persistence: a first visit's spawn point to store.
pub(crate) type FirstVisit = Option<PlayerState>;

/// Every player's session; see the module docs.
pub(crate) struct Sessions {
    players: Vec<Player>,
    by_session: foldhash::HashMap<u64, usize>,
    by_user: HashMap<i64, usize>,
    /// Sealed control replies (keep-alives, server info, disconnects) for this tick.
    control: Vec<(SocketAddr, Vec<u8>)>,
    rng: SystemRandom,
    max_players: usize,
    map_id: MapId,
    /// A session joined, left, or changed address since the last
    /// [`Sessions::changed_directory`].
    directory_stale: bool,
    /// For a timeout, the earliest time any present player can have been silent for
    /// longer than it ([`Sessions::expire`]).
    silence_bound: Option<(Duration, Instant)>,
}

/// The sessions of `players` silent for longer than `timeout` at `now`, and the
/// earliest time any other can be (its last datagram plus `timeout`).
fn silent_players(players: &[Player], now: Instant, timeout: Duration) -> (Vec<u64>, Option<Instant>) {
    let one = |p: &Player| {
        let silent = now.saturating_duration_since(p.last_heard) > timeout;
        (silent.then_some(p.session_id), (!silent).then(|| p.last_heard + timeout))
    };
    let earliest = |a: Option<Instant>, b: Option<Instant>| a.into_iter().chain(b).min();
    if players.len() >= PARALLEL_EXPIRE_MIN {
        use rayon::prelude::*;
        players
            .par_iter()
            .fold(
                || (Vec::new(), None),
                |(mut ids, bound), p| {
                    let (id, due) = one(p);
                    ids.extend(id);
                    (ids, earliest(bound, due))
                },
            )
            .reduce(
                || (Vec::new(), None),
                |(mut a, x), (b, y)| {
                    a.extend(b);
                    (a, earliest(x, y))
                },
            )
    } else {
        players.iter().map(one).fold((Vec::new(), None), |(mut ids, bound), (id, due)| {
            ids.extend(id);
            (ids, earliest(bound, due))
        })
    }
}

/// Counts and logs a player whose object is not in the world.
pub(crate) fn missing_entity(p: &Player) {
    tracing::error!(user = %p.username, entity = p.entity.0, "player object missing from the world");
    metrics::counter!("myriad_missing_entity_total").increment(1);
}

impl Sessions {
    /// An empty table for at most `max_players` players on map `map_id`.
    pub fn new(max_players: usize, map_id: MapId) -> Self {
        Sessions {
            players: Vec::new(),
            by_session: foldhash::HashMap::default(),
            by_user: HashMap::new(),
            control: Vec::new(),
            rng: SystemRandom::new(),
            max_players,
            map_id,
            directory_stale: true,
            silence_bound: None,
        }
    }

    /// A fresh [`SessionDirectory`] for the receiver thread, when a session joined, left
    /// or changed address since the last call; `None` when the last one still holds.
    pub fn changed_directory(&mut self) -> Option<Arc<SessionDirectory>> {
        if !std::mem::take(&mut self.directory_stale) {
            return None;
        }
        Some(Arc::new(SessionDirectory::new(self.players.iter().map(|p| (p.session_id, p.addr)))))
    }

    /// The table's half of an answer ([`Player::answer`]): the published directory is
    /// stale if the player's address moved, and the sealed reply is queued for this
    /// tick's send.
    pub fn take_answer(&mut self, answered: Answered) {
        self.directory_stale |= answered.moved;
        self.control.extend(answered.reply);
    }

    /// Players logged in.
    pub fn len(&self) -> usize {
        self.players.len()
    }

    /// Every player, in table order.
    #[cfg(test)]
    pub fn iter(&self) -> impl Iterator<Item = &Player> {
        self.players.iter()
    }

    /// Every player, mutably, in table order.
    pub fn iter_mut(&mut self) -> impl Iterator<Item = &mut Player> {
        self.players.iter_mut()
    }

    /// Every player, mutably, in table order, for rayon.
    pub fn par_iter_mut(&mut self) -> rayon::slice::IterMut<'_, Player> {
        use rayon::prelude::*;
        self.players.par_iter_mut()
    }

    /// The player of `session_id`.
    #[cfg(test)]
    pub fn by_session_mut(&mut self, session_id: u64) -> Option<&mut Player> {
        let idx = *self.by_session.get(&session_id)?;
        self.players.get_mut(idx)
    }

    /// The player at table position `idx` (stable until the next join or removal).
    pub fn get(&self, idx: usize) -> Option<&Player> {
        self.players.get(idx)
    }

    /// The player at table position `idx`, mutably.
    pub fn get_mut(&mut self, idx: usize) -> Option<&mut Player> {
        self.players.get_mut(idx)
    }

    /// The players at the table positions `ascending` (increasing, as their name says),
    /// mutably and all at once (the receive applies their datagrams on the pool): one
    /// entry per position, `None` for a position past the table or not above the one
    /// before it.
    pub fn players_at_mut(&mut self, ascending: impl IntoIterator<Item = usize>) -> Vec<Option<&mut Player>> {
        let (mut rest, mut base): (&mut [Player], usize) = (&mut self.players, 0);
        ascending
            .into_iter()
            .map(|idx| {
                if idx < base || idx - base >= rest.len() {
                    return None;
                }
                let (_, tail) = std::mem::take(&mut rest).split_at_mut(idx - base);
                let (p, tail) = tail.split_first_mut()?;
                (rest, base) = (tail, idx + 1);
                Some(p)
            })
            .collect()
    }

    /// The table position of the player of `session_id`.
    pub fn index_of(&self, session_id: u64) -> Option<usize> {
        self.by_session.get(&session_id).copied()
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
                bytes.fill(0);
                return Ok(keys);
            }
        }
    }

    /// Admits an authenticated user, or gives it a fresh session if it is already
    /// logged in (the object, and its position in the world, newer than the stored one,
    /// stays; the old session gets a `Replaced` disconnect). A first visit spawns the
    /// player's object and returns its spawn point for the store.
    pub fn join(
        &mut self,
        world: &mut World,
        user_id: UserId,
        username: String,
        state: Option<PlayerState>,
        ctx: JoinContext,
    ) -> Result<(Joined, FirstVisit), RefusalReason> {
        if let Some(&idx) = self.by_user.get(&user_id.0) {
            let keys = self.fresh_keys()?;
            self.queue_disconnect(idx, DisconnectReason::Replaced);
            let session = ServerSession::new(&keys);
            let p = &mut self.players[idx];
            let Some(slot) = world.dynamics.slot(p.entity) else {
                missing_entity(p);
                return Err(RefusalReason::Unavailable);
            };
            self.by_session.remove(&p.session_id);
            p.session_id = keys.session_id;
            p.opener = session.opener;
            p.view = Subscriber::new(slot as u32, world.dynamics.positions()[slot].to_array(), session.sealer);
            p.addr = None;
            p.ready = false;
            p.reply_credit = 0;
            p.reply_owed = None;
            p.last_frame = None;
            p.jump_tick = None;
            p.last_heard = Instant::now();
            self.by_session.insert(keys.session_id, idx);
            self.directory_stale = true;
            tracing::info!(user = %username, "session replaced by a new login");
            return Ok((self.joined(world, idx, keys, ctx)?, None));
        }
        if self.players.len() >= self.max_players {
            return Err(RefusalReason::ServerFull);
        }
        let keys = self.fresh_keys()?;
        let (shape, pos) = match &state {
            Some(s) => (crate::world::core_shape(s.shape), clamp_into_world(world, Vec3::from_array(s.position))),
            None => (PLAYER_SHAPE, spawn_point(world, user_id, PLAYER_SHAPE)),
        };
        let entity = world.dynamics.spawn(shape, pos, ObjectKind::User).map_err(|e| {
            tracing::error!(error = %e, "cannot spawn a player");
            RefusalReason::Unavailable
        })?;
        let idx = self.admit(world, user_id, username.clone(), entity, shape, &keys)?;
        tracing::info!(user = %username, entity = entity.0, "player joined");
        let first_visit =
            state.is_none().then(|| PlayerState::new(user_id, self.map_id, store_shape(shape), pos.to_array()));
        Ok((self.joined(world, idx, keys, ctx)?, first_visit))
    }

    /// Makes `entity`, an object already in the world, the player of `user_id` with a
    /// fresh session, as a login would (the tick benchmark's and the scripted
    /// harness's join).
    pub fn adopt(&mut self, world: &World, user_id: UserId, entity: EntityId, ctx: JoinContext) -> JoinResult {
        let Some(slot) = world.dynamics.slot(entity) else { return Err(RefusalReason::Unavailable) };
        if self.by_user.contains_key(&user_id.0) || self.players.len() >= self.max_players {
            return Err(RefusalReason::Unavailable);
        }
        let keys = self.fresh_keys()?;
        let shape = world.dynamics.shape_of(slot);
        let idx = self.admit(world, user_id, format!("player{}", user_id.0), entity, shape, &keys)?;
        self.joined(world, idx, keys, ctx)
    }

    fn admit(
        &mut self,
        world: &World,
        user_id: UserId,
        username: String,
        entity: EntityId,
        shape: Shape,
        keys: &SessionKeys,
    ) -> Result<usize, RefusalReason> {
        let slot = world.dynamics.slot(entity).ok_or(RefusalReason::Unavailable)?;
        let session = ServerSession::new(keys);
        let view = Subscriber::new(slot as u32, world.dynamics.positions()[slot].to_array(), session.sealer);
        self.players.push(Player {
            user_id,
            username,
            entity,
            slot_hint: Some(slot as u32),
            shape,
            session_id: keys.session_id,
            opener: session.opener,
            view,
            addr: None,
            ready: false,
            last_heard: Instant::now(),
            reply_credit: 0,
            reply_owed: None,
            last_frame: None,
            jump_tick: None,
            connected_since: std::time::SystemTime::now(),
            bytes_sent: 0,
            rate_mark: (0, Instant::now()),
        });
        self.directory_stale = true;
        let idx = self.players.len() - 1;
        self.by_user.insert(user_id.0, idx);
        self.by_session.insert(keys.session_id, idx);
        Ok(idx)
    }

    fn joined(&self, world: &World, idx: usize, keys: SessionKeys, ctx: JoinContext) -> JoinResult {
        let p = &self.players[idx];
        let Some(slot) = world.dynamics.slot(p.entity) else {
            missing_entity(p);
            return Err(RefusalReason::Unavailable);
        };
        Ok(Joined {
            keys,
            entity: u64::from(p.entity.0),
            position: world.dynamics.positions()[slot].to_array(),
            shape: shape_desc(p.shape),
            tick: ctx.tick,
            dilation_permille: ctx.dilation_permille,
        })
    }

    /// Seals `msg` for player `idx` and queues it for this tick's send; nothing is
    /// queued before the player's address is known.
    pub fn queue_message(&mut self, idx: usize, msg: &ServerMessage) {
        if let Some(sealed) = self.players.get_mut(idx).and_then(|p| p.seal_control(msg)) {
            self.control.push(sealed);
        }
    }

    /// Queues [`DISCONNECT_COPIES`] Disconnects for player `idx`.
    fn queue_disconnect(&mut self, idx: usize, reason: DisconnectReason) {
        for _ in 0..DISCONNECT_COPIES {
            self.queue_message(idx, &ServerMessage::Disconnect(reason));
        }
    }

    /// Queues `msg` for every player that gets state updates (ready, address known).
    pub fn queue_to_active(&mut self, msg: &ServerMessage) {
        for idx in 0..self.players.len() {
            if self.players[idx].active() {
                self.queue_message(idx, msg);
            }
        }
    }

    /// Queues a disconnect for every player (shutdown).
    pub fn disconnect_all(&mut self, reason: DisconnectReason) {
        for idx in 0..self.players.len() {
            self.queue_disconnect(idx, reason);
        }
    }

    /// The control replies queued since the last call.
    pub fn control(&self) -> &[(SocketAddr, Vec<u8>)] {
        &self.control
    }

    /// Forgets the queued control replies (after the send).
    pub fn clear_control(&mut self) {
        self.control.clear();
    }

    /// Removes every player silent for longer than `timeout` (queuing a `Timeout`
    /// disconnect); returns their final states for the persister.
    ///
    /// A pass reads every player's entry, a cache line each (0.28 ms a tick for 50,000
    /// players on a GPU host's 16 cores), so it runs only when someone can be silent
    /// that long: each pass notes the earliest time a player left can be (its last
    /// datagram plus `timeout`), and until then there is nothing to find, as
    /// `last_heard` only moves forward and a player who joins after is heard at its
    /// join. With players sending every tick, that is one pass a `timeout`.
    pub fn expire(&mut self, world: &mut World, now: Instant, timeout: Duration) -> Vec<PlayerState> {
        if let Some((t, bound)) = self.silence_bound
            && t == timeout
            && now < bound
        {
            return Vec::new();
        }
        let (expired, bound) = silent_players(&self.players, now, timeout);
        // Those removed below were silent; the rest give the next bound (none: nobody
        // is left, and any player who joins is heard at its join, after now).
        self.silence_bound = Some((timeout, bound.unwrap_or(now + timeout)));
        let mut states = Vec::new();
        for session_id in expired {
            if let Some(p) = self.by_session.get(&session_id).and_then(|&i| self.players.get(i)) {
                tracing::info!(user = %p.username, "session timed out");
            }
            states.extend(self.remove(world, session_id, Some(DisconnectReason::Timeout)));
        }
        states
    }

    /// The session of the account `username` (compared without case, as logins
    /// compare it), if it is here.
    pub fn session_of(&self, username: &str) -> Option<u64> {
        self.players.iter().find(|p| p.username.eq_ignore_ascii_case(username)).map(|p| p.session_id)
    }

    /// Removes the player of `session_id` (queuing `reason`, if any, first): its object
    /// leaves the world; returns its final state for the persister.
    pub fn remove(
        &mut self,
        world: &mut World,
        session_id: u64,
        reason: Option<DisconnectReason>,
    ) -> Option<PlayerState> {
        let idx = *self.by_session.get(&session_id)?;
        if let Some(reason) = reason {
            self.queue_disconnect(idx, reason);
        }
        let state = self.state_of(world, idx);
        let p = self.players.swap_remove(idx);
        self.by_session.remove(&p.session_id);
        self.by_user.remove(&p.user_id.0);
        if let Some(moved) = self.players.get(idx) {
            self.by_session.insert(moved.session_id, idx);
            self.by_user.insert(moved.user_id.0, idx);
        }
        world.dynamics.despawn(p.entity);
        self.directory_stale = true;
        tracing::info!(user = %p.username, "player left");
        state
    }

    fn state_of(&self, world: &World, idx: usize) -> Option<PlayerState> {
        self.states_of(world, &self.players[idx..=idx]).pop()
    }

    /// Every player's current state, for the persister.
    pub fn states(&self, world: &World) -> Vec<PlayerState> {
        self.states_of(world, &self.players)
    }

    /// The states of `players` whose objects are in `world` (a missing one is logged and
    /// counted), their positions in one read: a GPU backend's step leaves the positions
    /// on the device, and only these players' come back.
    fn states_of(&self, world: &World, players: &[Player]) -> Vec<PlayerState> {
        let d = &world.dynamics;
        let present: Vec<(&Player, u32)> = players
            .iter()
            .filter_map(|p| match d.slot(p.entity) {
                Some(slot) => Some((p, slot as u32)),
                None => {
                    missing_entity(p);
                    None
                }
            })
            .collect();
        let slots: Vec<u32> = present.iter().map(|&(_, s)| s).collect();
        let mut positions = Vec::new();
        d.positions_at(&slots, &mut positions);
        present
            .iter()
            .zip(positions)
            .map(|(&(p, _), pos)| PlayerState::new(p.user_id, self.map_id, store_shape(p.shape), pos.to_array()))
            .collect()
    }
}

impl SessionAddresses for Sessions {
    fn address_of(&self, session_id: u64) -> Option<Option<SocketAddr>> {
        self.by_session.get(&session_id).map(|&i| self.players[i].addr)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn world() -> World {
        myriad_core::ScenarioSpec::custom(3).counts(10, 0, 0).map_size(64.0, 17).build().unwrap()
    }

    const CTX: JoinContext = JoinContext { tick: 0, dilation_permille: 1000 };

    #[test]
    fn indexes_follow_removals_and_replacements() {
        let mut w = world();
        let mut s = Sessions::new(3, MapId(1));
        let mut ids = Vec::new();
        for u in 1..=3 {
            let (j, first) = s.join(&mut w, UserId(u), format!("u{u}"), None, CTX).unwrap();
            assert!(first.is_some(), "a first visit is stored");
            ids.push(j.keys.session_id);
        }
        assert_eq!(w.dynamics.len(), 13);
        assert!(matches!(s.join(&mut w, UserId(4), "u4".into(), None, CTX), Err(RefusalReason::ServerFull)));
        // Removing the first moves the last into its place; both indexes follow.
        assert!(s.remove(&mut w, ids[0], None).is_some());
        assert_eq!(w.dynamics.len(), 12);
        assert_eq!(s.by_session_mut(ids[2]).unwrap().user_id, UserId(3));
        assert!(s.by_session_mut(ids[0]).is_none());
        // A second login of user 3 replaces its session, keeps its object.
        let entity = s.by_session_mut(ids[2]).unwrap().entity;
        let (j, first) = s.join(&mut w, UserId(3), "u3".into(), None, CTX).unwrap();
        assert!(first.is_none());
        assert!(s.by_session_mut(ids[2]).is_none(), "the old session is gone");
        assert_eq!(s.by_session_mut(j.keys.session_id).unwrap().entity, entity);
        assert_eq!(s.len(), 2);
        assert_eq!(w.dynamics.len(), 12);
    }

    #[test]
    fn a_missing_object_is_an_error_not_slot_zero() {
        let mut w = world();
        let mut s = Sessions::new(4, MapId(1));
        let (j, _) = s.join(&mut w, UserId(1), "u1".into(), None, CTX).unwrap();
        let entity = s.by_session_mut(j.keys.session_id).unwrap().entity;
        w.dynamics.despawn(entity);
        assert!(s.states(&w).is_empty(), "no state is made up for a missing object");
        assert!(matches!(s.join(&mut w, UserId(1), "u1".into(), None, CTX), Err(RefusalReason::Unavailable)));
    }

    #[test]
    fn players_at_mut_hands_each_position_once_and_refuses_the_rest() {
        let mut w = world();
        let mut s = Sessions::new(4, MapId(1));
        for u in 1..=4 {
            s.join(&mut w, UserId(u), format!("u{u}"), None, CTX).unwrap();
        }
        let users = |got: Vec<Option<&mut Player>>| got.into_iter().map(|p| p.map(|p| p.user_id.0)).collect::<Vec<_>>();
        assert_eq!(users(s.players_at_mut([0, 2, 3])), [Some(1), Some(3), Some(4)]);
        // A position repeated or below the one before, or past the table: none.
        assert_eq!(users(s.players_at_mut([1, 1, 0, 3, 4, 9])), [Some(2), None, None, Some(4), None, None]);
        assert_eq!(users(s.players_at_mut([])), []);
    }

    #[test]
    fn silent_sessions_expire_with_their_final_state() {
        let mut w = world();
        let mut s = Sessions::new(4, MapId(1));
        s.join(&mut w, UserId(1), "u1".into(), None, CTX).unwrap();
        let later = Instant::now() + Duration::from_secs(30);
        assert!(s.expire(&mut w, Instant::now(), Duration::from_secs(10)).is_empty());
        let states = s.expire(&mut w, later, Duration::from_secs(10));
        assert_eq!(states.len(), 1);
        assert_eq!(states[0].user_id, UserId(1));
        assert_eq!(s.len(), 0);
        assert_eq!(w.dynamics.len(), 10);
    }

    /// The check that skips its pass until someone can be silent long enough finds
    /// each silent player at the same tick as a pass every tick would, as players are
    /// heard, join and leave, and with a timeout that changes.
    #[test]
    fn the_silence_check_finds_each_silent_player_at_the_tick_a_pass_every_tick_would() {
        let mut w = world();
        let mut s = Sessions::new(64, MapId(1));
        let start = Instant::now();
        let tick = Duration::from_millis(33);
        let mut ids = Vec::new();
        let mut found = Vec::new();
        let mut rng = 7u64;
        let mut next = || {
            rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            rng >> 33
        };
        for t in 0..600u32 {
            let now = start + tick * t;
            let timeout = Duration::from_secs(if t < 300 { 2 } else { 1 });
            if t % 25 == 0 && s.len() < 40 {
                let u = 100 + i64::from(t);
                let (j, _) = s.join(&mut w, UserId(u), format!("u{u}"), None, CTX).unwrap();
                s.by_session_mut(j.keys.session_id).unwrap().last_heard = now;
                ids.push(j.keys.session_id);
            }
            // Some players are heard this tick (each only ever later than before).
            for (i, &id) in ids.iter().enumerate() {
                // Every fourth player is never heard after its join: the one that joins
                // at tick 275 is silent for 0.8 s when the timeout falls to 1 s.
                if next() % 3 != 0
                    && i % 4 != 3
                    && let Some(p) = s.by_session_mut(id)
                {
                    p.last_heard = now;
                }
            }
            // What a pass over every player would find now.
            let expected: Vec<u64> = s
                .players
                .iter()
                .filter(|p| now.saturating_duration_since(p.last_heard) > timeout)
                .map(|p| p.session_id)
                .collect();
            let before: Vec<u64> = s.players.iter().map(|p| p.session_id).collect();
            s.expire(&mut w, now, timeout);
            let gone: Vec<u64> = before.iter().copied().filter(|id| s.by_session_mut(*id).is_none()).collect();
            assert_eq!(gone, expected, "tick {t}");
            found.extend(gone);
        }
        assert!(found.len() >= 5, "the run must time some players out: {found:?}");
    }
}
