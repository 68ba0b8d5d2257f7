//! Sessions shared by several servers: the gateways of one zoned world.
//!
//! Within one server a second login of an account replaces the first session (the
//! sessions table, `session.rs`). Across servers the [`SessionRegistry`] does it: the
//! tick claims every session it admits, and ends as `Replaced` the sessions whose
//! accounts another server claimed since. `myriad_zone::claims` implements it over NATS.

/// A cluster-wide record of which server holds each account's session.
pub trait SessionRegistry: Send {
    /// A session of `username` was admitted here: claim the account.
    fn claim(&mut self, username: &str);
    /// Accounts whose sessions here another server has claimed since (a newer login
    /// there). Never blocks.
    fn taken(&mut self) -> Vec<String>;
}
