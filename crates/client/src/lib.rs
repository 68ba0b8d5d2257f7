//! Client library of Myriad: log in over TLS, hold the sealed UDP session, mirror the
//! world around the player, count what arrives — and a bot swarm built on all of it.
//!
//! - [`tls`]: [`Trust`]: pin the server's development certificate or trust CA roots.
//! - [`connection`]: [`login`] and [`Connection`]: actions, keep-alives, receiving
//!   updates into the [`WorldMirror`], reconnecting with a fresh login.
//! - [`liveness`]: what a session resends (Ready, keep-alive probes, Disconnect copies)
//!   and when it is declared silent.
//! - [`relay`]: a seeded, lossy UDP relay on loopback (tests and `myriad relay`).
//! - [`mirror`]: [`WorldMirror`], objects by id with their newest states (per-object tick
//!   rule of docs/protocol.md §5.5), stale marking, and each object's position at a
//!   render time: interpolated with a render delay, extrapolated for a capped time.
//! - [`clock`]: [`ServerClock`], the estimate of the server's tick from the updates'
//!   ticks and arrival times, which the render time follows.
//! - [`quality`]: [`Quality`], staleness and error of what a player holds, near and over
//!   the whole area of interest (`myriad bench`, `myriad bots`).
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

pub mod clock;
pub mod connection;
pub mod error;
pub mod flood;
pub mod liveness;
pub mod mirror;
pub mod quality;
pub mod relay;
pub mod stats;
pub mod swarm;
pub mod tls;

pub use clock::ServerClock;
pub use connection::{ClientConfig, Connection, Credentials, Event, SessionEnd, login, server_socket};
pub use error::ClientError;
pub use mirror::{Interpolation, MirrorObject, RenderMode, Rendered, TickState, WorldMirror};
pub use quality::{Percentiles, Quality, QualitySummary};
pub use stats::{ClientStats, Rates};
pub use swarm::{Behaviour, Swarm, SwarmConfig, SwarmSnapshot, movement_ok_share};

pub use tls::Trust;
