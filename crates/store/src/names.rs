//! The one rule for user names, enforced here for every path that takes one: creating an
//! account (`myriad user add`, `seed`), changing a password and every login (through
//! [`Store::check_credentials`](crate::Store::check_credentials)).
//!
//! # The rule
//! A user name is 1 to [`MAX_USERNAME_LEN`] bytes of ASCII letters, digits, `_`, `-` and
//! `.`, that
//! - starts and ends with a letter or a digit (so no `.`, `..`, `-x` or `x.`),
//! - has no two punctuation characters in a row (no `..`, `._`, `--`).
//!
//! ASCII only means no control characters, no invisible or zero-width characters, no
//! look-alike letters from other scripts and no trailing spaces: every name displays as
//! itself, is safe in a file name or a log line, and compares the same on both backends
//! (SQLite's `COLLATE NOCASE` folds ASCII case, MariaDB's `utf8mb4_unicode_ci` would also
//! fold accents). Names compare case-insensitively.

use crate::error::{Result, StoreError};
use crate::password;

pub use crate::password::MAX_USERNAME_LEN;

/// Checks `username` against the one rule for user names; the error says which part
/// failed.
///
/// A user name is 1 to [`MAX_USERNAME_LEN`] bytes of ASCII letters, digits, `_`, `-` and
/// `.`, starting and ending with a letter or a digit, with no two of `_`, `-`, `.` in a
/// row (so no `.`, `..` or `a..b`). Being ASCII, it has no control, invisible or
/// look-alike characters. Names compare case-insensitively.
pub fn validate_username(username: &str) -> Result<()> {
    // Length and the character set (shared with the hashing code's own check).
    password::validate_username(username)?;
    let bad = |why: &str| Err(StoreError::InvalidInput(format!("username {username:?}: {why}")));
    let bytes = username.as_bytes();
    let punct = |b: u8| !b.is_ascii_alphanumeric();
    if punct(bytes[0]) || punct(bytes[bytes.len() - 1]) {
        return bad("must start and end with a letter or a digit");
    }
    if bytes.windows(2).any(|w| punct(w[0]) && punct(w[1])) {
        return bad("no two of '.', '_', '-' in a row (no \"..\")");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_follow_the_rule() {
        for ok in ["a", "user0", "Alice", "bob.smith", "x_y-z", "a.b.c", "9lives", &"a".repeat(32)] {
            assert!(validate_username(ok).is_ok(), "{ok:?}");
        }
        let bad = [
            "",
            ".",
            "..",
            "...",
            ".hidden",
            "trailing.",
            "a..b",
            "a._b",
            "-x",
            "x_",
            "a b",
            "tab\tx",
            "nul\0x",
            "zero\u{200b}width",
            "bidi\u{202e}x",
            "caf\u{e9}",
            "\u{430}dmin",
            "a/b",
            "a\\b",
            &"a".repeat(33),
        ];
        for b in bad {
            assert!(matches!(validate_username(b), Err(StoreError::InvalidInput(_))), "{b:?}");
        }
    }
}
