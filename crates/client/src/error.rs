//! Error type of the client library.

use myriad_protocol::login::RefusalReason;

/// Why a client operation failed. Transport failures, refusals by the server and
/// protocol violations by the server are separate variants.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// A socket or TLS stream failed.
    #[error("{what}: {source}")]
    Io {
        /// What was being done.
        what: &'static str,
        /// The error.
        #[source]
        source: std::io::Error,
    },
    /// The trust configuration (certificate file) is unusable.
    #[error("tls setup: {0}")]
    Tls(String),
    /// The server refused the login.
    #[error("login refused: {reason}")]
    Refused {
        /// Why.
        reason: RefusalReason,
        /// When to retry, if the server said.
        retry_after_ms: u32,
    },
    /// The server sent something that does not follow the protocol.
    #[error("protocol violation by the server: {0}")]
    Protocol(String),
    /// Nothing arrived in time.
    #[error("timed out: {0}")]
    Timeout(&'static str),
    /// Bad arguments (a username too long, ...).
    #[error("invalid input: {0}")]
    Invalid(String),
}

impl ClientError {
    pub(crate) fn io(what: &'static str) -> impl FnOnce(std::io::Error) -> ClientError {
        move |source| ClientError::Io { what, source }
    }

    /// Whether trying again later may succeed (rate limit, server full, database down, busy,
    /// network trouble).
    pub fn is_retryable(&self) -> bool {
        match self {
            ClientError::Refused { reason, .. } => {
                matches!(
                    reason,
                    RefusalReason::RateLimited
                        | RefusalReason::ServerFull
                        | RefusalReason::Unavailable
                        | RefusalReason::Busy
                )
            }
            ClientError::Io { .. } | ClientError::Timeout(_) => true,
            _ => false,
        }
    }
}
