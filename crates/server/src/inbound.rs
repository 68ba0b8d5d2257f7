//! Receiving: datagrams from the [`Transport`] are routed by session id, opened by the
//! session's opener and applied.
//!
//! **Invariant:** only a datagram that opens under its session's keys (length, version,
//! kind, session, replay window, tag, body: see `myriad_protocol::Opener`) changes any
//! state — address, action, timers, replay window — and nothing is sent back to one
//! that does not. The one exception is the receive budget, which is not session state a
//! client relies on: it is spent before the tag check, so that a flood can only waste
//! a bounded amount of cryptography.
//!
//! # The receive budget
//!
//! Every datagram passes the [gate](crate::gate) before its tag check: per session and
//! per tick at most a few datagrams reach the cryptography. A transport that gates on
//! its own thread ([`crate::receiver`]) hands over only what passed; otherwise the gate
//! runs here, and receiving also stops at a deadline ([`ReceiveLimits::time`]); what is
//! left stays in the socket buffer for the next tick (the kernel drops what
//! overflows). A flood of garbage, which costs no cryptography, then costs at most that
//! much of the tick.
//!
//! # Opening in parallel
//!
//! The tag checks (ChaCha20-Poly1305, about a microsecond each) are most of what a
//! receive costs, so each batch the transport hands over is opened in two phases:
//!
//! 1. the gate (when this receive gates) and the lookup of each datagram's session,
//!    with the same refusals and counters as one at a time: in arrival order on the
//!    tick thread when the gate is here, else (the receiver thread gated, and nothing
//!    in this phase depends on what came before) on the rayon pool for a large batch,
//!    the admitted kept in arrival order;
//! 2. the datagrams grouped by player, then, on the rayon pool for a large batch, each
//!    player's part, its datagrams in arrival order: `Opener::open_with` (the header, the
//!    replay window, the tag and the body, then the sequence number recorded, so of two
//!    copies of one datagram only the first is accepted), for an action the slot of the
//!    player's object (the slot it had last tick, else a look-up in the map of every
//!    object's id; no part of a receive changes slots), and what the message changes of
//!    that player alone (acknowledgements, frame, address and sealed reply); then, in
//!    arrival order on the tick thread, what players share: the world's actions, the
//!    counts, the published directory and the queue of replies. A player's part
//!    touches that player alone (and reads the world), so the order among players
//!    changes nothing, and each player's entry (several cache misses, at 50,000 players
//!    most of the receive's time on one thread) is fetched once, by the thread that
//!    opens its datagrams.
//!
//! Every decision is the one that opening the datagrams one at a time would make:
//!
//! * a player's datagrams are opened one at a time, in arrival order, each against the
//!   window as the ones before it left it;
//! * the one thing phase 2 changes that phase 1 reads is a session's address, which
//!   picks the gate's own-address or other-address budget. A datagram admitted from
//!   another address than its session's may move it, so the batch is cut before the
//!   session's next datagram, which is gated once everything before it was applied.
//!   Only the inline gate reads addresses: behind the receiver thread a batch is never
//!   cut. (Whoever makes the inline receive cut often only brings it back to one
//!   datagram at a time, as it was before.)

use std::collections::HashSet;
use std::net::SocketAddr;
use std::ops::Range;
use std::time::{Duration, Instant};

use myriad_core::{Action, Dynamics, World};
use myriad_protocol::{
    ClientMessage, DecodeError, Direction, ErrorClass, Header, ServerInfo, ServerMessage, peek_header,
};
use rayon::prelude::*;

#[cfg(doc)]
use crate::gate::ReceiveLimits;
use crate::gate::{Gate, Refusal};
use crate::session::{Answered, Player, Sessions, missing_entity};
use crate::transport::Transport;

/// Receive batches per tick at most, so a flood cannot starve the tick; what is left
/// waits for the next one.
const MAX_BATCHES: usize = 64;

/// Fewest datagrams whose tag checks go to the rayon pool; fewer are checked on the
/// tick thread. Handing work to the pool and waiting for it costs about 10 to 15 µs
/// (`benches/open.rs` of `myriad-protocol` on a 2-core VM, where a tag check of an
/// action costs about 0.22 µs): there the pool ties at 128 datagrams and wins from 256
/// (58 -> 42 µs; 3,333: 764 -> 441 µs), while at 64 it loses (14 -> 22 µs). With 16
/// cores the tie comes earlier (about 70 by the same costs), so 128 keeps on the tick
/// thread only what the pool could barely speed up on any machine.
pub(crate) const PARALLEL_OPEN_MIN: usize = 128;

