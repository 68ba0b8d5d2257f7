//! The admin API's audit trail (issue 29): who did what to whom, when, from where, and
//! whether it was done. Appended by the server's admin API (migration 4), listed newest
//! first; never updated or deleted by Myriad.

use sqlx::Row;

use crate::error::Result;
use crate::store::Store;

/// Most entries one [`Store::list_audit`] call returns.
pub const MAX_AUDIT_LIST: u32 = 10_000;

/// Longest text of each column, in bytes (the MariaDB column sizes): longer text is cut
/// at a character boundary before it is written, so an entry is never refused for its
/// length (a refused request with a long junk path is still audited).
const ACTOR_LEN: usize = 64;
const ACTION_LEN: usize = 32;
const TARGET_LEN: usize = 255;
const DETAIL_LEN: usize = 1024;
const ORIGIN_LEN: usize = 64;

/// One line of the audit trail.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AuditEntry {
    /// When, milliseconds since the Unix epoch.
    pub at_ms: i64,
    /// Who: the name the client gave, or what it was refused as.
    pub actor: String,
    /// What: `kick`, `ban`, `unban`, `disable`, `enable`, `delete`, `password`, or a
    /// refusal (`refused`).
    pub action: String,
    /// On what: an account name, or the path of a refused request.
    pub target: String,
    /// Anything else: a reason, a ban's end, why a request was refused. Never a secret.
    pub detail: String,
    /// The client's address, `ip:port`.
    pub from: String,
    /// Whether the action was done (false: refused, or it failed).
    pub ok: bool,
}

/// `text` with control characters replaced by `�` (an entry is printed on operators'
/// terminals, where escape sequences would be obeyed, and its target may be any name a
/// client sent), cut to at most `max` bytes at a character boundary.
fn bounded(text: &str, max: usize) -> String {
    let mut out = String::with_capacity(text.len().min(max));
    for c in text.chars().map(|c| if c.is_control() { char::REPLACEMENT_CHARACTER } else { c }) {
        if out.len() + c.len_utf8() > max {
            break;
        }
        out.push(c);
    }
    out
}

impl Store {
    /// Appends `entry` to the audit trail (each text cut to its column's size).
    pub async fn append_audit(&self, entry: &AuditEntry) -> Result<()> {
        sqlx::query(
            "INSERT INTO admin_audit (at, actor, action, target, detail, origin, ok) VALUES (?, ?, ?, ?, ?, ?, ?)",
        )
        .bind(entry.at_ms)
        .bind(bounded(&entry.actor, ACTOR_LEN))
        .bind(bounded(&entry.action, ACTION_LEN))
        .bind(bounded(&entry.target, TARGET_LEN))
        .bind(bounded(&entry.detail, DETAIL_LEN))
        .bind(bounded(&entry.from, ORIGIN_LEN))
        .bind(i64::from(entry.ok))
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    /// The newest `limit` entries (at most [`MAX_AUDIT_LIST`]), newest first.
    pub async fn list_audit(&self, limit: u32) -> Result<Vec<AuditEntry>> {
        let rows = sqlx::query(
            "SELECT at, actor, action, target, detail, origin, ok FROM admin_audit ORDER BY id DESC LIMIT ?",
        )
        .bind(i64::from(limit.min(MAX_AUDIT_LIST)))
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|row| {
                Ok(AuditEntry {
                    at_ms: row.try_get("at")?,
                    actor: row.try_get("actor")?,
                    action: row.try_get("action")?,
                    target: row.try_get("target")?,
                    detail: row.try_get("detail")?,
                    from: row.try_get("origin")?,
                    ok: row.try_get::<i64, _>("ok")? != 0,
                })
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::bounded;

    #[test]
    fn long_text_is_cut_at_a_character_boundary_and_controls_replaced() {
        assert_eq!(bounded("abc", 3), "abc");
        assert_eq!(bounded("abcd", 3), "abc");
        // "é" is two bytes: a cut inside it backs off to before it.
        assert_eq!(bounded("aé", 2), "a");
        assert_eq!(bounded("a\u{1b}[31mb\n", 64), "a\u{fffd}[31mb\u{fffd}");
    }
}
