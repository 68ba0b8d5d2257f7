//! Errors of the physics backends.

/// What can go wrong in a backend.
#[derive(Debug, thiserror::Error)]
pub enum PhysicsError {
    /// The world holds more objects than a backend can index.
    #[error("{count} objects is more than this backend can hold ({max})")]
    TooManyObjects {
        /// Objects in the world.
        count: usize,
        /// The backend's limit.
        max: usize,
    },
    /// The backend cannot run on this machine or build.
    #[error("backend {backend} is unavailable: {reason}")]
    Unavailable {
        /// The backend's name.
        backend: &'static str,
        /// Why (no driver, not compiled in, ...).
        reason: String,
    },
    /// A backend name that is not known.
    #[error("unknown backend {0:?} (known: {known})", known = crate::BackendKind::NAMES.join(", "))]
    UnknownBackend(String),
    /// A device error (GPU backends).
    #[error("device error in {stage}: {message}")]
    Device {
        /// The stage that failed.
        stage: &'static str,
        /// The driver's message.
        message: String,
    },
}