/// Datagrams per rayon task: enough to amortise a task's cost over its tag checks.
const OPEN_CHUNK: usize = 16;

/// What one tick's receive did.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub(crate) struct InboundReport {
    /// Datagrams taken from the transport (before authentication).
    pub received: u64,
    /// Datagrams that reached their session's opener (its replay window, then its tag
    /// check): at most this many tag checks were paid for this tick.
    pub tag_checks: u64,
    /// Datagrams dropped, before any cryptography, because their session's budget for
    /// this tick was spent (either address).
    pub over_budget: u64,
    /// Actions applied to the world.
    pub actions: u64,
    /// Sessions that asked to leave (authenticated `Disconnect`), in arrival order.
    pub leaving: Vec<u64>,
    /// Time in each phase of the module docs (1, then 2 in its two parts: each
    /// player's, what players share), over every batch.
    pub phases: [Duration; 3],
}

/// Datagrams in arrival order, copied into one flat buffer: a batch taken from the
/// transport (whose buffers are lent only for one call) so that several threads can open
/// it, or the queue between the receiver thread and the tick ([`crate::receiver`]). Kept
/// between ticks for its memory.
#[derive(Debug, Default)]
pub(crate) struct Inbox {
    bytes: Vec<u8>,
    items: Vec<(SocketAddr, Range<usize>)>,
}

impl Inbox {
    /// Appends `datagram` from `from`.
    pub fn push(&mut self, from: SocketAddr, datagram: &[u8]) {
        let start = self.bytes.len();
        self.bytes.extend_from_slice(datagram);
        self.items.push((from, start..self.bytes.len()));
    }

    /// Appends `datagram` unless the inbox would then hold more than `max_items`
    /// datagrams or `max_bytes` bytes; false when it did not.
    pub fn push_within(&mut self, from: SocketAddr, datagram: &[u8], max_items: usize, max_bytes: usize) -> bool {
        if self.items.len() >= max_items || self.bytes.len() + datagram.len() > max_bytes {
            return false;
        }
        self.push(from, datagram);
        true
    }

    /// Datagrams held.
    pub fn len(&self) -> usize {
        self.items.len()
    }

    /// Whether it holds none.
    pub fn is_empty(&self) -> bool {
        self.items.is_empty()
    }

    /// Every datagram with its sender, in arrival order.
    pub fn iter(&self) -> impl Iterator<Item = (SocketAddr, &[u8])> {
        self.items.iter().map(|(from, range)| (*from, &self.bytes[range.clone()]))
    }

    /// Forgets every datagram, keeping the memory.
    pub fn clear(&mut self) {
        self.bytes.clear();
        self.items.clear();
    }
}

/// What a receive works in, kept between ticks for its memory: the batch being opened
/// and phase 1's bookkeeping (module docs).
#[derive(Debug, Default)]
pub(crate) struct ReceiveBuffers {
    inbox: Inbox,
    /// Phase 1's output, in arrival order.
    admitted: Vec<Admitted>,
    /// Sessions with a datagram from another address than their own in the current
    /// part of the batch (module docs).
    moving: HashSet<u64>,
    /// Phase 2: the admitted datagrams by player, then arrival (`player << 32 | index`).
    by_player: Vec<u64>,
    /// Phase 2: where each admitted datagram (by arrival) is in `by_player`.
    position: Vec<u32>,
}

/// A datagram past the gate, with its session.
#[derive(Debug, Clone, Copy)]
struct Admitted {
    /// Its index in the batch.
    item: usize,
    from: SocketAddr,
    session_id: u64,
    /// Its length, which earns its session's address reply credit.
    len: usize,
    /// Its player's position in the session table (stable during a receive: nothing
    /// joins or leaves meanwhile).
    player: usize,
}

