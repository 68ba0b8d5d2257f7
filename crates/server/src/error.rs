//! Error types of the server library.

use std::path::PathBuf;

/// A configuration that cannot be used; every variant names the key or file at fault.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("cannot read config file {path}: {reason}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        reason: String,
    },
    /// The file is not valid TOML or does not match the keys (toml names the key).
    #[error("config file {path}: {reason}")]
    File {
        /// The file.
        path: PathBuf,
        /// toml's message, with the key and line.
        reason: String,
    },
    /// A TOML document does not match the keys.
    #[error("config: {0}")]
    Parse(String),
    /// A key that does not exist.
    #[error("unknown config key `{0}`")]
    UnknownKey(String),
    /// A key with a bad value.
    #[error("config key `{key}`: {reason}")]
    Value {
        /// The key.
        key: String,
        /// What is wrong.
        reason: String,
    },
}

/// Why the server could not start or stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    /// Bad configuration.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The database failed.
    #[error("store: {0}")]
    Store(#[from] myriad_store::StoreError),
    /// The store opened but refused the start-up write (read-only file, full disk, no
    /// write grant): the server does not start rather than drop every position.
    #[error("store cannot write (checked at start-up with a real write): {0}")]
    NotWritable(#[source] myriad_store::StoreError),
    /// Shutdown could not save every position before its deadline.
    #[error("shutdown: {0}")]
    PositionsLost(#[source] myriad_store::ShutdownLoss),
    /// Building the world failed.
    #[error("world: {0}")]
    World(#[from] myriad_core::CoreError),
    /// The physics backend failed.
    #[error("physics: {0}")]
    Physics(#[from] myriad_physics::PhysicsError),
    /// A socket could not be opened.
    #[error("network: {0}")]
    Net(#[from] myriad_net::NetError),
    /// TLS setup failed (certificate, key).
    #[error("tls: {0}")]
    Tls(String),
    /// Other I/O.
    #[error("{what}: {source}")]
    Io {
        /// What was being done.
        what: String,
        /// The error.
        #[source]
        source: std::io::Error,
    },
    /// Metrics exporter.
    #[error("metrics: {0}")]
    Metrics(String),
    /// A thread or task died.
    #[error("internal: {0}")]
    Internal(String),
}

impl ServerError {
    pub(crate) fn io(what: impl Into<String>, source: std::io::Error) -> Self {
        ServerError::Io { what: what.into(), source }
    }
}
