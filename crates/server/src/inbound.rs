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
//! Every datagram that names a live session costs a Poly1305 check, and the session id
//! travels in clear, so anyone can make the server pay for one with a single datagram.
//! The work is therefore bounded **before any cryptography**:
//!
//! - per session and per tick, at most [`ReceiveLimits::per_session`] datagrams from the
//!   session's own address reach the tag check, and at most
//!   [`ReceiveLimits::other_address`] from any other address (address migration, or the
//!   first datagram before the address is known). Excess is dropped and counted
//!   (`myriad_packets_dropped_total{reason="over_budget"|"other_address"}`). The two
//!   budgets are separate so that a stranger flooding a player's session id from
//!   elsewhere cannot crowd out the player's own datagrams.
//! - per tick, receiving stops at a deadline ([`ReceiveLimits::time`]); what is left
//!   stays in the socket buffer for the next tick (the kernel drops what overflows). A
//!   flood of garbage, which costs no cryptography, then costs at most that much time.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use myriad_core::{Action, World};
use myriad_protocol::{ClientMessage, Direction, ErrorClass, MAX_DATAGRAM, ServerInfo, ServerMessage, peek_header};

use crate::session::{Sessions, missing_entity};
use crate::transport::Transport;

/// Receive batches per tick at most, so a flood cannot starve the tick; what is left
/// waits for the next one.
const MAX_BATCHES: usize = 64;

/// How much receive work one tick may do; see the module docs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct ReceiveLimits {
    /// Datagrams per session per tick from the session's own address that may reach
    /// the tag check.
    pub per_session: u16,
    /// Datagrams per session per tick from any other address that may reach the tag
    /// check.
    pub other_address: u16,
    /// Longest a tick's receive may run; checked between batches.
    pub time: Duration,
}

/// One session's receive budget in the current tick.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub(crate) struct ReceiveBudget {
    tick: u64,
    own: u16,
    other: u16,
}

impl ReceiveBudget {
    /// Spends one datagram of tick `tick`'s budget (from the session's own address or
    /// another); false when that budget is spent.
    pub fn take(&mut self, tick: u64, own_address: bool, limits: &ReceiveLimits) -> bool {
        if self.tick != tick {
            *self = ReceiveBudget { tick, own: 0, other: 0 };
        }
        let (used, limit) =
            if own_address { (&mut self.own, limits.per_session) } else { (&mut self.other, limits.other_address) };
        if *used >= limit {
            return false;
        }
        *used += 1;
        true
    }
}

/// What one tick's receive did.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub(crate) struct InboundReport {
    /// Datagrams taken from the transport (before authentication).
    pub received: u64,
    /// Datagrams that reached the tag check (the cryptography this tick paid for).
    pub tag_checks: u64,
    /// Datagrams dropped, before any cryptography, because their session's budget for
    /// this tick was spent (either address).
    pub over_budget: u64,
    /// Whether receiving stopped at the time limit with datagrams possibly left.
    pub out_of_time: bool,
    /// Actions applied to the world.
    pub actions: u64,
    /// Sessions that asked to leave (authenticated `Disconnect`), in arrival order.
    pub leaving: Vec<u64>,
}

/// Receives what is queued and applies it, within `limits`; see the module docs.
pub(crate) fn receive(
    transport: &mut dyn Transport,
    sessions: &mut Sessions,
    world: &mut World,
    info: ServerInfo,
    limits: &ReceiveLimits,
    now: Instant,
) -> InboundReport {
    let mut report = InboundReport::default();
    let ctx = Ctx { info, limits, tick: world.tick, now };
    for _ in 0..MAX_BATCHES {
        if now.elapsed() >= limits.time {
            report.out_of_time = true;
            metrics::counter!("myriad_receive_out_of_time_total").increment(1);
            break;
        }
        let mut each = |from: SocketAddr, bytes: &mut [u8]| handle(sessions, world, &ctx, &mut report, from, bytes);
        match transport.receive(&mut each) {
            Ok(0) => break,
            Ok(n) => {
                metrics::counter!("myriad_datagrams_received_total").increment(n as u64);
                report.received += n as u64;
            }
            Err(e) => {
                tracing::warn!(error = %e, "receive failed");
                break;
            }
        }
    }
    report
}

/// What every datagram of one receive shares.
struct Ctx<'a> {
    info: ServerInfo,
    limits: &'a ReceiveLimits,
    tick: u64,
    now: Instant,
}

fn handle(
    sessions: &mut Sessions,
    world: &mut World,
    ctx: &Ctx<'_>,
    report: &mut InboundReport,
    from: SocketAddr,
    bytes: &mut [u8],
) {
    let header = match peek_header(bytes, Direction::ClientToServer) {
        Ok(h) => h,
        Err(_) if bytes.len() > MAX_DATAGRAM => {
            dropped("oversized");
            return;
        }
        Err(_) => {
            dropped("malformed");
            return;
        }
    };
    let Some(p) = sessions.by_session_mut(header.session_id) else {
        dropped("unknown_session");
        return;
    };
    // The budget is spent before the tag check: past it, a datagram costs a table
    // lookup, never a Poly1305 computation.
    let own_address = p.addr == Some(from);
    if !p.budget.take(ctx.tick, own_address, ctx.limits) {
        report.over_budget += 1;
        dropped(if own_address { "over_budget" } else { "other_address" });
        return;
    }
    report.tag_checks += 1;
    let opened = match p.opener.open_with(bytes, ClientMessage::decode_body) {
        Ok(o) => o,
        Err(e) => {
            dropped(match e.class() {
                ErrorClass::Malformed => "malformed",
                ErrorClass::Authentication => "authentication",
                ErrorClass::Replayed => "replayed",
            });
            return;
        }
    };
    // Authenticated: the sender holds the session key, so its address is the player's
    // (this also follows a client whose NAT mapping changed).
    p.addr = Some(from);
    p.last_heard = ctx.now;
    let session_id = header.session_id;
    let reply = match opened.message {
        ClientMessage::Action(a) => {
            if p.accept_frame(a.client_frame) {
                if world.dynamics.set_action(p.entity, Action::from_bits_truncate(a.mask.bits())) {
                    report.actions += 1;
                } else {
                    missing_entity(p);
                }
            }
            None
        }
        ClientMessage::Ready => {
            p.ready = true;
            Some(ServerMessage::ServerInfo(ctx.info))
        }
        ClientMessage::KeepAlive => Some(ServerMessage::KeepAlive),
        ClientMessage::Disconnect => {
            report.leaving.push(session_id);
            None
        }
    };
    if let Some(reply) = reply {
        sessions.queue_message_to(session_id, &reply);
    }
}

fn dropped(reason: &'static str) {
    metrics::counter!("myriad_packets_dropped_total", "reason" => reason).increment(1);
}
