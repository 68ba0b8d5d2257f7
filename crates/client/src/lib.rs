//! Client library of Myriad: log in over TLS, hold the sealed UDP session, mirror the
//! world around the player, count what arrives — and a bot swarm built on all of it.
//!
//! - [`tls`]: [`Trust`]: pin the server's development certificate or trust CA roots.
//! - [`connection`]: [`login`] and [`Connection`]: actions, keep-alives, receiving
//!   updates into the [`WorldMirror`], reconnecting with a fresh login.
//! - [`liveness`]: what a session resends (Ready, keep-alive probes, Disconnect copies)
//!   and when it is declared silent.
//! - [`relay`]: a seeded, lossy UDP relay on loopback (tests and `myriad relay`).
//! - [`mirror`]: [`WorldMirror`], objects by id with the newest state (per-object tick
//!   rule of docs/protocol.md §5.5) and stale marking.
//! - [`stats`]: [`ClientStats`] (updates, bytes, last tick, loss from sequence gaps).
//! - [`swarm`]: many bots on one tokio runtime, each with its own socket.
//! - [`flood`]: bounded, loopback-only attack traffic (the server's abuse tests and
//!   `myriad flood`).
//!
//! ```no_run
//! # async fn demo() -> Result<(), myriad_client::ClientError> {
//! use myriad_client::*;
//! let trust = Trust::pin_file(std::path::Path::new("data/tls-cert.pem"))?;
//! let config = ClientConfig::new("127.0.0.1:7778".parse().unwrap(), &trust)?;
//! let mut c = Connection::connect(config, Credentials::test_user(0)).await?;
//! c.send_action(myriad_protocol::ActionMask::FORWARD).await?;
//! while let Some(event) = c.recv(std::time::Duration::from_millis(100)).await? {
//!     println!("{event:?}, me at {:?}", c.own_position());
//! }
//! # Ok(()) }
//! ```

pub mod connection;
pub mod error;
pub mod flood;
pub mod liveness;
pub mod mirror;
pub mod relay;
pub mod stats;
pub mod swarm;
pub mod tls;

pub use connection::{ClientConfig, Connection, Credentials, Event, SessionEnd, login, server_socket};
pub use error::ClientError;
pub use mirror::{MirrorObject, WorldMirror};
pub use stats::{ClientStats, Rates};
pub use swarm::{Behaviour, Swarm, SwarmConfig, SwarmSnapshot, movement_ok_share};

pub use tls::Trust;