/// Receives what is queued and applies it; see the module docs. `gate` is the gate
/// when this receive gates, `None` when the transport did ([`Transport::gates`]); the
/// caller has published the sessions to a gating transport.
pub(crate) fn receive(
    transport: &mut dyn Transport,
    sessions: &mut Sessions,
    world: &mut World,
    info: ServerInfo,
    gate: Option<&mut Gate>,
    buffers: &mut ReceiveBuffers,
    now: Instant,
) -> InboundReport {
    debug_assert_eq!(gate.is_none(), transport.gates(), "one gate per place datagrams are received");
    let mut report = InboundReport::default();
    let gated = gate.is_none();
    let mut ctx = Ctx { info, gate, tick: world.tick, now };
    for _ in 0..MAX_BATCHES {
        if let Some(gate) = &ctx.gate
            && now.elapsed() >= gate.limits().time
        {
            metrics::counter!("myriad_receive_out_of_time_total").increment(1);
            break;
        }
        let inbox = &mut buffers.inbox;
        inbox.clear();
        let taken = transport.receive(&mut |from, bytes| inbox.push(from, bytes));
        // A transport that failed part-way may have handed over some datagrams first.
        handle_batch(sessions, world, &mut ctx, &mut report, buffers);
        match taken {
            Ok(0) => break,
            Ok(n) if !gated => {
                metrics::counter!("myriad_datagrams_received_total").increment(n as u64);
                report.received += n as u64;
            }
            Ok(_) => {}
            Err(e) => {
                tracing::warn!(error = %e, "receive failed");
                break;
            }
        }
        if gated {
            // A gating transport hands over everything it has in one call.
            break;
        }
    }
    buffers.inbox.clear();
    if gated {
        let counts = transport.gate_counts();
        report.received = counts.taken;
        report.over_budget = counts.over_budget;
    }
    report
}

/// What every datagram of one receive shares.
struct Ctx<'a> {
    info: ServerInfo,
    /// The gate, when this receive gates (the transport did not).
    gate: Option<&'a mut Gate>,
    tick: u64,
    now: Instant,
}

/// Opens and applies one batch in the three phases of the module docs, part by part.
fn handle_batch(
    sessions: &mut Sessions,
    world: &mut World,
    ctx: &mut Ctx<'_>,
    report: &mut InboundReport,
    buffers: &mut ReceiveBuffers,
) {
    let mut start = 0;
    while start < buffers.inbox.len() {
        let t = Instant::now();
        start = admit(sessions, ctx, report, buffers, start);
        let admitted = Instant::now();
        let shared = open_and_apply(sessions, world, ctx, report, buffers);
        report.phases[0] += admitted - t;
        report.phases[1] += shared - admitted;
        report.phases[2] += shared.elapsed();
    }
}

/// Phase 1: gates and resolves the datagrams from `start` on, in order, into
/// `buffers.admitted`, up to the end of the batch or the first datagram whose gating
/// must wait for what came before to be applied (module docs); returns where it stopped.
fn admit(
    sessions: &Sessions,
    ctx: &mut Ctx<'_>,
    report: &mut InboundReport,
    buffers: &mut ReceiveBuffers,
    start: usize,
) -> usize {
    let ReceiveBuffers { inbox, admitted, moving, .. } = buffers;
    if ctx.gate.is_none() && inbox.len() - start >= PARALLEL_OPEN_MIN {
        // Behind the receiver thread nothing here depends on what came before (no
        // address is read, the batch is never cut): each datagram's session is looked
        // up on the pool, the admitted kept in arrival order.
        let Inbox { bytes, items } = &*inbox;
        admitted.par_extend(items[start..].par_iter().enumerate().filter_map(|(k, (from, range))| {
            let datagram = &bytes[range.clone()];
            resolve(sessions, start + k, *from, datagram, peek_header(datagram, Direction::ClientToServer))
        }));
        return inbox.len();
    }
    moving.clear();
    for (i, (from, bytes)) in inbox.iter().enumerate().skip(start) {
        let header = peek_header(bytes, Direction::ClientToServer);
        if let Ok(h) = &header
            && moving.contains(&h.session_id)
        {
            return i;
        }
        // The gate is passed before the tag check: past it, a datagram costs a table
        // lookup, never a Poly1305 computation.
        if let Some(gate) = ctx.gate.as_deref_mut()
            && let Err(refusal) = gate.admit(sessions, ctx.tick, from, bytes)
        {
            report.over_budget += u64::from(refusal.over_budget());
            refusal.count();
            continue;
        }
        let Some(a) = resolve(sessions, i, from, bytes, header) else { continue };
        if ctx.gate.is_some() && sessions.get(a.player).and_then(|p| p.addr) != Some(from) {
            moving.insert(a.session_id);
        }
        admitted.push(a);
    }
    inbox.len()
}

