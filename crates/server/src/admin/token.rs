//! The admin API's bearer token: generated into `<data_dir>/admin.token` at the first
//! start (32 random bytes as 64 hex characters, mode 0600), or read from
//! `admin_token_file`. Compared in constant time, as SHA-256 digests, so neither the
//! comparison's time nor the lengths tell an attacker how much of a guess was right.

use std::io::Write;
use std::path::{Path, PathBuf};

use ring::digest::{SHA256, digest};
use ring::rand::{SecureRandom, SystemRandom};
use subtle::ConstantTimeEq;

use crate::config::ServerConfig;
use crate::error::ServerError;

/// The generated token's file name in the data directory.
pub const TOKEN_FILE_NAME: &str = "admin.token";

/// Shortest token accepted from `admin_token_file` (a generated one has 64 characters).
const MIN_TOKEN_LEN: usize = 32;
/// Longest token accepted.
const MAX_TOKEN_LEN: usize = 512;

/// The token file a server with `config` uses: `admin_token_file`, or the generated one
/// in the data directory.
pub fn token_path(config: &ServerConfig) -> PathBuf {
    if config.admin_token_file.as_os_str().is_empty() {
        config.data_dir.join(TOKEN_FILE_NAME)
    } else {
        config.admin_token_file.clone()
    }
}

/// The token, kept only as its digest (the text itself is in the file, not in memory
/// any longer than reading it takes).
#[derive(Clone)]
pub(crate) struct Token {
    digest: [u8; 32],
}

impl std::fmt::Debug for Token {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Token(..)")
    }
}

fn sha256(bytes: &[u8]) -> [u8; 32] {
    let mut out = [0u8; 32];
    out.copy_from_slice(digest(&SHA256, bytes).as_ref());
    out
}

impl Token {
    /// Whether `presented` is the token, in constant time.
    pub fn matches(&self, presented: &str) -> bool {
        bool::from(sha256(presented.as_bytes()).ct_eq(&self.digest))
    }

    /// Reads the token of `config` ([`token_path`]), generating it first when it is the
    /// data directory's and does not exist yet.
    pub fn load_or_create(config: &ServerConfig) -> Result<(Token, PathBuf), ServerError> {
        let path = token_path(config);
        let generated = config.admin_token_file.as_os_str().is_empty();
        if generated && !path.exists() {
            create(&path)?;
        }
        let text = read_private(&path)?;
        Ok((Token { digest: sha256(text.as_bytes()) }, path))
    }
}

/// Writes a fresh token to `path`, created with mode 0600 (never readable by others,
/// not even for an instant).
fn create(path: &Path) -> Result<(), ServerError> {
    let mut bytes = [0u8; 32];
    SystemRandom::new().fill(&mut bytes).map_err(|_| ServerError::Internal("no system randomness".into()))?;
    let hex: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create_new(true);
    #[cfg(unix)]
    std::os::unix::fs::OpenOptionsExt::mode(&mut options, 0o600);
    let mut file =
        options.open(path).map_err(|e| ServerError::io(format!("creating the admin token {}", path.display()), e))?;
    file.write_all(format!("{hex}\n").as_bytes())
        .and_then(|()| file.sync_all())
        .map_err(|e| ServerError::io(format!("writing the admin token {}", path.display()), e))?;
    tracing::info!(path = %path.display(), "admin token generated");
    Ok(())
}

/// Reads a token file: refused when others than its owner may read it, or when its
/// token is too short, too long or holds spaces or control characters.
fn read_private(path: &Path) -> Result<String, ServerError> {
    let bad =
        |why: String| ServerError::Config(crate::ConfigError::Value { key: "admin_token_file".into(), reason: why });
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let meta = std::fs::metadata(path)
            .map_err(|e| ServerError::io(format!("reading the admin token {}", path.display()), e))?;
        if meta.permissions().mode() & 0o077 != 0 {
            return Err(bad(format!(
                "{} may be read by others than its owner (mode {:o}); chmod 600 it",
                path.display(),
                meta.permissions().mode() & 0o777
            )));
        }
    }
    let text = std::fs::read_to_string(path)
        .map_err(|e| ServerError::io(format!("reading the admin token {}", path.display()), e))?;
    let token = text.trim();
    if !(MIN_TOKEN_LEN..=MAX_TOKEN_LEN).contains(&token.len()) {
        return Err(bad(format!(
            "the token in {} is {} bytes; {MIN_TOKEN_LEN} to {MAX_TOKEN_LEN} are accepted",
            path.display(),
            token.len()
        )));
    }
    if token.chars().any(|c| c.is_whitespace() || c.is_control() || !c.is_ascii()) {
        return Err(bad(format!("the token in {} must be printable ASCII without spaces", path.display())));
    }
    Ok(token.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_generated_token_is_private_and_matches_only_itself() {
        let dir = tempfile::tempdir().unwrap();
        let config = ServerConfig { data_dir: dir.path().to_path_buf(), ..ServerConfig::default() };
        let (token, path) = Token::load_or_create(&config).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        let text = text.trim();
        assert_eq!(text.len(), 64);
        assert!(text.chars().all(|c| c.is_ascii_hexdigit()));
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            assert_eq!(std::fs::metadata(&path).unwrap().permissions().mode() & 0o777, 0o600);
        }
        assert!(token.matches(text));
        assert!(!token.matches(&text[1..]));
        assert!(!token.matches(""));
        // A second start reads the same token.
        let (again, _) = Token::load_or_create(&config).unwrap();
        assert!(again.matches(text));
    }

    #[cfg(unix)]
    #[test]
    fn a_token_file_others_may_read_is_refused() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("t");
        std::fs::write(&file, "x".repeat(40)).unwrap();
        std::fs::set_permissions(&file, std::fs::Permissions::from_mode(0o644)).unwrap();
        let config = ServerConfig { admin_token_file: file.clone(), ..ServerConfig::default() };
        let err = Token::load_or_create(&config).unwrap_err().to_string();
        assert!(err.contains("chmod 600"), "{err}");
        std::fs::set_permissions(&file, std::fs::Permissions::from_mode(0o600)).unwrap();
        assert!(Token::load_or_create(&config).unwrap().0.matches(&"x".repeat(40)));
        std::fs::write(&file, "short").unwrap();
        assert!(Token::load_or_create(&config).unwrap_err().to_string().contains("5 bytes"));
    }
}
