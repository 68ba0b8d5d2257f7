//! Argon2id password hashing, always off the async threads.
//!
//! Hashes are PHC strings (`$argon2id$v=19$m=...,t=...,p=...$salt$hash`): the cost is
//! stored with each hash, so raising [`HashCost`] later only affects new hashes and old
//! ones still verify. Hashing takes tens to hundreds of milliseconds by design, so every
//! call goes through [`tokio::task::spawn_blocking`] and never stalls a runtime worker
//! (or the server's tick thread).

use argon2::{Algorithm, Argon2, Params, PasswordHasher, PasswordVerifier, Version};

use crate::error::{Result, StoreError};

/// Longest accepted username in bytes (the login packet's username field is 32 bytes).
pub const MAX_USERNAME_LEN: usize = 32;
/// Longest accepted password in bytes (the login packet's password field is 64 bytes).
pub const MAX_PASSWORD_LEN: usize = 64;

/// Argon2id cost parameters used for new hashes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HashCost {
    /// Memory in KiB (at least `8 * p`).
    pub m_kib: u32,
    /// Number of passes.
    pub t: u32,
    /// Degree of parallelism (lanes).
    pub p: u32,
}

impl HashCost {
    /// The OWASP-recommended Argon2id minimum (19 MiB, 2 passes, 1 lane), also argon2's
    /// default: about 20-40 ms per hash or verification in a release build on one core
    /// (measured: see the crate README).
    pub const DEFAULT: HashCost = HashCost { m_kib: 19 * 1024, t: 2, p: 1 };

    /// A cheap cost for tests and benchmarks of everything but hashing. Never use it for
    /// real accounts: it offers almost no resistance to offline guessing.
    pub const INSECURE_FAST: HashCost = HashCost { m_kib: 64, t: 1, p: 1 };

    fn hasher(self) -> Result<Argon2<'static>> {
        let params = Params::new(self.m_kib, self.t, self.p, None)
            .map_err(|e| StoreError::InvalidInput(format!("argon2 cost {self:?}: {e}")))?;
        Ok(Argon2::new(Algorithm::Argon2id, Version::V0x13, params))
    }

    /// Checks that argon2 accepts these parameters.
    pub fn validate(self) -> Result<()> {
        self.hasher().map(|_| ())
    }
}

impl Default for HashCost {
    fn default() -> Self {
        HashCost::DEFAULT
    }
}

/// Rejects usernames the login packet cannot carry or that would compare differently on
/// the two backends: 1 to 32 bytes of ASCII letters, digits, `_`, `-` and `.`.
///
/// Restricting to ASCII keeps uniqueness identical on SQLite (`COLLATE NOCASE`, ASCII
/// case folding) and MariaDB (`utf8mb4_unicode_ci`, which would also fold accents and
/// ignore trailing spaces).
pub fn validate_username(username: &str) -> Result<()> {
    if username.is_empty() || username.len() > MAX_USERNAME_LEN {
        return Err(StoreError::InvalidInput(format!("username must be 1 to {MAX_USERNAME_LEN} bytes")));
    }
    if !username.bytes().all(|b| b.is_ascii_alphanumeric() || matches!(b, b'_' | b'-' | b'.')) {
        return Err(StoreError::InvalidInput(
            "username may only contain ASCII letters, digits, '_', '-' and '.'".into(),
        ));
    }
    Ok(())
}

/// Rejects empty passwords and passwords longer than the login packet's 64 bytes.
pub fn validate_password(password: &str) -> Result<()> {
    if password.is_empty() || password.len() > MAX_PASSWORD_LEN {
        return Err(StoreError::InvalidInput(format!("password must be 1 to {MAX_PASSWORD_LEN} bytes")));
    }
    Ok(())
}

/// Hashes synchronously; call only from a blocking context.
pub(crate) fn hash_blocking(cost: HashCost, password: &[u8]) -> Result<String> {
    let hash = cost
        .hasher()?
        .hash_password(password)
        .map_err(|e| StoreError::Internal(format!("argon2 hashing failed: {e}")))?;
    Ok(hash.to_string())
}

/// Verifies synchronously; call only from a blocking context. A malformed stored hash
/// counts as a mismatch (and is logged without its content).
pub(crate) fn verify_blocking(password: &[u8], phc: &str) -> bool {
    // The parameters come from the PHC string itself, not from the configured cost.
    match Argon2::default().verify_password(password, phc) {
        Ok(()) => true,
        Err(argon2::password_hash::Error::PasswordInvalid) => false,
        Err(e) => {
            tracing::warn!(error = %e, "stored password hash could not be verified");
            false
        }
    }
}

/// Hashes `password` with `cost` on the blocking pool.
pub async fn hash_password(cost: HashCost, password: &str) -> Result<String> {
    let password = password.as_bytes().to_vec();
    spawn_blocking(move || hash_blocking(cost, &password)).await?
}

/// Verifies `password` against a PHC string on the blocking pool.
pub async fn verify_password(password: &str, phc: String) -> Result<bool> {
    let password = password.as_bytes().to_vec();
    spawn_blocking(move || verify_blocking(&password, &phc)).await
}

/// Runs `f` on the blocking pool and turns a panic or cancellation into an error.
pub(crate) async fn spawn_blocking<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> Result<T> {
    tokio::task::spawn_blocking(f).await.map_err(|e| StoreError::Internal(format!("blocking task failed: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn usernames_are_checked() {
        for ok in ["a", "user0", "A.b-c_d", &"x".repeat(MAX_USERNAME_LEN)] {
            assert!(validate_username(ok).is_ok(), "{ok:?}");
        }
        for bad in ["", " ", "a b", "é", "a\0", "a'b", &"x".repeat(MAX_USERNAME_LEN + 1)] {
            assert!(matches!(validate_username(bad), Err(StoreError::InvalidInput(_))), "{bad:?}");
        }
    }

    #[test]
    fn passwords_are_checked_by_bytes() {
        assert!(validate_password("x").is_ok());
        assert!(validate_password(&"p".repeat(MAX_PASSWORD_LEN)).is_ok());
        assert!(validate_password("").is_err());
        // 33 two-byte characters are 66 bytes: over the packet's 64.
        assert!(validate_password(&"é".repeat(33)).is_err());
    }

    #[test]
    fn hashes_are_argon2id_phc_strings_that_verify() {
        let hash = hash_blocking(HashCost::INSECURE_FAST, "pässword".as_bytes()).unwrap();
        assert!(hash.starts_with("$argon2id$v=19$m=64,t=1,p=1$"), "{hash}");
        assert!(verify_blocking("pässword".as_bytes(), &hash));
        assert!(!verify_blocking(b"password", &hash));
        // Salted: the same password hashes differently.
        let again = hash_blocking(HashCost::INSECURE_FAST, "pässword".as_bytes()).unwrap();
        assert_ne!(hash, again);
        // A malformed stored hash is a mismatch, not a panic.
        assert!(!verify_blocking(b"x", "not a hash"));
        assert!(!verify_blocking(b"x", ""));
    }

    #[test]
    fn bad_costs_are_rejected() {
        assert!(HashCost::DEFAULT.validate().is_ok());
        assert!(HashCost::INSECURE_FAST.validate().is_ok());
        let too_little_memory = HashCost { m_kib: 1, t: 1, p: 1 };
        assert!(matches!(too_little_memory.validate(), Err(StoreError::InvalidInput(_))));
        assert!(HashCost { m_kib: 64, t: 0, p: 1 }.validate().is_err());
        assert!(HashCost { m_kib: 64, t: 1, p: 0 }.validate().is_err());
    }
}
