//! The receive gate: what a datagram must pass **before any cryptography** to reach its
//! session's tag check.
//!
//! Every datagram that names a live session costs a Poly1305 check, and the session id
//! travels in clear, so anyone can make the server pay for one with a single datagram.
//! The [`Gate`] bounds that work:
//!
//! - a datagram too long, too short or with a wrong header is dropped (`oversized`,
//!   `malformed`), and one naming no live session too (`unknown_session`);
//! - per session and per tick, at most [`ReceiveLimits::per_session`] datagrams from the
//!   session's own address pass, and at most [`ReceiveLimits::other_address`] from any
//!   other address (address migration, or the first datagram before the address is
//!   known). The two budgets are separate so that a stranger flooding a player's session
//!   id from elsewhere cannot crowd out the player's own datagrams. Excess is dropped
//!   and counted (`myriad_packets_dropped_total{reason="over_budget"|"other_address"}`).
//!
//! The gate is not session state a client relies on: passing it changes nothing but the
//! budget, and a datagram that passes may still fail its tag check. So it can run where
//! the sessions are not: on the receiver thread ([`crate::receiver`]), against the
//! [`SessionDirectory`] the tick publishes, or inline in the tick against the session table
//! itself (the in-memory transport of the tests).

use std::net::SocketAddr;
use std::time::Duration;

use myriad_protocol::{Direction, MAX_DATAGRAM, peek_header};

/// How much receive work one tick may do; see the module docs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReceiveLimits {
    /// Datagrams per session per tick from the session's own address that may reach
    /// the tag check.
    pub per_session: u16,
    /// Datagrams per session per tick from any other address that may reach the tag
    /// check.
    pub other_address: u16,
    /// Longest a tick's inline receive may run; checked between batches. (A receiver
    /// thread needs none: it never holds the tick up.)
    pub time: Duration,
}

/// One session's receive budget in the current tick.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
struct ReceiveBudget {
    tick: u64,
    own: u16,
    other: u16,
}

impl ReceiveBudget {
    /// Spends one datagram of tick `tick`'s budget (from the session's own address or
    /// another); false when that budget is spent.
    fn take(&mut self, tick: u64, own_address: bool, limits: &ReceiveLimits) -> bool {
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

/// Where a gate looks a session up.
pub trait SessionAddresses {
    /// `None` when no live session has this id; else the address its last
    /// authenticated datagram came from (`Some(None)` before the first).
    fn address_of(&self, session_id: u64) -> Option<Option<SocketAddr>>;
}

/// The live sessions as the receiver thread sees them: id and known address, a copy of
/// the session table's directory. The tick publishes a new one whenever a session
/// joins, leaves or moves.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct SessionDirectory {
    addresses: foldhash::HashMap<u64, Option<SocketAddr>>,
}

impl SessionDirectory {
    /// A directory of these sessions (session id, address).
    pub fn new(addresses: impl IntoIterator<Item = (u64, Option<SocketAddr>)>) -> Self {
        SessionDirectory { addresses: addresses.into_iter().collect() }
    }
}

impl SessionAddresses for SessionDirectory {
    fn address_of(&self, session_id: u64) -> Option<Option<SocketAddr>> {
        self.addresses.get(&session_id).copied()
    }
}

/// Why the gate dropped a datagram: the `reason` label of
/// `myriad_packets_dropped_total`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refusal {
    /// Longer than the protocol's datagram limit.
    Oversized,
    /// Not a client-to-server header.
    Malformed,
    /// No live session has its id.
    UnknownSession,
    /// Its session's own-address budget for this tick is spent.
    OverBudget,
    /// Its session's other-address budget for this tick is spent.
    OtherAddress,
}

impl Refusal {
    /// The metric label.
    pub fn reason(self) -> &'static str {
        match self {
            Refusal::Oversized => "oversized",
            Refusal::Malformed => "malformed",
            Refusal::UnknownSession => "unknown_session",
            Refusal::OverBudget => "over_budget",
            Refusal::OtherAddress => "other_address",
        }
    }

    /// Whether this is a budget refusal (the tick reports those apart).
    pub fn over_budget(self) -> bool {
        matches!(self, Refusal::OverBudget | Refusal::OtherAddress)
    }

    /// Counts it in `myriad_packets_dropped_total`.
    pub fn count(self) {
        self.count_many(1);
    }

    /// Counts `n` of them in `myriad_packets_dropped_total`.
    pub fn count_many(self, n: u64) {
        metrics::counter!("myriad_packets_dropped_total", "reason" => self.reason()).increment(n);
    }
}

/// Ticks between sweeps of budgets of sessions gone quiet (so the table stays the size
/// of the sessions that spoke recently).
const SWEEP_EVERY: u64 = 64;

/// The budgets of every session; see the module docs. One gate per place datagrams
/// are received (the receiver thread, or the tick inline), never both for one socket.
#[derive(Debug)]
pub struct Gate {
    limits: ReceiveLimits,
    budgets: foldhash::HashMap<u64, ReceiveBudget>,
    swept: u64,
}

impl Gate {
    /// A gate with these limits and no budget spent.
    pub fn new(limits: ReceiveLimits) -> Self {
        Gate { limits, budgets: foldhash::HashMap::default(), swept: 0 }
    }