/// Datagram `item` of the batch, from `from`, with its peeked `header`, as phase 1
/// admits it: `None` (counted) when it has no header (the gate, inline or on the
/// receiver thread, refuses those first) or no live session (with a receiver thread it
/// may have left since the directory was published).
fn resolve(
    sessions: &Sessions,
    item: usize,
    from: SocketAddr,
    datagram: &[u8],
    header: Result<Header, DecodeError>,
) -> Option<Admitted> {
    let Ok(header) = header else {
        Refusal::Malformed.count();
        return None;
    };
    let Some(player) = sessions.index_of(header.session_id) else {
        Refusal::UnknownSession.count();
        return None;
    };
    Some(Admitted { item, from, session_id: header.session_id, len: datagram.len(), player })
}

/// What phase 2 needs of the receive besides the datagram: the same for every player.
#[derive(Clone, Copy)]
struct Now {
    info: ServerInfo,
    tick: u64,
    now: Instant,
}

/// The admitted datagrams' bytes, in arrival order, apart (they lie in the inbox's
/// buffer in that order).
fn admitted_bytes<'a>(
    bytes: &'a mut [u8],
    items: &[(SocketAddr, Range<usize>)],
    admitted: &[Admitted],
) -> Vec<&'a mut [u8]> {
    let mut out = Vec::with_capacity(admitted.len());
    let (mut rest, mut offset) = (bytes, 0);
    for a in admitted {
        let range = &items[a.item].1;
        let (_, tail) = std::mem::take(&mut rest).split_at_mut(range.start - offset);
        let (datagram, tail) = tail.split_at_mut(range.len());
        (rest, offset) = (tail, range.end);
        out.push(datagram);
    }
    out
}

/// Phase 2 (module docs): each player's part of every admitted datagram (on the pool
/// for a large batch, a player's datagrams in arrival order on one thread), then the
/// shared part in arrival order. Returns when the shared part started (a small batch,
/// one datagram at a time, counts whole as the shared part).
fn open_and_apply(
    sessions: &mut Sessions,
    world: &mut World,
    ctx: &Ctx<'_>,
    report: &mut InboundReport,
    buffers: &mut ReceiveBuffers,
) -> Instant {
    let ReceiveBuffers { inbox: Inbox { bytes, items }, admitted, by_player, position, .. } = buffers;
    let now = Now { info: ctx.info, tick: ctx.tick, now: ctx.now };
    let mut datagrams = admitted_bytes(bytes, items, admitted);
    if admitted.len() < PARALLEL_OPEN_MIN {
        let started = Instant::now();
        for (a, datagram) in admitted.drain(..).zip(datagrams) {
            let done = apply_to_player(sessions.get_mut(a.player), &world.dynamics, now, &a, datagram);
            finish(sessions, world, report, &a, done);
        }
        return started;
    }
    by_player.clear();
    by_player.extend(admitted.iter().enumerate().map(|(i, a)| ((a.player as u64) << 32) | i as u64));
    by_player.par_sort_unstable();
    let arrival = |key: u64| key as u32 as usize;
    let mut items: Vec<(&mut [u8], Applied)> =
        by_player.iter().map(|&k| (std::mem::take(&mut datagrams[arrival(k)]), Applied::default())).collect();
    // One group a player, its datagrams in arrival order, and the player with it.
    let player_of = |k: &u64| (k >> 32) as usize;
    let mut groups = Vec::new();
    let mut rest = &mut items[..];
    for keys in by_player.chunk_by(|x, y| player_of(x) == player_of(y)) {
        let (group, tail) = std::mem::take(&mut rest).split_at_mut(keys.len());
        groups.push((keys, group));
        rest = tail;
    }
    let players = sessions.players_at_mut(groups.iter().map(|(keys, _)| player_of(&keys[0])));
    let admitted_now: &[Admitted] = admitted;
    let dynamics = &world.dynamics;
    players.into_par_iter().zip(groups).with_min_len(OPEN_CHUNK).for_each(|(mut p, (keys, group))| {
        for (&k, (datagram, done)) in keys.iter().zip(group) {
            *done = apply_to_player(p.as_deref_mut(), dynamics, now, &admitted_now[arrival(k)], datagram);
        }
    });
    let shared = Instant::now();
    position.clear();
    position.resize(admitted.len(), 0);
    for (at, &k) in by_player.iter().enumerate() {
        position[arrival(k)] = at as u32;
    }
    for (i, a) in admitted.drain(..).enumerate() {
        let done = std::mem::take(&mut items[position[i] as usize].1);
        finish(sessions, world, report, &a, done);
    }
    shared
}

