//! The TLS login service.
//!
//! # How it works
//!
//! A tokio task accepts TCP connections and runs each on its own task: TLS 1.3
//! handshake, one bounded [`LoginRequest`](myriad_protocol::login::LoginRequest) frame, a rate-limit check, then the password
//! check against the store, then the join through the tick loop, which creates the
//! session keys and the player's object; the response goes back over TLS, followed by
//! the map data when asked.
//!
//! # What a login may cost (issue 14)
//!
//! Every step is bounded, and the cheap checks come before the dear ones:
//!
//! 1. **Connections**: at most `login_connections_per_addr` in flight per client
//!    address (an IPv6 client is keyed by its /64) and 4,096 in all; beyond either the
//!    connection is closed at once, before any TLS work. One address can therefore never
//!    hold the global cap and lock out everyone else.
//! 2. **Handshake and request** within `login_handshake_timeout_ms`, so an idle or slow
//!    connection is gone quickly; the whole exchange within 15 s.
//! 3. **Failed-login limits** ([`RateLimiter`]), checked before any hashing: per
//!    (account, address) with exponential backoff, and per address. Nothing is counted
//!    per account alone, so a stranger can never lock the owner out.
//! 4. **Unknown users** are refused without hashing, after a pause as long as a typical
//!    verification, so the answer's timing still does not tell them apart.
//! 5. **Password checks** run on the store's verification pool (`hashing_threads()`
//!    threads, the cores less one for the tick by default), behind `HashGate`: at most
//!    that many at once, at most `login_queue` waiting, each for at most
//!    `login_queue_deadline_ms`; beyond that the answer is "busy, retry" (with a
//!    retry hint) at once. The queue serves addresses with fewer recent failures first,
//!    so a storm of wrong passwords cannot crowd out a client whose address has none,
//!    and at most `ACCOUNT_CHECKS_IN_FLIGHT` (2) checks of one account are in flight (a
//!    storm on one account is refused before hashing beyond that).
//!
//! Passwords never reach a log: `LoginRequest`'s `Debug` hides them and only the
//! username and address are logged.
//!
//! # Where it lives
//!
//! - `service.rs`: `LoginService`, the accept loop and one login's exchange;
//! - `limits.rs`: [`RateLimiter`] (failed-login limits) and the in-flight counts (per
//!   address connections, per account password checks);
//! - `hash_gate.rs`: `HashGate`, admission to the password-hashing pool.

mod hash_gate;
mod limits;
mod service;

pub use limits::{RateLimiter, limit_key};
pub(crate) use service::{LoginService, ServedMap};
