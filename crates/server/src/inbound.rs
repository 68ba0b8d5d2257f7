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

use std::net::SocketAddr;
use std::time::Instant;

use myriad_core::World;
use myriad_protocol::{ClientMessage, Direction, ErrorClass, ServerInfo, ServerMessage, peek_header};

#[cfg(doc)]
use crate::gate::ReceiveLimits;
use crate::gate::{Gate, Refusal};
use crate::session::{Sessions, missing_entity};
use crate::transport::Transport;

/// Receive batches per tick at most, so a flood cannot starve the tick; what is left
/// waits for the next one.
const MAX_BATCHES: usize = 64;

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

/// Receives what is queued and applies it, gating it here unless the transport did;
/// see the module docs.
pub(crate) fn receive(
    transport: &mut dyn Transport,
    sessions: &mut Sessions,
    world: &mut World,
    info: ServerInfo,
    gate: &mut Gate,
    now: Instant,
) -> InboundReport {
    let mut report = InboundReport::default();
    let gated = transport.gates();
    if gated {
        transport.publish(world.tick, sessions.view());
    }
    let mut ctx = Ctx { info, gate: (!gated).then_some(gate), tick: world.tick, now };
    for _ in 0..MAX_BATCHES {
        if let Some(gate) = &ctx.gate
            && now.elapsed() >= gate.limits().time
        {
            report.out_of_time = true;
            metrics::counter!("myriad_receive_out_of_time_total").increment(1);
            break;
        }
        let mut each = |from: SocketAddr, bytes: &mut [u8]| handle(sessions, world, &mut ctx, &mut report, from, bytes);
        match transport.receive(&mut each) {
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

fn handle(
    sessions: &mut Sessions,
    world: &mut World,
    ctx: &mut Ctx<'_>,
    report: &mut InboundReport,
    from: SocketAddr,
    bytes: &mut [u8],
) {
    let session_id = match ctx.gate.as_deref_mut() {
        // The gate is passed before the tag check: past it, a datagram costs a table
        // lookup, never a Poly1305 computation.
        Some(gate) => match gate.admit(&*sessions, ctx.tick, from, bytes) {
            Ok(id) => id,
            Err(refusal) => {
                report.over_budget += u64::from(refusal.over_budget());
                refusal.count();
                return;
            }
        },
        // Gated on the receiver thread already; the header was checked there.
        None => match peek_header(bytes, Direction::ClientToServer) {
            Ok(h) => h.session_id,
            Err(_) => {
                Refusal::Malformed.count();
                return;
            }
        },
    };
    // With a receiver thread the session may have left since its view was published.
    let Some(p) = sessions.by_session_mut(session_id) else {
        Refusal::UnknownSession.count();
        return;
    };
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
    p.last_heard = ctx.now;
    let reply = match opened.message {
        ClientMessage::Action(a) => {
            if p.accept_frame(a.client_frame) {
                let action = p.action_for(a.mask.bits(), ctx.tick);
                if world.dynamics.set_action(p.entity, action) {
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
    // Authenticated: the sender holds the session key, so its address is the player's
    // (this also follows a client whose NAT mapping changed). Set before the reply is
    // queued, which goes to the player's address.
    sessions.set_address(session_id, from);
    if let Some(reply) = reply {
        sessions.queue_message_to(session_id, &reply);
    }
}

fn dropped(reason: &'static str) {
    metrics::counter!("myriad_packets_dropped_total", "reason" => reason).increment(1);
}