/// What a datagram's player part left for the shared part ([`finish`]).
#[derive(Debug, Default)]
struct Applied {
    /// It reached the tag check (its session was there).
    checked: bool,
    /// An action to set at the slot of the player's object (`None`: the object is
    /// missing).
    action: Option<(Option<usize>, Action)>,
    /// The player asked to leave.
    leaving: bool,
    /// What the player's answer leaves for the table.
    answered: Option<Answered>,
}

/// Phase 2, a player's part: opens one datagram with the player's opener (the window
/// as the player's datagrams before it left it) and applies what its message changes of
/// that player alone, finding an action's slot in `dynamics`; `p` is `None` when the
/// session is gone.
fn apply_to_player(
    p: Option<&mut Player>,
    dynamics: &Dynamics,
    now: Now,
    a: &Admitted,
    datagram: &mut [u8],
) -> Applied {
    let Some(p) = p else {
        Refusal::UnknownSession.count();
        return Applied::default();
    };
    let mut done = Applied { checked: true, ..Applied::default() };
    let opened = match p.opener.open_with(datagram, ClientMessage::decode_body) {
        Ok(o) => o,
        Err(e) => {
            dropped(match e.class() {
                ErrorClass::Malformed => "malformed",
                ErrorClass::Authentication => "authentication",
                ErrorClass::Replayed => "replayed",
            });
            return done;
        }
    };
    p.last_heard = now.now;
    // Authenticated, so the acknowledgement is the client's: the next updates are sent
    // relative to the states it names. Idempotent, in any order (a replayed datagram
    // never gets here).
    if let Some(acks) = opened.message.acks() {
        p.view.acknowledge(acks);
    }
    let reply = match opened.message {
        ClientMessage::Action { input, .. } => {
            if p.accept_frame(input.client_frame) {
                let slot = dynamics.slot_hinted(p.entity, p.slot_hint);
                done.action = Some((slot, p.action_for(input.mask.bits(), now.tick)));
            }
            None
        }
        // Idempotent: the client resends Ready until the session starts, and each copy
        // is answered (within the reply credit) without resetting anything.
        ClientMessage::Ready => {
            p.ready = true;
            Some(ServerMessage::ServerInfo(now.info))
        }
        ClientMessage::KeepAlive { .. } => Some(ServerMessage::KeepAlive),
        ClientMessage::Disconnect => {
            done.leaving = true;
            None
        }
    };
    // Authenticated: the sender holds the session key, so its address is the player's
    // (this also follows a client whose NAT mapping changed). Set before the reply is
    // sealed, which goes to the player's address within its reply credit.
    done.answered = Some(p.answer(a.from, a.len, reply));
    done
}

/// Phase 2, the shared part of one datagram, in arrival order: the action into the
/// world, the counts, the table's half of the answer.
fn finish(sessions: &mut Sessions, world: &mut World, report: &mut InboundReport, a: &Admitted, done: Applied) {
    report.tag_checks += u64::from(done.checked);
    if let Some((slot, action)) = done.action {
        if slot.is_some_and(|s| world.dynamics.set_action_at(s, action)) {
            report.actions += 1;
        } else if let Some(p) = sessions.get(a.player) {
            missing_entity(p);
        }
    }
    if done.leaving {
        report.leaving.push(a.session_id);
    }
    if let Some(answered) = done.answered {
        sessions.take_answer(answered);
    }
}

fn dropped(reason: &'static str) {
    metrics::counter!("myriad_packets_dropped_total", "reason" => reason).increment(1);
}

#[cfg(test)]
#[path = "inbound_bench.rs"]
mod bench;
