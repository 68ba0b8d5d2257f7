//! Receiving: datagrams from the [`Transport`] are routed by session id, opened by the
//! session's opener and applied.
//!
//! **Invariant:** only a datagram that opens under its session's keys (length, version,
//! kind, session, replay window, tag, body: see `myriad_protocol::Opener`) changes any
//! state — address, action, timers, replay window — and nothing is sent back to one
//! that does not.

use std::net::SocketAddr;
use std::time::Instant;

use myriad_core::{Action, World};
use myriad_protocol::{ClientMessage, Direction, ErrorClass, ServerInfo, ServerMessage, peek_header};

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
    /// Actions applied to the world.
    pub actions: u64,
    /// Sessions that asked to leave (authenticated `Disconnect`), in arrival order.
    pub leaving: Vec<u64>,
}

/// Receives what is queued and applies it; see the module docs.
pub(crate) fn receive(
    transport: &mut dyn Transport,
    sessions: &mut Sessions,
    world: &mut World,
    info: ServerInfo,
    now: Instant,
) -> InboundReport {
    let mut report = InboundReport::default();
    for _ in 0..MAX_BATCHES {
        let mut each =
            |from: SocketAddr, bytes: &mut [u8]| handle(sessions, world, info, &mut report, from, bytes, now);
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

fn handle(
    sessions: &mut Sessions,
    world: &mut World,
    info: ServerInfo,
    report: &mut InboundReport,
    from: SocketAddr,
    bytes: &mut [u8],
    now: Instant,
) {
    let Ok(header) = peek_header(bytes, Direction::ClientToServer) else {
        dropped("malformed");
        return;
    };
    let Some(p) = sessions.by_session_mut(header.session_id) else {
        dropped("unknown_session");
        return;
    };
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
    p.last_heard = now;
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
            Some(ServerMessage::ServerInfo(info))
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