    /// The limits.
    pub fn limits(&self) -> &ReceiveLimits {
        &self.limits
    }

    /// Admits or refuses one datagram of tick `tick` from `from`; on admission returns
    /// its session id. Costs a header check and two table lookups, never cryptography.
    pub fn admit(
        &mut self,
        sessions: &dyn SessionAddresses,
        tick: u64,
        from: SocketAddr,
        bytes: &[u8],
    ) -> Result<u64, Refusal> {
        let header = match peek_header(bytes, Direction::ClientToServer) {
            Ok(h) => h,
            Err(_) if bytes.len() > MAX_DATAGRAM => return Err(Refusal::Oversized),
            Err(_) => return Err(Refusal::Malformed),
        };
        let session_id = header.session_id;
        let address = sessions.address_of(session_id).ok_or(Refusal::UnknownSession)?;
        if tick >= self.swept + SWEEP_EVERY {
            // A session that sent nothing for a sweep has no budget worth keeping.
            self.budgets.retain(|_, b| b.tick + SWEEP_EVERY > tick);
            self.swept = tick;
        }
        let own_address = address == Some(from);
        if self.budgets.entry(session_id).or_default().take(tick, own_address, &self.limits) {
            Ok(session_id)
        } else if own_address {
            Err(Refusal::OverBudget)
        } else {
            Err(Refusal::OtherAddress)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    fn limits() -> ReceiveLimits {
        ReceiveLimits { per_session: 3, other_address: 1, time: Duration::from_millis(5) }
    }

    /// A well-formed client header for `session` (the tag is not checked here).
    fn datagram(session: u64) -> Vec<u8> {
        let keys =
            myriad_protocol::SessionKeys { session_id: session, client_to_server: [7; 32], server_to_client: [8; 32] };
        let mut client = myriad_protocol::ClientSession::new(&keys);
        let mut out = Vec::new();
        client.sealer.seal_client_message(&myriad_protocol::ClientMessage::KeepAlive { acks: None }, &mut out).unwrap();
        out
    }

    #[test]
    fn budgets_are_per_session_per_tick_and_per_address_class() {
        let own: SocketAddr = "127.0.0.1:1000".parse().unwrap();
        let stranger: SocketAddr = "127.0.0.9:9".parse().unwrap();
        let directory = SessionDirectory::new(HashMap::from([(5, Some(own)), (6, None)]));
        let mut gate = Gate::new(limits());
        let d5 = datagram(5);
        // A stranger's flood spends only the other-address budget...
        assert_eq!(gate.admit(&directory, 1, stranger, &d5), Ok(5));
        for _ in 0..100 {
            assert_eq!(gate.admit(&directory, 1, stranger, &d5), Err(Refusal::OtherAddress));
        }
        // ...so the owner still gets its own three.
        for _ in 0..3 {
            assert_eq!(gate.admit(&directory, 1, own, &d5), Ok(5));
        }
        assert_eq!(gate.admit(&directory, 1, own, &d5), Err(Refusal::OverBudget));
        // Another session has its own budget; before its address is known every
        // datagram is "other".
        let d6 = datagram(6);
        assert_eq!(gate.admit(&directory, 1, own, &d6), Ok(6));
        assert_eq!(gate.admit(&directory, 1, own, &d6), Err(Refusal::OtherAddress));
        // The next tick starts afresh.
        assert_eq!(gate.admit(&directory, 2, own, &d5), Ok(5));
        assert_eq!(gate.admit(&directory, 2, stranger, &d5), Ok(5));
    }

    #[test]
    fn bad_headers_and_unknown_sessions_are_refused_before_any_budget() {
        let own: SocketAddr = "127.0.0.1:1000".parse().unwrap();
        let directory = SessionDirectory::new(HashMap::from([(5, Some(own))]));
        let mut gate = Gate::new(limits());
        assert_eq!(gate.admit(&directory, 1, own, &[0u8; 3]), Err(Refusal::Malformed));
        assert_eq!(gate.admit(&directory, 1, own, &vec![0u8; MAX_DATAGRAM + 1]), Err(Refusal::Oversized));
        assert_eq!(gate.admit(&directory, 1, own, &datagram(77)), Err(Refusal::UnknownSession));
        // None of that spent session 5's budget.
        for _ in 0..3 {
            assert_eq!(gate.admit(&directory, 1, own, &datagram(5)), Ok(5));
        }
        assert_eq!(Refusal::OtherAddress.reason(), "other_address");
        assert!(Refusal::OverBudget.over_budget() && !Refusal::UnknownSession.over_budget());
    }

    #[test]
    fn budgets_of_quiet_sessions_are_swept() {
        let own: SocketAddr = "127.0.0.1:1000".parse().unwrap();
        let sessions: HashMap<u64, Option<SocketAddr>> = (1..=100).map(|s| (s, Some(own))).collect();
        let directory = SessionDirectory::new(sessions);
        let mut gate = Gate::new(limits());
        for s in 1..=100 {
            gate.admit(&directory, 1, own, &datagram(s)).unwrap();
        }
        assert_eq!(gate.budgets.len(), 100);
        gate.admit(&directory, 1 + 2 * SWEEP_EVERY, own, &datagram(1)).unwrap();
        assert_eq!(gate.budgets.len(), 1, "only the session that spoke lately keeps a budget");
    }
}
