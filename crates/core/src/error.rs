//! Errors of the world model.

use std::path::PathBuf;

/// What can go wrong while building or loading a world.
#[derive(Debug, thiserror::Error)]
pub enum CoreError {
    /// A heightmap file could not be read.
    #[error("cannot read heightmap {path}: {source}")]
    HeightmapIo {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// A heightmap PNG could not be decoded or is not 16-bit grayscale.
    #[error("heightmap {path} is not a usable PNG: {reason}")]
    HeightmapPng {
        /// The file.
        path: PathBuf,
        /// What is wrong with it.
        reason: String,
    },
    /// A raw heightmap has a size that does not match any square or the given shape.
    #[error("raw heightmap {path} has {bytes} bytes, which is not {expected}")]
    HeightmapRawSize {
        /// The file.
        path: PathBuf,
        /// Its size.
        bytes: u64,
        /// What was expected.
        expected: String,
    },
    /// A parameter is out of range (the message names it).
    #[error("invalid {what}: {reason}")]
    Invalid {
        /// The parameter.
        what: &'static str,
        /// Why it is rejected.
        reason: String,
    },
}

impl CoreError {
    /// Shorthand for [`CoreError::Invalid`].
    pub fn invalid(what: &'static str, reason: impl Into<String>) -> CoreError {
        CoreError::Invalid { what, reason: reason.into() }
    }
}
