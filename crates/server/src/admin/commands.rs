//! What the admin API asks of the tick: end a player's session. Sent on a bounded
//! channel that the tick drains at the start of each tick (before receiving), answered
//! on a oneshot channel; the tick never waits on the admin (a full channel is the
//! admin's problem: it answers 503).

use std::sync::Arc;

use myriad_core::World;
use myriad_protocol::DisconnectReason;
use myriad_store::PlayerState;
use tokio::sync::{mpsc, oneshot};

use super::AdminShared;
use super::snapshot::Publisher;
use crate::session::Sessions;

/// Commands that may wait for the tick at once; more are refused with 503.
pub(crate) const COMMAND_QUEUE: usize = 64;

/// A request to the tick.
#[derive(Debug)]
pub(crate) enum AdminCommand {
    /// End the session of `account` (if it is online here) with `reason`; answers
    /// whether there was one.
    End { account: String, reason: DisconnectReason, reply: oneshot::Sender<bool> },
}

/// The tick's side of the admin API: the commands to drain and the snapshots to take.
#[derive(Debug)]
pub(crate) struct TickAdmin {
    commands: mpsc::Receiver<AdminCommand>,
    publisher: Publisher,
    shared: Arc<AdminShared>,
}

impl TickAdmin {
    pub(crate) fn new(commands: mpsc::Receiver<AdminCommand>, shared: Arc<AdminShared>) -> Self {
        TickAdmin { commands, publisher: Publisher::new(shared.clone()), shared }
    }

    /// The admin's shared state (the tick records its backend there).
    pub(crate) fn shared(&self) -> &AdminShared {
        &self.shared
    }

    /// Carries out the waiting commands (at most [`COMMAND_QUEUE`] a tick); the final
    /// states of the players removed go to `left`, for the persister.
    pub(crate) fn drain(&mut self, sessions: &mut Sessions, world: &mut World, left: &mut Vec<PlayerState>) {
        for _ in 0..COMMAND_QUEUE {
            let Ok(command) = self.commands.try_recv() else { return };
            match command {
                AdminCommand::End { account, reason, reply } => {
                    let session = sessions.session_of(&account);
                    if let Some(session) = session {
                        tracing::info!(user = %account, ?reason, "session ended by an operator");
                        metrics::counter!("myriad_admin_sessions_ended_total").increment(1);
                        left.extend(sessions.remove(world, session, Some(reason)));
                    }
                    // The request may have timed out: nothing to undo.
                    let _ = reply.send(session.is_some());
                }
            }
        }
    }

    /// Publishes a snapshot if one is wanted and due (see [`Publisher`]); `backend`
    /// gives the zone cuts on a gateway.
    pub(crate) fn publish(&mut self, sessions: &mut Sessions, world: &World, backend: &dyn myriad_physics::Backend) {
        self.publisher.maybe_publish(sessions, world, backend);
    }
}
